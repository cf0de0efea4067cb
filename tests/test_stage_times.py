"""Step and stage times: a rheonomic constraint holds at every step end to the round-off of
``g``, for every fixed-step family, however far ``t`` lies from 0."""

from functools import lru_cache

import jax.numpy as jnp
import numpy as np
import pytest

import integrators
from integrators import Grid
from problems import System, make_case

#: The pendulum's pivot slides along x as ``A sin(Omega t)``; the run starts at ``T0``,
#: where an ulp of ``t`` (1.1e-13) times ``|g_t|`` (up to ``2 L A Omega = 20``) is far
#: above the round-off of ``g`` (a few 1e-16).
A, OMEGA, LENGTH, T0 = 1.0, 10.0, 1.0, 1000.0

#: The families that impose ``g = 0`` at every step end, and which of them impose
#: ``G v + g_t = 0`` too.
FAMILIES = {"rattle": True, "lobatto3ab2": True, "lobatto3ab3": True, "genalpha": False,
            "genalpha-ggl": True, "hht": False}


@lru_cache(maxsize=None)
def driven_pendulum():
    """A unit point mass on a rod of length ``LENGTH`` whose pivot is driven along x, under
    gravity, started hanging below the pivot and moving with it at ``T0``."""
    def pivot(t):
        return A * jnp.sin(OMEGA * t)

    system = System(
        n=2, m=1, mass=np.ones(2), rheonomic=True,
        potential=lambda q: 9.81 * q[1],
        constraints=lambda q, t: jnp.array([(q[0] - pivot(t)) ** 2 + q[1] ** 2
                                            - LENGTH ** 2]),
    )
    q0 = np.array([A * np.sin(OMEGA * T0), -LENGTH])
    v0 = np.array([A * OMEGA * np.cos(OMEGA * T0), 0.0])
    return make_case("driven-pendulum", system, q0, v0, (T0, T0 + 0.2), {},
                     energy_scale=1.0)


@pytest.mark.parametrize("key", FAMILIES)
def test_rheonomic_residual_at_round_off(key):
    case = driven_pendulum()
    traj = integrators.make(key, h=1e-3).prepare(case, Grid(case.t0, case.t_end))()
    assert traj.status.name == "OK", traj.message
    # Measured at t0 + (k + 1) h after a step that imposed its end conditions at
    # (t0 + k h) + h, every family reads |g| = 2.3e-12 and |G v + g_t| = 3.8e-11 here; the round-off of g is a few 1e-16,
    # of G v + g_t (|v| up to 10) a few 1e-15.
    assert np.max(traj.windows["pos"]) <= 1e-14, np.max(traj.windows["pos"])
    if FAMILIES[key]:
        assert np.max(traj.windows["vel"]) <= 1e-13, np.max(traj.windows["vel"])
