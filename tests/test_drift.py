"""Growth classification of drift series on synthetic series with known growth."""

import math

import numpy as np
import pytest

from benchmarks.drift import classify, fit_order

# 1000 windows over [0, 1000], as a run's default recording grid.
T = np.linspace(1.0, 1000.0, 1000)
RNG = np.random.default_rng(7)


def noisy(y, level=0.3):
    """Multiplicative noise of +-30 %: window maxima of real runs scatter like this."""
    return y * (1.0 + level * RNG.random(len(y)))


@pytest.mark.parametrize("name, y, kind, exponent", [
    ("bounded oscillation", 1e-5 * (1.1 + np.sin(0.7 * T)), "bounded", 0.0),
    ("linear", noisy(3e-9 * T), "linear", 1.0),
    ("quadratic", noisy(2e-12 * T ** 2), "quadratic", 2.0),
    ("cubic", 1e-15 * T ** 3, "superquadratic", 3.0),
])
def test_power_laws_are_classified_with_their_exponent(name, y, kind, exponent):
    g = classify(T, y, floor=1e-16)
    assert g.kind == kind, name
    # The envelope of a +-30 % noise moves the fitted exponent by a few hundredths.
    assert g.exponent == pytest.approx(exponent, abs=0.1), name


def test_exponential_growth_is_told_from_a_power_law():
    rate = 0.01
    g = classify(T, noisy(1e-14 * np.exp(rate * T), 0.1), floor=1e-16)
    assert g.kind == "exponential"
    # A +-10 % scatter on e^{0.01 t} over 900 time units moves the fitted rate by < 2 %.
    assert g.rate == pytest.approx(rate, rel=0.02)


def test_round_off_level_is_bounded_whatever_its_shape():
    g = classify(T, 1e-16 * np.sqrt(T) / np.sqrt(T[-1]), floor=1e-13)
    assert g.kind == "bounded" and "round-off" in g.label()


def test_random_walk_of_round_off_above_the_floor_grows_like_sqrt_t():
    g = classify(T, noisy(1e-12 * np.sqrt(T)), floor=1e-15)
    assert g.kind == "linear"
    assert g.exponent == pytest.approx(0.5, abs=0.1)


def test_short_or_empty_series_are_indeterminate():
    assert classify(T[:5], T[:5]).kind == "indeterminate"
    assert classify([], []).kind == "indeterminate"
    assert classify([1.0, 2.0], [np.nan, np.nan]).kind == "indeterminate"


def test_growth_is_measured_from_t0():
    """The same linear drift on a horizon that starts at t0 = 500 is still linear."""
    t = 500.0 + T
    g = classify(t, noisy(3e-9 * T), t0=500.0, floor=1e-16)
    assert g.kind == "linear"


def test_fit_order_recovers_the_slope_and_skips_round_off():
    h = np.array([0.1, 0.05, 0.025, 0.0125, 0.00625])
    err = 3.0 * h ** 4
    err[-1] = 1e-16  # at round-off: must not bend the fit
    order, used = fit_order(h, err, floor=1e-12)
    assert used.tolist() == [True, True, True, True, False]
    assert order == pytest.approx(4.0, abs=1e-9)  # exact power law: exact slope
    assert math.isnan(fit_order([0.1], [1e-3])[0])
