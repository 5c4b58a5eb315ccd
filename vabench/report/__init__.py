"""The report of a sweep: `python -m vabench.report RUN_DIR` writes RUN_DIR/report/.

Modules: `load` (results.jsonl into validated records); statistics as pure functions: `stats`
(the paper's base aggregation), `active_passive` (the sign test), `conditions` (records by
model, protocol and summary mode), `summaries` (summary source, learning stage) and `suites`
(controlled transfer, long horizon): the last two are sections shown only when the sweep holds
their data; sections of tables: `tables` (the table model, Markdown/CSV), `base_tables`,
`summary_tables`, `suite_tables`, `diagnostics` (from RUN_DIR/annotations/), `spend` (the
bill); `figures` (PNG), `html` (self-contained page), `build` (assembling and writing). The
sweep calls `make_report(run_dir)` at its end.
"""

from vabench.report.build import ReportOutput, generate, make_report
from vabench.report.load import ReportError, load_results

__all__ = ["ReportError", "ReportOutput", "generate", "load_results", "make_report"]
