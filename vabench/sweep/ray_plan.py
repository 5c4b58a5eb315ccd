"""The plan of a Ray sweep's engines (`ray_executor` runs the sweep): how many engines and what
each claims from Ray's scheduler (`engine_plan`), what an engine's process is started with
(`engine_environment`), and the checkout shipped to the cluster (`project_runtime_env`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import vabench
from vabench.config import SweepConfig
from vabench.config.choices import Choices, for_engines
from vabench.tuning.engine_env import engines_per_gpu, ray_environment

CHUNKS_PER_ENGINE = 8
"""Chunks per engine the plan is cut into: enough that engines finish close together."""
SHIPPED = ("vabench", "configs", "assets", "pyproject.toml")
"""What an engine needs of the checkout; the rest stays home (another virtual environment, run
directories, caches: they can pass Ray's 512 MiB limit on the package it uploads)."""
SHIP_EXCLUDES = ["__pycache__", "*.pyc", "*.egg-info", ".cache", ".*_cache"]
"""Left out inside what ships."""


def ship_excludes(root: Path) -> list[str]:
    """Ray's `excludes` (gitignore patterns; a leading / anchors at `root`) that leave out every
    top-level entry of `root` but `SHIPPED`, and the caches inside those."""
    others = sorted(p.name for p in root.iterdir() if p.name not in SHIPPED)
    return [f"/{name}" for name in others] + SHIP_EXCLUDES


def project_runtime_env() -> dict[str, Any]:
    """Ray's runtime environment that ships this checkout to the engines (`SHIPPED`), or
    nothing for an installed vabench (then every node has its own)."""
    root = Path(vabench.__file__).resolve().parents[1]
    if not ((root / "pyproject.toml").is_file() and (root / "assets").is_dir()):
        return {}
    return {"working_dir": str(root), "excludes": ship_excludes(root)}


def upload_failure(err: BaseException) -> str:
    """One line for Ray's failure to upload the checkout: its cause (Ray's last line), the fix."""
    lines = [line.strip() for line in str(err).splitlines() if line.strip()]
    cause = next((x for x in reversed(lines) if "size" in x.lower()), lines[-1] if lines else "")
    return (
        f"ray: the checkout could not be uploaded to the cluster as the engines' working "
        f"directory: {cause}; move what is not {', '.join(SHIPPED)} out of the checkout, or "
        "install vabench on every node (pip install .) so that nothing is uploaded"
    )


def engine_plan(
    config: SweepConfig, choices: Choices, cluster: Mapping[str, float]
) -> tuple[int, dict[str, float], Choices]:
    """(how many engines, what each claims from Ray's scheduler, the choices they run with
    (`config.choices.for_engines`)) on a cluster of `cluster` resources: with batched physics on
    GPUs `engines_per_gpu` a GPU, else one per `1 + render.workers` CPUs, or `executor.actors`."""
    asked = config.executor.actors
    gpus = int(cluster.get("GPU", 0))
    engines = for_engines(choices, config, gpus)
    if engines.physics.batched and gpus >= 1:
        # more engines than GPUs: each claims its share of one, so that several engine
        # processes share a GPU under CUDA MPS (one process is paced by its host side)
        n = asked or gpus * engines_per_gpu(config.executor.mps)
        share = 1.0 / math.ceil(n / gpus)  # 1 / engines per GPU: all of them fit
        return n, {"num_cpus": 1.0, "num_gpus": share}, engines
    cpus = 1 + config.render.workers
    resources = {"num_cpus": float(cpus), "num_gpus": 0.0}
    return asked or max(1, int(cluster.get("CPU", 1)) // cpus), resources, engines


def engine_environment(
    config: SweepConfig, cores: int, gpu_share: int = 1, sweep: str = "", ranked: bool = False
) -> dict[str, str]:
    """What an engine's process is started with (`engine_env.ray_environment`): the node's
    MPS daemon of the sweep `sweep` unless `executor.mps` is off, the config's API keys."""
    keys = [m.api_key_env for m in config.models if m.api_key_env]
    sweep = sweep if config.executor.mps == "auto" else ""
    return ray_environment(cores, gpu_share, sweep, ranked, keys)
