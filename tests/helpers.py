"""Shared helpers of the problem tests: one run, and its error against the reference."""

import numpy as np

import integrators
import problems
from integrators import Grid


def solve(spec, key, t_end=None, **options):
    """Run integrator ``key`` with ``options`` on problem ``spec``; it must succeed."""
    case = problems.make(spec)
    if t_end is not None:
        case = case.with_t_end(t_end)
    traj = integrators.make(key, **options).prepare(case, Grid(case.t0, case.t_end))()
    assert traj.status == "ok", traj.message
    return case, traj


def state_error(case, traj):
    """Max-norm error of the final ``(q, v)`` against the case's reference."""
    q_ref, v_ref = case.reference.solution(traj.t_final)
    return max(np.max(np.abs(traj.q_final - q_ref)), np.max(np.abs(traj.v_final - v_ref)))
