"""Seed reproduction: the reduced SPS receiver of the first seed (its Figs. 3 and 4, its claim).

The seed integrates its reduced receiver model (``sps-receiver``: the model, its
parameters and its constraint are the problem's, nothing is restated here) with a 2-stage
symplectic PRK scheme at ``h = 0.5`` over ``t`` in ``[0, 50]`` and reports that the
constraint violation stays within ``[-2e-9, 2e-9]`` at every step (its Fig. 4). This study
runs that setting and a step-size sweep of the same scheme (``lobatto3ab2``) and of RATTLE
with the constraint violation recorded at every step, and writes

``runs`` (table)
    ``integrator, h, status, steps, reached, max_g, vs_bound, message`` for each setting.
``claim`` (table)
    What these runs say about the seed's claim, in a sentence (:func:`verdict`).
``snapshots`` (table) and ``fig3_positions.svg``
    The radii ``(R, r)`` and the constraint residual at the times the seed's Fig. 3 shows,
    from the seed's own run if it finished, else the coarsest finished 2-stage run.
``fig4_violation.svg``
    ``|g(q_n)|`` at each step of every run against the seed's bound.

Run alone with ``python -m studies.seed_sps --out DIR``; a suite names it
``studies = ["seed-sps"]``.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np
import pandas as pd

import integrators
import problems
from benchmarks import compilation
from integrators import Grid

PROBLEM = "sps-receiver"
#: The seed's claim: ``|g|`` within ``2e-9`` at every step on ``[0, 50]`` (its Fig. 4).
BOUND = 2e-9
#: The seed's step and its scheme (the 2-stage Lobatto IIIA-IIIB pair).
SEED_H, SEED_SCHEME = 0.5, "lobatto3ab2"
#: What runs: the seed's scheme over a step-size sweep, and RATTLE beside it.
SETTINGS = tuple((SEED_SCHEME, h) for h in (0.5, 0.25, 0.1, 0.05)) + \
    tuple(("rattle", h) for h in (0.5, 0.1))
#: Times of the position snapshots (the seed's Fig. 3 shows several times in [0, 50]).
SNAPSHOT_TIMES = (0.0, 10.0, 20.0, 30.0, 40.0, 50.0)


def solve(key: str, h: float):
    """One run of ``key`` at step ``h`` over the seed's horizon, ``|g|`` kept at every step."""
    case = problems.make(PROBLEM)
    steps = int(round((case.t_end - case.t0) / h))
    grid = Grid(case.t0, case.t_end, n_windows=steps, n_samples=steps + 1)
    # Its programs are kept whole for the next process, as a suite's runs are.
    with compilation.kept("study seed-sps", key, h):
        return case, integrators.make(key, h=h).prepare(case, grid)()


def verdict(runs: pd.DataFrame) -> str:
    """What ``runs`` (the ``runs`` table) say about the seed's claim, in a sentence or two."""
    scheme = runs[runs["integrator"] == SEED_SCHEME]
    at_seed = scheme[np.isclose(scheme["h"], SEED_H)]
    if at_seed.empty:
        return "No run at the seed's setting (h = 0.5): the claim is not checked."
    row = at_seed.iloc[0]
    if row["status"] == "ok":
        g = float(row["max_g"])
        first = (f"At the seed's setting ({SEED_SCHEME}, h = 0.5) the run reached t = 50 with "
                 f"max |g| = {g:.3g}, {'within' if g <= BOUND else 'above'} the seed's bound "
                 f"of 2e-9, so the data {'support' if g <= BOUND else 'contradict'} the claim.")
    else:
        first = (f"At the seed's setting ({SEED_SCHEME}, h = 0.5) the run {row['status']} "
                 f"(reached t = {row['reached']:.4g}): {row['message']}; the claim |g| <= 2e-9 "
                 "at h = 0.5 is therefore not reproduced by the 2-stage scheme.")
    done = scheme[scheme["status"] == "ok"]
    if done.empty:
        return first + " No 2-stage run completed [0, 50] at any step size tried."
    best = done.loc[done["h"].idxmax()]
    if row["status"] == "ok" and math.isclose(best["h"], SEED_H):
        return first
    g = float(best["max_g"])
    return (first + f" The coarsest step at which {SEED_SCHEME} completed [0, 50] is "
            f"h = {best['h']:g}, with max |g| = {g:.3g} ({'within' if g <= BOUND else 'above'}"
            " 2e-9).")


def run(out: Path) -> dict[str, pd.DataFrame]:
    """Run the seed's setting and the sweep; write the tables and the two figures.

    Parameters
    ----------
    out : pathlib.Path
        Output directory (created if missing).

    Returns
    -------
    dict of str to pandas.DataFrame
        ``runs``, ``claim`` and ``snapshots`` (module notes).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    rows, series, finished = [], [], {}
    for key, h in SETTINGS:
        case, traj = solve(key, h)
        g = traj.windows.get("pos", np.array([]))
        max_g = float(np.max(g)) if len(g) else math.nan
        rows.append(dict(integrator=key, h=h, status=traj.status, steps=traj.counts["n_steps"],
                         reached=traj.t_final, max_g=max_g,
                         vs_bound=("within" if max_g <= BOUND else "above")
                         if traj.status == "ok" else traj.status, message=traj.message))
        series.append((f"{key} h={h:g}", traj.windows.get("t", np.array([])), g,
                       traj.status != "ok"))
        if traj.status == "ok":
            finished[(key, h)] = (case, traj)
    table = pd.DataFrame(rows)
    claim = pd.DataFrame({"verdict": [verdict(table)]})

    # Fig. 3 analogue: the seed's own run if it finished, else the coarsest finished run
    # of the seed's scheme, else of any method.
    ranked = sorted(finished, key=lambda kh: (kh[0] != SEED_SCHEME, -kh[1]))
    snaps = pd.DataFrame(columns=["integrator", "h", "t", "R", "r", "g"])
    if ranked:
        case, traj = finished[ranked[0]]
        t, q = traj.samples["t"], traj.samples["q"]
        picks = [int(np.argmin(np.abs(t - s))) for s in SNAPSHOT_TIMES if s <= t[-1] + 1e-9]
        residual = [float(case.system.constraints(q[k], t[k])[0]) for k in picks]
        snaps = pd.DataFrame(dict(integrator=ranked[0][0], h=ranked[0][1], t=t[picks],
                                  R=q[picks, 0], r=q[picks, 1], g=residual))
    _figure3(plt, snaps, out / "fig3_positions.svg")
    _figure4(plt, series, out / "fig4_violation.svg")
    tables = {"claim": claim, "runs": table, "snapshots": snaps}
    for stem, frame in tables.items():
        frame.to_csv(out / f"{stem}.csv", index=False)
    return tables


def _figure3(plt, snaps: pd.DataFrame, path: Path) -> None:
    """The receiver's twelve points in the co-rotating plane at each snapshot: outer
    points (*) at radius R and angles k * 60 deg, inner points (+) at radius r and
    30 + k * 60 deg, joined by the bars in zig-zag order."""
    n = max(1, len(snaps))
    cols = min(3, n)
    rows = math.ceil(n / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(3.0 * cols, 3.0 * rows), squeeze=False)
    lim = 1.15 * float(max(snaps["R"].max(), snaps["r"].max())) if len(snaps) else 1.0
    outer = np.deg2rad(60.0 * np.arange(6))
    inner = outer + np.deg2rad(30.0)
    for ax, (_, s) in zip(axes.flat, snaps.iterrows()):
        xo, yo = s["R"] * np.cos(outer), s["R"] * np.sin(outer)
        xi, yi = s["r"] * np.cos(inner), s["r"] * np.sin(inner)
        zx, zy = np.ravel(np.column_stack([xo, xi])), np.ravel(np.column_stack([yo, yi]))
        ax.plot(np.append(zx, zx[0]), np.append(zy, zy[0]), color="0.6", lw=0.8)
        ax.plot(xo, yo, "*", color="tab:red", ms=8, label=f"R = {s['R']:.4f}")
        ax.plot(xi, yi, "+", color="tab:blue", ms=8, mew=1.5, label=f"r = {s['r']:.4f}")
        ax.set(xlim=(-lim, lim), ylim=(-lim, lim), aspect="equal", title=f"t = {s['t']:g}")
        ax.legend(loc="lower right", fontsize=6)
    for ax in list(axes.flat)[len(snaps):]:
        ax.set_visible(False)
    if len(snaps):
        fig.suptitle(f"{PROBLEM}: {snaps['integrator'].iloc[0]}, h = {snaps['h'].iloc[0]:g}")
    fig.tight_layout()
    fig.savefig(path, format="svg")
    plt.close(fig)


def _figure4(plt, series, path: Path) -> None:
    """``|g(q_n)|`` at each step against ``t`` (log axis), the seed's bound dashed; a
    failed run is dotted and ends in a cross."""
    fig, ax = plt.subplots(figsize=(9.0, 4.0))
    for label, t, g, failed in series:
        if not len(t):
            continue
        g = np.maximum(g, 1e-17)  # zeros drawn at the bottom of the log axis
        line, = ax.semilogy(t, g, lw=0.9, ls=":" if failed else "-", label=label,
                            marker="." if len(t) <= 200 else None, ms=3)
        if failed:
            ax.plot(t[-1], g[-1], "x", ms=9, mew=2, color=line.get_color())
    ax.axhline(BOUND, color="k", ls="--", lw=0.8, label=f"seed's bound {BOUND:g}")
    # Up to a decade above the largest value drawn, and never above 10: a blown-up run
    # would squeeze every other line.
    drawn = [np.max(g) for _, t, g, _ in series if len(t)] + [BOUND]
    ax.set_ylim(top=min(10.0, 10.0 * float(np.nanmax(drawn))))
    ax.set(xlabel="t", ylabel="|g(q_n)|", title=f"{PROBLEM}: |g| at each step, t in [0, 50]")
    ax.legend(fontsize=7, loc="center left", bbox_to_anchor=(1.0, 0.5))
    fig.tight_layout()
    fig.savefig(path, format="svg")
    plt.close(fig)


def main(argv: list[str] | None = None) -> None:
    """Command line: ``python -m studies.seed_sps --out DIR``."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("results/seed-sps"),
                        help="output directory (default: results/seed-sps)")
    tables = run(parser.parse_args(argv).out)
    print(tables["runs"].to_string(index=False))
    print(tables["claim"]["verdict"].iloc[0])


if __name__ == "__main__":
    main()
