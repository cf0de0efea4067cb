"""The host's drift record (:class:`integrators.record.Recorder`) measures the points of a
run in full batches, whatever the lengths in which they arrive, and keeps what point-by-point
recording keeps."""

from __future__ import annotations

import numpy as np

import problems
from integrators.base import Grid
from integrators.record import Recorder


def test_points_are_measured_in_full_batches():
    case = problems.make("pendulum")
    grid = Grid(0.0, 1.0, n_windows=10, n_samples=11)
    recorders = [Recorder(case.mech, grid) for _ in range(2)]
    rows = recorders[0].rows
    t = np.linspace(0.0, 1.0, rows + 1)
    theta = 0.3 * np.sin(7 * t)
    q = np.stack([np.sin(theta), -np.cos(theta)], 1)
    v = np.stack([np.cos(theta), np.sin(theta)], 1) * (2.1 * np.cos(7 * t))[:, None]
    calls = []
    measure = recorders[0]._measure
    recorders[0]._measure = lambda *a: calls.append(1) or measure(*a)
    # The start point, then chunks of rows - 1 and 1 points: rows + 1 points, two batches
    # (a batch measured at every chunk's arrival would make three).
    recorders[0].start(t[0], q[0], v[0])
    recorders[0].extend(t[1:rows], q[1:rows], v[1:rows])
    recorders[0].extend(t[rows:], q[rows:], v[rows:])
    by_chunks = recorders[0].windows(), recorders[0].samples()
    assert len(calls) == 2
    recorders[1].start(t[0], q[0], v[0])
    for i in range(1, rows + 1):
        recorders[1].add(t[i], q[i], v[i])
    by_points = recorders[1].windows(), recorders[1].samples()
    for chunked, pointwise in zip(by_chunks, by_points):
        assert list(chunked) == list(pointwise)
        for name in chunked:
            np.testing.assert_array_equal(chunked[name], pointwise[name])
