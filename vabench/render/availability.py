"""Whether MuJoCo Warp's renderer can run on a device: the one check that both the choice of a
renderer (`backends.resolve_renderer`, `check_renderer`) and the renderer itself
(`warp_renderer.WarpRenderPool.start`) make.

It sits below both: `backends` builds the Warp renderer, so the renderer asking `backends` would
make the two modules import each other.
"""

from __future__ import annotations

from vabench.sim_mjx.warp.device import warp_problem


def renderer_problem(device: str) -> str | None:
    """Why the Warp renderer cannot run on `device` (None when it can)."""
    problem = warp_problem(device)
    if problem is None:
        return None
    return problem.replace("the Warp backend", "the Warp renderer").replace(
        "Use backend c", "Use render backend gl"
    )
