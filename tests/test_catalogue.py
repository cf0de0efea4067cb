"""The integrator catalogue: every registered method declares its traits, and each trait
holds when the method runs.

The tests are parametrised over :func:`integrators.keys`, so a new method is covered as
soon as it is registered. They run on the pendulum, whose exact solution (elliptic
functions) is the reference, so no check depends on another integrator.
"""

import math

import numpy as np
import pytest

import integrators
from integrators import Integrator
from helpers import solve, state_error

KEYS = integrators.keys()


@pytest.mark.parametrize("key", KEYS)
def test_traits_are_declared(key):
    integ = integrators.make(key)
    assert isinstance(integ.family, str) and integ.family, f"{key}: no family"
    assert isinstance(integ.adaptive, bool) and isinstance(integ.symplectic, bool)
    assert set(integ.enforces) <= set(Integrator.LEVELS), (key, integ.enforces)
    order = integ.nominal_order
    assert order is None or (isinstance(order, int) and order >= 1), (key, order)
    # A fixed-step method has a nominal order (convergence fits need it) and a step size;
    # an adaptive one has tolerances instead.
    if integ.adaptive:
        assert hasattr(integ, "rtol") and not hasattr(integ, "h"), key
    else:
        assert order is not None and hasattr(integ, "h"), key
    # Symplecticity is a property of a fixed-step map.
    assert not (integ.symplectic and integ.adaptive), key


@pytest.mark.parametrize("key", KEYS)
def test_enforced_levels_hold_and_others_drift(key):
    """An enforced level stays at the solver's tolerance over the horizon; a level that is
    not enforced moves off the manifold by more than round-off (otherwise the trait would
    undersell the method). Adaptive methods run at ``rtol = 1e-10``, fixed-step ones at
    their default step, whose Newton tolerance is far below the bound."""
    integ = integrators.make(key)
    _, traj = solve("pendulum", key, 10.0, **({"rtol": 1e-10} if integ.adaptive else {}))
    for level, series in (("position", "pos"), ("velocity", "vel")):
        worst = float(np.max(traj.windows[series]))
        if level in integ.enforces:
            assert worst <= 1e-8, (key, level, worst)
        else:
            assert worst > 1e-13, (key, level, worst)


@pytest.mark.parametrize("key", [k for k in KEYS if integrators.make(k).symplectic])
def test_symplectic_methods_keep_energy_bounded(key):
    """Over 50 periods the energy error of a symplectic method oscillates without growth:
    the last window's maximum is no larger than the first tenth's (up to round-off)."""
    _, traj = solve("pendulum", key, 400.0, h=0.05)
    energy = traj.windows["energy"]
    tenth = len(energy) // 10
    first, last = float(np.max(energy[:tenth])), float(np.max(energy[-tenth:]))
    assert last <= 1.5 * first + 1e-13, (key, first, last)


@pytest.mark.parametrize("key", [k for k in KEYS if not integrators.make(k).adaptive])
def test_nominal_order_is_observed(key):
    """Halving ``h`` divides the final error against the exact solution by about
    ``2**nominal_order`` (step sizes chosen per order so both errors lie well above
    round-off and inside the asymptotic range)."""
    order = integrators.make(key).nominal_order
    h = {2: 0.01, 4: 0.02, 6: 0.1}.get(order, 0.02)
    errors = [state_error(*solve("pendulum", key, 2.0, h=step)) for step in (h, h / 2)]
    observed = math.log2(errors[0] / errors[1])
    assert abs(observed - order) < 0.4, (key, errors, observed)
