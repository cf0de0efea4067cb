"""Every error about a user's problem or method names the file and line that defined it,
whichever check finds it: the audit of the physics (shapes, finiteness, the mass), the case
builder (shapes, consistency) and the integrator option checks (the base class's, the
method's own, an unknown option)."""

import pytest

import integrators
import problems
from benchmarks import run
from problems.case import InconsistentInitialValues
from problems.source import defined_at, located
from problems.spec import SpecError

HEADER = """
from dataclasses import dataclass

import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp

import integrators
from integrators.base import Integrator
from problems import System, make_case, register

"""

#: A pendulum as a user writes it, one function a line, so that each has a line of its own.
PROBLEM = """
@register("{name}")
def factory(t_end: float = 0.5):
    system = System(n=2, m=1,
                    mass={mass},
                    potential={potential},
                    constraints=lambda q, t: jnp.array([q[0] ** 2 + q[1] ** 2 - 1.0]))
    return make_case("{name}", system, {q0}, [0.0, 0.0], (0.0, t_end), {{}},
                     energy_scale=9.81)
"""

GOOD = dict(mass="np.ones(2)", potential="lambda q: 9.81 * q[1]", q0="[1.0, 0.0]")

#: A fixed-step method with an option of its own and its own check of it.
METHOD = """
@dataclass(frozen=True)
class Euler(Integrator):
    h: float = 0.1
    newton_tol: float = 1e-12
    order: int = 1

    def check(self):
        super().check()
        if self.order != 1:
            raise ValueError(f"order = {{self.order}}: this method has order 1 only")

    def prepare(self, case, grid):
        raise NotImplementedError


integrators.register("{key}", f"{{__name__}}:Euler")
"""

#: (id, what differs from GOOD, the text of the line the message must name, its words)
PROBLEMS = [
    ("constant-mass-not-positive-definite", {"mass": "np.array([1.0, -1.0])"}, "@register",
     ["mass of problem", "not positive definite"]),
    ("sparse-mass-not-positive-definite", {"mass": "sp.diags([1.0, -1.0])"}, "@register",
     ["mass of problem", "not positive definite"]),
    ("sparse-mass-not-finite", {"mass": "sp.diags([1.0, np.nan])"}, "@register",
     ["mass of problem", "not finite"]),
    # Found when the case derives its mechanics, from the call that makes the case.
    ("constant-mass-wrong-shape", {"mass": "np.ones(3)"}, "return make_case",
     ["mass has shape (3,)"]),
    ("mass-function-not-symmetric", {"mass": "lambda q: jnp.array([[1.0, 0.5], [0.0, 1.0]])"},
     "mass=", ["not symmetric"]),
    ("potential-not-finite", {"potential": "lambda q: 9.81 * jnp.log(q[1])"}, "potential=",
     ["potential(q)", "not finite"]),
    ("initial-values-inconsistent", {"q0": "[1.1, 0.0]"}, "return make_case",
     ["inconsistent initial values"]),
    ("initial-values-wrong-shape", {"q0": "[1.0, 0.0, 0.0]"}, "return make_case",
     ["must both have shape (2,)"]),
]

#: (id, the integrator's spec with {key} for its name, its words)
METHODS = [
    ("option-out-of-range", "{key}:newton_tol=2", ["newton_tol = 2", "(0, 1)"]),
    ("method-own-check", "{key}:order=2", ["order = 2", "order 1 only"]),
    ("unknown-option", "{key}:ordr=2", ["no option 'ordr'", "did you mean order"]),
]


def line_of(text: str, marker: str) -> int:
    """The line number of the one line of ``text`` that holds ``marker``."""
    lines = [i for i, line in enumerate(text.splitlines(), 1) if marker in line]
    assert len(lines) == 1, marker
    return lines[0]


def refused(tmp_path, capsys, text: str, problem: str, integrator: str) -> str:
    """Load ``text`` as a user's file on the command line; assert the run was refused on one
    line; return it."""
    path = tmp_path / "model.py"
    path.write_text(text)
    out = tmp_path / "out"
    code = run.main(["--load", str(path), "--problems", problem, "--integrators", integrator,
                     "--h", "0.1", "--jobs", "1", "--out", str(out), "--no-report"])
    err = capsys.readouterr().err
    assert code == 2 and "Traceback" not in err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    assert not out.exists()
    return lines[0]


@pytest.mark.parametrize("change, marker, words", [c[1:] for c in PROBLEMS],
                         ids=[c[0] for c in PROBLEMS])
def test_an_error_in_a_user_problem_names_its_file_and_line(change, marker, words, tmp_path,
                                                            capsys, request):
    name = f"test-o-{request.node.callspec.id}"
    text = HEADER + PROBLEM.format(name=name, **{**GOOD, **change})
    line = refused(tmp_path, capsys, text, name, "rattle")
    assert f"{tmp_path / 'model.py'}:{line_of(text, marker)}: " in line
    for word in words:
        assert word in line


@pytest.mark.parametrize("spec, words", [c[1:] for c in METHODS], ids=[c[0] for c in METHODS])
def test_an_error_in_a_user_method_s_options_names_its_file_and_line(spec, words, tmp_path,
                                                                     capsys, request):
    key = f"test-o-{request.node.callspec.id}"
    text = HEADER + METHOD.format(key=key)
    line = refused(tmp_path, capsys, text, "pendulum", spec.format(key=key))
    # A dataclass is defined where its decorator stands.
    assert f"{tmp_path / 'model.py'}:{line_of(text, '@dataclass')}: " in line
    for word in words:
        assert word in line


def test_the_python_api_names_the_file_and_line_too(tmp_path):
    text = (HEADER + PROBLEM.format(name="test-o-api", **{**GOOD, "q0": "[1.1, 0.0]"})
            + METHOD.format(key="test-o-api"))
    path = tmp_path / "api_model.py"
    path.write_text(text)
    problems.load(str(path))
    with pytest.raises(InconsistentInitialValues) as caught:
        problems.make("test-o-api")
    where = f"{path}:{line_of(text, 'return make_case')}"
    assert str(caught.value).startswith(f"{where}: test-o-api: ")
    with pytest.raises(SpecError) as caught:
        integrators.make("test-o-api:newton_tol=0")
    # Once, in front, although the base class's check named the place before make did.
    message = str(caught.value)
    assert message.startswith(f"{path}:{line_of(text, '@dataclass')}: integrator ")
    assert message.count(str(path)) == 1


def test_located_leads_with_the_place_once():
    here = defined_at(line_of)
    assert here == f"{__file__}:{line_of.__code__.co_firstlineno}"
    assert located("bad", line_of) == f"{here}: bad"
    assert located(f"outer: {here}: inner", line_of) == f"{here}: outer: inner"
    # The first object with a source file; none: the message as it is.
    assert located("bad", None, len, line_of) == f"{here}: bad"
    assert located("bad", None, len) == "bad"
