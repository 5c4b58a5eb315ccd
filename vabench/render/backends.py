"""The one edge where a renderer is chosen.

    backend "gl"    the GL worker processes (`worker.RenderPool`): EGL on an NVIDIA GPU, Mesa's
                    llvmpipe without one. Debug overlays are drawn only here.
    backend "warp"  MuJoCo Warp's batch ray tracer (`warp_renderer.WarpRenderPool`): every image
                    of a request in one pass on the GPU, sharing device memory with Warp physics.
    backend "auto"  "warp" where a CUDA GPU and the [gpu] extra are present, else "gl".

Asking for "warp" where it cannot run raises `BackendUnavailable` naming the missing package or
device (`availability.renderer_problem`, which the Warp renderer checks too), never a silent
fallback. `VABENCH_WARP_DEVICE` picks the Warp device, as for physics
("cpu" runs the same kernels on the CPU: slow, for tests).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol

from vabench.render.availability import renderer_problem
from vabench.render.images import ImageSettings, RenderItem, RenderStats
from vabench.sim_mjx.backends import BackendUnavailable
from vabench.sim_mjx.warp.device import warp_device

RENDER_BACKENDS = ("auto", "warp", "gl")


class Renderer(Protocol):
    """What the engine needs of a renderer (both backends provide it)."""

    stats: RenderStats

    def start(self) -> Any: ...

    def render(
        self,
        task: str,
        items: list[RenderItem],
        settings: ImageSettings | None = None,
        source: Any = None,
    ) -> list[bytes]:
        """`source`: the physics batch whose slots the items name; a renderer that `shares` it
        reads their states there (Warp on the physics' GPU), any other draws `item.qpos`."""
        ...

    def close(self) -> None: ...


@dataclass(frozen=True)
class RenderChoice:
    backend: str  # "warp" or "gl"
    reason: str

    @property
    def title(self) -> str:
        """How `--dry-run` names it."""
        return {"gl": "GL worker processes", "warp": "MuJoCo Warp's ray tracer"}[self.backend]

    @property
    def is_warp(self) -> bool:
        """Images from MuJoCo Warp's ray tracer (its kernels compile like the physics')."""
        return self.backend == "warp"


def resolve_renderer(
    backend: str = "auto", device: str | None = None, *, probe: bool = True
) -> RenderChoice:
    """The renderer that runs, with the reason. Raises BackendUnavailable for an explicit
    "warp" that cannot run here. `probe=False`: decide for a device known to be an NVIDIA GPU
    without looking at this machine (a Ray sweep's engines; the renderer checks when it
    starts)."""
    if backend not in RENDER_BACKENDS:
        raise ValueError(f"render backend must be one of {RENDER_BACKENDS}, got {backend!r}")
    if backend == "gl":
        return RenderChoice("gl", "GL was asked for")
    device = device or warp_device()
    problem = renderer_problem(device) if probe else None
    if backend == "warp":
        if problem is not None:
            raise BackendUnavailable(problem)
        return RenderChoice("warp", f"MuJoCo Warp's ray tracer on {device}")
    if problem is None:
        return RenderChoice("warp", f"auto: MuJoCo Warp's ray tracer on {device}")
    # the reason alone: the fix it ends with ("Use render backend gl") is what auto just did
    return RenderChoice("gl", f"auto: {problem.split('. Use ')[0]}")


def check_renderer(choice: RenderChoice, device: str | None = None) -> None:
    """Raise BackendUnavailable when `choice`, made elsewhere, cannot run here (Warp's renderer
    without its packages or its device); a check of a choice, never a new one."""
    if choice.backend == "warp":
        problem = renderer_problem(device or warp_device())
        if problem is not None:
            raise BackendUnavailable(problem)


def make_renderer(
    backend: str | RenderChoice = "auto",
    *,
    workers: int = 2,
    platform: str = "auto",
    max_size: tuple[int, int] = (1280, 960),
    device: str | None = None,
) -> tuple[Renderer, RenderChoice]:
    """A renderer (not started) of the chosen backend, and why it was chosen: `backend` is a
    name to resolve, or a choice made already (a sweep's, `config.choices`), taken as it is.
    `workers` and `platform` are the GL pool's."""
    choice = backend if isinstance(backend, RenderChoice) else resolve_renderer(backend, device)
    if choice.backend == "warp":
        from vabench.render.warp_renderer import WarpRenderPool

        return WarpRenderPool(device=device, max_size=max_size), choice
    from vabench.render.worker import RenderPool

    return RenderPool(workers=workers, platform=platform, max_size=max_size), choice
