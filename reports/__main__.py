"""``python -m reports --db results/driftbench.sqlite --out results/``: rebuild the report.

``--scaling DIR`` adds the section of the scaling benchmark's results in ``DIR``
(``python -m benchmarks.perf.scaling --out DIR``); ``--efficiency DIR`` adds "What the
harness costs" from ``DIR/efficiency.json`` (``python -m benchmarks.perf.efficiency --out
DIR``) and marks the headline's cost verdicts where a family named is over twice its native
cost per step; ``--targets`` sets the accuracy targets of
the per-problem target tables; ``--x`` and ``--y`` choose the work-precision diagrams'
axes. Bad input is one line on stderr and exit status 2.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

from benchmarks.records import EXIT_INPUT, CommandParser, one_line
from benchmarks.store import STORE_NAME, StoreError
from reports import build
from reports.analysis import COST_AXES, DEFAULT_TARGETS, DEFAULT_X, DEFAULT_Y, PRECISION_AXES
from reports.efficiency import EfficiencyError
from reports.scaling import ScalingError


def _target(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"{text!r} must be positive and finite")
    return value


def parser() -> argparse.ArgumentParser:
    p = CommandParser(prog="python -m reports",
                description="Rebuild report.md and report.html from a results store.")
    p.add_argument("--db", type=Path, help=f"results store (default: OUT/{STORE_NAME})")
    p.add_argument("--out", type=Path, default=Path("results"),
                   help="output folder (default: results/)")
    p.add_argument("--scaling", type=Path, metavar="DIR",
                   help="add the scaling section from DIR/scaling.json "
                        "(python -m benchmarks.perf.scaling --out DIR)")
    p.add_argument("--efficiency", type=Path, metavar="DIR",
                   help="add 'What the harness costs' from DIR/efficiency.json "
                        "(python -m benchmarks.perf.efficiency --out DIR) and mark the "
                        "headline's cost verdicts where a family is over 2x its yardstick")
    p.add_argument("--targets", type=_target, nargs="+", default=list(DEFAULT_TARGETS),
                   metavar="LEVEL",
                   help="accuracy targets of the per-problem target tables (default: "
                        f"{' '.join(f'{t:g}' for t in DEFAULT_TARGETS)})")
    p.add_argument("--x", nargs="+", choices=list(COST_AXES), default=list(DEFAULT_X),
                   help=f"work-precision cost axes (default: {' '.join(DEFAULT_X)})")
    p.add_argument("--y", nargs="+", choices=list(PRECISION_AXES), default=list(DEFAULT_Y),
                   help=f"work-precision precision axes (default: {' '.join(DEFAULT_Y)}; "
                        "g is max |g|, Gv max |G v + g_t|, energy the max relative energy "
                        "error)")
    return p


def main(argv=None) -> int:
    args = parser().parse_args(argv)
    try:
        paths = build(args.db or args.out / STORE_NAME, args.out, args.scaling,
                      targets=args.targets, x=tuple(dict.fromkeys(args.x)),
                      y=tuple(dict.fromkeys(args.y)), efficiency=args.efficiency)
    except (StoreError, ScalingError, EfficiencyError) as exc:
        print(f"error: {one_line(exc)}", file=sys.stderr)
        return EXIT_INPUT
    except OSError as exc:  # an output folder that cannot be made or written
        print(f"error: the report could not be written under {args.out}: "
              f"{exc.strerror or exc}{f' ({exc.filename})' if exc.filename else ''}",
              file=sys.stderr)
        return EXIT_INPUT
    for path in paths[:2]:
        print(f"wrote {path}")
    print(f"wrote {len(paths) - 2} figures under {args.out / 'figures'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
