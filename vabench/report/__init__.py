"""The report of a sweep: `python -m vabench.report RUN_DIR` writes RUN_DIR/report/.

Modules: `load` (results.jsonl into validated records), `stats` (the paper's aggregation as
pure functions), `tracks` and `track_tables` (summary source, learning stage, transfer, long
horizon: sections shown only when the sweep holds their data), `tables` (Markdown/CSV),
`figures` (PNG), `html` (self-contained page), `build` (assembling and writing). The sweep
calls `make_report(run_dir)` at its end.
"""

from vabench.report.build import ReportOutput, generate, make_report
from vabench.report.load import ReportError, load_results

__all__ = ["ReportError", "ReportOutput", "generate", "load_results", "make_report"]
