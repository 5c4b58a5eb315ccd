"""The nine trajectory-level behavioural diagnostics of the paper: criteria and rubric
(`criteria`), the run's episodes (`episodes`), annotations on disk (`store`), agreement
statistics (`stats`), labels and scores (`aggregate`), evidence hints for annotators
(`hints`), the automatic judge (`judge`), CSV exchange (`csv_io`) and the agreement of a votes
file alone (`votes_file`).

    python -m vabench.diagnostics RUN_DIR                      # tables, agreement, vote rules
    python -m vabench.diagnostics judge RUN_DIR --model NAME   # an automatic annotator
    python -m vabench.diagnostics export RUN_DIR --out annotations.csv
    python -m vabench.diagnostics import RUN_DIR annotations.csv
    python -m vabench.diagnostics agreement votes.csv          # a votes file alone

Annotate in a browser with `python -m vabench.view RUN_DIR` (docs/DIAGNOSTICS.md).
"""
