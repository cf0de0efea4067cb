"""Ensembles: initial states drawn reproducibly, one compiled loop whose lanes equal single
runs, failures confined to their lanes, and the records, store and report that show them."""

from __future__ import annotations

from dataclasses import replace

import jax
import numpy as np
import pandas as pd
import pytest

import integrators
import problems
from benchmarks import run as cli
from benchmarks.execute import execute, merge
from benchmarks import plan as planning
from benchmarks.plan import ENSEMBLE_GRID, GPU_MIN_LANES, jax_device, lane_ranges, plan
from benchmarks.records import ACCURACY_COLUMNS, RunSpec
from benchmarks.store import load_lanes, load_runs
from integrators.base import Grid
from problems import ensemble
from problems.ensemble import draw


def _grid(case):
    return Grid(case.t0, case.t_end, **ENSEMBLE_GRID)


def test_draws_are_consistent_reproducible_and_lane_by_lane():
    case = problems.make("sps-receiver")
    q, v = draw(case, 6, seed=4)
    again, _ = draw(case, 9, seed=4)
    other, _ = draw(case, 6, seed=5)
    assert np.array_equal(q[0], case.q0) and np.array_equal(v[0], case.v0)
    np.testing.assert_array_equal(q, again[:6])  # a lane does not depend on the ensemble size
    assert not np.allclose(q[1:], other[1:])
    assert np.all(np.abs(q[1:] - case.q0).max(axis=1) > 1e-6)  # perturbed, not copied
    mech = case.mech
    for qi, vi in zip(q, v):
        pos, vel = problems.case.residuals(mech, qi, vi, case.t0)
        assert max(pos, vel) <= 1e-12


def test_ensemble_size_is_checked():
    with pytest.raises(ValueError, match="1 to"):
        draw(problems.make("pendulum"), 0)


@pytest.mark.parametrize("method, h", [("rattle", 0.05), ("lobatto3ab2", 0.05),
                                       ("genalpha", 0.05), ("baumgarte-rk4", 0.05),
                                       ("genalpha", 0.2)])
def test_each_lane_equals_its_single_run(method, h):
    case = problems.make("pendulum").with_t_end(5.0)
    q0s, v0s = draw(case, 5, seed=1)
    integ = integrators.make(method, h=h)
    solve = integ.prepare_ensemble(case, _grid(case), q0s, v0s)
    lanes = solve()
    assert len(lanes) == 5
    # At h = 0.2 generalized-alpha's simplified Newton fails on some steps, and the lanes
    # go on with the exact-Jacobian fallback (a loop compiled as late set-up).
    assert solve.late_setup_s > 0 or h != 0.2
    for i, lane in enumerate(lanes):
        single = integ.prepare(case.with_initial(q0s[i], v0s[i]), _grid(case))()
        assert lane.status == single.status == "ok"
        # The same arithmetic, vectorised over the lanes: equal to round-off accumulated
        # over 25 to 100 steps (baumgarte-rk4's single run steps by t_{k+1} - t_k, the loop
        # by h). Newton's counts are not compared: the fallback's Krylov solves round
        # differently batched, which moves Newton's stop at the round-off floor by an
        # iteration here and there (257 against 255 on lane 0 at h = 0.2).
        np.testing.assert_allclose(lane.q_final, single.q_final, rtol=0, atol=1e-12)
        np.testing.assert_allclose(lane.v_final, single.v_final, rtol=0, atol=1e-12)
        # Maxima over the run (baumgarte-rk4's single run lays its windows out by time).
        for name in ("pos", "vel", "energy"):
            assert np.max(lane.windows[name]) == pytest.approx(np.max(single.windows[name]),
                                                               rel=1e-6, abs=1e-14)


def test_a_failing_lane_stops_only_itself():
    case = problems.make("pendulum").with_t_end(5.0)
    q0s, v0s = draw(case, 4, seed=2)
    v0s[2] *= 1e4  # still consistent (G v = 0 is linear in v); Newton cannot follow it
    integ = integrators.make("rattle", h=0.1)
    lanes = integ.prepare_ensemble(case, _grid(case), q0s, v0s)()
    assert lanes[2].status == "failed" and lanes[2].fail_step is not None
    for i in (0, 1, 3):
        single = integ.prepare(case.with_initial(q0s[i], v0s[i]), _grid(case))()
        assert lanes[i].status == "ok"
        assert lanes[i].counts["n_steps"] == single.counts["n_steps"] == 50
        np.testing.assert_allclose(lanes[i].q_final, single.q_final, rtol=0, atol=1e-13)


def test_a_failed_lane_does_not_hold_the_others_at_its_iteration_limit():
    # A step whose iteration runs to its limit (and fails) from lane 2's states at
    # t >= 3h. Every lane is computed at every step, so the loop must not step a failed
    # lane from its own state again: the mapped iteration would run to that limit for all
    # lanes at every later step. The iterations of every lane are recorded as computed.
    import jax.numpy as jnp
    from integrators.base import Failure
    from integrators.loop import march
    case = problems.make("pendulum").with_t_end(1.0)
    q0s, v0s = draw(case, 4, seed=0)
    h, limit, seen = 0.1, 1000, {i: [] for i in range(4)}

    def step(carry, t, h):
        q, v, lane = carry
        stop = jnp.where((lane == 2) & (t >= 2.5 * h), limit, 1)
        count = jax.lax.while_loop(lambda i: i < stop, lambda i: i + 1, 0)
        jax.debug.callback(lambda i, c: seen[int(i)].append(int(c)), lane, count)
        code = jnp.where(count >= limit, Failure.NEWTON, Failure.NONE)
        return carry, code, jnp.asarray(0.0), {"n_newton": count}

    carry0 = (jnp.asarray(q0s), jnp.asarray(v0s), jnp.arange(4))
    lanes = march(case.mech, _grid(case), h, carry0, step, lambda carry: carry[:2],
                  lanes=True)()
    assert lanes[2].status == "failed" and lanes[2].fail_step == 4
    assert [lane.counts["n_steps"] for lane in lanes] == [10, 10, 3, 10]
    # Four lanes were computed at each of the 10 steps (the callback names the state a
    # lane stepped from). Lane 2's state was stepped four times, the last to the limit,
    # and after its failure it stepped from a live lane's state; every computation but
    # that one took one iteration. The loop with the fallback then took lane 2's failed
    # step once more, alone (here the same step, which fails again).
    assert sum(len(counts) for counts in seen.values()) == 41
    assert seen[2] == [1, 1, 1, limit, limit]
    assert all(c == 1 for i in (0, 1, 3) for c in seen[i])


def test_lanes_retaken_with_the_fallback_go_on_from_the_steps_they_failed_at():
    # Traced without the fallback (as the first loop of every path is), the step
    # fails for lane 1 at step 3 and for lane 3 at step 6; with it, never. The loop with the
    # fallback takes those two lanes from their own failed steps: from step 3 on, lane 3
    # waiting (stepped from lane 1's state, its result dropped) until step 6.
    import jax.numpy as jnp
    from integrators.base import Failure
    from integrators.loop import march
    from integrators.newton import _deferred
    case = problems.make("pendulum").with_t_end(1.0)
    q0s, v0s = draw(case, 4, seed=0)
    h, seen = 0.1, []

    def step(carry, t, h):
        q, v, lane = carry
        k = jnp.round((t - case.t0) / h)
        fails = ((lane == 1) & (k == 3)) | ((lane == 3) & (k == 6))
        code = jnp.where(fails & _deferred.get(), Failure.NEWTON, Failure.NONE)
        jax.debug.callback(lambda i, k, late: seen.append((int(i), int(k), bool(late))),
                           lane, k, not _deferred.get())
        return (q + h * v, v, lane), code, jnp.asarray(0.0), {"n_newton": jnp.asarray(1)}

    carry0 = (jnp.asarray(q0s), jnp.asarray(v0s), jnp.arange(4))
    lanes = march(case.mech, _grid(case), h, carry0, step, lambda carry: carry[:2],
                  linear_solver="banded", lanes=True)()
    assert [str(lane.status) for lane in lanes] == ["ok"] * 4
    assert [lane.counts["n_steps"] for lane in lanes] == [10] * 4
    assert [lane.counts["n_newton"] for lane in lanes] == [10] * 4  # failed attempts not counted
    for i, lane in enumerate(lanes):
        np.testing.assert_allclose(lane.q_final, q0s[i] + 10 * h * v0s[i], rtol=0, atol=1e-14)
    first = [s for s in seen if not s[2]]
    late = sorted((i, k) for i, k, retaken in seen if retaken)
    assert len(first) == 40  # four lanes at each of ten steps
    # Two lanes at steps 3 to 9: lane 1 at each, and for lane 3 lane 1 again until step 6.
    assert late == sorted([(1, k) for k in range(3, 10)] + [(1, 3), (1, 4), (1, 5)]
                          + [(3, k) for k in range(6, 10)])


@pytest.mark.parametrize("method", ["baumgarte-tsit5", "baumgarte-dopri5",
                                    "baumgarte-dopri8"])
def test_adaptive_lanes_equal_their_single_runs(method):
    """The vmapped adaptive loop takes each lane's own steps: the same step sequence (every
    counter equal) and the same recorded windows, samples and final state as the single
    run from the lane's initial state."""
    case = problems.make("pendulum").with_t_end(5.0)
    q0s, v0s = draw(case, 5, seed=1)
    integ = integrators.make(method, rtol=1e-8)
    assert integ.batched
    lanes = integ.prepare_ensemble(case, _grid(case), q0s, v0s)()
    for i, lane in enumerate(lanes):
        single = integ.prepare(case.with_initial(q0s[i], v0s[i]), _grid(case))()
        assert lane.status == single.status == "ok"
        assert lane.counts == single.counts and lane.sampling == single.sampling
        # The same attempts in the same order, vectorised: bit for bit in a plain process;
        # under the tests' settings apart by round-off accumulated over some 200 steps
        # (measured: final states and measures by up to 1.7e-14; step times by up to 5e-13,
        # and with them the sampled states, by up to 3.7e-12 in v).
        np.testing.assert_allclose(lane.q_final, single.q_final, rtol=0, atol=1e-13)
        np.testing.assert_allclose(lane.v_final, single.v_final, rtol=0, atol=1e-13)
        for got, want in ((lane.windows, single.windows), (lane.samples, single.samples)):
            for name in want:
                np.testing.assert_allclose(got[name], want[name], rtol=1e-12, atol=1e-11)


def test_a_failing_adaptive_lane_stops_only_itself():
    """Lane 2 (three times the velocity) needs 94 steps over 5 s where the others need 90:
    with max_steps = 92 it alone fails, at the step a single run fails, and the others run
    to t_end exactly as their single runs do."""
    case = problems.make("pendulum").with_t_end(5.0)
    q0s, v0s = draw(case, 4, seed=2)
    v0s[2] *= 3.0  # still consistent (G v = 0 is linear in v)
    integ = integrators.make("baumgarte-dopri5:max_steps=92", rtol=1e-6)
    lanes = integ.prepare_ensemble(case, _grid(case), q0s, v0s)()
    assert [lane.status for lane in lanes] == ["ok", "ok", "failed", "ok"]
    assert "max_steps = 92" in lanes[2].message and lanes[2].fail_step == 93
    for i, lane in enumerate(lanes):
        single = integ.prepare(case.with_initial(q0s[i], v0s[i]), _grid(case))()
        assert (lane.status, lane.message, lane.counts) == (single.status, single.message,
                                                           single.counts)
        np.testing.assert_allclose(lane.q_final, single.q_final, rtol=0, atol=1e-13)


def test_sps_receiver_ensemble_keeps_every_lane_on_the_constraints():
    """256 perturbed lanes of RATTLE at h = 0.05 to t = 50: every lane ok with max |g| at
    round-off, and five lanes picked at random equal single runs from their states."""
    case = problems.make("sps-receiver")
    q0s, v0s = draw(case, 256, seed=0)
    integ = integrators.make("rattle", h=0.05)
    lanes = integ.prepare_ensemble(case, _grid(case), q0s, v0s)()
    assert all(lane.status == "ok" for lane in lanes)
    assert max(float(np.max(lane.windows["pos"])) for lane in lanes) <= 1e-12
    for i in np.random.default_rng(7).choice(256, 5, replace=False):
        single = integ.prepare(case.with_initial(q0s[i], v0s[i]), _grid(case))()
        np.testing.assert_allclose(lanes[i].q_final, single.q_final, rtol=0, atol=1e-12)
        np.testing.assert_allclose(lanes[i].v_final, single.v_final, rtol=0, atol=1e-12)


@pytest.mark.slow
def test_command_line_records_quantiles_lanes_and_report(tmp_path):
    out = tmp_path / "out"
    code = cli.main(["--problems", "pendulum", "--integrators", "rattle", "ida-ggl",
                     "--h", "0.05", "--rtol", "1e-6", "--t-end", "2", "--ensemble", "6",
                     "--seed", "3", "--jobs", "1", "--out", str(out)])
    assert code == 0
    runs = pd.read_csv(out / "runs.csv")
    assert set(runs["lanes"]) == {6} and set(runs["seed"]) == {3}
    assert list(runs.sort_values("integrator")["batched"]) == [0, 1]  # ida lane by lane
    assert (runs["failed_fraction"] == 0).all()
    assert (runs["pos_q0"] <= runs["pos_q50"]).all()
    assert (runs["pos_q50"] <= runs["pos_q100"]).all()
    assert np.allclose(runs["pos_q100"], runs["max_pos_residual"])  # the worst lane
    stored = load_runs(out / "driftbench.sqlite")
    lanes = load_lanes(out / "driftbench.sqlite", int(stored["run_id"].iloc[0]))
    assert list(lanes["seed"]) == list(range(6)) and (lanes["status"] == 0).all()
    assert np.isfinite(lanes["final_state_error"]).all()  # each lane against its own
    assert (runs["final_q50"] <= runs["final_q100"]).all()
    html = (out / "report.html").read_text()
    assert "Ensembles: pendulum" in html and "ensemble-distributions" in html
    assert "final q50" in html and "final error per lane" in html


@pytest.mark.parametrize("argv, what", [(["--ensemble", "0"], "--ensemble 0"),
                                        (["--ensemble", "100000000"], "--ensemble 100000000"),
                                        (["--ensemble", "2", "--seed", "-1"], "--seed -1")])
def test_bad_ensemble_arguments_are_one_line(tmp_path, capsys, argv, what):
    code = cli.main(["--problems", "pendulum", "--integrators", "rattle", "--out",
                     str(tmp_path), *argv])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and what in err[0]


def _suite_errors(tmp_path, capsys, lines: str) -> tuple[int, list[str]]:
    """The exit status and the error lines of a suite of one group of RATTLE on the
    pendulum with ``lines`` added (from line 5 of the file ``s.toml``)."""
    suite = tmp_path / "s.toml"
    suite.write_text('description = "x"\n[[group]]\nproblems = ["pendulum"]\n'
                     f'integrators = ["rattle"]\n{lines}\n')
    code = cli.main(["--suite", str(suite), "--out", str(tmp_path / "o")])
    return code, capsys.readouterr().err.strip().splitlines()


def test_bad_ensemble_in_a_suite_names_the_line(tmp_path, capsys):
    code, err = _suite_errors(tmp_path, capsys, "ensemble = -3")
    assert code == 2 and len(err) == 1 and "s.toml:5" in err[0] and "ensemble" in err[0]


@pytest.mark.parametrize("method", ["rattle", "baumgarte-dopri5"])
def test_chunks_merge_into_the_unchunked_record(method):
    """An ensemble run as chunks of lanes, each executed on its own as a worker executes
    it, merges into the record of the ensemble run whole: every lane bit for bit (a lane
    is drawn alike in any chunk, and XLA compiles these small widths alike), and so every
    summary; only the timing differs."""
    spec = RunSpec("pendulum", method, h=0.05 if method == "rattle" else None,
                   rtol=None if method == "rattle" else 1e-6, t_end=2.0, lanes=7, seed=3,
                   lanes_per_chunk=2)
    planned = plan([spec], "test")[0]
    assert planned.chunks == ((0, 2), (2, 4), (4, 7)) and planned.run.chunks == 3
    whole = execute(planned, repeats=1)
    parts = [execute(replace(planned, lanes=lanes), repeats=1) for lanes in planned.chunks]
    merged = merge(planned, parts[::-1])  # in any order
    assert list(merged.lanes["seed"]) == list(range(7))
    assert merged.lanes.keys() == whole.lanes.keys()
    for name, values in whole.lanes.items():
        np.testing.assert_array_equal(merged.lanes[name], values, err_msg=name)
    for name, values in whole.windows.items():
        np.testing.assert_array_equal(merged.windows[name], values, err_msg=name)
    assert (merged.ending, merged.metrics, merged.spread, merged.run) == \
        (whole.ending, whole.metrics, whole.spread, whole.run)
    assert replace(merged.work, device=None) == replace(whole.work, device=None)
    assert merged.work.device == whole.work.device == "cpu"


def test_lane_ranges_hold_at_most_the_lanes_per_chunk_and_never_one_alone():
    assert lane_ranges(5, 1024) == ((0, 5),)
    assert lane_ranges(2047, 1024) == ((0, 1023), (1023, 2047))
    assert lane_ranges(4096, 1024) == ((0, 1024), (1024, 2048), (2048, 3072), (3072, 4096))
    assert lane_ranges(3, 2) == ((0, 3),) and lane_ranges(5, 2) == ((0, 2), (2, 5))
    ranges = lane_ranges(16384 + 5, 1000)
    assert ranges[0][0] == 0 and ranges[-1][1] == 16389 and len(ranges) == 17
    assert all(a[1] == b[0] for a, b in zip(ranges, ranges[1:]))
    assert all(2 <= stop - first <= 1000 for first, stop in ranges)


@pytest.mark.slow
def test_chunked_ensemble_on_the_cluster_equals_the_unchunked_one(tmp_path):
    """Chunks of 2 lanes on a Dask cluster of two workers against one task in the local
    pool: the same per-lane tables and accuracy columns, bit for bit."""
    common = ["--problems", "pendulum", "--integrators", "rattle", "baumgarte-tsit5",
              "--h", "0.05", "--rtol", "1e-6", "--t-end", "2", "--ensemble", "5",
              "--seed", "2", "--no-report"]
    assert cli.main([*common, "--lanes-per-chunk", "2", "--cluster", "local:2",
                     "--out", str(tmp_path / "chunked")]) == 0
    assert cli.main([*common, "--jobs", "1", "--out", str(tmp_path / "whole")]) == 0
    chunked, whole = (pd.read_csv(tmp_path / name / "runs.csv") for name in ("chunked", "whole"))
    assert list(chunked["chunks"]) == [2, 2] and list(whole["chunks"]) == [1, 1]
    assert set(chunked["device"]) == set(whole["device"]) == {"cpu"}
    pd.testing.assert_frame_equal(chunked[list(ACCURACY_COLUMNS)], whole[list(ACCURACY_COLUMNS)])
    for name in ("chunked", "whole"):
        stored = load_runs(tmp_path / name / "driftbench.sqlite")
        tables = [load_lanes(tmp_path / name / "driftbench.sqlite", int(i))
                  for i in stored.sort_values("integrator")["run_id"]]
        if name == "chunked":
            first = tables
    for got, want in zip(first, tables):
        assert list(got["seed"]) == list(range(5))
        pd.testing.assert_frame_equal(got, want)


def test_device_auto_runs_on_the_cpu_without_a_gpu(tmp_path):
    assert jax_device("auto").platform == "cpu"  # no GPU on the machines this was written on
    spec = RunSpec("pendulum", "rattle", h=0.1, t_end=1.0, lanes=3, seed=0, device="auto")
    record = execute(plan([spec], "test")[0], repeats=1)
    assert record.ending.status == "ok" and record.work.device == "cpu"


def test_device_auto_takes_a_gpu_only_for_large_ensembles_and_then_one_chunk(monkeypatch):
    # Plan as if JAX saw a GPU: nothing runs, only where the runs would go.
    cpu = jax_device("cpu")
    monkeypatch.setattr(planning, "jax_device", lambda name: cpu)
    specs = [RunSpec("pendulum", "rattle", h=0.1, t_end=1.0, lanes=k, seed=0, device=device,
                     lanes_per_chunk=per_chunk)
             for k, device, per_chunk in [(GPU_MIN_LANES - 1, "auto", None),
                                          (GPU_MIN_LANES, "auto", None),
                                          (GPU_MIN_LANES, "auto", 512),
                                          (64, "gpu", None), (GPU_MIN_LANES, "cpu", None)]]
    got = [(run.device, len(run.chunks)) for run in plan(specs, "test")]
    assert got == [("cpu", 2), ("gpu", 1), ("gpu", 2), ("gpu", 1), ("cpu", 2)]


@pytest.mark.skipif(jax_device("gpu") is not None, reason="a GPU is present")
def test_device_gpu_without_one_is_one_line(tmp_path, capsys):
    code = cli.main(["--problems", "pendulum", "--integrators", "rattle", "--ensemble", "2",
                     "--device", "gpu", "--out", str(tmp_path)])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "device = 'gpu'" in err[0] and "no GPU" in err[0]
    code, err = _suite_errors(tmp_path, capsys, 'ensemble = 2\ndevice = "gpu"')
    assert code == 2 and len(err) == 1 and "s.toml:2 ([[group]] 1)" in err[0] and "no GPU" in err[0]


@pytest.mark.parametrize("text, what", [('device = "tpu"', "device"),
                                        ("lanes_per_chunk = 1", "lanes_per_chunk")])
def test_bad_device_or_chunk_in_a_suite_names_the_line(tmp_path, capsys, text, what):
    code, err = _suite_errors(tmp_path, capsys, f"ensemble = 4\n{text}")
    assert code == 2 and len(err) == 1 and "s.toml:6" in err[0] and what in err[0]


def test_states_drawn_across_projection_slices_do_not_depend_on_the_ensemble_size():
    """More lanes than one projection slice (problems.case.PROJECT_WIDTH): a lane is the
    same in an ensemble of 300 as in one of 600, and on the constraints."""
    case = problems.make("chain:N=8")
    q, v = draw(case, 300, seed=3)
    more, more_v = draw(case, 600, seed=3)
    np.testing.assert_array_equal(q, more[:300])
    np.testing.assert_array_equal(v, more_v[:300])
    pos, vel = problems.case.residuals(case.mech, more[450], more_v[450], case.t0)
    assert max(pos, vel) <= 1e-12


def test_this_process_has_one_xla_thread_and_all_its_cores():
    """conftest calls benchmarks.pool.one_xla_thread: XLA's CPU pool has one thread (so
    jaxlib's batched LAPACK kernels cannot deadlock it), and no thread stays pinned."""
    import os
    from pathlib import Path

    jax.devices()
    names = [Path(f"/proc/self/task/{tid}/comm").read_text().strip()
             for tid in os.listdir("/proc/self/task")]
    assert names.count("tf_XLAEigen") == 1
    cores = os.sched_getaffinity(0)
    for tid in os.listdir("/proc/self/task"):
        try:
            assert os.sched_getaffinity(int(tid)) == cores
        except ProcessLookupError:  # a thread that ended meanwhile
            pass


@pytest.mark.slow
def test_the_memory_benchmark_runs_the_method_and_step_it_is_given(capsys):
    """``benchmarks.perf.ensemble``'s memory runs (fresh processes) take ``--memory-method``
    and ``--memory-h``, and report the peak and every lane's status."""
    from benchmarks.perf import ensemble

    code = ensemble.main(["--methods", "--memory-lanes", "8", "--memory-steps", "20",
                          "--memory-h", "0.002", "--memory-method",
                          "rattle:linear_solver=dense", "--device", "cpu"])
    out = capsys.readouterr().out
    assert code == 0
    assert "rattle:linear_solver=dense on chain:N=8, 8 lanes, h = 0.002" in out
    assert "2e+01 steps (cpu, dense linear solver" in out and "8 of 8 lanes ok" in out
    assert "under 2 GiB at every step count: holds" in out


@pytest.mark.parametrize("argv, what", [(["--methods", "nonsense"], "unknown integrator"),
                                        (["--memory-method", "rattle:foo=1"], "option 'foo'"),
                                        (["--problems", "nope"], "unknown problem"),
                                        (["--lanes", "4", "0"],
                                         "--lanes 0 must be a number of lanes from 1 to"),
                                        (["--memory-lanes", "-2"], "--memory-lanes -2"),
                                        (["--h", "0"], "--h 0 must be positive"),
                                        (["--steps", "0.5"], "--steps 0.5 must be at least 1"),
                                        (["--steps", "1e300", "--h", "1e300"],
                                         "no finite horizon")])
def test_the_ensemble_benchmark_refuses_bad_input_in_one_line(capsys, argv, what):
    from benchmarks.perf import ensemble

    with pytest.raises(SystemExit) as exit_:
        ensemble.main([*argv, "--skip-memory"])
    # In this process, which computed before main set it up as a worker, one note says so
    # first (benchmarks.perf.processes.like_a_worker); run as a program, main starts with it.
    lines = [line for line in capsys.readouterr().err.splitlines()
             if not line.startswith("note: XLA started before")]
    assert exit_.value.code == 2 and len(lines) == 1 and what in lines[0]


def test_the_ensemble_benchmark_times_the_one_trajectory_in_turn_with_the_ensemble():
    """Each ensemble solve is followed by a burst of one-trajectory solves, so the two rates
    of a ratio come from the same stretch of time."""
    import time

    from benchmarks.perf import ensemble

    calls = []

    def batch():
        calls.append("E")
        time.sleep(0.03)
        return "lanes"

    def one():
        calls.append("S")
        time.sleep(0.01)

    ens_s, one_s, out = ensemble.in_turn(batch, one, repeats=3)
    assert out == "lanes" and calls[0] == "E" and calls.count("E") >= 3
    bursts = "".join(calls).split("E")[1:]
    assert len(bursts) == calls.count("E") and all(b and set(b) == {"S"} for b in bursts)
    assert 0.03 <= ens_s < 0.2 and 0.01 <= one_s < 0.1


@pytest.mark.slow
def test_the_ensemble_benchmark_sets_itself_up_as_a_worker_before_it_computes():
    """Run as a program, the benchmark gets the workers' XLA flags (the one-kernel flag):
    resolving its problems first had started XLA without them, and one pendulum trajectory
    ran at a quarter to a tenth of its rate as a worker (9.3e5 and 1.2e6 against 4.5e6 to
    9.4e6 steps per second)."""
    import subprocess
    import sys

    done = subprocess.run(
        [sys.executable, "-m", "benchmarks.perf.ensemble", "--methods", "rattle",
         "--problems", "pendulum", "--lanes", "2", "--steps", "200", "--skip-memory",
         "--device", "cpu"], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert "rattle on pendulum: one trajectory" in done.stdout
    assert "2 lanes on cpu" in done.stdout
    assert "note: XLA started before" not in done.stderr


@pytest.mark.slow
def test_failed_lanes_are_recorded_and_kept_out_of_the_worst_lane_and_the_verdicts(tmp_path):
    """RATTLE at h = 0.22 on the pendulum loses most of 16 lanes before t = 20: the record's
    worst-lane metrics are over the lanes that finished, all alike (max energy error too),
    each failed lane has its failure step and time, a run with failed lanes cannot win
    the report's verdicts on the strength of its survivors, and the report quotes its
    message (and, with no single run, says the headline has none)."""
    from benchmarks.store import Store
    from reports import build
    from reports.ensembles import _verdicts

    spec = RunSpec("pendulum", "rattle", h=0.22, t_end=20.0, lanes=16, seed=0)
    record = execute(plan([spec], "test")[0], repeats=1)
    lanes = record.lanes
    failed = lanes["status"] == 1
    assert failed.any() and not failed.all()
    assert np.isfinite(lanes["fail_step"][failed]).all()
    assert np.isnan(lanes["fail_step"][~failed]).all()
    assert np.isnan(lanes["fail_time"][~failed]).all()
    np.testing.assert_array_less(lanes["fail_time"][failed], 20.0)
    assert record.metrics.rel_energy_error == np.max(lanes["rel_energy_error"][~failed])
    assert record.metrics.max_energy_error == pytest.approx(
        record.metrics.rel_energy_error * record.run.energy_scale, rel=1e-12)
    runs = pd.DataFrame([
        {"integrator": "rattle", "h": 0.22, "failed_fraction": float(np.mean(failed)),
         "energy_q50": 1e-3, "energy_q100": 1e-3},
        {"integrator": "genalpha", "h": 0.2, "failed_fraction": 0.0,
         "energy_q50": 0.5, "energy_q100": 0.8}])
    verdict = _verdicts(runs)
    assert "rattle" not in verdict and verdict.count("genalpha") == 2
    assert _verdicts(runs.iloc[:1]) == "Verdicts: no run finished every lane."
    with Store(tmp_path / "driftbench.sqlite") as st:
        st.add(st.begin("unit"), record)
    md = build(tmp_path / "driftbench.sqlite", tmp_path)[0].read_text()
    assert "No single runs: the runs here are ensembles" in md
    assert (f"Runs with failed lanes: rattle h=0.22: {int(failed.sum())} of 16 lanes "
            f"failed; the first, lane ") in md


def _pendulum_by_angle(q0, v0, t, L=1.0, gravity=9.81):
    """The pendulum's position at ``t`` from ``(q0, v0)`` by its one angle,
    ``theta'' = -(g / L) sin(theta)``, and scipy's Radau: neither the coordinates nor the
    method of the lanes' references."""
    from scipy.integrate import solve_ivp

    theta = np.arctan2(q0[0], -q0[1])
    omega = (q0[0] * v0[1] - q0[1] * v0[0]) / L**2
    sol = solve_ivp(lambda s, y: [y[1], -gravity / L * np.sin(y[0])], (0.0, t),
                    [theta, omega], method="Radau", rtol=1e-12, atol=1e-12)
    theta, omega = sol.y[:, -1]
    return np.array([L * np.sin(theta), -L * np.cos(theta)])


def test_lane_references_agree_with_the_closed_form_and_an_independent_solve():
    """Lane 0's computed reference is within its floor of the closed form; the perturbed
    lanes' agree with the angle ODE solved by another method; the floors are the size a
    tight integration over 5 s has; a lane's reference does not depend on which lanes are
    asked for, nor on the block's being computed again."""
    case = problems.make("pendulum").with_t_end(5.0)
    refs, notes = ensemble.references(case, 1, 0, 6, 5.0)
    assert notes == ()
    q0s, v0s = draw(case, 6, seed=1)
    exact, _ = case.reference.solution(5.0)
    assert np.max(np.abs(refs[0].solution(5.0)[0] - exact)) <= refs[0].floor
    for i in range(1, 6):
        q, _ = refs[i].solution(5.0)
        assert refs[i].scored == (0, 1) and refs[i].times == (5.0,)
        assert 0 < refs[i].floor < 1e-10
        np.testing.assert_allclose(q, _pendulum_by_angle(q0s[i], v0s[i], 5.0), rtol=0,
                                   atol=1e-9)
    ensemble._BLOCKS.clear()
    part, _ = ensemble.references(case, 1, 2, 4, 5.0)
    assert [(r.floor, *r.solution(5.0)[0]) for r in part] == \
        [(r.floor, *r.solution(5.0)[0]) for r in refs[2:4]]
    # None where the case has no reference at t (the chain's are at t = 1 and 5).
    assert ensemble.references(problems.make("chain"), 1, 0, 2, 2.0) == ([None, None], ())


def test_reference_blocks_are_kept_by_their_bytes(monkeypatch):
    """A sweep over the blocks of an ensemble's references computes each once while they
    fit in :data:`problems.ensemble.KEPT_BYTES`, and drops the oldest beyond it."""
    case = problems.make("pendulum").with_t_end(0.5)
    made, real = [], ensemble._block
    monkeypatch.setattr(ensemble, "_block", lambda *a: made.append(a[2]) or real(*a))
    monkeypatch.setattr(ensemble, "_BLOCKS", type(ensemble._BLOCKS)())
    lanes = 3 * ensemble.REFERENCE_LANES
    first, _ = ensemble.references(case, 1, 0, lanes, 0.5)
    again, _ = ensemble.references(case, 1, 0, lanes, 0.5)
    assert made == [0, 1, 2] and [r.floor for r in again] == [r.floor for r in first]
    states, floors, _ = ensemble._BLOCKS[next(iter(ensemble._BLOCKS))]
    monkeypatch.setattr(ensemble, "KEPT_BYTES", 2 * (states.nbytes + floors.nbytes))
    ensemble.forget()
    made.clear()
    for _ in range(2):
        ensemble.references(case, 1, 0, lanes, 0.5)
    assert made == [0, 1, 2, 0, 1, 2] and len(ensemble._BLOCKS) == 2


def test_ensemble_final_errors_are_each_lanes_against_its_reference(monkeypatch):
    """The per-lane table holds each lane's final error against its own reference, with
    its floor; the record's final error is the worst lane's and its floor the largest; a
    block of references that runs out of evaluations leaves its lanes without a final
    error, no summary of final errors and the run ok, its message saying why."""
    spec = RunSpec("pendulum", "lobatto3ab3", h=0.1, t_end=5.0, lanes=6, seed=1)
    record = execute(plan([spec], "test")[0], repeats=1)
    lanes = record.lanes
    assert record.ending.status == "ok" and np.isfinite(lanes["final_state_error"]).all()
    refs, _ = ensemble.references(problems.make("pendulum").with_t_end(5.0), 1, 0, 6, 5.0)
    np.testing.assert_array_equal(lanes["reference_floor"][1:], [r.floor for r in refs[1:]])
    assert lanes["reference_floor"][0] == 0.0  # lane 0: the closed form
    assert record.metrics.final_state_error == np.max(lanes["final_state_error"])
    assert record.metrics.scd == np.min(lanes["scd"])
    assert record.metrics.reference_floor == np.max(lanes["reference_floor"])
    assert record.spread.final_q0 == np.min(lanes["final_state_error"])
    assert record.spread.final_q100 == np.max(lanes["final_state_error"])
    monkeypatch.setattr(ensemble, "MAX_REFERENCE_EVALS", 10)
    monkeypatch.setattr(ensemble, "_BLOCKS", type(ensemble._BLOCKS)())
    spent = execute(plan([spec], "test")[0], repeats=1)
    assert spent.ending.status == "ok"
    assert spent.ending.message == (
        "no final errors: no reference for lanes 0 to 255: DOP853 needed more than 10 "
        "right-hand sides (problems.ensemble.MAX_REFERENCE_EVALS)")
    assert np.isnan(spent.lanes["final_state_error"][1:]).all()
    assert spent.lanes["final_state_error"][0] == lanes["final_state_error"][0]
    # Lane 0 alone is no distribution: no summary of final errors at all.
    assert spent.metrics.final_state_error is None and spent.spread.final_q50 is None
    assert spent.metrics.reference_floor is None and spent.metrics.scd is None
    # A block that could not be made, none of whose lanes finished (here: none ran), takes
    # nothing from the lanes that did, and the message does not say it does.
    real = ensemble.references
    monkeypatch.undo()  # evaluations as before, and without the blocks that ran out
    monkeypatch.setattr(ensemble, "references", lambda *a: (
        real(*a)[0], ("lanes 256 to 511: no lane of it finished",)))
    other = execute(plan([spec], "test")[0], repeats=1)
    assert other.ending.message == "" and other.spread.final_q100 == record.spread.final_q100


def test_final_error_quantiles_at_the_reference_floor_say_so():
    from reports.ensembles import _final

    row = pd.Series({"final_q50": 2e-9, "final_q100": 3e-7, "reference_floor": 1e-8})
    assert (_final(row, 50), _final(row, 100)) == ("at floor", "3e-07")
    exact = pd.Series({"final_q50": 0.0, "reference_floor": 0.0})  # a closed form
    assert _final(exact, 50) == "0"
    assert _final(pd.Series({"final_q50": np.nan, "reference_floor": np.nan}), 50) == ""
