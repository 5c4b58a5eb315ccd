"""Settled initial states on disk: a reset of many slots is a copy, not thousands of steps.

Every episode starts with the seed's objects placed and settled (2,000-2,500 physics steps with
the arms held, then the drift gate of FACTS over the last 200). That work depends only on the
scene, the seed's initial pose, the settle schedule and the physics that ran it, so its result
is cached under a key that hashes exactly those: the compiled model of the slot's variant (its
binary: assets and solver settings included), the initial qpos (the sampler's output), the
schedule, and the backend's id (which names the MuJoCo / MuJoCo Warp release and, for Warp, the
GPU architecture). Change any of them and the key changes; nothing is ever invalidated by hand.

Entries are small .npz files under `~/.cache/vabench/settled/` (`$VABENCH_STATE_CACHE`;
"off" disables the cache), written atomically, so concurrent sweep processes share them; a
process also keeps what it read in memory. Slots whose settling failed for infrastructure
reasons (a Warp buffer overflow) are never cached.
"""

from __future__ import annotations

import hashlib
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np

from vabench import switches

FORMAT = 2  # bump when what an entry holds changes (2: C MuJoCo's silent resets while
# settling are non-finite settles; format 1 may hold such worlds as clean ones)


@dataclass(frozen=True)
class Settled:
    """One slot after the reset gate: its physics state (STATE_FIELDS rows) and the gate."""

    state: dict[str, np.ndarray]
    finite: bool
    drift_deg: float


def model_digest(model: mujoco.MjModel) -> str:
    """A digest of the compiled model (geometry, masses, solver options, everything)."""
    buf = np.zeros(mujoco.mj_sizeModel(model), np.uint8)
    mujoco.mj_saveModel(model, None, buf)
    return hashlib.sha256(buf.tobytes()).hexdigest()


def settle_key(
    task: str, backend_id: str, model_hash: str, qpos: np.ndarray, schedule: tuple[int, ...]
) -> str:
    h = hashlib.sha256()
    for part in (str(FORMAT), task, backend_id, model_hash, repr(schedule)):
        h.update(part.encode())
        h.update(b"\0")
    h.update(np.ascontiguousarray(qpos, np.float64).tobytes())
    return h.hexdigest()


def default_root() -> Path | None:
    value = switches.get("state_cache")
    if value == switches.OFF:
        return None
    return Path(value) if value else Path.home() / ".cache" / "vabench" / "settled"


class SettledCache:
    """Settled states by key: memory first, then disk."""

    def __init__(self, root: Path | None):
        self.root = root
        self._memory: dict[str, Settled] = {}
        self.hits = 0
        self.misses = 0

    @staticmethod
    def default() -> SettledCache:
        return SettledCache(default_root())

    def _path(self, key: str) -> Path:
        assert self.root is not None
        return self.root / key[:2] / f"{key}.npz"

    def get(self, key: str) -> Settled | None:
        hit = self._memory.get(key)
        if hit is None and self.root is not None:
            try:
                with np.load(self._path(key)) as z:
                    state = {k[2:]: z[k] for k in z.files if k.startswith("s_")}
                    hit = Settled(state, bool(z["finite"]), float(z["drift_deg"]))
            except (OSError, KeyError, ValueError):
                hit = None  # absent, or a partial file of a crashed writer: recompute
            if hit is not None:
                self._memory[key] = hit
        if hit is None:
            self.misses += 1
        else:
            self.hits += 1
        return hit

    def put(self, key: str, value: Settled) -> None:
        self._memory[key] = value
        if self.root is None:
            return
        path = self._path(key)
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            arrays = {f"s_{k}": v for k, v in value.state.items()}
            fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".tmp")
            with os.fdopen(fd, "wb") as f:
                # numpy's stubs read the keyword arrays as its `allow_pickle` flag
                np.savez(f, finite=value.finite, drift_deg=value.drift_deg, **arrays)  # type: ignore[arg-type]
            os.replace(tmp, path)
        except OSError:
            pass  # a read-only or full disk costs speed, never a result
