"""Shared helpers of the tests: one run, its error against the reference, the receiver
ring state built from the reduced model's radii, and the yardstick tests' marker and row
keys."""

import shutil

import numpy as np
import pytest

import integrators
import problems
from integrators import Grid

#: Skips a test that compiles a C yardstick where no C compiler is on ``PATH``.
needs_cc = pytest.mark.skipif(shutil.which("cc") is None and shutil.which("gcc") is None,
                              reason="no C compiler (cc or gcc) on PATH")

#: The keys of the ``ida`` comparison's rows, which every comparison's rows carry.
IDA_KEYS = {"family", "driver", "problem", "yardstick", "t_end", "rtol", "atol", "steps",
            "yardstick_steps", "us_per_step", "yardstick_us_per_step", "ratio_per_step",
            "ratio_per_solve", "steps_ratio", "final_q_difference", "final_v_difference",
            "multipliers"}


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
