"""The task families, one module each, whose docstring is its spec; each exports TASK, a `Task`.

Every module here is a family: `vabench.tasks` puts the TASK of each into its REGISTRY, and a
module without one is an error there, not skipped. What several families share (and what runs
them) lives one folder up, in `vabench/tasks/`.
"""
