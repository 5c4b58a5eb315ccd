"""Warp's compiled modules stay loaded while the process runs.

When a kernel is added to a Warp module after the module was loaded (a kernel specialised on
first use, an overload), Warp loads the module's new build and drops the old one, and the
CUDA code of the old one is unloaded when its last reference goes. Captured graphs keep
theirs, but a plain launch of the old code queued on another stream may still be running:
with a stream per batch and per render pass (`streams`), the GPU is never idle at that moment.
Unloading code under a running kernel is undefined behaviour in CUDA (an illegal memory
access, which kills the process's context). `keep_loaded` keeps every loaded build
referenced for the life of the process (a few MB of code at most) and logs each replacement,
so that a run's log says whether any happened.
"""

from __future__ import annotations

import logging
import threading
from typing import Any

log = logging.getLogger(__name__)

_KEPT: dict[int, Any] = {}  # id -> every module build loaded in this process
_LAST: dict[tuple[int, Any, int], Any] = {}  # (module, context, block_dim) -> its latest build
_GUARD = threading.Lock()
_PATCHED = False


def keep_loaded() -> None:
    """Patch Warp's module loading (once per process) to keep every build it loads. Warp
    calls `Module.load` on every launch: the patch costs a dict lookup there."""
    global _PATCHED
    with _GUARD:
        if _PATCHED:
            return
        from warp._src import context  # the loader; no public hook exists

        load = context.Module.load

        def load_and_keep(module: Any, *args: Any, **kwargs: Any) -> Any:
            loaded = load(module, *args, **kwargs)
            if loaded is not None and id(loaded) not in _KEPT:
                _keep(module, loaded)
            return loaded

        context.Module.load = load_and_keep  # type: ignore[method-assign,assignment]
        _PATCHED = True


def _keep(module: Any, loaded: Any) -> None:
    key = (id(module), getattr(loaded.device, "context", None), loaded.block_dim)
    with _GUARD:
        _KEPT[id(loaded)] = loaded
        old = _LAST.get(key)
        _LAST[key] = loaded
    if old is not None and old is not loaded:
        log.warning(
            "warp module %s was rebuilt while loaded (%s -> %s); its old code stays loaded",
            module.name,
            (old.module_hash or b"").hex()[:8],
            (loaded.module_hash or b"").hex()[:8],
        )


def kept() -> int:
    """How many module builds are kept (tests)."""
    return len(_KEPT)
