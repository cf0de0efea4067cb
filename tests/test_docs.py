"""The README and the documentation site: generated tables current, links and citations
that resolve, performance pages read from the perf outputs, and the site building without
warnings."""

from __future__ import annotations

import importlib.util
import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "docs"))

import generate  # noqa: E402

README = ROOT / "README.md"


def test_readme_tables_are_those_of_the_registries():
    text = README.read_text()
    assert generate.readme_with_tables(text) == text, (
        "README.md's tables are stale: run `python docs/generate.py --readme`")


def test_a_stale_readme_table_is_caught_and_rewritten(tmp_path, monkeypatch):
    text = README.read_text()
    stale = text.replace("| `rattle` |", "| `rattle-old` |", 1)
    assert stale != text
    copy = tmp_path / "README.md"
    copy.write_text(stale)
    monkeypatch.setattr(generate, "README", copy)
    assert generate.main(["--check"]) == 1
    assert generate.main(["--readme"]) == 0
    assert copy.read_text() == text
    assert generate.main(["--check"]) == 0


def test_a_newly_registered_problem_joins_the_table(monkeypatch):
    import problems

    def widget(k: float = 1.0, t_end: float = 1.0):
        """A problem registered by this test only."""

    widget.__module__ = "problems.pendulum"  # as if it were one of the package's modules
    monkeypatch.setitem(problems.REGISTRY, "test-widget", widget)
    monkeypatch.setitem(problems.ORIGINS, "test-widget", "built-in")
    rows = [line for line in generate.problem_table().splitlines() if "test-widget" in line]
    assert len(rows) == 1 and "`k`, `t_end`" in rows[0]


def test_readme_is_short_and_opens_with_the_setup_commands():
    lines = README.read_text().splitlines()
    assert len(lines) <= 150
    head = "\n".join(lines[:40])
    assert "make run" in head and "make test" in head


def test_readme_links_resolve():
    for target in re.findall(r"\]\(([^)#]+)\)", README.read_text()):
        if "://" not in target:
            assert (ROOT / target).exists(), target


def test_design_citations_in_code_name_sections_that_exist():
    sections = set(re.findall(r"^## (\d+)\. ", (ROOT / "docs" / "design.md").read_text(), re.M))
    cited = []
    for folder in ("problems", "integrators", "linalg", "benchmarks", "reports", "studies"):
        for path in (ROOT / folder).rglob("*.py"):
            text = path.read_text()
            assert "design notes" not in text, f"{path}: cites the old design notes"
            cited += [(path, n) for n in re.findall(r"docs/design\.md,? \(?section (\d+)", text)]
    assert cited, "no code cites docs/design.md"
    for path, number in cited:
        assert number in sections, f"{path}: docs/design.md has no section {number}"


def test_tutorials_include_every_example_and_only_existing_files():
    tutorials = ROOT / "docs" / "tutorials"
    included = set()
    for page in tutorials.glob("*.md"):
        for target in re.findall(r"```\{literalinclude\} (\S+)", page.read_text()):
            path = (page.parent / target).resolve()
            assert path.is_file(), f"{page.name}: {target}"
            included.add(path)
    assert set((ROOT / "examples").glob("*.py")) <= included


def test_performance_page_reads_the_perf_outputs(tmp_path):
    absent = generate.performance_page(tmp_path)
    assert "python -m benchmarks.perf.suite_time" in absent
    assert "python -m benchmarks.perf.exudyn --out docs/performance/exudyn" in absent
    (tmp_path / "suite-time").mkdir()
    (tmp_path / "suite-time" / "suite_time.json").write_text(json.dumps([{
        "suite": "quick", "wall_s": 41.25, "budget_s": 60, "load_before": 0.5,
        "load_after": 1.5, "statuses": {"ok": 26, "failed": 2}, "within": True}]))
    (tmp_path / "speedup").mkdir()
    (tmp_path / "speedup" / "parallel_speedup.json").write_text(json.dumps({
        "suite": "quick", "runs": 27, "cores": 2, "results": [
            {"engine": "jobs 1", "wall_s": 80.0, "speedup": 1.0, "load_before": 0.1,
             "load_after": 1.0},
            {"engine": "jobs 2", "wall_s": 50.0, "speedup": 1.6, "load_before": 1.0,
             "load_after": 2.0}]}))
    (tmp_path / "scaling").mkdir()
    (tmp_path / "scaling" / "scaling.json").write_text(json.dumps({"points": [
        {"problem": "chain", "n": 1024, "family": "rattle", "status": "ok",
         "wall_per_step": 2.5e-4, "ratio_c": 1.5, "newton_per_step": 1.01,
         "peak_rss": 300 * 2**20}]}))
    (tmp_path / "efficiency").mkdir()
    (tmp_path / "efficiency" / "efficiency.json").write_text(json.dumps({
        "goal_ratio_per_step": 3.0, "rounds": 5, "load": 1.25, "rows": [
            {"family": "ida-ggl", "driver": "native", "problem": "pendulum",
             "us_per_step": 2.5, "yardstick_us_per_step": 2.0, "ratio_per_step": 1.25,
             "ratio_per_solve": 1.3, "steps": 100, "yardstick_steps": 100,
             "final_q_difference": 0.0}]}))
    (tmp_path / "exudyn").mkdir()
    (tmp_path / "exudyn" / "exudyn.json").write_text(json.dumps({
        "exudyn": "1.9.0", "goal_ratio_per_step": 1.0, "agreement": 1e-9, "rounds": 3,
        "load": 0.75, "rows": [
            {"problem": "chain", "N": 256, "h": 1e-5, "status": "ok", "steps": 100,
             "exudyn_steps": 100, "us_per_step": 42.0, "exudyn_us_per_step": 50.0,
             "ratio_per_step": 0.84, "newton_per_step": 2.0, "exudyn_newton_per_step": 2.5,
             "final_q_difference": 1e-14, "final_v_difference": 4e-10, "agree": True},
            {"problem": "rigid-chain", "N": 64, "h": 5e-4, "status": "ok", "steps": 100,
             "exudyn_steps": 100, "us_per_step": 300.0, "exudyn_us_per_step": 200.0,
             "ratio_per_step": 1.5, "newton_per_step": 3.0, "exudyn_newton_per_step": 3.0,
             "final_q_difference": 1e-6, "final_v_difference": 2e-6, "agree": False},
            {"problem": "chain", "N": 4096, "h": 1e-5,
             "status": "Exudyn: Newton | did not converge"}]}))
    page = generate.performance_page(tmp_path)
    assert "| `quick` | 41.2 | 60 | 0.50 / 1.50 | 2 failed, 26 ok |" in page
    assert "Exudyn 1.9.0's generalized-alpha solver" in page and "load 0.75" in page
    assert "| `chain` | 256 | 1e-05 | ok | 42 | 50 | 0.84 | 2.00 | 2.50 | 1.0e-14 | 4.0e-10 |" \
        in page
    assert "| `rigid-chain` | 64 | 0.0005 | ok, final states disagree | 300 | 200 | 1.50 |" in page
    assert "| `chain` | 4096 | 1e-05 | Exudyn: Newton \\| did not converge | - |" in page
    assert "| jobs 2 | 50.0 | 1.60 | 1.00 / 2.00 |" in page
    assert "| `chain` | 1024 | rattle | ok | 250 | 1.5 | 1.01 | 300 |" in page
    assert "| `ida-ggl` | native | `pendulum` | 2.5 | 2 | 1.25 | 1.30 | 100 | 100 |" in page
    assert "python -m benchmarks.perf" not in page


def test_every_integrator_and_problem_gets_a_page_and_no_other(tmp_path):
    import integrators
    import problems

    (tmp_path / "problems").mkdir()
    (tmp_path / "problems" / "unregistered.rst").write_text("outside every toctree")
    generate.write_docs(tmp_path)
    assert not (tmp_path / "problems" / "unregistered.rst").exists()
    # Every integrator and problem of the project's own (a test may have registered more in
    # this process: those get no page).
    own = {k for k in integrators.keys() if integrators.REGISTRY[k][0].startswith("integrators.")}
    assert {r["key"] for r in generate.integrator_rows()} == own
    for module in {integrators.REGISTRY[k][0].split(":")[0] for k in own}:
        page = (tmp_path / "integrators" / f"{module.rsplit('.', 1)[-1]}.md").read_text()
        assert f".. automodule:: {module}" in page
    for name in (r["name"] for r in generate.problem_rows()):
        assert f".. automodule:: {problems.REGISTRY[name].__module__}" in (
            tmp_path / "problems" / f"{name}.rst").read_text()
    assert {"pendulum", "andrews", "rigid-chain"} <= {r["name"] for r in generate.problem_rows()}


def test_the_command_line_page_holds_every_subcommand_help():
    page = generate.cli_page()
    for name in ("run", "report", "check", "cache"):
        assert f"usage: driftbench {name} [-h]" in page
    assert "--t-end" in page and "--baseline" in page and "--clear" in page


@pytest.mark.slow
@pytest.mark.skipif(importlib.util.find_spec("sphinx") is None,
                    reason="the docs extra (requirements-docs.lock) is not installed")
def test_the_site_builds_without_warnings(tmp_path):
    done = subprocess.run([sys.executable, "-m", "sphinx", "-E", "-W", "--keep-going", "-q",
                           "-b", "html", str(ROOT / "docs"), str(tmp_path)],
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    assert (tmp_path / "index.html").is_file()
