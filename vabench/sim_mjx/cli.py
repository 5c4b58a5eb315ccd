"""The physics backend on the command line: the same `--backend` and `--impl` in every CLI
that steps a task (`vabench.replay`, `vabench.seeds verify`, `vabench.episode`)."""

from __future__ import annotations

import argparse
from typing import Any


def add_physics_arguments(parser: argparse.ArgumentParser, backend: str = "mjx") -> None:
    """`--backend mjx|c` (default `backend`) and `--impl jax|warp` (default jax)."""
    parser.add_argument(
        "--backend",
        choices=("mjx", "c"),
        default=backend,
        help=f"MJX (an MJX batch) or C MuJoCo (default {backend})",
    )
    parser.add_argument(
        "--impl",
        choices=("jax", "warp"),
        default="jax",
        help="with --backend mjx: MJX on JAX (default) or MuJoCo Warp (NVIDIA GPU, [gpu] extra)",
    )


def physics_kwargs(args: argparse.Namespace) -> dict[str, Any]:
    """The batch arguments of the chosen backend: `impl` only for mjx."""
    return {"impl": args.impl} if args.backend == "mjx" else {}
