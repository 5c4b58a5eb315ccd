"""A model's capability radar for the viewer's run page, drawn from the annotations as they
are now (so it follows an annotator's work), with the report's own drawing and numbers
(`report.publication.profiles`, `report.pub_figures.radar_figure`)."""

from __future__ import annotations

from pathlib import Path

from vabench.diagnostics.episodes import RunIndex


def radar_png(run_dir: Path, index: RunIndex, model: str, track: str = "") -> bytes | None:
    """The radar of `model` on `track` (default: its active track, else its first annotated
    one); None when that condition has no annotated episode."""
    from vabench.diagnostics import sections as diagnostics
    from vabench.report.pub_figures import radar_figure
    from vabench.report.publication import profiles

    mine = [p for p in profiles(diagnostics.load(run_dir, index)) if p.model == model]
    if track:
        mine = [p for p in mine if p.track == track]
    else:
        mine.sort(key=lambda p: (p.track != "active", p.track))
    return radar_figure(mine[0]) if mine else None
