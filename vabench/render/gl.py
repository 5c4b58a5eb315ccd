"""Choosing the OpenGL platform for off-screen rendering, before MuJoCo is imported.

MuJoCo's Python bindings and PyOpenGL read `MUJOCO_GL` / `PYOPENGL_PLATFORM` once, when they
are first imported, so a process must pick its platform before anything imports `mujoco`: the
rendering worker does it first thing in a fresh (spawned) process.

"auto" tries EGL first. On a machine with an NVIDIA driver EGL renders on the GPU; without one,
Mesa's EGL falls back to llvmpipe, a multithreaded software rasteriser, which is the software
fallback here (no X server needed). OSMesa is tried last. `describe()` reports which one
actually runs, from the driver's own strings, so the choice is logged, never guessed.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

PLATFORMS = ("auto", "egl", "osmesa")
_SOFTWARE_MARKERS = ("llvmpipe", "softpipe", "swrast", "software")


@dataclass(frozen=True)
class GLInfo:
    platform: str  # "egl" | "osmesa"
    vendor: str
    renderer: str
    version: str

    @property
    def software(self) -> bool:
        return any(m in self.renderer.lower() for m in _SOFTWARE_MARKERS)

    def __str__(self) -> str:
        kind = "software" if self.software else "hardware"
        return f"{self.platform} ({kind}: {self.renderer}; {self.version})"


def configure(platform: str) -> None:
    """Set the environment for `platform` ("egl" or "osmesa"); call before importing mujoco."""
    if platform not in ("egl", "osmesa"):
        raise ValueError(f"render platform must be 'egl' or 'osmesa', got {platform!r}")
    os.environ["MUJOCO_GL"] = platform
    os.environ["PYOPENGL_PLATFORM"] = platform


def make_context(platform: str, width: int, height: int):  # -> mujoco GLContext
    """A current off-screen GL context of at least `width` x `height` pixels."""
    if platform == "egl":
        from mujoco.egl import GLContext
    elif platform == "osmesa":
        from mujoco.osmesa import GLContext
    else:
        raise ValueError(f"render platform must be 'egl' or 'osmesa', got {platform!r}")
    ctx = GLContext(width, height)
    ctx.make_current()
    return ctx


def describe(platform: str) -> GLInfo:
    """What the current context renders with (call with a context current)."""
    from OpenGL import GL

    def s(name: int) -> str:
        value = GL.glGetString(name)
        return value.decode() if isinstance(value, bytes) else str(value)

    return GLInfo(platform, s(GL.GL_VENDOR), s(GL.GL_RENDERER), s(GL.GL_VERSION))
