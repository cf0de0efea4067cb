"""The drift gate: direction-aware comparison, and a planted regression that must fail it."""

import dataclasses
import json
import os
import subprocess
import sys
import textwrap

import pytest

import benchmarks.plan as plan_module
from benchmarks import check
from benchmarks.executors import PLUGIN_ENV
from benchmarks.gate import compare, compare_metric
from integrators.lobatto import LobattoIIIAIIIB


def entry(status="ok", sensitive=False, fail_step=None, **metrics):
    return {"status": status, "message": "", "fail_step": fail_step, "sensitive": sensitive,
            "metrics": metrics}


@pytest.mark.parametrize("metric, base, cur, verdict", [
    ("max_pos_residual", 1e-10, 1e-8, "regression"),     # 100x worse, above the floor
    ("max_pos_residual", 1e-8, 1e-10, "improvement"),
    ("max_pos_residual", 1e-10, 3e-10, None),             # within the factor
    ("max_pos_residual", 4e-16, 5e-14, None),             # both at round-off
    ("max_pos_residual", 4e-16, 5e-12, "regression"),     # out of round-off
    ("scd", 6.0, 4.0, "regression"),                       # higher is better: 2 digits lost
    ("scd", 4.0, 6.0, "improvement"),
    ("scd", 6.0, 5.9, None),
    ("scd", 13.0, 15.0, None),                             # beyond the digit floor: round-off
    ("final_state_error", 1e-6, None, "regression"),       # no longer measured
    ("final_state_error", 1e-6, float("inf"), "regression"),
    ("inv:angular momentum", 1e-9, 1e-6, "regression"),
])
def test_metrics_are_compared_in_their_direction(metric, base, cur, verdict):
    assert compare_metric(metric, base, cur)[0] == verdict


def test_status_changes_and_sensitive_problems():
    base = {"a": entry(max_pos_residual=1e-10), "b": entry("failed", fail_step=5),
            "c": entry(max_pos_residual=1e-10, sensitive=True), "gone": entry()}
    cur = {"a": entry("failed", fail_step=3), "b": entry("failed", fail_step=2),
           "c": entry(max_pos_residual=1e-3, sensitive=True), "new": entry()}
    found = {(f.run, f.metric): f for f in compare(base, cur)}
    assert found[("a", "status")].kind == "regression" and found[("a", "status")].gating
    assert found[("b", "fail_step")].kind == "regression"  # fails earlier than before
    sensitive = found[("c", "max_pos_residual")]
    assert sensitive.kind == "regression" and not sensitive.gating
    assert not found[("new", "run")].gating
    # A baseline run that did not run would let the gate pass by comparing less.
    assert found[("gone", "run")].kind == "regression" and found[("gone", "run")].gating
    back = {(f.run, f.metric): f.kind for f in compare(cur, base)}
    assert back[("a", "status")] == "improvement"


def test_final_errors_below_the_reference_floor_are_the_references_not_the_methods():
    """A final error that moved only below the larger of the two runs' reference floors
    (an ensemble's lanes are scored against computed references) is no change, nor are
    its digits; one that rose above it is a regression."""
    base = {"a": {**entry(final_state_error=8.2e-14, scd=13.0), "floor": 1e-15}}
    cur = {"a": {**entry(final_state_error=3.6e-12, scd=11.2), "floor": 1.1e-11}}
    assert compare(base, cur) == []
    cur["a"]["metrics"].update(final_state_error=1e-9, scd=8.0)
    found = {f.metric: f.kind for f in compare(base, cur)}
    assert found == {"final_state_error": "regression", "scd": "regression"}
    # Without a floor (an older baseline's entry) the first change is a regression (its
    # digits, both beyond scd's floor of 11, are not).
    del base["a"]["floor"]
    cur["a"].update(floor=None, metrics={"final_state_error": 3.6e-12, "scd": 11.2})
    assert [f.metric for f in compare(base, cur)] == ["final_state_error"]


def test_drift_classes_that_grow_faster_regress():
    base = {"a": {**entry(), "growth": {"pos_growth": "bounded", "energy_growth": "linear"}}}
    cur = {"a": {**entry(), "growth": {"pos_growth": "quadratic", "energy_growth": "bounded"}}}
    found = {f.metric: f for f in compare(base, cur)}
    assert found["pos_growth"].kind == "regression" and found["pos_growth"].gating
    assert found["energy_growth"].kind == "improvement"
    # An indeterminate class (too few windows) compares with nothing.
    cur["a"]["growth"]["pos_growth"] = "indeterminate"
    assert "pos_growth" not in {f.metric for f in compare(base, cur)}


def test_metrics_that_round_off_decides_are_compared_but_not_gating():
    base = {"a": {**entry(max_pos_residual=1e-11, max_vel_residual=1e-12),
                  "growth": {"pos_growth": "bounded"},
                  "roundoff": ["max_pos_residual", "pos_growth"]}}
    cur = {"a": {**entry(max_pos_residual=3e-8, max_vel_residual=1e-8),
                 "growth": {"pos_growth": "exponential"}}}
    found = {f.metric: f for f in compare(base, cur)}
    assert found["max_pos_residual"].kind == "regression"
    assert not found["max_pos_residual"].gating and not found["pos_growth"].gating
    assert found["max_vel_residual"].gating  # not in the list: gated as before
    cur["a"]["status"] = "failed"  # a run's status is always gated
    assert {f.metric: f for f in compare(base, cur)}["status"].gating


@pytest.mark.parametrize("final, scd, expect", [
    (3.0e-5, 5.3, {}),  # inside the range round-off gave: neither
    (1.3e-3, 4.3, {"final_state_error": "regression"}),  # over 4x its worst end
    (2.0e-6, 6.2, {"final_state_error": "improvement", "scd": "improvement"}),
    (2.6e-4, 3.5, {"scd": "regression"}),  # 0.6 digits below the fewest the probes had
])
def test_a_metric_with_a_round_off_spread_is_gated_from_its_ends(final, scd, expect):
    """ida-ggl on andrews: the final error ranged 1.7e-5 to 3.0e-4 over initial positions
    scaled by 1 + eps, |eps| <= 2e-14; a factor of four from the one baseline value would
    fail on either side of it (benchmarks.check)."""
    base = {"a": {**entry(final_state_error=2.6e-4, scd=4.3, max_pos_residual=1e-12),
                  "roundoff": ["final_state_error", "scd", "pos_growth"],
                  "spread": {"final_state_error": [1.7e-5, 3.0e-4], "scd": [4.2, 5.5]}}}
    cur = {"a": entry(final_state_error=final, scd=scd, max_pos_residual=1e-12)}
    found = {f.metric: f for f in compare(base, cur)}
    assert {m: f.kind for m, f in found.items()} == expect
    assert all(f.gating for f in found.values())
    # Without its spread a listed metric is compared but not gating, as before.
    del base["a"]["spread"]
    assert not any(f.gating for f in compare(base, cur))


PROBED = """
description = "round-off probe test: an adaptive run that round-off decides, and one it does not"
[[group]]
problems = ["flyball-governor"]
integrators = ["ida-ggl"]
rtol = [1e-8]
atol = [1e-8]
t_end = 2.0

[[group]]
problems = ["andrews"]
integrators = ["ida-ggl"]
rtol = [1e-6]
atol = [1e-8]

[[group]]
problems = ["pendulum"]
integrators = ["baumgarte-dopri5"]
rtol = [1e-8]
atol = [1e-10]
t_end = 5.0
"""


@pytest.mark.slow
def test_update_probes_adaptive_runs_and_lists_what_round_off_decides(tmp_path, monkeypatch):
    """ida-ggl on the flyball governor: initial positions scaled by 1 + eps move max |g|
    from 9.7e-12 past the gate's factor; on andrews they move the final error, measured
    against the unperturbed reference (module notes of benchmarks.check)."""
    suite, baseline = tmp_path / "probe.toml", tmp_path / "baseline.json"
    suite.write_text(PROBED)
    args = ["--suite", str(suite), "--baseline", str(baseline), "--jobs", "1"]
    # A probe's case has its run's system: the library's here, which no audit checks.
    audited = []
    monkeypatch.setattr(plan_module, "audit", lambda case, notes=None: audited.append(case))
    assert check.main([*args, "--update"]) == 0
    assert audited == []
    runs = json.loads(baseline.read_text())["runs"]
    flyball = runs["flyball-governor / ida-ggl / rtol=1e-08 atol=1e-08 / t_end=2"]
    assert "max_pos_residual" in flyball["roundoff"]
    lo, hi = flyball["spread"]["max_pos_residual"]
    assert lo <= flyball["metrics"]["max_pos_residual"] <= hi and hi > 4 * lo
    andrews = runs["andrews / ida-ggl / rtol=1e-06 atol=1e-08 / t_end=0.03"]
    assert "final_state_error" in andrews["roundoff"]
    lo, hi = andrews["spread"]["final_state_error"]
    assert 1e-6 < lo and hi > 4 * lo and hi < 1e-2  # errors of the method, not of a lost reference
    assert "roundoff" not in runs["pendulum / baumgarte-dopri5 / rtol=1e-08 atol=1e-10 / t_end=5"]
    assert check.main(args) == 0


SUITE = """
description = "drift gate test: two deterministic short runs"
[[group]]
problems = ["pendulum"]
integrators = ["lobatto3ab3", "rattle"]
h = [0.05]
t_end = 5.0
"""

NEWTON_TOL = next(f.default for f in dataclasses.fields(LobattoIIIAIIIB) if f.name == "newton_tol")
#: The planted regression: lobatto3ab3's Newton tolerance loosened a millionfold, as if a
#: code change had altered its preset (run keys and the suite stay the same).
PLANT = textwrap.dedent(f"""
    import integrators
    target, preset = integrators.REGISTRY["lobatto3ab3"]
    integrators.REGISTRY["lobatto3ab3"] = (target, {{**preset, "newton_tol": {NEWTON_TOL * 1e6!r}}})
""")


@pytest.mark.slow
def test_the_gate_passes_unchanged_code_and_fails_a_planted_regression(tmp_path):
    suite, baseline = tmp_path / "gate.toml", tmp_path / "baseline.json"
    suite.write_text(SUITE)
    args = ["--suite", str(suite), "--baseline", str(baseline), "--jobs", "1"]
    assert check.main([*args, "--update"]) == 0
    data = json.loads(baseline.read_text())
    assert len(data["runs"]) == 2 and data["commit"] is not None

    assert check.main(args) == 0  # the same code again: deterministic, so nothing moves

    plugin = tmp_path / "loose_newton.py"
    plugin.write_text(PLANT)
    env = {**os.environ, PLUGIN_ENV: str(plugin)}
    proc = subprocess.run([sys.executable, "-m", "benchmarks.check", *args], env=env,
                          capture_output=True, text=True, timeout=900)
    assert proc.returncode == check.EXIT_REGRESSION, proc.stdout + proc.stderr
    regressions = [line for line in proc.stdout.splitlines() if line.startswith("regression")]
    assert regressions, proc.stdout
    assert all("lobatto3ab3" in line for line in regressions)  # rattle is untouched
    assert any("max_vel_residual" in line for line in regressions), proc.stdout
    assert "FAILED" in proc.stdout


def test_bad_input_exits_2_before_running(tmp_path, capsys):
    assert check.main(["--suite", "no-such-suite", "--baseline", str(tmp_path / "b.json")]) == 2
    assert "unknown suite" in capsys.readouterr().err
    suite = tmp_path / "gate.toml"
    suite.write_text(SUITE)
    assert check.main(["--suite", str(suite), "--baseline", str(tmp_path / "none.json")]) == 2
    assert "--update" in capsys.readouterr().err


def baseline_file(path, suite="gate", runs=None):
    runs = {"pendulum / rattle / h=0.05 / t_end=5": entry(max_pos_residual=1e-12)} \
        if runs is None else runs
    path.write_text(json.dumps({"format": check.BASELINE_FORMAT, "suite": suite,
                                "runs": runs}, allow_nan=True))
    return path


@pytest.mark.parametrize("suite, runs, words", [
    ("library", None, "made for suite 'library', not 'gate'"),
    ("gate", {}, "holds no runs"),
    ("gate", {"a": {"status": "ok"}}, "run 'a' needs a status and metrics"),
    ("gate", {"a": {"metrics": {}}}, "run 'a' needs a status and metrics"),
    ("gate", {"a": entry(max_pos_residual=float("nan"))}, "max_pos_residual = nan"),
    ("gate", {"a": entry(final_state_error=float("inf"))}, "final_state_error = inf"),
    ("gate", {"a": entry(scd="12")}, "scd = '12'"),
    ("gate", {"a": entry(scd=10 ** 400)}, "scd = 1000000000"),   # beyond a float
    ("gate", {"a": {**entry(), "floor": -1.0}}, "floor = -1.0 must be a reference floor"),
    ("gate", {"a": {**entry(), "roundoff": "max_pos_residual"}}, "roundoff must be a list"),
    ("gate", {"a": {**entry(), "spread": {"scd": [1.0]}}}, "spread must map metric names"),
    ("gate", {"a": {**entry(), "spread": {"final_state_error": [1e-5, float("nan")]}}},
     "spread must map metric names"),
])
def test_baselines_that_cannot_gate_are_refused_before_anything_runs(suite, runs, words,
                                                                      tmp_path, capsys):
    (tmp_path / "gate.toml").write_text(SUITE)
    base = baseline_file(tmp_path / "b.json", suite, runs)
    out = tmp_path / "out"
    code = check.main(["--suite", str(tmp_path / "gate.toml"), "--baseline", str(base),
                       "--out", str(out)])
    err = capsys.readouterr().err
    assert code == check.EXIT_INPUT and words in err, err
    assert len(err.strip().splitlines()) == 1
    assert not out.exists()  # refused before the batch made its output folder


def test_an_exact_final_state_is_a_valid_baseline(tmp_path):
    # scd = +inf is what a run matching its reference exactly records; it is comparable.
    base = baseline_file(tmp_path / "b.json", runs={"a": entry(scd=float("inf"))})
    assert check.read_baseline(base, "gate")["runs"]["a"]["metrics"]["scd"] == float("inf")


def test_a_baseline_run_missing_from_the_results_fails_and_the_count_is_said(
        tmp_path, monkeypatch, capsys):
    from benchmarks.records import Ending, Metrics, Record, Run, RunSpec, Status
    (tmp_path / "gate.toml").write_text(SUITE)
    ran = RunSpec("pendulum", "rattle", 0.05, t_end=5.0)
    gone = RunSpec("pendulum", "lobatto3ab3", 0.05, t_end=5.0)
    base = baseline_file(tmp_path / "b.json", runs={
        ran.label(): entry(max_pos_residual=1e-12), gone.label(): entry(max_pos_residual=1e-12)})
    # Only the gate's bookkeeping is under test: the batch returns one of the two runs.
    monkeypatch.setattr(check, "run_specs", lambda *a, **k: [Record(
        Run("pendulum", "rattle", h=0.05, t_end=5.0), Ending(Status.OK),
        metrics=Metrics(max_pos_residual=1e-12))])
    code = check.main(["--suite", str(tmp_path / "gate.toml"), "--baseline", str(base)])
    out = capsys.readouterr().out.strip().splitlines()
    assert code == check.EXIT_REGRESSION
    assert any("in the baseline, not run" in line and "lobatto3ab3" in line for line in out)
    assert out[-1].startswith("drift gate FAILED: compared 1 runs") and "1 of its runs missing" \
        in out[-1], out[-1]
