"""Growth classification of drift series (docs/design.md, section 5).

A run keeps per-window maxima ``y_k`` of ``|H - H0|`` and of ``|g|`` at window end times
``t_k``. Their growth is judged on the running envelope ``E_k = max_{j <= k} y_j`` (an
oscillating but bounded error has a flat envelope) over the fitted range
``t - t0 >= FIT_START * (t_end - t0)``, which skips the initial transient, with two
least-squares fits:

- power law: ``log E = log C + p log(t - t0)``, exponent ``p``;
- exponential: ``log E = a + lam (t - t0)``, rate ``lam``.

Classes: ``exponential`` when the exponential fit has the smaller residual and the
envelope grows by more than :data:`EXP_MIN_GROWTH` over the fitted range (an exponential
seen through a power law has a steep but curved log-log graph, so the exponent alone does
not tell); otherwise by the exponent: ``bounded`` (``p < 0.35``, or the whole series at or
below the round-off ``floor``), ``linear`` (``0.35 <= p < 1.5``; this includes the
``p = 1/2`` random walk of accumulated round-off), ``quadratic`` (``1.5 <= p < 2.5``) and
``superquadratic`` (a faster power law). ``indeterminate`` when fewer than
:data:`MIN_POINTS` finite windows lie in the fitted range.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: Fraction of the horizon skipped before fitting (the transient of the first periods).
FIT_START = 0.1
#: Windows needed in the fitted range for a fit to mean anything.
MIN_POINTS = 8
#: Exponent thresholds between bounded | linear | quadratic | faster.
BOUNDED_BELOW, LINEAR_BELOW, QUADRATIC_BELOW = 0.35, 1.5, 2.5
#: Growth of the envelope over the fitted range that an exponential class needs.
EXP_MIN_GROWTH = 20.0

CLASSES = ("bounded", "linear", "quadratic", "superquadratic", "exponential", "indeterminate")
#: Classes of growth from the mildest to the fastest (``indeterminate`` is not among them).
SEVERITY = ("bounded", "linear", "quadratic", "superquadratic", "exponential")
#: Round-off floors of the fits of a run's series: ``|g|`` (absolute) and energy (relative
#: to the case's energy scale); a few hundred ulps of O(1) quantities.
POS_FLOOR = 1e-13
ENERGY_REL_FLOOR = 1e-13


@dataclass(frozen=True)
class Growth:
    """A classified series.

    ``exponent`` is the power-law exponent ``p`` (``nan`` when indeterminate); ``rate`` the
    exponential rate ``lam`` (per unit time); ``level`` the envelope at the end.
    """

    kind: str
    exponent: float
    rate: float
    level: float
    n_points: int

    def label(self) -> str:
        """Short text: the class with its fitted exponent (or rate, for exponential)."""
        if self.kind == "indeterminate":
            return f"indeterminate ({self.n_points} windows)"
        # Adding 0.0 turns a -0.0 into 0.0, so a flat fit does not print as "p = -0.00".
        p = round(self.exponent, 2) + 0.0
        if self.kind == "exponential":
            return f"exponential (rate {self.rate:.3g}, p = {p:.2f})"
        if self.kind == "bounded" and not math.isfinite(self.exponent):
            return "bounded (round-off)"
        return f"{self.kind} (p = {p:.2f})"


def kind_of(label: str | None) -> str | None:
    """The class of a :meth:`Growth.label` text (its first word), or None."""
    return label.split(" ", 1)[0] if label else None


def classify(t, y, t0: float = 0.0, floor: float = 0.0) -> Growth:
    """Classify the growth of the windowed maxima ``y`` at window end times ``t``.

    Parameters
    ----------
    t, y : array_like
        Window end times and per-window maxima (non-finite entries are dropped).
    t0 : float
        Start of the horizon: growth is measured in ``t - t0``.
    floor : float
        Round-off level: a series that never exceeds it is ``bounded``, and values below it
        are raised to it before the logarithm (a zero error has no logarithm).
    """
    t = np.asarray(t, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    keep = np.isfinite(t) & np.isfinite(y) & (t > t0)
    t, y = t[keep] - t0, y[keep]
    if len(t) == 0:
        return Growth("indeterminate", math.nan, math.nan, math.nan, 0)
    envelope = np.maximum.accumulate(np.abs(y))
    level = float(envelope[-1])
    tiny = max(floor, np.finfo(float).tiny)
    if level <= floor:
        return Growth("bounded", math.nan, math.nan, level, len(t))
    fitted = t >= FIT_START * t[-1]
    tf, ef = t[fitted], np.log(np.maximum(envelope[fitted], tiny))
    if len(tf) < MIN_POINTS or tf[0] == tf[-1]:
        return Growth("indeterminate", math.nan, math.nan, level, int(len(tf)))
    (p, c), res_pow = _line(np.log(tf), ef)
    (lam, a), res_exp = _line(tf, ef)
    if res_exp < res_pow and ef[-1] - ef[0] > math.log(EXP_MIN_GROWTH):
        kind = "exponential"
    elif p < BOUNDED_BELOW:
        kind = "bounded"
    elif p < LINEAR_BELOW:
        kind = "linear"
    elif p < QUADRATIC_BELOW:
        kind = "quadratic"
    else:
        kind = "superquadratic"
    return Growth(kind, float(p), float(lam), level, int(len(tf)))


def _line(x: np.ndarray, y: np.ndarray) -> tuple[tuple[float, float], float]:
    """Least-squares line ``y = slope x + intercept``; returns it and the residual sum."""
    design = np.stack([x, np.ones_like(x)], axis=1)
    coef, *_ = np.linalg.lstsq(design, y, rcond=None)
    residual = float(np.sum((design @ coef - y) ** 2))
    return (float(coef[0]), float(coef[1])), residual


def fit_order(h, err, floor: float = 0.0) -> tuple[float, np.ndarray]:
    """Observed convergence order: slope of ``log err`` against ``log h``.

    Points at or below ``floor`` (round-off, where the error no longer follows ``h^p``)
    and non-finite ones are left out. Returns ``(order, mask of the points used)``; the
    order is ``nan`` with fewer than two distinct step sizes.
    """
    h = np.asarray(h, dtype=np.float64)
    err = np.asarray(err, dtype=np.float64)
    keep = np.isfinite(h) & np.isfinite(err) & (h > 0) & (err > floor) & (err > 0)
    if len(np.unique(h[keep])) < 2:
        return math.nan, keep
    (slope, _), _ = _line(np.log(h[keep]), np.log(err[keep]))
    return float(slope), keep
