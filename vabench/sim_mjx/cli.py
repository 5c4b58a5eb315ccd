"""The physics backend on the command line: the same `--backend` (and the old `--impl`) in every
CLI that steps a task (`vabench.replay`, `vabench.seeds verify`, `vabench.episode`)."""

from __future__ import annotations

import argparse

from vabench.sim_mjx.backends import Physics, as_physics


def add_physics_arguments(parser: argparse.ArgumentParser, backend: str = "mjx") -> None:
    """`--backend warp|mjx|c` (default `backend`) and the old `--impl jax|warp`."""
    parser.add_argument(
        "--backend",
        choices=[physics.value for physics in Physics],
        default=backend,
        help="warp (MuJoCo Warp: an NVIDIA GPU, the [gpu] extra), mjx (MJX on JAX) or c (C "
        f"MuJoCo) (default {backend})",
    )
    parser.add_argument(
        "--impl",
        choices=("jax", "warp"),
        default=None,
        help="the old spelling: --backend mjx --impl warp is --backend warp, --impl jax the "
        "default",
    )


def physics_of(parser: argparse.ArgumentParser, args: argparse.Namespace) -> Physics:
    """The backend the flags name; a usage error when `--backend` and `--impl` contradict."""
    try:
        return as_physics(args.backend, args.impl)
    except ValueError as err:
        parser.error(f"--impl {args.impl}: {err}")


def physics_flag(args: argparse.Namespace) -> str:
    """The flag an error about the chosen backend names (`--impl warp` where it was given)."""
    return f"--impl {args.impl}" if args.impl else f"--backend {args.backend}"
