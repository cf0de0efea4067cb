"""A user's mistakes: each is one line that says what and where (the ``file:line`` of the
user's definition or call), the right exit status, and no result already written is lost.

The mistakes are made against an output folder that holds the results of an earlier
invocation (``--resume``): bad input is refused before the folder is touched, and a batch
whose runs end ``error`` keeps the earlier rows of the store. The user's mechanism is a
Kapitza pendulum (its pivot driven vertically, ``g(q, t) = |q - p(t)|^2 - L^2``), which the
suite does not ship. The words of most messages are checked further in
``tests/test_validation.py`` (command lines, suite files), ``tests/test_user.py``
(malformed files) and ``tests/test_origins.py`` (the line of every audit finding).
"""

from __future__ import annotations

import csv
import inspect
import json
import shutil
import sqlite3
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest

import problems
from benchmarks import audit, check, run
from benchmarks.audit import check_rheonomic
from benchmarks.executors import PLUGIN_ENV
from benchmarks.plan import plan
from benchmarks.records import CODE_VERSION_ENV, Ending, Metrics, Record, Run, RunSpec, Status
from problems import Perturbation, Reference, System, make_case
from problems.source import ArgumentError

PLUGIN = Path(__file__).parent / "plugins" / "faulty.py"

HEADER = """
import jax.numpy as jnp
import numpy as np
from problems import Reference, System, make_case, register

"""

#: The Kapitza pendulum as a user writes it, one argument a line, so that each has a line
#: of its own; {name} and the fields of GOOD are filled in per mistake.
KAPITZA = """
@register("{name}")
def kapitza(a: float = 0.05, omega: float = 40.0, t_end: float = 0.2):
    def pivot(t):
        return jnp.array([0.0, a * jnp.cos(omega * t)])

    system = System(n=2, m=1,
                    mass={mass},
                    potential={potential},
                    constraints={constraints},
                    rheonomic={rheonomic})
    reference = {reference}
    return make_case("{name}", system, {q0}, [0.0, 0.0], (0.0, t_end), {{}},
                     energy_scale={energy_scale}, reference=reference)
"""

GOOD = dict(mass="np.ones(2)", potential="lambda q: 9.81 * q[1]",
            constraints="lambda q, t: jnp.array([jnp.sum((q - pivot(t)) ** 2) - 1.0])",
            rheonomic="True", reference="None", q0="[0.6, a - 0.8]", energy_scale="9.81")

SOLUTION = "lambda t: (np.zeros(2), np.zeros(2))"

#: (id, what differs from GOOD, the text of the line the message must name, its words)
FILE_MISTAKES = [
    ("rheonomic-left-out", {"rheonomic": "False"}, "constraints=",
     ["depend on t", "declared scleronomic", "set rheonomic=True"]),
    ("python-if-on-q", {"potential": "lambda q: 9.81 * q[1] if q[1] < 0.0 else 0.0"},
     "potential=", ["TracerBoolConversionError", "not traceable by JAX"]),
    ("constraints-wrong-shape", {"constraints": "lambda q, t: jnp.array([q @ q - 1.0, q[0]])"},
     "return make_case", ["constraints(q, t) returns shape (2,), not (1,)"]),
    ("initial-values-inconsistent", {"q0": "[0.7, a - 0.8]"}, "return make_case",
     ["inconsistent initial values"]),
    ("mass-and-kinetic", {"mass": "np.ones(2), kinetic=lambda q, v: 0.5 * v @ v"},
     "system = System(", ["either as mass or as kinetic, not both"]),
    ("reference-scored-true", {"reference": f'Reference("exact", "x", {SOLUTION}, scored=True)'},
     "reference = ", ["Reference scored = True", "sequence of indices"]),
    ("reference-kind-unknown",
     {"reference": f'Reference("closed-form", "x", {SOLUTION}, scored=(0,))'},
     "reference = ", ["Reference kind 'closed-form'", "exact, published, computed"]),
    ("reference-solution-not-callable",
     {"reference": 'Reference("exact", "x", np.zeros(4), scored=(0,))'},
     "reference = ", ["Reference solution must be callable", "ndarray"]),
    ("reference-scored-past-the-state",
     {"reference": f'Reference("exact", "x", {SOLUTION}, scored=(0, 4))'},
     "return make_case", ["scored index 4", "2 n = 4"]),
    ("energy-scale-zero", {"energy_scale": "0.0"}, "return make_case",
     ["energy_scale = 0.0", "> 0"]),
]

#: (id, command-line arguments, words of the message) of mistakes without a user file.
COMMAND_MISTAKES = [
    ("problem-typo", ["--problems", "pendulm", "--integrators", "rattle"],
     ["unknown problem 'pendulm'"]),
    ("integrator-typo", ["--problems", "pendulum", "--integrators", "ratle"],
     ["unknown integrator 'ratle'"]),
    ("h-negative", ["--problems", "pendulum", "--integrators", "rattle", "--h", "-0.05"],
     ["--h -0.05", "positive"]),
    ("load-file-missing", ["--load", "no_such_dir/mine.py", "--problems", "pendulum",
                           "--integrators", "rattle"],
     ["no_such_dir/mine.py", "no such Python file"]),
]

#: The earlier invocation: one run that ends ok, one whose method fails (data).
EARLIER = ["--problems", "pendulum", "--integrators", "rattle", "test-nan", "--h", "0.1",
           "--t-end", "0.5", "--jobs", "1", "--no-report"]


def line_of(text: str, marker: str) -> int:
    """The line number of the one line of ``text`` that holds ``marker``."""
    lines = [i for i, line in enumerate(text.splitlines(), 1) if marker in line]
    assert len(lines) == 1, marker
    return lines[0]


def snapshot(folder: Path) -> dict[str, bytes]:
    """Every file under ``folder``, by relative path, with its bytes."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*"))
            if p.is_file()}


def stored_runs(folder: Path) -> list[tuple]:
    with sqlite3.connect(f"file:{folder / 'driftbench.sqlite'}?mode=ro", uri=True) as con:
        return con.execute("SELECT run_key, integrator, status, session FROM runs "
                           "ORDER BY id").fetchall()


@pytest.fixture(scope="module")
def earlier(tmp_path_factory):
    """An output folder with the results of an earlier invocation, and the fault-injection
    plugin and a pinned code version for the module."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv(PLUGIN_ENV, str(PLUGIN))
        mp.setenv(CODE_VERSION_ENV, "test-version")
        out = tmp_path_factory.mktemp("earlier") / "out"
        # A method that fails is data: the invocation ends as planned.
        assert run.main([*EARLIER, "--out", str(out)]) == run.EXIT_OK
        yield out


def refused(argv, out: Path, capsys) -> str:
    """Run the command line against ``out``; assert it was refused on one line with exit
    status 2 and that ``out`` is as it was; return that line."""
    before = snapshot(out)
    code = run.main(["--h", "0.1", "--jobs", "1", "--resume", "--no-report",
                     "--out", str(out), *argv])
    err = capsys.readouterr().err
    assert code == 2 and "Traceback" not in err, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    assert snapshot(out) == before
    return lines[0]


@pytest.mark.parametrize("change, marker, words", [c[1:] for c in FILE_MISTAKES],
                         ids=[c[0] for c in FILE_MISTAKES])
def test_a_mistake_in_a_user_file_names_its_line_and_keeps_earlier_results(
        change, marker, words, earlier, tmp_path, capsys, request):
    name = f"kapitza-{request.node.callspec.id}"
    text = HEADER + KAPITZA.format(name=name, **{**GOOD, **change})
    path = tmp_path / "kapitza.py"
    path.write_text(text)
    line = refused(["--load", str(path), "--problems", name, "--integrators", "rattle"],
                   earlier, capsys)
    assert line.startswith(f"error: {path}:{line_of(text, marker)}: "), line
    for word in words:
        assert word in line


@pytest.mark.parametrize("argv, words", [c[1:] for c in COMMAND_MISTAKES],
                         ids=[c[0] for c in COMMAND_MISTAKES])
def test_a_mistake_on_the_command_line_keeps_earlier_results(argv, words, earlier, capsys):
    line = refused(argv, earlier, capsys)
    for word in words:
        assert word in line


def test_the_kapitza_pendulum_declared_rheonomic_passes_and_a_still_one_gets_a_note(
        tmp_path):
    text = HEADER + KAPITZA.format(name="kapitza-good", **GOOD) + KAPITZA.format(
        name="kapitza-still", **{**GOOD, "constraints": "lambda q, t: jnp.array([q @ q - 1.0])",
                                 "q0": "[0.6, -0.8]"})
    path = tmp_path / "kapitza.py"
    path.write_text(text)
    problems.load(str(path))
    notes: list[str] = []
    plan([RunSpec("kapitza-good", "rattle", 0.1), RunSpec("kapitza-still", "rattle", 0.1)],
         "test-version", notes=notes)
    # The one note is the still pendulum's, at the line of its constraints.
    line = line_of(text, "jnp.array([q @ q - 1.0])")
    assert len(notes) == 1 and notes[0].startswith(f"{path}:{line}: note: "), notes
    assert "rheonomic=True but g_t = 0" in notes[0]


@pytest.mark.parametrize("dense_max", [2000, 0], ids=["projected", "large-unprojected"])
def test_a_drive_that_starts_late_is_found_at_a_random_time(dense_max, monkeypatch):
    # g_t vanishes at the initial state (the pivot rests until t = 0.5): only the sampled
    # states at later times show that g reads t. Above DENSE_AUDIT_MAX coordinates the
    # states are not projected and g's size comes from the structured G.
    monkeypatch.setattr(audit, "DENSE_AUDIT_MAX", dense_max)

    def pivot(t):
        return jnp.array([0.0, 0.05 * jnp.sin(40.0 * jnp.maximum(t - 0.5, 0.0))])

    system = System(n=2, m=1, mass=np.ones(2), potential=lambda q: 9.81 * q[1],
                    constraints=lambda q, t: jnp.array([jnp.sum((q - pivot(t)) ** 2) - 1.0]))
    case = make_case("late-drive", system, [0.6, -0.8], [0.0, 0.0], (0.0, 2.0), {}, 9.81)
    with pytest.raises(ValueError, match=r"depend on t \(\|g_t\| = .* at t = "):
        check_rheonomic(case)


#: Constructors of the authoring API called with an argument out of its contract, each on
#: a line of its own, and the words of the refusal.
CONSTRUCTOR_MISTAKES = [
    (lambda: Reference("exact", "x", lambda t: t, scored=True), "Reference scored = True"),
    (lambda: Reference("analytic", "x", lambda t: t, scored=(0,)), "kind 'analytic'"),
    (lambda: Reference("exact", "x", "q(t)", scored=(0,)), "solution must be callable"),
    (lambda: Reference("exact", "", lambda t: t, scored=(0,)), "source '' must be"),
    (lambda: Reference("exact", "x", lambda t: t, scored=(0, -1)), "-1 is not an index"),
    (lambda: Reference("exact", "x", lambda t: t, scored=(0,), floor=-1.0), "floor = -1.0"),
    (lambda: Reference("exact", "x", lambda t: t, scored=(0,), times=()), "times is empty"),
    (lambda: Perturbation(position=-1e-3), "Perturbation position = -0.001"),
    (lambda: Perturbation(velocity=float("inf")), "Perturbation velocity = inf"),
    (lambda: Perturbation(fixed=(True,)), "True is not an index"),
    (lambda: System(0, 1, np.ones(1), lambda q, t: q), "System n = 0"),
    (lambda: System(2, 1, np.ones(2), "g"), "constraints must be callable"),
    (lambda: System(2, 1, None, lambda q, t: q), "not neither"),
    (lambda: System(2, 1, np.ones(2), lambda q, t: q, rheonomic="yes"), "rheonomic = 'yes'"),
    (lambda: System(2, 1, np.ones(2), lambda q, t: q, invariants={"E": 1.0}), "invariants"),
]


@pytest.mark.parametrize("make, words", CONSTRUCTOR_MISTAKES,
                         ids=[c[1] for c in CONSTRUCTOR_MISTAKES])
def test_an_authoring_object_is_refused_where_it_is_made(make, words):
    with pytest.raises(ArgumentError) as caught:
        make()
    message = str(caught.value)
    assert message.startswith(f"{__file__}:{inspect.getsourcelines(make)[1]}: "), message
    assert words in message and "\n" not in message


def test_make_case_refuses_its_arguments_at_the_call():
    system = System(n=2, m=1, mass=np.ones(2),
                    constraints=lambda q, t: jnp.array([q @ q - 1.0]))
    ref = Reference("exact", "x", lambda t: t, scored=[0, 1])  # a list is taken as a tuple
    assert ref.scored == (0, 1)
    calls = [
        (lambda: make_case("p", system, [1.0, 0.0], [0.0, 0.0], (0, 1), {}, -2.0),
         "energy_scale = -2.0"),
        (lambda: make_case("p", system, [1.0, 0.0], [0.0, 0.0], (0, 1), {}, 1.0,
                           perturbation=Perturbation(fixed=(2,))), "fixed index 2"),
        (lambda: make_case("p", system, [1.0, 0.0], [0.0, 0.0], (0, 1), [], 1.0),
         "params must be a mapping"),
        (lambda: make_case("p", system, [1.0, 0.0], [0.0, 0.0], 1.0, {}, 1.0),
         "t_span = 1.0 must be (t0, t_end)"),
        (lambda: make_case("p", system, [1.0, 0.0], [0.0, 0.0], (0, 1), {}, 1.0,
                           reference=ref.solution), "reference must be a Reference"),
    ]
    for make, words in calls:
        with pytest.raises(ArgumentError, match=words.replace("(", r"\(").replace(")", r"\)")) \
                as caught:
            make()
        assert str(caught.value).startswith(f"{__file__}:{inspect.getsourcelines(make)[1]}: ")


@pytest.mark.slow
def test_a_sweep_whose_every_run_ends_error_exits_1_and_keeps_earlier_results(
        earlier, tmp_path, capsys):
    out = tmp_path / "out"
    shutil.copytree(earlier, out)
    before = stored_runs(out)
    code = run.main(["--problems", "pendulum", "--integrators", "test-raise", "--h", "0.1",
                     "--t-end", "0.5", "--jobs", "1", "--resume", "--no-report",
                     "--out", str(out)])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == run.EXIT_RUN_ERROR
    assert err[-1].startswith("error: 1 of 1 runs ended error or timeout"), err
    after = stored_runs(out)
    assert after[:len(before)] == before  # the earlier results, as they were
    assert [(integrator, status) for _, integrator, status, _ in after[len(before):]] == [
        ("test-raise", "error")]
    with open(out / "runs.csv") as fh:
        assert [r["status"] for r in csv.DictReader(fh)] == ["error"]


def test_help_states_the_exit_statuses():
    text = " ".join(run.parser().format_help().split())
    assert "exit status: 0 when every run ended ok or failed" in text
    assert "1 when a run ended error or timeout" in text and "2 for bad input" in text
    gate = " ".join(check.parser().format_help().split())
    assert "1 on a regression or a run that ended error or timeout" in gate


def test_the_drift_gate_fails_and_writes_no_baseline_when_a_run_ends_error(
        tmp_path, monkeypatch, capsys):
    suite = tmp_path / "gate.toml"
    suite.write_text('[[group]]\nproblems = ["pendulum"]\nintegrators = ["rattle"]\n'
                     'h = [0.05]\nt_end = 5.0\n')
    spec = Run("pendulum", "rattle", h=0.05, t_end=5.0)
    ok = Record(spec, Ending(Status.OK), metrics=Metrics(max_pos_residual=1e-12))
    error = Record(spec, Ending(Status.ERROR, message="RuntimeError: defect"))
    # Only the gate's bookkeeping is under test: the batch returns the records given.
    records = [ok]
    monkeypatch.setattr(check, "run_specs", lambda *a, **k: records)
    baseline = tmp_path / "b.json"
    args = ["--suite", str(suite), "--baseline", str(baseline)]
    assert check.main([*args, "--update"]) == check.EXIT_OK
    written = baseline.read_text()
    records[:] = [error]
    assert check.main([*args, "--update"]) == run.EXIT_RUN_ERROR
    assert baseline.read_text() == written
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["error: 1 of 1 runs ended error or timeout, with no metrics to record: no "
                   "baseline written (first: pendulum / rattle / h=0.05 / t_end=5)"]
    # The same error in the baseline's run: still a failed gate.
    baseline.write_text(json.dumps({**json.loads(written), "runs": {
        "pendulum / rattle / h=0.05 / t_end=5": {"status": "error", "metrics": {}}}}))
    assert check.main(args) == run.EXIT_RUN_ERROR
    assert "drift gate FAILED" in capsys.readouterr().out


@pytest.mark.slow
def test_every_shipped_problem_declares_its_time_dependence():
    for path in ("slider_crank.py", "spherical_pendulum.py"):
        problems.load(str(Path(__file__).parent.parent / "examples" / path))
    for name in problems.names():
        if problems.origin(name) == "built-in" or "examples" in problems.origin(name):
            notes: list[str] = []
            check_rheonomic(problems.make(name), notes)
            assert not notes, notes
