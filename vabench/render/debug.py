"""Settings of debug views for people, kept apart from model images.

Only `SceneRenderer.render_debug` reads these; the model-image path takes no settings at all,
so turning an overlay on here can never change what a model sees.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class DebugOverlays:
    """What a person may add to an observer image; never applied to a model image."""

    contacts: bool = False  # contact points and forces
    gc_markers: bool = False  # a sphere at each arm's finger midpoint
    frames: bool = False  # site frames (end effector, finger pads)
    collision_geoms: bool = False  # shapes drawn only for collision (e.g. the table plane)
    label: str | None = None  # text in the top-left corner

    @classmethod
    def all(cls, label: str = "debug") -> DebugOverlays:
        return cls(contacts=True, gc_markers=True, frames=True, collision_geoms=True, label=label)
