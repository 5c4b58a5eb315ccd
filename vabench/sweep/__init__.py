"""The main job: plan, run, resume and report a multi-model sweep (`python -m vabench.sweep`).

`plan` lists the episodes; `driver` runs them on the engines of one executor (`local`,
`processes`, `ray`), resumable from the ledger (`results`); `display` shows progress;
`vabench.report` writes the tables at the end. Module map: docs/DESIGN.md.
"""
