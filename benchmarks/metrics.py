"""Accuracy metrics of a finished run, as the design notes (section 5) define them.

Pure functions of a :class:`~integrators.base.Trajectory` and its case: nothing here runs
inside a time loop.
"""

from __future__ import annotations

import math

import numpy as np

from integrators.base import Trajectory
from problems.case import Case


def _max(x: np.ndarray) -> float:
    return float(np.max(x)) if len(x) else math.nan


def reference_error(case: Case, traj: Trajectory) -> tuple[float, float]:
    """Final-state error and significant correct digits against the case's reference.

    ``final_state_error`` is the max-norm of ``y - y_ref`` on the scored components of
    ``y = (q, v)`` at ``t_final``; ``scd = -log10(max_i |y_i - y_ref,i| / |y_ref,i|)`` on the
    same components (the IVP Test Set's definition; a component whose reference is exactly
    zero is scored by its absolute error). NaN where there is no reference at ``t_final``.
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


def summarize(case: Case, traj: Trajectory) -> dict[str, float]:
    """The accuracy columns of ``runs.csv`` for one run.

    - ``max_pos_residual``: max over recorded steps of ``||g(q_n, t_n)||_inf``;
    - ``max_vel_residual``: max over recorded steps of ``||G v_n + g_t||_inf``;
    - ``max_energy_error``: max of ``|H_n - H_0|``, and ``rel_energy_error`` that divided by
      the case's ``energy_scale``; NaN where energy is not conserved;
    - ``max_inv:NAME``: max error of each declared invariant;
    - ``final_state_error`` and ``scd`` (see :func:`reference_error`), and
      ``reference_floor``, the reference's own accuracy
      (:attr:`~problems.case.Reference.floor`), so that the report can tell a method's
      error from its reference's; NaN where there is no reference at ``t_final``.
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
    out.update({f"max_{k}": _max(v) for k, v in w.items() if k.startswith("inv:")})
    out["final_state_error"], out["scd"] = reference_error(case, traj)
    out["reference_floor"] = case.reference.floor \
        if not math.isnan(out["final_state_error"]) else math.nan
    return out
