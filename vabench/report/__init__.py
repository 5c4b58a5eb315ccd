"""The report of a sweep: `python -m vabench.report RUN_DIR` writes RUN_DIR/report/.

Reading results.jsonl into validated records is `vabench.run_records`'s; the table model and
its Markdown/CSV text are `vabench.tables`'s (the diagnostics print theirs with it). Modules
here: statistics as pure functions: `stats` (the paper's base aggregation), `active_passive`
(the sign test), `conditions` (records by model, protocol and summary mode), `summaries`
(summary source, learning stage) and `suites` (controlled transfer, long horizon): the last two
are sections shown only when the sweep holds their data; sections of tables: `base_tables`,
`summary_tables`, `suite_tables`, `spend` (the bill), and the diagnostics' sections
(`vabench.diagnostics.sections`, from RUN_DIR/annotations/); `figures` (PNG), `html`
(self-contained page), `build` (assembling and writing). The paper's headline views:
`publication` (conditions, task matrix, capability profiles), `pub_tables`, `pub_figures`,
with `published` (the paper's scores as reference data); `results_file` (results.json and its
schema), `leaderboard` (several sweeps in one report). The sweep calls `make_report(run_dir)`
at its end.
"""

from vabench.report.build import ReportOutput, generate, make_report
from vabench.run_records import ReportError, load_results

__all__ = ["ReportError", "ReportOutput", "generate", "load_results", "make_report"]
