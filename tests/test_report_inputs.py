"""What the report takes from other layers: the gate's rule for a regression (its history
must mark exactly what the gate fails) and a suite's accuracy targets."""

from dataclasses import asdict

import pytest

from benchmarks import check, records, suites


def test_the_history_and_the_gate_share_one_regression_rule():
    assert {k: asdict(v) for k, v in records.TOLERANCES.items()} == \
        {k: asdict(v) for k, v in check.TOLERANCES.items()}
    assert asdict(records.INVARIANT_TOLERANCE) == asdict(check.INVARIANT_TOLERANCE)
    cases = [("max_pos_residual", 1e-10, 5e-10), ("max_pos_residual", 1e-10, 3e-10),
             ("max_pos_residual", 1e-15, 1e-14), ("scd", 10.0, 9.0), ("scd", 10.0, 9.5),
             ("final_state_error", 1e-6, None), ("final_state_error", 1e-6, float("inf"))]
    for metric, base, cur in cases:
        assert records.compare_metric(metric, base, cur) == check.compare_metric(metric, base,
                                                                                 cur)


def test_a_suite_sets_its_accuracy_targets(tmp_path):
    body = '[[group]]\nproblems = ["pendulum"]\nintegrators = ["rattle"]\nh = [0.1]\n'
    path = tmp_path / "mine.toml"
    path.write_text("targets = [1e-6, 1e-10]\n" + body)
    assert suites.load(str(path)).targets == (1e-6, 1e-10)
    path.write_text(body)
    assert suites.load(str(path)).targets == ()
    path.write_text("targets = [0.0]\n" + body)
    with pytest.raises(suites.SuiteError, match=r"mine.toml:1: 'targets' = 0.0 must be positive"):
        suites.load(str(path))
