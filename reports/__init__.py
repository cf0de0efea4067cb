"""The report stage: reads the results store only and writes Markdown and one HTML file.

``build(db_path, out_dir)`` writes ``report.md`` (with its SVG figures in ``figures/``) and a
self-contained ``report.html``; ``python -m reports --db PATH --out DIR`` rebuilds them
(``--scaling DIR`` and ``--efficiency DIR`` add the benchmarks' sections).
"""

from reports.report import build

__all__ = ["build"]
