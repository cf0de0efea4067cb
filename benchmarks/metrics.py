"""Accuracy metrics of a finished run, as docs/design.md (section 5) defines them.

Pure functions of a :class:`~integrators.base.Trajectory` and its case: nothing here runs
inside a time loop.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from benchmarks import columns
from benchmarks.balance import balance
from integrators.base import Status, Trajectory
from problems.case import Case


def _max(x: np.ndarray) -> float:
    return float(np.max(x)) if len(x) else math.nan


def reference_error(case: Case, traj: Trajectory) -> tuple[float, float]:
    """Final-state error and significant correct digits against the case's reference.

    ``final_state_error`` is the max-norm of ``y - y_ref`` on the scored components of
    ``y = (q, v)`` at ``t_final``; ``scd = -log10(max_i |y_i - y_ref,i| / |y_ref,i|)`` on the
    same components (the IVP Test Set's definition; a component whose reference is exactly
    zero is scored by its absolute error). NaN where there is no reference at ``t_final``
    (none at all, none at that time, or ``t_final`` outside the reference's span: a
    reference evaluated past the span it was computed on extrapolates, and its error would
    be the reference's, not the run's; :func:`unscored` says why).
    """
    ref = case.reference
    if ref is None or not ref.available_at(traj.t_final):
        return math.nan, math.nan
    q_ref, v_ref = ref.solution(traj.t_final)
    y = np.concatenate([traj.q_final, traj.v_final])[list(ref.scored)]
    y_ref = np.concatenate([q_ref, v_ref])[list(ref.scored)]
    err = np.abs(y - y_ref)
    scale = np.where(y_ref != 0.0, np.abs(y_ref), 1.0)
    rel = float(np.max(err / scale))
    scd = -math.log10(rel) if rel > 0 else math.inf
    return float(np.max(err)), scd


def unscored(case: Case, traj: Trajectory) -> str:
    """Why a run that finished has no final error although its case has a reference: the
    run ends outside the reference's :attr:`~problems.case.Reference.span`, or at none of
    its :attr:`~problems.case.Reference.times`; ``""`` where the run is scored, has no
    reference, or did not finish (its message says why it stopped)."""
    ref, t = case.reference, traj.t_final
    if ref is None or traj.status != Status.OK or ref.available_at(t):
        return ""
    if ref.span is not None and not replace(ref, times=None).available_at(t):
        return (f"no final error: the run ends at t = {t:.6g}, outside the span "
                f"[{ref.span[0]:.6g}, {ref.span[1]:.6g}] its reference is valid on")
    shown = ", ".join(f"{s:.6g}" for s in ref.times[:5]) + (", ..." if len(ref.times) > 5
                                                           else "")
    return f"no final error: the run ends at t = {t:.6g}; the reference exists only at t = {shown}"


def _balance(case: Case, traj: Trajectory) -> dict[str, float]:
    """The energy balance columns of :func:`summarize` (NaN for a conservative system)."""
    nan = dict(max_balance_error=math.nan, rel_balance_error=math.nan, balance_floor=math.nan)
    if case.mech.has_energy:
        return nan
    try:
        _, error, floor = balance(case.mech, traj.samples)
    except np.linalg.LinAlgError:  # samples that share a time: no quadrature through them
        return nan
    # A run that blew up has its balance up to its last finite state, and its status says
    # so; a finished run has all of it or none.
    if np.isnan(error).all() or (traj.status == Status.OK and np.isnan(error).any()):
        return nan
    worst = float(np.nanmax(error))
    return dict(max_balance_error=worst, rel_balance_error=worst / case.energy_scale,
                balance_floor=float(np.nanmax(floor)) / case.energy_scale)


def summarize(case: Case, traj: Trajectory) -> dict[str, float]:
    """The accuracy columns of ``runs.csv`` for one run.

    - ``max_pos_residual``: max over recorded steps of ``||g(q_n, t_n)||_inf``;
    - ``max_vel_residual``: max over recorded steps of ``||G v_n + g_t||_inf``;
    - ``max_energy_error``: max of ``|H_n - H_0|``, and ``rel_energy_error`` that divided by
      the case's ``energy_scale``; NaN where energy is not conserved;
    - ``max_balance_error``: where it is not (applied forces, moving constraints), the max
      over the sampled states of the energy balance's error ``|H - H_0 - W|``, ``W`` the
      work done on the system, and ``rel_balance_error`` that divided by
      ``energy_scale``; ``balance_floor``, on the same scale, the error estimate of the
      quadrature that gives ``W`` (:mod:`benchmarks.balance`); NaN where energy is
      conserved;
    - ``max_inv:NAME``: max error of each declared invariant;
    - ``final_state_error`` and ``scd`` (see :func:`reference_error`), and
      ``reference_floor``, the reference's own accuracy
      (:attr:`~problems.case.Reference.floor`), so that the report can tell a method's
      error from its reference's; NaN where there is no reference at ``t_final``;
    - every other declared column's ``compute(case, traj)`` (:mod:`benchmarks.columns`).
    """
    w = traj.windows
    has_energy = case.mech.has_energy
    e = _max(w["energy"]) if has_energy else math.nan
    out = {
        "max_pos_residual": _max(w["pos"]),
        "max_vel_residual": _max(w["vel"]),
        "max_energy_error": e,
        "rel_energy_error": e / case.energy_scale if has_energy else math.nan,
    }
    out.update(_balance(case, traj))
    out.update({f"max_{k}": _max(v) for k, v in w.items() if k.startswith("inv:")})
    out["final_state_error"], out["scd"] = reference_error(case, traj)
    out["reference_floor"] = case.reference.floor \
        if not math.isnan(out["final_state_error"]) else math.nan
    out.update({c.name: c.compute(case, traj) for c in columns.computed()})
    return out
