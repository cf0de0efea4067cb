"""The user-written integrator of examples/euler_projection.py: loaded from its file as
``--load`` loads it, it passes the same catalogue checks as the built-in methods."""

import csv
from pathlib import Path

import pytest

import integrators
import problems
import test_catalogue as catalogue
from benchmarks import run
from benchmarks.records import CODE_VERSION_ENV

EXAMPLE = Path(__file__).resolve().parent.parent / "examples" / "euler_projection.py"
KEY = "euler-projection"


@pytest.fixture(scope="module", autouse=True)
def loaded():
    problems.load(str(EXAMPLE))


def test_the_example_is_short():
    assert len(EXAMPLE.read_text().splitlines()) < 100


@pytest.mark.parametrize("check", ["test_traits_are_declared",
                                   "test_enforced_levels_hold_and_others_drift",
                                   "test_symplectic_methods_keep_energy_bounded",
                                   "test_nominal_order_is_observed"])
def test_the_example_passes_the_catalogue(check):
    # The catalogue's own checks, applied as its parametrisation applies them: the
    # energy check only to symplectic methods, the order check only to fixed-step ones.
    method = integrators.make(KEY)
    if check == "test_symplectic_methods_keep_energy_bounded" and not method.symplectic:
        pytest.skip("not declared symplectic")
    if check == "test_nominal_order_is_observed" and method.adaptive:
        pytest.skip("adaptive")
    getattr(catalogue, check)(KEY)


@pytest.mark.slow
def test_the_example_runs_from_the_command_line(tmp_path, monkeypatch):
    monkeypatch.setenv(CODE_VERSION_ENV, "test-version")
    args = ["--load", str(EXAMPLE), "--problems", "pendulum", "--integrators", KEY,
            "--h", "0.01", "--t-end", "1", "--jobs", "1", "--repeats", "1", "--no-report",
            "--out", str(tmp_path)]
    assert run.main(args) == 0
    with open(tmp_path / "runs.csv") as fh:
        row = next(csv.DictReader(fh))
    assert row["integrator"] == KEY and row["status"] == "ok", row["message"]
    # Both levels are projected to round-off at every step.
    assert float(row["max_pos_residual"]) <= 1e-13
    assert float(row["max_vel_residual"]) <= 1e-13
