"""Shared helpers of the problem tests: one run, its error against the reference, and the
receiver ring state built from the reduced model's radii."""

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


def embed(samples, N):
    """The ring state whose every point sits on its ray at the reduced model's radii."""
    angles = np.pi * np.arange(2 * N) / N
    inner = np.arange(2 * N) % 2 == 0
    radius = np.where(inner, samples["q"][:, [1]], samples["q"][:, [0]])
    rate = np.where(inner, samples["v"][:, [1]], samples["v"][:, [0]])
    ray = np.stack([np.cos(angles), np.sin(angles)], axis=1)
    return radius[..., None] * ray, rate[..., None] * ray
