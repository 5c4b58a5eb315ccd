"""The main job: plan, run, resume and report a multi-model sweep.

    python -m vabench.sweep configs/all.yaml [--dry-run] [--out DIR]

`vabench.config` validates the YAML; `plan` lists every episode (models x tracks x tasks x
seeds x runs) deterministically and estimates calls, tokens and cost; `driver` runs them on
engines, resumable from `results.jsonl` (`local_executor`: one engine in this process, every
task batch concurrent, `runner`; `process_executor`: worker processes of one host;
`ray_executor`: engine actors on a Ray cluster, four per GPU); `display` shows progress; at
the end `vabench.report` writes the paper's tables.
"""
