"""User-defined problems: the worked examples, the Python API, loading from a file, a suite,
a module or a package, and malformed user code refused with its file named.
"""

from __future__ import annotations

import csv
import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

import problems
from benchmarks import run, suites
from benchmarks.api import sweep
from benchmarks.records import ACCURACY_COLUMNS, CODE_VERSION_ENV, InputError

ROOT = Path(__file__).resolve().parent.parent
SLIDER = str(ROOT / "examples" / "slider_crank.py")
SPHERE = str(ROOT / "examples" / "spherical_pendulum.py")


@pytest.fixture(autouse=True)
def pinned_version(monkeypatch):
    # Concurrent edits of the working tree must not change the code version mid-test.
    monkeypatch.setenv(CODE_VERSION_ENV, "test-version")


@pytest.mark.slow
def test_the_examples_run_with_every_family_and_meet_their_references(tmp_path):
    runs = sweep(["slider-crank", "spherical-pendulum"],
                 ["rattle", "lobatto3ab3", "ida-ggl", "baumgarte-dopri5"], h=[0.01],
                 rtol=[1e-8], t_end=2.0, load=[SLIDER, SPHERE], out=tmp_path, report=True,
                 repeats=1, log=None)
    assert (runs["status"] == "ok").all(), runs[["problem", "integrator", "message"]]
    exact = runs[runs["integrator"].isin(["rattle", "lobatto3ab3"])]
    # Both enforce g = 0 at step ends by Newton to round-off.
    assert (exact["max_pos_residual"] <= 1e-12).all()
    error = runs.set_index(["problem", "integrator"])["final_state_error"]
    # Order 4 at h = 0.01 over 2 s leaves ~1e-8 (a few periods, unit-size states); the
    # order-2 RATTLE ~1e-4; both far above the references' 1e-11 and far below O(1).
    for problem in ("slider-crank", "spherical-pendulum"):
        assert error[problem, "lobatto3ab3"] < 1e-6
        assert error[problem, "rattle"] < 1e-2
        assert error[problem, "lobatto3ab3"] < error[problem, "rattle"]
    # RATTLE is equivariant under rotations about the vertical: L_z holds to round-off.
    sphere = runs[(runs["problem"] == "spherical-pendulum") & (runs["integrator"] == "rattle")]
    assert json.loads(sphere["invariant_errors"].iloc[0])["L_z"] < 1e-12
    html = (tmp_path / "report.html").read_text()
    assert "Problem: slider-crank" in html and "Problem: spherical-pendulum" in html


@pytest.mark.slow
def test_the_command_line_and_the_python_api_agree_bit_for_bit(tmp_path, capsys):
    args = ["--load", SLIDER, "--problems", "slider-crank", "--integrators", "rattle",
            "--h", "0.02", "--t-end", "1", "--jobs", "1", "--repeats", "1", "--no-report"]
    assert run.main([*args, "--out", str(tmp_path / "cli")]) == 0
    with open(tmp_path / "cli" / "runs.csv") as fh:
        cli = next(csv.DictReader(fh))
    api = sweep(["slider-crank"], ["rattle"], h=[0.02], t_end=1.0, load=[SLIDER], jobs=1,
                repeats=1, out=tmp_path / "api", log=None)
    with open(tmp_path / "api" / "runs.csv") as fh:
        written = next(csv.DictReader(fh))
    # Same code, same pool settings: the same text in runs.csv, and the same numbers.
    assert {c: cli[c] for c in ACCURACY_COLUMNS} == {c: written[c] for c in ACCURACY_COLUMNS}
    assert float(cli["max_pos_residual"]) == api["max_pos_residual"].iloc[0]


@pytest.mark.slow
def test_a_case_object_runs_and_its_name_may_not_shadow_a_problem(tmp_path):
    problems.load(SPHERE)
    case = problems.make("spherical-pendulum:spin=1.2")
    mine = problems.make_case("my-nutating", case.system, case.q0, case.v0, (0.0, 1.0),
                              dict(case.params), case.energy_scale)
    runs = sweep([mine], ["rattle"], h=[0.05], jobs=1, repeats=1, log=None)
    assert list(runs["problem"]) == ["my-nutating"] and runs["status"].iloc[0] == "ok"
    assert runs["final_state_error"].isna().all()  # no reference: n/a, not a number
    with pytest.raises(InputError, match="registered"):
        sweep([problems.make("pendulum")], ["rattle"], h=[0.05], log=None)


def test_list_shows_where_problems_come_from(capsys):
    assert run.main(["--load", SLIDER, "--list"]) == 0
    out = capsys.readouterr().out
    assert "slider-crank: r=0.5" in out and f"[{Path(SLIDER).resolve()}]" in out
    assert "pendulum: L=1.0" in out and "[built-in]" in out


def test_a_suite_loads_files_relative_to_itself(tmp_path):
    (tmp_path / "models").mkdir()
    (tmp_path / "models" / "crank.py").write_text(Path(SLIDER).read_text()
                                                  .replace('"slider-crank"', '"crank-2"'))
    suite = tmp_path / "mine.toml"
    suite.write_text('load = ["models/crank.py"]\n[[group]]\nproblems = ["crank-2:r=0.4"]\n'
                     'integrators = ["rattle"]\nh = [0.1]\n')
    loaded = suites.load(str(suite))
    assert loaded.load == (str((tmp_path / "models" / "crank.py").resolve()),)
    assert str(loaded.runs[0].problem) == "crank-2:r=0.4"
    assert loaded.runs[0].problem.kwargs["r"] == 0.4  # resolved where the suite is read
    assert problems.origin("crank-2") == loaded.load[0]


@pytest.mark.slow
def test_an_installed_package_registers_through_its_entry_point(tmp_path):
    site = tmp_path / "site"
    (site / "fancy_mechanisms-1.0.dist-info").mkdir(parents=True)
    (site / "fancy_mechanisms-1.0.dist-info" / "METADATA").write_text(
        "Metadata-Version: 2.1\nName: fancy-mechanisms\nVersion: 1.0\n")
    (site / "fancy_mechanisms-1.0.dist-info" / "entry_points.txt").write_text(
        "[driftbench.problems]\nfancy = fancy_mechanisms\n")
    (site / "fancy_mechanisms.py").write_text(
        Path(SLIDER).read_text().replace('"slider-crank"', '"fancy-crank"'))
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(site), str(ROOT)])}
    out = subprocess.run([sys.executable, "-m", "benchmarks.run", "--list"], cwd=tmp_path,
                         env=env, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert "fancy-crank: r=0.5" in out.stdout
    assert "[package fancy-mechanisms (fancy_mechanisms)]" in out.stdout


HEADER = """
import itertools
import jax.numpy as jnp
import numpy as np
from problems import System, make_case, register

"""

#: A pendulum as a user writes it, with one thing wrong: {name}, {mass}, {potential},
#: {constraints}, {forces} and {q0} are filled in per case.
BODY = """
@register("{name}")
def factory(t_end: float = 0.5):
    system = System(n=2, m=1, mass={mass}, potential={potential},
                    constraints={constraints}, forces={forces})
    return make_case("{name}", system, {q0}, [0.0, 0.0], (0.0, t_end), {{}},
                     energy_scale=9.81)
"""

GOOD = dict(mass="np.ones(2)", potential="lambda q: 9.81 * q[1]",
            constraints="lambda q, t: jnp.array([q[0] ** 2 + q[1] ** 2 - 1.0])",
            forces="None", q0="[1.0, 0.0]")

#: (id, text of the file (None: no file), problem run, words the one-line error holds)
MALFORMED = [
    ("missing-file", None, "pendulum", ["no such Python file"]),
    ("syntax-error", "def broken(:\n    pass\n", "pendulum", ["SyntaxError"]),
    ("raises-on-import", "raise RuntimeError('cannot find my data file')\n", "pendulum",
     ["RuntimeError: cannot find my data file"]),
    ("registered-twice", BODY.format(**{**GOOD, "name": "pendulum"}), "pendulum",
     ["problem 'pendulum' registered twice", "built-in"]),
    ("wrong-shape", BODY.format(**{**GOOD, "name": "u-shape", "constraints":
                                   "lambda q, t: jnp.array([q @ q - 1.0, 0.0 * q[1]])"}), "u-shape",
     ["constraints(q, t)", "returns shape (2,), not (1,)"]),
    # The extra constraint not zero at q0: still its shape that is named, not the values.
    ("wrong-shape-not-zero", BODY.format(**{**GOOD, "name": "u-shape2", "constraints":
                                            "lambda q, t: jnp.array([q @ q - 1.0, q[0]])"}),
     "u-shape2", ["constraints(q, t) returns shape (2,), not (1,)"]),
    ("not-finite", BODY.format(**{**GOOD, "name": "u-nan", "potential":
                                  "lambda q: 9.81 * jnp.log(q[1])"}), "u-nan",
     ["potential(q)", "not finite"]),
    ("mass-not-spd", BODY.format(**{**GOOD, "name": "u-spd", "mass":
                                    "lambda q: jnp.diag(jnp.array([1.0, -1.0]))"}), "u-spd",
     ["mass", "not positive definite"]),
    ("kinetic-not-spd", BODY.format(**{**GOOD, "name": "u-kin", "mass":
                                       "None, kinetic=lambda q, v: 0.5 * (v[0] ** 2 - v[1] ** 2)"}),
     "u-kin", ["mass", "not positive definite"]),
    ("not-traceable", BODY.format(**{**GOOD, "name": "u-trace", "constraints":
                                     "lambda q, t: jnp.array([np.sqrt(q @ q) - 1.0])"}),
     "u-trace",
     ["not traceable by JAX"]),
    # Python control flow on q works on the concrete values autodiff alone sees, not in
    # the integrators' compiled programs.
    ("python-if-on-q", BODY.format(**{**GOOD, "name": "u-if", "potential":
                                      "lambda q: 9.81 * q[1] if q[1] > -2.0 else 0.0"}),
     "u-if", ["potential(q)", "TracerBoolConversionError", "not traceable by JAX"]),
    ("inconsistent", BODY.format(**{**GOOD, "name": "u-start", "q0": "[1.1, 0.0]"}), "u-start",
     ["inconsistent initial values"]),
]


@pytest.mark.parametrize("text, name, words", [c[1:] for c in MALFORMED],
                         ids=[c[0] for c in MALFORMED])
def test_malformed_user_files_are_refused_naming_the_file(text, name, words, tmp_path, capsys):
    path = tmp_path / "model.py"
    if text is not None:
        path.write_text(HEADER + text)
    out = tmp_path / "out"
    code = run.main(["--load", str(path), "--problems", name, "--integrators", "rattle",
                     "--h", "0.1", "--jobs", "1", "--out", str(out), "--no-report"])
    err = capsys.readouterr().err
    assert code == 2 and "Traceback" not in err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    assert str(path) in lines[0]
    for word in words:
        assert word in lines[0]
    assert not out.exists()


@pytest.mark.slow
def test_an_error_in_user_code_during_a_run_costs_that_run_alone(tmp_path, capsys):
    path = tmp_path / "drive.py"
    # A drive torque from NumPy code through a callback: it passes the audit (evaluated
    # and traced alone) but has no batching rule, which SPARK's stages need (their forces
    # are vmapped). JAX meets that when it batches the traced program, where no frame of
    # the user's file is on the stack: the message names where the problem is defined.
    path.write_text("import jax\n" + HEADER + BODY.format(**{
        **GOOD, "name": "u-drive", "forces": "lambda t, q, v: jax.pure_callback("
        "lambda q: np.zeros(2), jax.ShapeDtypeStruct((2,), jnp.float64), q)"}))
    out = tmp_path / "out"
    code = run.main(["--load", str(path), "--problems", "u-drive", "pendulum",
                     "--integrators", "lobatto3ab3", "--h", "0.1", "--t-end", "0.5",
                     "--jobs", "1", "--out", str(out), "--no-report"])
    assert code == 1, capsys.readouterr().err  # a run ended error: the others are written
    with open(out / "runs.csv") as fh:
        rows = {r["problem"]: r for r in csv.DictReader(fh)}
    assert rows["pendulum"]["status"] == "ok"
    assert rows["u-drive"]["status"] == "error"
    line = path.read_text().splitlines().index('@register("u-drive")') + 1
    assert rows["u-drive"]["message"].startswith(f"{path}:{line}: in problem 'u-drive': ")
    assert "pure_callback" in rows["u-drive"]["message"]


def test_user_code_is_loaded_by_the_module_name_too(tmp_path, monkeypatch):
    (tmp_path / "my_models.py").write_text(textwrap.dedent(
        Path(SLIDER).read_text().replace('"slider-crank"', '"module-crank"')))
    monkeypatch.syspath_prepend(str(tmp_path))
    assert problems.load("my_models") == "my_models"
    assert problems.origin("module-crank") == "module my_models"
    with pytest.raises(problems.LoadError, match="no such Python file or importable module"):
        problems.load("no_such_models_here")


@pytest.mark.slow
def test_the_drift_gate_takes_a_suite_that_loads_user_code(tmp_path, capsys):
    from benchmarks import check

    suite, baseline = tmp_path / "mine.toml", tmp_path / "baseline.json"
    suite.write_text(f'load = ["{SLIDER}"]\n[[group]]\nproblems = ["slider-crank"]\n'
                     'integrators = ["rattle"]\nh = [0.05]\nt_end = 0.5\n')
    args = ["--suite", str(suite), "--baseline", str(baseline), "--jobs", "1"]
    assert check.main([*args, "--update"]) == 0
    entry = json.loads(baseline.read_text())["runs"]["slider-crank / rattle / h=0.05 / t_end=0.5"]
    assert entry["status"] == "ok" and entry["metrics"]["final_state_error"] is not None
    assert check.main(args) == 0  # deterministic: nothing moves
    assert "drift gate passed" in capsys.readouterr().out
