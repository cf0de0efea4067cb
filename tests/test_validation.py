"""Bad input is refused before any run starts: one line naming what and where, exit status 2.

Every case runs the command line in-process (``benchmarks.run.main``) and checks that the
error is one line starting with ``error:``, holds the expected words, shows no traceback
and that nothing was written under ``--out``.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from benchmarks import run
from benchmarks.executors import PLUGIN_ENV
from benchmarks.records import CODE_VERSION_ENV

PLUGIN = Path(__file__).parent / "plugins" / "faulty.py"
GOOD = ["--problems", "pendulum", "--integrators", "rattle"]

#: (id, arguments, words the message must hold)
COMMAND_LINES = [
    ("unknown-problem", ["--problems", "pendulm", "--integrators", "rattle"],
     ["unknown problem 'pendulm'", "did you mean pendulum"]),
    ("unknown-integrator", ["--problems", "pendulum", "--integrators", "ratle"],
     ["unknown integrator 'ratle'", "did you mean rattle"]),
    ("unknown-suite", ["--suite", "seed-spz"], ["unknown suite 'seed-spz'", "seed-sps"]),
    ("unknown-parameter", ["--problems", "pendulum:Lx=2", "--integrators", "rattle"],
     ["problem 'pendulum' has no parameter 'Lx'", "did you mean L"]),
    ("parameter-type", ["--problems", "pendulum:L=abc", "--integrators", "rattle"],
     ["parameter 'L'", "'abc' is not a valid float"]),
    ("malformed-spec", ["--problems", "pendulum:L", "--integrators", "rattle"],
     ["'pendulum:L'", "not of the form key=value"]),
    ("unknown-option", ["--problems", "pendulum", "--integrators", "rattle:newton_tl=1e-10"],
     ["integrator 'rattle' has no option 'newton_tl'", "did you mean newton_tol"]),
    ("h-zero", [*GOOD, "--h", "0"], ["--h 0", "positive"]),
    ("h-negative", [*GOOD, "--h", "0.1", "-0.05"], ["--h -0.05", "positive"]),
    ("h-nan", [*GOOD, "--h", "nan"], ["--h nan", "finite"]),
    ("h-not-a-number", [*GOOD, "--h", "abc"], ["--h", "invalid float value: 'abc'"]),
    ("t-end-negative", [*GOOD, "--t-end", "-5"], ["--t-end -5", "positive"]),
    ("rtol-above-one", [*GOOD, "--rtol", "1.5"], ["--rtol 1.5", "(0, 1)"]),
    ("stages-unsupported", ["--problems", "pendulum", "--integrators", "lobatto3ab3:stages=9"],
     ["stages = 9", "2..6"]),
    ("newton-iterations", ["--problems", "pendulum", "--integrators", "rattle:newton_max_iter=0"],
     ["newton_max_iter = 0", ">= 1"]),
    ("modes-below-one", ["--problems", "flexible-spacecraft:n_modes=-1", "--integrators",
                         "rattle"], ["n_modes = -1"]),
    ("timeout-negative", [*GOOD, "--timeout", "-1"], ["--timeout -1", "positive"]),
    ("jobs-zero", [*GOOD, "--jobs", "0"], ["--jobs 0", "from 1 to"]),
    ("repeats-zero", [*GOOD, "--repeats", "0"], ["--repeats 0", "at least 1"]),
    ("mass-negative", ["--problems", "pendulum:mass=-1", "--integrators", "rattle"],
     ["pendulum", "mass = -1.0", "positive"]),
    ("lattice-spacing-zero", ["--problems", "sps-lattice:H=0", "--integrators", "rattle"],
     ["sps-lattice", "H = 0.0", "positive"]),
    ("initial-values-not-finite", ["--problems", "pendulum:theta0=nan", "--integrators", "rattle"],
     ["pendulum", "initial values are not finite"]),
    ("initial-values-inconsistent", ["--problems", "test-offset-pendulum:dx=0.01",
                                     "--integrators", "rattle"],
     ["inconsistent initial values", "|g(q0)| = 2.010e-02"]),
    ("suite-and-problems", ["--suite", "seed-sps", *GOOD], ["either --suite or --problems"]),
    ("problems-alone", ["--problems", "pendulum"], ["needs both --problems and --integrators"]),
    ("cluster-malformed", [*GOOD, "--cluster", "locl:2"], ["cluster 'locl:2'", "local:N"]),
    ("jobs-and-cluster", [*GOOD, "--jobs", "1", "--cluster", "local:1"],
     ["either jobs", "or a cluster"]),
    ("jobs-too-many", [*GOOD, "--jobs", "100000"], ["--jobs 100000", "per usable core"]),
    ("cluster-too-many", [*GOOD, "--cluster", "local:100000"],
     ["cluster 'local:100000'", "per usable core"]),
    ("seed-too-large", [*GOOD, "--ensemble", "2", "--seed", str(2 ** 63)],
     [f"--seed {2 ** 63}", f"{2 ** 63 - 1}"]),
    ("seed-without-ensemble", [*GOOD, "--seed", "3"], ["seed applies to ensembles only"]),
    ("device-without-ensemble", [*GOOD, "--device", "cpu"],
     ["device applies to ensembles only"]),
    ("suite-seed-without-ensembles", ["--suite", "seed-sps", "--seed", "3"],
     ["--seed applies to ensembles only", "suite 'seed-sps' has none"]),
    ("linear-solver-unknown", ["--problems", "pendulum", "--integrators",
                               "rattle:linear_solver=lu"],
     ["rattle.py:", "linear_solver = 'lu'", "auto, dense, banded"]),
    ("h-in-spec-and-swept", ["--problems", "pendulum", "--integrators", "rattle:h=0.02", "--h",
                             "0.01"], ["'rattle:h=0.02' sets h = 0.02", "also swept"]),
]

#: (id, suite file text, line the message must name (0: none), words it must hold)
SUITE_FILES = [
    ("invalid-toml", 'description = "x"\n[[group]\nproblems = ["pendulum"]\n', 2,
     ["invalid TOML"]),
    ("unknown-key", '[[group]]\nproblems = ["pendulum"]\nintgrators = ["rattle"]\n', 3,
     ["unknown key 'intgrators' in [[group]] 1", "did you mean integrators"]),
    ("wrong-type", '[[group]]\nproblems = ["pendulum"]\nintegrators = ["rattle"]\nh = "0.1"\n', 4,
     ["'h' in [[group]] 1 must be a list of numbers"]),
    ("h-out-of-range", '[[group]]\nproblems = ["pendulum"]\nintegrators = ["rattle"]\n'
                       'h = [0.1, -0.2]\n', 4, ["-0.2", "positive"]),
    ("unknown-integrator-in-second-group",
     '[[group]]\nproblems = ["pendulum"]\nintegrators = ["rattle"]\n\n'
     '[[group]]\nproblems = ["pendulum"]\nintegrators = ["lobato3ab3"]\n', 7,
     ["unknown integrator 'lobato3ab3'", "[[group]] 2", "lobatto3ab3"]),
    ("unknown-problem", '[[group]]\nproblems = ["pendulum", "sps-reciever"]\n'
                        'integrators = ["rattle"]\n', 2,
     ["unknown problem 'sps-reciever'", "sps-receiver"]),
    ("missing-integrators", 'description = "x"\n\n[[group]]\nproblems = ["pendulum"]\n', 3,
     ["lacks the required key 'integrators'"]),
    ("unknown-study", 'studies = ["flexible-modl"]\n', 1,
     ["unknown study 'flexible-modl'", "flexible-modal"]),
    ("timeout-negative", 'timeout = -3\n[[group]]\nproblems = ["pendulum"]\n'
                         'integrators = ["rattle"]\n', 1, ["timeout", "-3", "positive"]),
    ("budget-zero", 'description = "x"\nbudget = 0\n[[group]]\nproblems = ["pendulum"]\n'
                    'integrators = ["rattle"]\n', 2, ["budget", "positive number of seconds"]),
    ("repeats-boolean", 'repeats = true\n[[group]]\nproblems = ["pendulum"]\n'
                        'integrators = ["rattle"]\n', 1, ["'repeats' must be a whole number"]),
    ("empty", 'description = "nothing"\n', 0, ["no [[group]] table and no studies"]),
    ("cluster-no-workers", 'cluster = "local:0"\n[[group]]\nproblems = ["pendulum"]\n'
                           'integrators = ["rattle"]\n', 1, ["cluster 'local:0'", "takes 1 to"]),
    ("seed-too-large", '[[group]]\nproblems = ["pendulum"]\nintegrators = ["rattle"]\n'
                       f'ensemble = 2\nseed = {2 ** 63}\n', 5, ["'seed'", "64-bit"]),
    ("seed-negative", '[[group]]\nproblems = ["pendulum"]\nintegrators = ["rattle"]\n'
                      'ensemble = 2\nseed = -1\n', 5, ["'seed'", f"0 to {2 ** 63 - 1}"]),
    ("h-beyond-int64", '[[group]]\nproblems = ["pendulum"]\nintegrators = ["rattle"]\n'
                      f'h = [1{"0" * 400}]\n', 4, ["'h'", "beyond TOML's 64-bit range"]),
    ("timeout-beyond-int64", f'timeout = {2 ** 63}\n[[group]]\nproblems = ["pendulum"]\n'
                             'integrators = ["rattle"]\n', 1, ["'timeout'", "64-bit"]),
    ("group-as-one-table", 'description = "x"\n\n[group]\nproblems = ["pendulum"]\n', 3,
     ["'group' must be an array of [[group]] tables"]),
    ("seed-without-ensemble", '[[group]]\nproblems = ["pendulum"]\nintegrators = ["rattle"]\n'
                              'seed = 4\n', 4, ["'seed' in [[group]] 1 applies to ensembles"]),
    ("bad-parameter-in-group", '[[group]]\nproblems = ["pendulum:L=-1"]\n'
                               'integrators = ["rattle"]\nh = [0.1]\n', 1,
     ["([[group]] 1)", "pendulum", "L = -1.0", "positive"]),
]


@pytest.fixture(autouse=True)
def plugins(monkeypatch):
    monkeypatch.setenv(PLUGIN_ENV, str(PLUGIN))
    monkeypatch.setenv(CODE_VERSION_ENV, "test-version")


def refused(argv, capsys) -> str:
    """Run the command line; assert it was refused on one line; return that line."""
    try:
        code = run.main(argv)
    except SystemExit as exc:  # argparse's own errors leave through SystemExit
        code = exc.code
    err = capsys.readouterr().err
    assert code == 2
    assert "Traceback" not in err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    return lines[0]


@pytest.mark.parametrize("argv, words", [c[1:] for c in COMMAND_LINES],
                         ids=[c[0] for c in COMMAND_LINES])
def test_bad_command_lines_are_refused_on_one_line(argv, words, tmp_path, capsys):
    out = tmp_path / "out"
    line = refused([*argv, "--out", str(out), "--no-report"], capsys)
    for word in words:
        assert word in line
    assert not out.exists()


@pytest.mark.parametrize("text, line_no, words", [c[1:] for c in SUITE_FILES],
                         ids=[c[0] for c in SUITE_FILES])
def test_bad_suite_files_are_refused_with_file_and_line(text, line_no, words, tmp_path, capsys):
    path = tmp_path / "bad.toml"
    path.write_text(text)
    out = tmp_path / "out"
    line = refused(["--suite", str(path), "--out", str(out), "--no-report"], capsys)
    assert str(path) in line
    if line_no:
        assert f"{path}:{line_no}" in line
    for word in words:
        assert word in line
    assert not out.exists()


@pytest.mark.parametrize("target", ["no_such_module:Euler", "integrators.rattle:NoSuchClass",
                                    "integrators.base:Grid"])
def test_a_registration_of_no_integrator_class_is_refused_where_it_is_made(target, tmp_path,
                                                                            capsys):
    user = tmp_path / "mine.py"
    user.write_text(f"import integrators\n\nintegrators.register('mine', {target!r})\n")
    line = refused(["--load", str(user), *GOOD, "--out", str(tmp_path / "out")], capsys)
    assert f"{user}:3" in line and "'mine'" in line and repr(target) in line


def test_a_suites_ensembles_take_the_seed_and_its_single_runs_stay_single(tmp_path):
    suite = tmp_path / "mixed.toml"
    suite.write_text('[[group]]\nproblems = ["pendulum"]\nintegrators = ["rattle"]\n'
                     'h = [0.1]\n\n[[group]]\nproblems = ["pendulum"]\n'
                     'integrators = ["rattle"]\nh = [0.05]\nensemble = 4\nseed = 1\n')
    runs, _, _ = run.plan(run.parser().parse_args(["--suite", str(suite), "--seed", "5",
                                                   "--device", "cpu"]))
    assert [(r.h, r.lanes, r.seed, r.device) for r in runs] == \
        [(0.1, None, None, None), (0.05, 4, 5, "cpu")]
    runs, _, _ = run.plan(run.parser().parse_args(["--suite", str(suite), "--ensemble", "8"]))
    assert [(r.lanes, r.seed) for r in runs] == [(8, 0), (8, 1)]


@pytest.mark.slow
def test_the_python_api_takes_one_name_or_number_alone_and_names_a_bad_setting():
    from benchmarks.api import sweep
    from benchmarks.records import InputError

    with pytest.raises(InputError, match="^unknown problem 'pendulm'"):
        sweep("pendulm", "rattle")
    with pytest.raises(InputError, match=r"^h = \['abc'\]: not a number"):
        sweep("pendulum", "rattle", h=["abc"])
    with pytest.raises(InputError, match="^t_end = 'long': not a number"):
        sweep("pendulum", "rattle", t_end="long")
    runs = sweep("pendulum", "rattle", h=0.1, t_end=0.5, jobs=1, log=None)
    assert list(runs["h"]) == [0.1] and list(runs["status"]) == ["ok"]
