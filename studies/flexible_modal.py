"""Flexible-spacecraft modal study: plate verification, full FE modes, the seed's Table 1 analogue.

Run alone with ``python -m studies.flexible_modal --out DIR``; the suite runner calls
:func:`run`. ``python -m studies.flexible_modal --regenerate`` rebuilds the reduced model
that the ``flexible-spacecraft`` problem loads (:func:`regenerate`).

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
import json
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

from problems.flexible_spacecraft import DATA, N_STORED  # noqa: E402
from studies.flexible import reduced_model, selection, substructures  # noqa: E402
from studies.flexible.spacecraft import SpacecraftDesign  # noqa: E402
from studies.flexible.study import (  # noqa: E402
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


def regenerate(path: Path = DATA, n_stored: int = N_STORED, tol: float = 0.01) -> dict:
    """Build the reduced FE model, select the retained modes and store the benchmark's data.

    Steps (seed section 4): the ``n_stored``-mode system modal set
    (``reduced_model("system", n_stored)``); its Table-2 analysis
    (:func:`studies.flexible.selection.table2`) gives the retained system modes; the
    smallest number of structural modes whose model reproduces those modes' frequencies
    of the full finite-element model within ``tol``
    (:func:`studies.flexible.selection.structural_mode_count`, at least two) is stored
    as the default of the ``flexible-spacecraft`` problem, which reads ``path``. The stored
    ``M``, ``K`` are the ``n_stored``-mode model; the problem takes their leading block,
    which is the model with fewer system modes (the system modes do not depend on how
    many are kept; checked here to 1e-9).
    """
    full = reduced_model("system", n_modes=n_stored)
    M, K = np.asarray(full.M, dtype=float), np.asarray(full.K, dtype=float)
    table, _ = selection.table2(full)
    retained = [int(i) for i in table.loc[table["retained"], "mode"]]
    f_fe = fe_modes(substructures().fe)["f_hz"].to_numpy()[6:]
    n_struct, trials = selection.structural_mode_count(
        lambda k: reduced_model("system", n_modes=k), retained,
        f_fe[[i - 1 for i in retained]], tol, n_stored)
    n_default = max(2, n_struct if n_struct is not None else n_stored)
    small = reduced_model("system", n_modes=n_default)
    block = np.r_[0:6 + n_default]
    for name, A, B in (("M", small.M, M), ("K", small.K, K)):
        gap = np.max(np.abs(A - B[np.ix_(block, block)])) / np.max(np.abs(B))
        if gap > 1e-9:
            raise RuntimeError(f"the {n_default}-mode {name} is not the leading block of the "
                               f"{n_stored}-mode one (relative gap {gap:.1e})")
    meta = dict(source=f"studies.flexible.reduced_model('system', n_modes={n_stored})",
                command="python -m studies.flexible_modal --regenerate",
                retained_system_modes=retained, n_structural=n_default,
                structural_mode_count=n_struct, tol=tol,
                reference_hz=[float(f_fe[i - 1]) for i in retained],
                trials={c: [v if isinstance(v, (bool, np.bool_)) or np.isfinite(v) else None
                            for v in trials[c].tolist()] for c in trials.columns})
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(path, M=M, K=K, meta=np.array(json.dumps(meta)))
    return meta


def main(argv: list[str] | None = None) -> None:
    """Command line: ``python -m studies.flexible_modal --out DIR`` (or ``--regenerate``)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("results/flexible-modal"),
                        help="output directory (default: results/flexible-modal)")
    parser.add_argument("--regenerate", action="store_true",
                        help=f"rebuild the flexible-spacecraft problem's stored model {DATA}")
    args = parser.parse_args(argv)
    if args.regenerate:
        print(json.dumps(regenerate(), indent=1))
    else:
        run(args.out)


if __name__ == "__main__":
    main()
