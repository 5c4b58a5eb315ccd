"""Reading the verified seed manifests, `configs/seeds/<task>.json`.

`vabench.seeds` screens candidates and writes the manifests; this module only reads them, so the
task CLI (and anything below `vabench.seeds`) can list a family's verified seeds without
importing the screening.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from vabench.sim_mjx import robot_constants as rc

MANIFEST_DIR = rc.ASSETS.parent / "configs" / "seeds"
MANIFEST_VERSION = 1


def manifest_path(task: str, directory: Path = MANIFEST_DIR) -> Path:
    return directory / f"{task}.json"


def load_manifest(task: str, directory: Path = MANIFEST_DIR) -> dict[str, Any]:
    """A family's manifest; raises FileNotFoundError naming the command that makes it."""
    path = manifest_path(task, directory)
    if not path.exists():
        raise FileNotFoundError(
            f"no seed manifest {path}; run `python -m vabench.seeds verify --task {task}`"
        )
    doc = json.loads(path.read_text())
    if doc.get("version") != MANIFEST_VERSION or doc.get("task") != task:
        raise ValueError(f"{path}: not a version-{MANIFEST_VERSION} manifest of {task}")
    return doc


def verified_seeds(task: str, directory: Path = MANIFEST_DIR) -> list[int]:
    return list(load_manifest(task, directory)["retained"])
