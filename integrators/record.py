"""Drift bookkeeping for steps that reach the host in batches (adaptive methods).

The compiled fixed-step loop (:mod:`integrators.loop`) keeps its windows by step count
because it knows the number of steps in advance. An adaptive method does not, so the layout
here is by time over the horizon ``[t0, t_end]`` of length ``T``:

- window ``w`` (of ``W``) holds the points with ``t0 + w T/W < t <= t0 + (w+1) T/W``
  (``t0`` itself in window 0) and keeps the maxima of ``|g|``, ``|G v + g_t|``,
  ``|H - H0|`` and of each declared invariant's error; windows that no point reached are
  dropped from the result;
- sample slot ``j`` (of ``S``) keeps the first point with ``t >= t0 + j T/(S-1)``, so at
  most ``S`` states are kept whatever the number of steps.

Points arrive one at a time (IDA's one-step mode) or a batch at a time (Radau IIA's chunked
compiled loop); they are measured in batches by one compiled, vectorised call and reduced
at once, so memory is one batch plus the windows and samples. The Baumgarte methods'
compiled loop, a single run's and an ensemble's alike, keeps the same windows and samples
inside itself (:func:`tracker`), with the same index arithmetic (:func:`window_and_slot`),
and its trajectories are assembled by the same functions (:func:`series`, :func:`kept`,
:func:`ended`): an ensemble's lanes cannot hand their steps to the host one lane at a time,
and a large system's steps would reach it a few per chunk (two at rigid-chain:N=16384,
whose run then took about a sixth longer than with the record kept in the loop).
"""

from __future__ import annotations

import math
from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from integrators.base import Grid, Status, Trajectory
from linalg.compiled import compile_lifted
from problems.mechanics import Mechanics

#: Host memory one batch of points may take (bytes); fixes the batch length.
BATCH_BYTES = 1 << 22

#: Margin of :func:`window_and_slot` (in windows or sample spacings): far above the
#: rounding of a step's time, far below a step.
BOUNDARY = 1e-9


def batch_length(n: int) -> int:
    """Points per batch for ``n`` coordinates: about :data:`BATCH_BYTES`, in 1..4096.

    No floor above one: the batch lives in the compiled chunk's output, on the host and in
    the batched measurement (whose temporaries are several states per point), so a large
    system's batch is kept to a few states: its steps cost far more than handing a chunk
    over."""
    return int(min(4096, max(1, BATCH_BYTES // (8 * (2 * n + 1)))))


def measurer(mech: Mechanics):
    """``measure(t, q, v, E0, I0) -> (|g|, |G v + g_t|, |H - H0|, |I - I0|...)`` at one point."""

    def measure(t, q, v, E0, I0):
        return jnp.concatenate([
            jnp.stack([
                jnp.max(jnp.abs(mech.g(q, t)), initial=0.0),
                jnp.max(jnp.abs(mech.vel_residual(q, v, t)), initial=0.0),
                jnp.abs(mech.energy(q, v) - E0),
            ]),
            jnp.abs(mech.invariant_values(q, v) - I0),
        ])

    return measure


def series_names(mech: Mechanics) -> list[str]:
    """The names of the windowed series, in the order of :func:`measurer`'s values."""
    return ["pos", "vel", "energy"] + [f"inv:{s}" for s in mech.system.invariants]


def sample_count(grid: Grid) -> int:
    """Sample slots kept over the horizon (at least the first and the last)."""
    return max(2, grid.n_samples)


def window_and_slot(t, grid: Grid, xp=np):
    """Window index and sample slot of the time(s) ``t`` (the layout of the module notes).

    ``xp`` is ``numpy`` (the host :class:`Recorder`) or ``jax.numpy`` (the compiled loop
    of :func:`tracker`): one formula, so both put a point in the same window and slot. A
    point within :data:`BOUNDARY` of a window's end or a slot's time, in units of their
    spacing, counts as on it: a step that lands on a window's end belongs to the window it
    ends, as in the fixed-step loop's layout by step count. Without the margin XLA's
    arithmetic and numpy's, a rounding apart, put a fixed step's points on 184 of the 1000
    window ends of the pendulum's 100 s in different windows.
    """
    frac = (t - grid.t0) / (grid.t_end - grid.t0)
    W, S = grid.n_windows, sample_count(grid)
    w = xp.clip(xp.ceil(frac * W - BOUNDARY).astype(xp.int64) - 1, 0, W - 1)
    slot = xp.clip(xp.floor(frac * (S - 1) + BOUNDARY).astype(xp.int64), 0, S - 1)
    return w, slot


def series(grid: Grid, names: list[str], wins: np.ndarray, hit: np.ndarray
           ) -> dict[str, np.ndarray]:
    """The drift series: window end times and per-window maxima ``wins`` of the windows
    that some point reached (``hit``)."""
    W = grid.n_windows
    ends = grid.t0 + (grid.t_end - grid.t0) * (np.arange(W) + 1) / W
    out = {"t": ends[hit]}
    out.update({name: wins[hit, i] for i, name in enumerate(names)})
    return out


def kept(samp_t: np.ndarray, samp_q: np.ndarray, samp_v: np.ndarray, filled: np.ndarray
         ) -> dict[str, np.ndarray]:
    """The kept states (the ``filled`` slots), in time order."""
    return {"t": samp_t[filled], "q": samp_q[filled], "v": samp_v[filled]}


def ended(failure: str, t_final: float, q_final, v_final, counts: dict[str, int],
          sampling: str, windows: dict[str, np.ndarray], samples: dict[str, np.ndarray],
          extra: dict[str, float] | None = None, linear_solver: str = "dense",
          pattern_nnz: int | None = None) -> Trajectory:
    """The :class:`Trajectory` of a recorded run that ended at ``t_final`` after
    ``counts["n_steps"]`` steps: ``ok`` for an empty ``failure``, else ``failed`` with that
    message at the next step."""
    q_final = np.asarray(q_final)
    assert q_final.dtype == np.float64, "the backend must hand over float64 states"
    status, fail_step, fail_time = Status.OK, None, None
    if failure:
        status, fail_step = Status.FAILED, counts["n_steps"] + 1
        fail_time = None if math.isnan(t_final) else float(t_final)
    return Trajectory(status, failure, float(t_final), q_final, np.asarray(v_final),
                      windows, samples, dict(counts), sampling, fail_step, fail_time,
                      dict(extra or {}), linear_solver, pattern_nnz)


class Tally(NamedTuple):
    """What :func:`tracker` keeps of one lane inside a compiled loop: the reference energy
    and invariants, the window maxima and which windows were reached, and the sample slots
    (times, states, which are filled)."""

    E0: jax.Array
    I0: jax.Array
    wins: jax.Array
    hit: jax.Array
    samp_t: jax.Array
    samp_q: jax.Array
    samp_v: jax.Array
    filled: jax.Array


def tracker(mech: Mechanics, grid: Grid):
    """``(start, add)``: :class:`Recorder`'s bookkeeping as pure functions for a compiled
    loop, one point at a time.

    ``start(t0, q0, v0) -> Tally`` takes ``H0`` and the invariants at the initial point and
    records it; ``add(tally, keep, t, q, v) -> Tally`` records the point where ``keep``
    (an accepted step) and returns ``tally`` unchanged otherwise. Memory is the windows and
    the samples, whatever the number of steps.
    """
    measure = measurer(mech)
    W, S, n = grid.n_windows, sample_count(grid), mech.n

    def add(tally: Tally, keep, t, q, v) -> Tally:
        w, slot = window_and_slot(t, grid, jnp)
        m = measure(t, q, v, tally.E0, tally.I0)
        fresh = keep & ~tally.filled[slot]
        return tally._replace(
            wins=tally.wins.at[w].set(jnp.where(keep, jnp.maximum(tally.wins[w], m),
                                                tally.wins[w])),
            hit=tally.hit.at[w].set(tally.hit[w] | keep),
            samp_t=tally.samp_t.at[slot].set(jnp.where(fresh, t, tally.samp_t[slot])),
            samp_q=tally.samp_q.at[slot].set(jnp.where(fresh, q, tally.samp_q[slot])),
            samp_v=tally.samp_v.at[slot].set(jnp.where(fresh, v, tally.samp_v[slot])),
            filled=tally.filled.at[slot].set(tally.filled[slot] | fresh))

    def start(t0, q0, v0) -> Tally:
        I0 = mech.invariant_values(q0, v0)
        tally = Tally(mech.energy(q0, v0), I0, jnp.zeros((W, 3 + I0.size)),
                      jnp.zeros(W, bool), jnp.zeros(S), jnp.zeros((S, n)),
                      jnp.zeros((S, n)), jnp.zeros(S, bool))
        return add(tally, jnp.asarray(True), t0, q0, v0)

    return start, add


@partial(jax.jit, static_argnames="mech")
def measure_batch(t, q, v, E0, I0, *, mech: Mechanics):
    """:func:`measurer` over a batch of points (compiled once per system and batch length)."""
    return jax.vmap(measurer(mech), in_axes=(0, 0, 0, None, None))(t, q, v, E0, I0)


@partial(jax.jit, static_argnames="mech")
def reference_values(q, v, *, mech: Mechanics):
    """Energy and declared invariants at one point (the run's ``H0`` and ``I0``)."""
    return mech.energy(q, v), mech.invariant_values(q, v)


class Recorder:
    """Per-window maxima and bounded samples of the points of one run.

    Build once in ``prepare`` (it compiles the measurements, so that no solve pays for
    them), call :meth:`start` at the beginning of every solve, feed points with
    :meth:`add` or :meth:`extend`, and finish with :meth:`trajectory`.
    """

    def __init__(self, mech: Mechanics, grid: Grid):
        self.mech, self.grid = mech, grid
        self.n = mech.n
        self.rows = batch_length(mech.n)
        self.names = series_names(mech)
        n_inv = len(mech.system.invariants)
        f64 = jnp.float64
        spec = jax.ShapeDtypeStruct
        self._measure = compile_lifted(
            measure_batch, spec((self.rows,), f64), spec((self.rows, self.n), f64),
            spec((self.rows, self.n), f64), spec((), f64), spec((n_inv,), f64), mech=mech)
        self._reference = compile_lifted(reference_values, spec((self.n,), f64),
                                         spec((self.n,), f64), mech=mech)
        self.n_samples = sample_count(grid)
        self._t = np.empty(self.rows)
        self._q = np.empty((self.rows, self.n))
        self._v = np.empty((self.rows, self.n))

    def start(self, t0: float, q0: np.ndarray, v0: np.ndarray) -> None:
        """Reset, take ``H0`` and the invariants at the initial point, and record it."""
        E0, I0 = self._reference(jnp.asarray(q0, jnp.float64), jnp.asarray(v0, jnp.float64))
        self._E0, self._I0 = np.float64(E0), np.asarray(I0, dtype=np.float64)
        W = self.grid.n_windows
        self.wins = np.zeros((W, len(self.names)))
        self.hit = np.zeros(W, dtype=bool)
        self.samp_t = np.zeros(self.n_samples)
        self.samp_q = np.zeros((self.n_samples, self.n))
        self.samp_v = np.zeros((self.n_samples, self.n))
        self.filled = np.zeros(self.n_samples, dtype=bool)
        self.count = 0
        self.add(t0, q0, v0)

    def add(self, t: float, q: np.ndarray, v: np.ndarray) -> None:
        """Record one point (buffered; measured when the batch is full)."""
        i = self.count
        self._t[i] = t
        self._q[i] = q
        self._v[i] = v
        self.count = i + 1
        if self.count == self.rows:
            self.flush()

    def extend(self, t: np.ndarray, q: np.ndarray, v: np.ndarray) -> None:
        """Record a batch of points in time order (any length), after the buffered ones:
        a batch is measured when it is full, whole batches of points each (the compiled
        measurement costs a full batch however few points it holds)."""
        start = 0
        while start < len(t):
            i = self.count
            k = min(self.rows - i, len(t) - start)
            stop = start + k
            self._t[i:i + k], self._q[i:i + k], self._v[i:i + k] = (t[start:stop],
                                                                   q[start:stop], v[start:stop])
            self.count = i + k
            start = stop
            if self.count == self.rows:
                self.flush()

    def flush(self) -> None:
        """Measure the buffered points and fold them into the windows and samples."""
        k = self.count
        if k == 0:
            return
        # The compiled measurement has a fixed batch length: pad with the last point,
        # whose repeats change no maximum and no first-in-slot choice.
        for buf in (self._t, self._q, self._v):
            buf[k:] = buf[k - 1]
        vals = np.asarray(self._measure(self._t, self._q, self._v, self._E0, self._I0))[:k]
        t = self._t[:k]
        w, slots = window_and_slot(t, self.grid)
        np.maximum.at(self.wins, w, vals)
        self.hit[w] = True
        first_slot, first_row = np.unique(slots, return_index=True)
        new = ~self.filled[first_slot]
        first_slot, first_row = first_slot[new], first_row[new]
        self.samp_t[first_slot] = t[first_row]
        self.samp_q[first_slot] = self._q[first_row]
        self.samp_v[first_slot] = self._v[first_row]
        self.filled[first_slot] = True
        self.count = 0

    def windows(self) -> dict[str, np.ndarray]:
        """The drift series: window end times and per-window maxima (reached windows)."""
        self.flush()
        return series(self.grid, self.names, self.wins, self.hit)

    def samples(self) -> dict[str, np.ndarray]:
        """The kept states, in time order."""
        self.flush()
        return kept(self.samp_t, self.samp_q, self.samp_v, self.filled)

    def trajectory(self, failure: str, t_final: float, q_final: np.ndarray,
                   v_final: np.ndarray, counts: dict[str, int], sampling: str,
                   extra: dict[str, float] | None = None, linear_solver: str = "dense",
                   pattern_nnz: int | None = None) -> Trajectory:
        """The :class:`Trajectory` of the recorded run, which ended at ``t_final`` after
        ``counts["n_steps"]`` steps: ``ok`` for an empty ``failure``, else ``failed`` with
        that message at the next step (:func:`ended`)."""
        return ended(failure, t_final, q_final, v_final, counts, sampling, self.windows(),
                     self.samples(), extra, linear_solver, pattern_nnz)
