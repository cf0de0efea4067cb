"""Flexible-spacecraft modal study: plate verification, full FE modes, the seed's Table 1 analogue.

Run alone with ``python -m benchmarks.flexible_modal --out DIR``; the suite
runner calls :func:`run`.

Files written under ``out``:

``plate_verification.csv``
    ``case, mode, mesh, value, classical, rel_error``: square-plate frequency
    parameters (cantilever, simply supported, free) and the free hub box's
    frequencies (Hz) on a sequence of meshes.
``fe_modes.csv``
    ``mode, f_hz``: the full model's free-free frequencies, rigid-body ones
    included, on the study mesh.
``fe_convergence.csv``
    ``element_size, n_dof, mode, f_hz, rel_change``: the full model's elastic
    frequencies on coarser and finer meshes.
``table1.csv``
    ``modal_set, mode, f_hz, f_fe_hz, rel_error``: first six non-zero
    frequencies of each modal set's reduced model (seed's mode counts)
    beside the full model's.
``modal_convergence.csv``
    ``modal_set, n_modes, n_hub, n_panel, n_dof, mode, f_hz, f_fe_hz,
    rel_error``: the trial strategy, errors against retained modes.
``modal_convergence.svg``
    Its plot.
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

if __name__ == "__main__":
    # Run alone, the study's dense products are small enough that a second
    # BLAS thread only spins: on the shared 2-core machine it tripled the CPU
    # time (67 s against 19 s). This must precede the first numpy import and
    # leaves an explicit setting alone; when the suite runner imports this
    # module, thread settings stay the runner's.
    for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS"):
        os.environ.setdefault(_var, "1")

import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

from problems.flexible import reduced_model, selection, substructures  # noqa: E402
from problems.flexible.spacecraft import SpacecraftDesign  # noqa: E402
from problems.flexible.study import (  # noqa: E402
    SEED_ORDERING,
    SEED_TABLE1,
    convergence_summary,
    fe_convergence,
    fe_modes,
    modal_convergence,
    plate_verification,
    plot_modal_convergence,
    set_ordering,
    table1,
)

STUDY_DESIGN = SpacecraftDesign(element_size=0.125)
"""Design and mesh of the study (18.6k degrees of freedom); the convergence
table shows where this mesh stands against finer ones."""
CONVERGENCE_SIZES = (0.5, 0.25, 0.125, 1.0 / 12.0)
"""Element sizes (m) of the full model's mesh-convergence check."""


def _format_table1(table: pd.DataFrame, f_fe: np.ndarray) -> str:
    lines = ["Table 1 analogue: first six non-zero free-free frequencies (Hz), relative error to full FE"]
    header = f"{'':>16}" + "".join(f"{j:>18d}" for j in range(1, 7))
    lines.append(header)
    for s, d in table.groupby("modal_set", sort=False):
        cells = "".join(f"{f:>9.4f} ({e:+7.2%})" for f, e in zip(d["f_hz"], d["rel_error"]))
        lines.append(f"{s:>16}" + cells)
    lines.append(f"{'full FE':>16}" + "".join(f"{f:>18.4f}" for f in f_fe[:6]))
    lines.append("Seed's Table 1 (Hz), for comparison:")
    for s, values in SEED_TABLE1.items():
        lines.append(f"{s:>16}" + "".join(f"{v:>18.2f}" for v in values))
    return "\n".join(lines)


def run(out: Path) -> dict[str, pd.DataFrame]:
    """Build the spacecraft model, compare the four modal sets and write the tables.

    Parameters
    ----------
    out : pathlib.Path
        Output directory (created if missing).

    Returns
    -------
    dict of str to pandas.DataFrame
        The tables, keyed by file stem: ``plate_verification``, ``fe_modes``,
        ``fe_convergence``, ``table1``, ``modal_convergence``, ``table2`` (modal cost and
        influence coefficients of the 20-system-mode model) and ``truncation_bound``
        (balanced-truncation error against its H-infinity bound).
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()

    plates = plate_verification()
    sub = substructures(STUDY_DESIGN)
    fe = sub.fe
    modes = fe_modes(fe)
    f_all = modes["f_hz"].to_numpy()
    f_fe = f_all[6:]
    n_zero = int(np.sum(np.abs(f_all) < 1e-3))
    convergence_fe = fe_convergence(CONVERGENCE_SIZES, design=STUDY_DESIGN)
    t1 = table1(sub, f_fe)
    sweep = modal_convergence(sub, f_fe)
    t2, truncation = selection.table2(reduced_model("system"))

    tables = {
        "plate_verification": plates,
        "fe_modes": modes,
        "fe_convergence": convergence_fe,
        "table1": t1,
        "modal_convergence": sweep,
        "table2": t2,
        "truncation_bound": truncation,
    }
    for stem, df in tables.items():
        df.to_csv(out / f"{stem}.csv", index=False)
    plot_modal_convergence(sweep, out / "modal_convergence.svg")

    cantilever = plates[(plates["case"] == "cantilever") & (plates["mesh"] == "24x24")]
    print("Cantilever square plate, 24x24 mesh: lambda =",
          ", ".join(f"{v:.4f} ({e:+.2%})" for v, e in zip(cantilever["value"], cantilever["rel_error"])))
    print(f"Full model: {fe.n_dof} dof, {n_zero} frequencies below 1e-3 Hz, "
          f"first elastic {f_fe[0]:.4f} Hz (seed's FE: 0.55 Hz)")
    print(_format_table1(t1, f_fe))
    ordering = set_ordering(t1)
    print("Ordering found (worst to best, largest |error| of the six):",
          ", ".join(f"{s} {e:.2%}" for s, e in ordering))
    print(f"Seed's claim: {SEED_ORDERING}.")
    summary = convergence_summary(sweep)
    print("Trial strategy (largest |error| of the first six):")
    print(summary.to_string(index=False, float_format=lambda v: f"{v:.3e}"))
    print("Table 2 analogue (3 hub torques in, 3 hub angles out, zeta = "
          f"{selection.ZETA}):")
    print(t2[["mode", "f_hz", "modal_cost", "hsv_exact", "hsv_gregory", "retained"]]
          .head(8).to_string(index=False, float_format=lambda v: f"{v:.4g}"))
    print(f"Retained: modes {', '.join(str(m) for m in t2.loc[t2['retained'], 'mode'])}; "
          "seed's conclusion: the first two system modes dominate.")
    print(f"Balanced truncation: the H-infinity bound holds at "
          f"{int(truncation['holds'].sum())} of {len(truncation)} orders.")
    print(f"flexible-modal done in {time.perf_counter() - start:.1f} s; files in {out}")
    return tables


def main(argv: list[str] | None = None) -> None:
    """Command line: ``python -m benchmarks.flexible_modal --out DIR``."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("results/flexible-modal"),
                        help="output directory (default: results/flexible-modal)")
    args = parser.parse_args(argv)
    run(args.out)


if __name__ == "__main__":
    main()
