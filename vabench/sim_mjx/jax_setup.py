"""JAX as the simulator needs it, set once before its first compilation: imported by every
module of sim_mjx that uses JAX (the package's __init__ imports nothing, so that a command
reading the machine's choices, or C MuJoCo alone, does not pay for it).

It enables JAX's persistent compilation cache (unless the user configured one) so that each
model shape compiles once per machine, not once per process, and asks for full float32 matrix
products (see `_full_precision_matmuls`).
"""

from __future__ import annotations

import contextlib
import io
import os
from pathlib import Path

# JAX takes 75 % of a GPU's memory at its first GPU operation unless told otherwise; here it
# shares the card with MuJoCo Warp (physics), the renderer and other sweep processes, and its
# own arrays (predicates, MJX batches) are small. Set before JAX starts a backend.
os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")

import jax

from vabench import switches


def quiet_stdout() -> contextlib.AbstractContextManager[object]:
    """Around `from mujoco import mjx`: it prints "Failed to import warp" on stdout when MuJoCo
    Warp is absent; the CLIs that print JSON keep stdout clean. Only the MJX backend imports
    mjx: it also imports its own copy of MuJoCo Warp and Warp itself, ~4 s of every process's
    start on a 2-core machine, which the C and Warp backends never use."""
    return contextlib.redirect_stdout(io.StringIO())


_USERS_CACHE = jax.config.jax_compilation_cache_dir  # type: ignore[attr-defined]
"""A cache the user configured for JAX itself (JAX_COMPILATION_CACHE_DIR), kept as it is."""


def configure() -> None:
    """Set the cache and the precision from the switches (`vabench.switches`): on import, and
    again in the sweep's process once its config's switches are in its environment
    (`tuning.engine_env.configure_jax`), before its first compilation."""
    _enable_compilation_cache()
    _full_precision_matmuls()


def _enable_compilation_cache() -> None:
    if _USERS_CACHE:
        return
    path = switches.get("jax_cache") or str(Path.home() / ".cache" / "vabench" / "jax")
    jax.config.update("jax_compilation_cache_dir", None if path == switches.OFF else path)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)


def _full_precision_matmuls() -> None:
    """JAX computes float32 matmuls in TF32 on recent NVIDIA GPUs by default (10-bit mantissa).
    Contact dynamics and the planner's IK are not neural networks and need float32 products
    (docs/PERFORMANCE.md, "Seed screening"). VABENCH_MATMUL_PRECISION
    overrides the choice ("default" restores JAX's)."""
    value = switches.get("matmul_precision")
    jax.config.update("jax_default_matmul_precision", None if value == "default" else value)


configure()
