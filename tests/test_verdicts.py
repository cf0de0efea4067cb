"""Every verdict of the report on small hand-made runs: winners with timing spread, accuracy
targets, reference floors, order fits and the history's regressions.

The frames stand in for ``load_runs``: only the columns a verdict reads are filled, so each
test states exactly which numbers decide it.
"""

import math

import numpy as np
import pandas as pd
import pytest

from reports.analysis import (accuracies, at_floor, cheapest, convergence, cost_winner, fit,
                              history, standings, targets, timing)


def run(integrator, h=None, rtol=None, status="ok", wall=1.0, spread=(0.0, 0.0), repeats=3,
        evals=100, final=None, floor=None, pos=None, energy=None, t_end=1.0, **extra):
    """One stored run: median wall time ``wall`` with ``wall - spread[0]`` to
    ``wall + spread[1]`` as its fastest and slowest solves."""
    missing = wall is None
    return {"problem": "p", "integrator": integrator, "h": h, "rtol": rtol, "atol": None,
            "t_end": t_end, "status": status, "wall_s": wall,
            "wall_min_s": None if missing else wall - spread[0],
            "wall_max_s": None if missing else wall + spread[1], "repeats": repeats,
            "n_f_evals": evals, "n_steps": None if evals is None else evals // 2,
            "final_state_error": final, "reference_floor": floor,
            "max_pos_residual": pos, "max_vel_residual": pos, "rel_energy_error": energy,
            "sensitive": 0, "nominal_order": extra.pop("order", math.nan), **extra}


def frame(*rows):
    return pd.DataFrame(list(rows)).astype({"h": float, "rtol": float, "atol": float,
                                            "final_state_error": float,
                                            "reference_floor": float,
                                            "rel_energy_error": float,
                                            "max_pos_residual": float})


# --------------------------------------------------------------------------- timing spread

def test_a_wall_time_winner_needs_a_difference_beyond_the_spread():
    # 1.0 s (0.9-1.1) against 1.3 s (1.2-1.4): the slowest solve of a beat b's fastest.
    apart = cheapest(frame(run("a", wall=1.0, spread=(0.1, 0.1)),
                           run("b", wall=1.3, spread=(0.1, 0.1))), "wall_s")
    assert apart.winner and apart.row["integrator"] == "a" and not apart.ties
    # 1.0 s (0.9-1.25) against 1.3 s (1.2-1.4): the spreads overlap, no winner.
    close = cheapest(frame(run("a", wall=1.0, spread=(0.1, 0.25)),
                           run("b", wall=1.3, spread=(0.1, 0.1))), "wall_s")
    assert not close.winner and close.ties == ["b"]
    assert "no winner: within the timing spread of b" in close.text


def test_a_single_timed_solve_names_no_wall_time_winner():
    one = cheapest(frame(run("a", wall=1.0, repeats=1), run("b", wall=3.0, repeats=1)),
                   "wall_s")
    assert not one.winner and one.row["integrator"] == "a"
    assert "spread was not measured" in one.text


def test_a_solve_too_long_to_repeat_gets_the_widest_measured_spread():
    # "a" spans 0.9-1.2 (ratio 4/3), "c" 5-10: the widest measured ratio is 2, c's.
    a = run("a", wall=1.0, spread=(0.1, 0.2))
    c = run("c", wall=5.0, spread=(0.0, 5.0))
    beaten = cheapest(frame(a, c, run("b", wall=3.0, repeats=1)), "wall_s")
    # b's one solve of 3 s counts as no faster than 3 / 2 = 1.5 > 1.2: a wins.
    assert beaten.winner and beaten.row["integrator"] == "a" and beaten.ties == []
    close = cheapest(frame(a, c, run("b", wall=2.2, repeats=1)), "wall_s")
    # 2.2 / 2 = 1.1 <= 1.2: a tie.
    assert not close.winner and close.ties == ["b"]
    assert "within the timing spread of b" in close.text
    # The cheapest solved once: 0.5 s counts as up to 1 s, below c's fastest (5 s).
    alone = cheapest(frame(run("b", wall=0.5, repeats=1), c), "wall_s")
    assert alone.winner and alone.row["integrator"] == "b"


def test_evaluation_counts_are_exact():
    pick = cheapest(frame(run("a", evals=120), run("b", evals=100), run("c", evals=100)),
                    "n_f_evals")
    assert pick.row["integrator"] == "b" and pick.ties == ["c"] and not pick.winner


def test_timing_shows_the_spread_of_the_timed_solves():
    t = timing({"wall_s": 2.0, "wall_min_s": 2.0, "wall_max_s": 2.0, "repeats": 1})
    assert (t.low, t.high, t.repeats, t.measured) == (2.0, 2.0, 1, False)
    assert timing(run("a", wall=2.0, spread=(0.5, 1.0))).text() == "2 (1.5-3, 3 solves)"


# --------------------------------------------------------------------------- floors

def accuracy(row: dict, column: str) -> float:
    return float(accuracies(pd.DataFrame([row]), column)[0])


def test_a_final_error_at_the_floor_counts_as_the_floor():
    r = run("a", final=4.8e-12, floor=6e-12)
    assert at_floor(r) and accuracy(r, "final_state_error") == 6e-12
    above = run("a", final=1e-10, floor=6e-12)
    assert not at_floor(above) and accuracy(above, "final_state_error") == 1e-10
    # Without a recorded floor (an exact reference, an older store) only round-off is.
    assert not at_floor(run("a", final=1e-15))
    assert accuracy(run("a", final=1e-15), "final_state_error") == 1e-12  # the plateau


def test_the_reference_error_does_not_decide_the_cost_at_matched_accuracy():
    # b's smaller error lies below the floor, so a and b are equally accurate as far as the
    # reference can tell; a is cheaper and wins. Unmasked, the target would be 3e-12 and a
    # would count as not reaching it.
    runs = frame(run("a", h=0.01, wall=1.0, spread=(0.05, 0.05), final=5e-12, floor=6e-12),
                 run("b", h=0.01, wall=2.0, spread=(0.05, 0.05), final=1e-13, floor=6e-12),
                 run("c", h=0.01, wall=0.5, spread=(0.05, 0.05), final=1e-6, floor=6e-12))
    win = cost_winner(runs)
    assert win.integrator == "a"
    assert "≤ 6e-12" in win.text and "not reached by c" in win.text


def test_the_headline_figure_places_each_method_by_its_cost_at_matched_accuracy():
    # Best accuracies 1e-8 (a), 1e-6 (b), 1e-3 (c): matched at their median, 1e-6. a's
    # cheapest run reaching it is its coarse one; b reaches it only at its finest; c never
    # does and is placed at its most accurate run. Drift and energy are those of each
    # method's run at the longest horizon (b's failed there).
    runs = frame(run("a", h=0.1, wall=1.0, final=1e-6, pos=1e-9),
                 run("a", h=0.01, wall=5.0, final=1e-8, pos=1e-10),
                 run("b", h=0.1, wall=0.5, final=1e-4, pos=1e-5),
                 run("b", h=0.01, wall=3.0, final=1e-6, pos=1e-6),
                 run("c", rtol=1e-3, wall=0.1, final=1e-2, pos=1e-3),
                 run("c", rtol=1e-4, wall=0.2, final=1e-3, pos=1e-4),
                 run("a", h=0.1, wall=90.0, t_end=100.0, pos=1e-12, energy=1e-7,
                     energy_growth="bounded (p = 0.01)", pos_growth="bounded (round-off)"),
                 run("b", h=0.1, status="failed", wall=None, t_end=100.0, pos=1e-2))
    got = {st.integrator: st for st in standings(runs)}
    assert (got["a"].wall_s, got["a"].n_f_evals, got["a"].reached) == (1.0, 100, True)
    assert (got["b"].wall_s, got["b"].reached) == (3.0, True)
    assert (got["c"].wall_s, got["c"].reached) == (0.2, False)
    assert got["a"].drift == 1e-12 and got["a"].energy == 1e-7 and got["a"].finished
    assert (got["a"].drift_class, got["a"].energy_class) == ("bounded", "bounded")
    assert got["b"].drift == 1e-2 and not got["b"].finished
    assert got["c"].drift == 1e-3  # one horizon: its coarsest run (rtol 1e-3) represents it


# --------------------------------------------------------------------------- targets

def test_targets_name_the_cheapest_run_and_who_never_reaches():
    runs = frame(run("a", h=0.1, wall=1.0, evals=100, final=1e-5, pos=1e-15),
                 run("a", h=0.01, wall=10.0, evals=1000, final=1e-9, pos=1e-15),
                 run("b", rtol=1e-6, wall=2.0, evals=50, final=1e-7, pos=1e-9),
                 run("c", h=0.1, status="failed", wall=None, evals=None))
    rows = {(t.column, t.target): t for t in targets(runs, (1e-4, 1e-8, 1e-12))}
    t4 = rows["final_state_error", 1e-4]
    assert t4.by_wall.row["integrator"] == "a" and t4.by_wall.winner  # 1 s vs 2 s, no spread
    assert t4.by_evals.row["integrator"] == "b"  # 50 evaluations against 100
    assert t4.missed == ["c (no finished run)"]
    t8 = rows["final_state_error", 1e-8]
    assert t8.by_wall.row["h"] == 0.01 and t8.missed == ["b (best 1e-07)", "c (no finished run)"]
    t12 = rows["final_state_error", 1e-12]
    assert t12.by_wall.row is None and "a (best 1e-09)" in t12.missed
    g8 = rows["max_pos_residual", 1e-8]
    assert g8.by_wall.row["integrator"] == "a" and "b (best 1e-09)" not in g8.missed
    # No energy was measured: no energy rows.
    assert not any(c == "rel_energy_error" for c, _ in rows)


def test_a_target_below_the_round_off_plateau_cannot_be_checked():
    runs = frame(run("a", h=0.1, final=1e-15), run("b", h=0.1, final=1e-6))
    rows = {t.target: t for t in targets(runs, (1e-4, 1e-14))
            if t.column == "final_state_error"}
    assert rows[1e-4].missed == [] and "round-off plateau" in rows[1e-14].note


def test_a_target_below_the_reference_floor_cannot_be_checked():
    runs = frame(run("a", h=0.1, final=1e-12, floor=2e-9))
    rows = {t.target: t for t in targets(runs, (1e-4, 1e-12))
            if t.column == "final_state_error"}
    assert rows[1e-4].by_wall.row["integrator"] == "a"
    assert rows[1e-12].by_wall is None and "cannot be checked" in rows[1e-12].note


# --------------------------------------------------------------------------- fits

def test_points_at_the_floor_are_left_out_of_the_fit():
    # Sixth order down to the floor 2e-9, then the reference's own error: 1.4e-9.
    h = np.array([8e-4, 4e-4, 2e-4, 1e-4, 5e-5])
    err = np.maximum(1.92e-4 * (h / 8e-4) ** 6, 1.4e-9)
    c = fit("lobatto3ab4", h, err, 6.0, plateau=1e-12, floor=2e-9)
    assert c.threshold == pytest.approx(2e-8)  # a decade above the floor
    assert list(c.h[c.fitted]) == [2e-4, 4e-4, 8e-4]  # the three points above 2e-8
    assert c.left_out[:2] == ["reference floor"] * 2
    assert c.order == pytest.approx(6.0, abs=1e-9)
    # Without the floor, the asymptotic range alone still leaves the two out, for the
    # bend they put in the pairwise orders (5.07, then 0).
    unmasked = fit("lobatto3ab4", h, err, 6.0, plateau=1e-12)
    assert unmasked.left_out[:2] == ["past the asymptotic range"] * 2


def test_too_few_points_above_the_floor_give_no_order():
    h = np.array([2e-3, 1e-3, 5e-4])
    c = fit("lobatto3ab4", h, np.array([6e-11, 5.2e-12, 4.8e-12]), 6.0, 1e-12, 6e-12)
    assert c.n_fit == 0 and math.isnan(c.order)


def geometric(h0, orders, e0=1.0):
    """Step sizes halving from ``h0`` and errors whose pairwise orders are ``orders``."""
    h = h0 / 2.0 ** np.arange(len(orders) + 1)
    return h, e0 / 2.0 ** np.concatenate([[0.0], np.cumsum(orders)])


def test_a_pre_asymptotic_point_is_left_out_and_named():
    # The coarsest pair has order 3.10; the finer ones settle at 2: the fit through all four
    # would say 2.3.
    h, err = geometric(0.04, [3.10, 1.95, 2.02])
    c = fit("rattle", h, err, 2.0, 1e-12)
    assert c.pairwise == pytest.approx([3.10, 1.95, 2.02])
    assert list(c.h[c.fitted]) == [0.005, 0.01, 0.02]
    assert c.left_out == ["", "", "", "pre-asymptotic"]  # h ascending
    assert c.order == pytest.approx(1.985, abs=1e-9)


def test_two_pairwise_orders_that_disagree_give_no_order():
    # A pendulum's RATTLE orders 3.10 then 1.89: a fit through the three would say 2.5.
    h, err = geometric(0.04, [3.10, 1.89])
    c = fit("rattle", h, err, 2.0, 1e-12)
    assert math.isnan(c.order) and c.n_fit == 0
    assert set(c.left_out) == {"pairwise orders disagree"}
    assert c.pairwise == pytest.approx([3.10, 1.89])


def test_two_points_give_a_pairwise_order_but_no_fit():
    h, err = geometric(0.02, [2.0])
    c = fit("rattle", h, err, 2.0, 1e-12)
    assert math.isnan(c.order) and c.left_out == ["too few points"] * 2
    assert c.pairwise == pytest.approx([2.0])


def test_points_past_the_range_are_left_out_on_the_fine_side():
    # Fourth order, then an error that levels off above round-off: the finest pair is out.
    h, err = geometric(0.1, [4.0, 4.1, 4.0, 1.2])
    c = fit("lobatto3ab3", h, err, 4.0, 1e-14)
    assert c.left_out[0] == "past the asymptotic range" and c.n_fit == 4
    assert c.order == pytest.approx(4.04, abs=1e-9)  # least squares over the four


def test_of_equally_long_ranges_the_finest_is_fitted():
    h, err = geometric(0.1, [2.0, 2.1, 3.0, 3.05])
    c = fit("m", h, err, 3.0, 1e-14)
    assert list(c.h[c.fitted]) == pytest.approx([0.00625, 0.0125, 0.025])
    assert c.left_out[3:] == ["pre-asymptotic"] * 2


def test_an_exact_zero_is_round_off_and_a_missing_error_says_so():
    c = fit("m", [0.1, 0.05, 0.025], [1e-3, 0.0, math.nan], 2.0, 1e-12)
    assert c.left_out == ["no error", "round-off", "too few points"]


def test_convergence_reads_the_floor_from_the_runs():
    rows = [run("m", h=h, final=max(1e-3 * h ** 4, 1e-11), floor=1e-11, order=4, run_id=i)
            for i, h in enumerate((0.4, 0.2, 0.1, 0.05, 0.0125))]
    (c,), basis = convergence(frame(*rows))
    assert "accurate to 1e-11" in basis
    assert c.n_fit == 4 and c.order == pytest.approx(4.0, abs=1e-9)


# --------------------------------------------------------------------------- history

def commit_runs(commit, started, **metrics):
    rows = []
    for integrator, (status, pos, sensitive) in metrics.items():
        rows.append(run(integrator, h=0.1, status=status, pos=pos, final=None,
                        commit=commit, session_started=started, dirty=0, sensitive=sensitive))
    return rows


def test_history_marks_what_the_gate_would_fail():
    runs = frame(*commit_runs("aaaa", 1.0, a=("ok", 1e-10, 0), b=("ok", 1e-10, 0),
                              c=("ok", 1e-10, 1), d=("ok", 1e-10, 0)),
                 *commit_runs("bbbb", 2.0, a=("ok", 1e-8, 0), b=("ok", 3e-10, 0),
                              c=("ok", 1e-6, 1), d=("failed", None, 0)))
    hist = history(runs)
    assert list(hist.commits["label"]) == ["aaaa", "bbbb"]
    found = {(i.split(" / ")[1], m) for i, m, _, _, _ in hist.regressions}
    # a: 100x worse |g| and |G v|; b: 3x, within the gate's factor 4; c: chaotic, never
    # gated; d: no longer finishes.
    assert found == {("a", "max_pos_residual"), ("a", "max_vel_residual"), ("d", "status")}
    assert hist.values["max_pos_residual"].loc["p / a / h=0.1 / t_end=1", "bbbb"] == 1e-8


def test_history_marks_drift_classes_invariants_and_earlier_failures():
    # What the gate fails beyond the five metrics: a drift class that grows faster, a
    # declared invariant 100x worse, and a failed run that now fails earlier.
    def two(commit, started, growth, invariant, fail_step):
        return [run("e", h=0.1, pos=1e-12, commit=commit, session_started=started, dirty=0,
                    pos_growth=growth),
                run("f", h=0.1, pos=1e-12, commit=commit, session_started=started, dirty=0,
                    invariant_errors=f'{{"momentum": {invariant}}}'),
                run("g", h=0.1, status="failed", commit=commit, session_started=started,
                    dirty=0, fail_step=fail_step)]

    hist = history(frame(*two("aaaa", 1.0, "bounded (round-off)", 1e-10, 50),
                         *two("bbbb", 2.0, "linear (p = 1.00)", 1e-8, 20)))
    found = {(i.split(" / ")[1], m) for i, m, _, _, _ in hist.regressions}
    assert found == {("e", "pos_growth"), ("f", "inv:momentum"), ("g", "fail_step")}
