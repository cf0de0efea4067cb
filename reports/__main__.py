"""``python -m reports --db results/driftbench.sqlite --out results/``: rebuild the report.

``--scaling DIR`` adds the section of the scaling benchmark's results in ``DIR``
(``python -m benchmarks.scaling --out DIR``).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from benchmarks.store import STORE_NAME, StoreError
from reports import build
from reports.scaling import ScalingError


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m reports",
                                description="Rebuild report.md and report.html from a results store.")
    p.add_argument("--db", type=Path, help=f"results store (default: OUT/{STORE_NAME})")
    p.add_argument("--out", type=Path, default=Path("results"),
                   help="output folder (default: results/)")
    p.add_argument("--scaling", type=Path, metavar="DIR",
                   help="add the scaling section from DIR/scaling.json "
                        "(python -m benchmarks.scaling --out DIR)")
    args = p.parse_args(argv)
    try:
        paths = build(args.db or args.out / STORE_NAME, args.out, args.scaling)
    except (StoreError, ScalingError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    for path in paths[:2]:
        print(f"wrote {path}")
    print(f"wrote {len(paths) - 2} figures under {args.out / 'figures'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
