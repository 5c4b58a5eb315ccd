"""The episode viewer: `python -m vabench.view RUN_DIR [--port P] [--host H]` serves a run
read-only with its timelines and the annotation endpoints of the nine diagnostics
(vabench.view.app; docs/DIAGNOSTICS.md)."""
