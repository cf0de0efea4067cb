"""Docstrings and comments state what the code does, not how fast it ran where.

Timings, machine loads, throw-away measurement scripts, the history of a work session and
citations of issues or of documents outside the repository belong in the perf benchmarks'
outputs and the changelog. Comments are read with :mod:`tokenize` and docstrings with
:mod:`ast`, so string literals printed to users (which may quote a load or a timing on
purpose) are not read. ``benchmarks/perf/`` measures and ``tests/`` quotes the patterns, so
neither is read.
"""

import ast
import io
import re
import tokenize
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("integrators", "problems", "linalg", "benchmarks", "reports")
EXCLUDED = (ROOT / "benchmarks" / "perf",)

#: Name -> pattern (case-insensitive) of text that does not belong in a comment or
#: docstring. Each is narrow enough to let a load case, a step size ``h = 1e-3 s`` or a
#: word containing "ms" pass.
FORBIDDEN = {
    "machine load": r"\bload (average|about|of|was|is)?\s*[0-9]|\bload average\b"
                    r"|[(,;] ?(on )?(one|two|2) cores?\b[,;)]|\bon (one|two|2) cores\b",
    "timing": r"\b[0-9][0-9.,]*(e-?[0-9]+)?\s?(us|µs|ms|ns)\b|\btook [0-9]"
              r"|\b[0-9][0-9.]* ?(times|x) (as fast|faster|slower|as long)\b"
              r"|[0-9] ?lane-steps/s\b",
    "measurement narrative": r"\bside by side in one process\b|\balternating (in one process"
                             r"|processes)\b|\bmeasured on\b|\bprofiled\b",
    "scratch": r"\bscratch\b",
    "session history": r"\bthis (stop|session)\b",
    "issue citation": r"\bissues? ?#?[0-9]+|\bissue's\b|\bthe issue\b",
    "design notes": r"\bdesign notes\b|(?<!docs/)\bdesign\.md\b",
}
PATTERNS = {name: re.compile(rx, re.IGNORECASE) for name, rx in FORBIDDEN.items()}


def sources() -> list[Path]:
    """The ``.py`` files whose comments and docstrings are read."""
    found = []
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            if not any(path.is_relative_to(skip) for skip in EXCLUDED):
                found.append(path)
    return found


def texts(source: str) -> list[tuple[int, str]]:
    """(line, text) of every comment and docstring of a module's source.

    A docstring is the first statement of a module, class or function when it is a string
    constant, and the string constant that follows an assignment (the ``#:`` convention's
    sibling for attributes)."""
    found = [(tok.start[0], tok.string)
             for tok in tokenize.generate_tokens(io.StringIO(source).readline)
             if tok.type == tokenize.COMMENT]
    for node in ast.walk(ast.parse(source)):
        body = getattr(node, "body", None)
        if not isinstance(body, list):
            continue
        for i, stmt in enumerate(body):
            first = i == 0 and isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef,
                                                 ast.AsyncFunctionDef))
            after_assignment = i > 0 and isinstance(body[i - 1], (ast.Assign, ast.AnnAssign))
            if ((first or after_assignment) and isinstance(stmt, ast.Expr)
                    and isinstance(stmt.value, ast.Constant)
                    and isinstance(stmt.value.value, str)):
                found.append((stmt.lineno, stmt.value.value))
    return found


def offences(source: str) -> list[tuple[int, str, str]]:
    """(line, pattern name, matched text) for every forbidden pattern in the comments and
    docstrings of ``source``. A match's line is that of the comment or docstring it starts
    in plus the newlines before it."""
    found = []
    for line, text in texts(source):
        flat = text.replace("``", "")
        for name, pattern in PATTERNS.items():
            for match in pattern.finditer(flat):
                found.append((line + flat.count("\n", 0, match.start()), name, match.group()))
    return sorted(found)


@pytest.mark.parametrize("text", [
    "# took 3 us where hashing took 67",
    "# (one core, load 1.5)",
    "# 0.45 ms per call",
    '"""The step took 1.75 to 1.84 µs packed."""',
    "# (scratch script)",
    "# as decided in this session",
    "# the issue's bar",
    "# see issue 28",
    "# see the design notes",
    "# see ../shared/design.md",
    "# 4.8 to 12 times as fast",
    "# (alternating in one process)",
])
def test_patterns_catch(text):
    """Each kind of offence is caught, in a comment or a docstring."""
    assert offences(text + "\n")


@pytest.mark.parametrize("text", [
    "# the load case of the crane, h = 1e-3 s",
    '"""Solve with step h = 1e-5 s; forms, items and terms are kept."""',
    "# Every worker is pinned to one core, even a lone one.",
    "# see docs/design.md section 4",
    "# the residual agrees to 1e-12 with the reference",
    'print(f"1-minute load average: {load}, took 3 ms")',
    "# mass matrix, systems, columns",
])
def test_patterns_let_pass(text):
    """Legitimate text passes, and strings printed to users are not read."""
    assert not offences(text + "\n")


def test_comments_and_docstrings_state_what_the_code_does():
    """No comment or docstring of the packages quotes a timing, a machine load, a scratch
    measurement, a session's history, an issue or the old design notes."""
    found = [f"{path.relative_to(ROOT)}:{line}: {name}: {text!r}"
             for path in sources() for line, name, text in offences(path.read_text())]
    assert not found, "\n".join(found)
