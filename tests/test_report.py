"""The report: self-contained HTML, a figure per problem, the study sections, escaping.

The store is filled with synthetic runs (the report reads the store only, so it cannot tell
them from real ones) to keep this file fast; the quick suite exercises it end to end.
"""

import json
import re
import sqlite3
from dataclasses import replace
from html.parser import HTMLParser

import numpy as np
import pandas as pd
import pytest

from benchmarks.records import COLUMNS, Record
from benchmarks.store import Store
from reports import build

EVIL = '<script>alert("x")</script> & <img src="http://evil.example/x.png"> | *bold*'
SEED = {"M": 0.8, "m": 1.0, "w": 1.0, "R0": 1.0, "r0": 0.8, "l": 0.504341}


def run(problem, integrator, h, status="ok", message="", t_end=10.0, params=None, order=2,
        pos=1e-15, energy=1e-6, final=None, n=200):
    """A synthetic run whose series grow as its metrics say."""
    row = {c: None for c in COLUMNS}
    t = np.linspace(t_end / n, t_end, n)
    stop = n if status == "ok" else 3
    row.update(problem=problem, integrator=integrator, h=h, t_end=t_end, status=status,
               message=message, n_steps=stop * 5, n_f_evals=stop * 20, wall_s=1e-3 / h,
               max_pos_residual=pos, max_vel_residual=pos / 2,
               max_energy_error=energy, rel_energy_error=energy / 2.0,
               final_state_error=final, scd=None if final is None else -np.log10(final),
               t_final=t[stop - 1], fail_step=None if status == "ok" else stop + 1,
               q_final=json.dumps([1.0 + (final or 0.0), 0.8]), v_final=json.dumps([0.0, 0.0]),
               options=json.dumps({"h": h, "stages": order // 2 + 1}),
               params=json.dumps(params or {}), nominal_order=order, sensitive=0,
               pos_growth="bounded (round-off)" if status == "ok" else None,
               energy_growth="linear (p = 1.00)" if status == "ok" else None)
    windows = {"t": t[:stop], "pos": np.full(stop, pos), "vel": np.full(stop, pos / 2),
               "energy": energy * (0.5 + 0.5 * np.abs(np.sin(t[:stop])))}
    phase = np.linspace(0.0, 1.0, stop + 1)
    samples = {"t": np.concatenate([[0.0], t[:stop]]),
               "q": np.stack([1.0 - 0.1 * phase, 0.8 + 0.1 * phase], axis=1),
               "v": np.zeros((stop + 1, 2))}
    return Record.from_row(row, windows, samples)


def fill(path, commit=None):
    with Store(path) as st:
        session = st.begin("unit")
        for h, final in ((0.1, 1e-4), (0.05, 2.5e-5), (0.025, 6.25e-6)):
            st.add(session, run("pendulum", "rattle", h, final=final))
            st.add(session, run("pendulum", "lobatto3ab3", h, final=final ** 2, energy=1e-9))
        st.add(session, run("pendulum", "lobatto3ab3", 0.2, status="failed", message=EVIL))
        for h in (0.5, 0.1, 0.05):
            status = "failed" if h == 0.5 else "ok"
            st.add(session, run("sps-receiver", "lobatto3ab2", h, status=status, t_end=50.0,
                                message="Newton failed at step 2" if status != "ok" else "",
                                params=SEED, pos=5e-16))
        st.add_table(session, "flexible-modal", "frequencies",
                     pd.DataFrame({"mode": [1, 2], "f [Hz]": [0.125, 0.5]}))
        st.add_figure(session, "flexible-modal", "mode shapes",
                      '<svg xmlns="http://www.w3.org/2000/svg" onload="alert(1)">'
                      '<script>alert(2)</script><image href="http://evil.example/y.png"/>'
                      '<style>body { display: none }</style>'
                      '<rect id="r" width="5" height="5"/><use href="#r"/></svg>')
        st.add_figure(session, "flexible-modal", "broken", "<svg><g></svg>")
    if commit:
        with sqlite3.connect(path) as db:
            db.execute("UPDATE sessions SET commit_sha = ? WHERE id = "
                       "(SELECT max(id) FROM sessions)", (commit,))


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    out = tmp_path_factory.mktemp("report")
    db = out / "driftbench.sqlite"
    fill(db, commit="1111111111aaaa")
    fill(db, commit="2222222222bbbb")
    paths = build(db, out)
    return out, paths


class Resources(HTMLParser):
    """Every attribute that could make a browser fetch something, and every tag."""

    def __init__(self):
        super().__init__()
        self.refs, self.tags = [], []

    def handle_starttag(self, tag, attrs):
        self.tags.append(tag)
        for name, value in attrs:
            if name in ("src", "href", "xlink:href", "srcset", "poster", "data", "action"):
                self.refs.append((tag, name, value or ""))


def sections(html: str) -> dict[str, str]:
    """The HTML of each h2 section, by its heading text."""
    parts = re.split(r'<h2 id="[^"]*">', html)[1:]
    return {p[:p.index("</h2>")]: p for p in parts}


def test_both_reports_and_their_figures_are_written(report):
    out, paths = report
    assert paths[0] == out / "report.md" and paths[1] == out / "report.html"
    figures = paths[2:]
    assert figures and all(p.suffix == ".svg" and p.parent == out / "figures" for p in figures)
    md = (out / "report.md").read_text()
    for p in figures:
        assert f"(figures/{p.name})" in md


def test_html_loads_nothing_from_outside(report):
    out, _ = report
    html = (out / "report.html").read_text()
    parser = Resources()
    parser.feed(html)
    assert "script" not in parser.tags and "link" not in parser.tags
    assert "iframe" not in parser.tags and "img" not in parser.tags
    for tag, name, value in parser.refs:
        assert value.startswith("#"), (tag, name, value)  # in-page anchors and SVG ids only
    assert "@import" not in html
    assert not re.search(r"url\(\s*['\"]?(?!#)", html)


def test_every_problem_has_a_figure_and_the_main_sections_are_there(report):
    out, _ = report
    secs = sections((out / "report.html").read_text())
    for problem in ("pendulum", "sps-receiver"):
        assert "<svg" in secs[f"Problem: {problem}"]
    assert "Headline" in secs and "History across commits" in secs and "Provenance" in secs
    assert "1111111111" in secs["History across commits"]
    assert "Study: flexible-modal" in secs


def test_the_headline_figure_is_one_per_report_and_one_per_problem(report):
    out, paths = report
    names = sorted(p.name for p in paths if "standing" in p.name or p.stem == "headline")
    assert names == ["headline.svg", "pendulum-standing.svg", "sps-receiver-standing.svg"]
    md, html = (out / "report.md").read_text(), (out / "report.html").read_text()
    # The verdict tables open the headline, the overview follows, in both reports.
    headline = md[md.index("## Headline"):md.index("## History")]
    assert headline.index("| problem |") < headline.index("(figures/headline.svg)")
    secs = sections(html)
    assert secs["Headline"].index("<table") < secs["Headline"].index("<svg")
    for problem in ("pendulum", "sps-receiver"):
        assert f"(figures/{problem}-standing.svg)" in md
        assert "against cost" in secs[f"Problem: {problem}"]


def test_drift_classes_and_orders_are_the_recorded_ones(report):
    """The report shows what each run recorded; it reconstructs nothing."""
    out, _ = report
    problem = sections((out / "report.html").read_text())["Problem: pendulum"]
    assert "bounded (round-off)" in problem and "linear (p = 1.00)" in problem
    order_rows = [r for r in problem.split("<tr") if "rattle" in r and "fitted" not in r]
    assert any("<td>2</td>" in r for r in order_rows)  # the nominal order RATTLE recorded


def test_messages_are_escaped_and_failed_runs_show_as_failed(report):
    out, _ = report
    html = (out / "report.html").read_text()
    assert EVIL not in html and "<script>alert" not in html
    assert '&lt;script&gt;alert(&quot;x&quot;)&lt;/script&gt;' in html
    problem = sections(html)["Problem: pendulum"]
    failed_row = next(r for r in problem.split("<tr") if "h=0.2" in r)
    assert "failed" in failed_row and "&lt;script&gt;" in failed_row
    md = (out / "report.md").read_text()
    assert "<script>" not in md and "&lt;script>" in md


def test_study_figures_are_sanitised(report):
    out, _ = report
    study = sections((out / "report.html").read_text())["Study: flexible-modal"]
    assert "onload" not in study and "alert(2)" not in study and "evil.example" not in study
    assert "display: none" not in study  # its style would have applied to the whole page
    assert "<table" in study and "0.125" in study
    assert "Figure broken cannot be shown: not well-formed SVG" in study
    ids = re.findall(r'\bid="([^"]+)"', study)
    assert any(i.endswith("-r") for i in ids)  # ids prefixed, references kept working
    assert re.search(r'href="#f\d+-r"', study)


def test_markdown_and_html_have_the_same_sections(report):
    out, _ = report
    md_heads = re.findall(r"^#{2,3} (.+)$", (out / "report.md").read_text(), re.M)
    html_heads = re.findall(r'<h[23] id="[^"]*">([^<]+)</h[23]>',
                            (out / "report.html").read_text())
    unescape = [re.sub(r"\\(.)", r"\1", h) for h in md_heads]
    assert unescape == [h.replace("&#x27;", "'") for h in html_heads]


def test_the_report_stage_imports_no_integrator():
    """Layering: reports read the store only (and so never pay for importing JAX)."""
    import subprocess
    import sys

    code = ("import sys, reports, reports.report; "
            "print(sorted(m for m in ('integrators', 'problems', 'jax') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"


@pytest.mark.slow
def test_a_version_1_store_still_gives_a_report(tmp_path):
    """Old stores load through the migration; what they lack shows as 'n/a', not a crash."""
    from test_store import write_v1

    write_v1(tmp_path / "old.sqlite")
    md, html = build(tmp_path / "old.sqlite", tmp_path)[:2]
    text = html.read_text()
    assert "Problem: pendulum" in text and "<svg" in sections(text)["Problem: pendulum"]
    # The synthetic old run has no evaluation count and no energy error: 'n/a', not blank.
    assert "| rattle | h=0.01 | 10 | ok | 1000 | n/a |" in md.read_text()


@pytest.mark.slow
def test_a_300_character_problem_spec_names_bounded_files(tmp_path):
    """Figure files are named from problem specs: a long spec gets a bounded, sanitised name
    with a hash of the full spec, and every later report of that store builds too."""
    from reports.document import MAX_STEM, file_stem

    spec = "pendulum:L=1." + "0" * 287
    assert len(spec) == 300
    db = tmp_path / "driftbench.sqlite"
    with Store(db) as st:
        session = st.begin("unit")
        for h in (0.1, 0.05):
            st.add(session, run(spec, "rattle", h, final=h ** 2))
        st.add(session, run(spec[:-1] + "1", "rattle", 0.1, final=1e-2))
    for _ in range(2):
        paths = build(db, tmp_path)
    stems = [p.stem for p in paths[2:]]
    assert all(len(p.name) <= MAX_STEM + 4 and re.fullmatch(r"[a-z0-9-]+", p.stem)
               for p in paths[2:])
    # Two specs that differ only in their last digit get files of their own.
    assert file_stem(f"{spec}-drift") in stems and file_stem(f"{spec[:-1]}1-drift") in stems
    assert file_stem(f"{spec}-drift") != file_stem(f"{spec[:-1]}1-drift")
    assert len(set(stems)) == len(stems)


def test_problem_sections_fold_and_the_contents_and_headline_come_first(report):
    out, _ = report
    html = (out / "report.html").read_text()
    body = html[html.index("<main>"):]
    assert body.index('<nav class="toc">') < body.index('id="headline"') \
        < body.index('<details class="section">')
    assert html.count('<details class="section">') == 2
    assert html.count("<details") == html.count("</details>") == 3
    assert re.search(r'<details class="section"><summary><h2 id="problem-pendulum">', html)


def test_the_contents_are_folded_one_line_per_section(report):
    """The first screen is the headline: the contents are one closed line, and open to one
    line per section with its subsections linked on it."""
    out, _ = report
    html = (out / "report.html").read_text()
    toc = html[html.index('<nav class="toc">'):html.index("</nav>")]
    assert toc.startswith('<nav class="toc"><details><summary>') and "open" not in toc
    lines = re.findall(r"<li>(.*?)</li>", toc)
    assert toc.count("<ul>") == 1 and len(lines) == len(sections(html))
    pendulum = next(line for line in lines if ">Problem: pendulum<" in line)
    assert '<a href="#pendulum-summary">summary</a>' in pendulum
    assert '<a href="#pendulum-convergence">convergence</a>' in pendulum


def test_the_headline_tables_wrap_to_the_page_instead_of_scrolling(report):
    """Verdicts and cost winners in two tables whose cells wrap: none scrolls sideways
    (checked at 1,400 px in a browser; here, the markup that decides it)."""
    out, _ = report
    headline = sections((out / "report.html").read_text())["Headline"]
    tables = re.findall(r"<table[^>]*>.*?</table>", headline, re.S)
    assert len(tables) == 2 and all(t.startswith('<table class="fit">') for t in tables)
    assert 'class="scroll"' not in headline
    assert "cheapest by wall time [s]" in tables[1] and "least drift" in tables[0]
    md = (out / "report.md").read_text()
    assert "| problem | matched accuracy | cheapest by wall time \\[s\\] |" in md


def test_timing_spread_and_targets_are_printed(report):
    out, _ = report
    problem = sections((out / "report.html").read_text())["Problem: pendulum"]
    assert "<th>wall min [s]</th><th>wall max [s]</th><th>solves</th>" in problem
    assert "pendulum: accuracy targets" in problem and "cheapest by evaluations" in problem


@pytest.mark.slow
def test_the_reference_floor_replaces_errors_below_it(tmp_path):
    """A final error within the reference's accuracy is not given as the method's error."""
    db = tmp_path / "driftbench.sqlite"
    with Store(db) as st:
        session = st.begin("unit")
        for h, final in ((2e-3, 3e-10), (1e-3, 5.5e-12), (5e-4, 4.8e-12)):
            rec = run("car-axis", "lobatto3ab4", h, final=final, order=6)
            st.add(session, replace(rec, metrics=rec.metrics.replace(reference_floor=6e-12)))
    md = build(db, tmp_path)[0].read_text()
    row = next(line for line in md.splitlines() if line.startswith("| lobatto3ab4 | h=0.0005 |"))
    assert "at reference floor (≤ 6e-12)" in row and "4.8e-12" not in md
    assert "too few points above the reference floor" in md


@pytest.mark.slow
def test_a_problem_without_errors_to_plot_gets_a_sentence_not_an_empty_convergence_figure(
        tmp_path):
    """One fixed-step run without a reference is its own reference: nothing to plot."""
    db = tmp_path / "driftbench.sqlite"
    with Store(db) as st:
        session = st.begin("unit")
        st.add(session, run("chain", "rattle", 1e-3, t_end=2.0))
        for h, final in ((0.1, 1e-4), (0.05, 2.5e-5)):
            st.add(session, run("pendulum", "rattle", h, final=final))
    md = build(db, tmp_path)[0].read_text()
    assert "No convergence figure: no finished fixed-step run has an error against another" in md
    assert "(figures/chain-convergence.svg)" not in md
    assert "(figures/pendulum-convergence.svg)" in md


def test_bad_command_line_input_is_one_line_and_exit_2(tmp_path, capsys):
    from reports.__main__ import main

    afile = tmp_path / "afile"
    afile.write_text("")
    db = tmp_path / "driftbench.sqlite"
    fill(db)
    for argv in (["--x", "flops"], ["--targets", "-1"], ["--db", str(tmp_path / "none")],
                 ["--db", str(db), "--out", str(afile)]):  # --out a file, not a folder
        with pytest.raises(SystemExit) as exc:
            code = main(["--out", str(tmp_path), *argv])
            raise SystemExit(code)
        assert exc.value.code == 2
        err = capsys.readouterr().err
        assert err.startswith("error: ") and err.count("\n") == 1, err


@pytest.mark.slow
def test_work_precision_axes_follow_the_command_line(tmp_path):
    from reports.__main__ import main

    db = tmp_path / "driftbench.sqlite"
    fill(db)
    assert main(["--db", str(db), "--out", str(tmp_path), "--x", "steps", "--y", "Gv"]) == 0
    svg = (tmp_path / "figures" / "pendulum-work-precision.svg").read_text()
    assert "max |G v + g_t|" in svg and ">steps<" in svg and "wall time" not in svg


def test_figure_colours_follow_the_integrators_families():
    """One hue per family (the integrators' ``family`` trait), shades and markers within."""
    from matplotlib.colors import rgb_to_hsv

    from reports.figures import palette

    colors = palette({"SPARK": ["lobatto3ab2", "lobatto3ab3"], "RATTLE": ["rattle"]})
    hue = {k: rgb_to_hsv(c)[0] for k, (c, _) in colors.items()}
    assert hue["lobatto3ab2"] == pytest.approx(hue["lobatto3ab3"], abs=1e-9)
    assert abs(hue["rattle"] - hue["lobatto3ab2"]) > 0.05
    assert colors["lobatto3ab2"][0] != colors["lobatto3ab3"][0]
    assert colors["lobatto3ab2"][1] != colors["lobatto3ab3"][1]


def test_a_drift_figure_draws_a_run_that_blew_up():
    # bricard with baumgarte-rk4 at h = 0.01 leaves window maxima of 2.6e285 before its state
    # turns non-finite; log-axis ticks at such values pass the largest float, and the
    # report must still be built.
    from reports import figures

    windows = {"t": np.array([0.25, 0.5, 0.75]), "pos": np.array([1e-9, 1e40, 2.6e285]),
               "energy": np.array([1e-6, 1e200, np.inf])}
    entry = {"label": "baumgarte-rk4", "integrator": "baumgarte-rk4", "windows": windows,
             "failed": True, "fail_time": 0.77}
    svg = figures.drift([entry], {"baumgarte-rk4": ("#1f77b4", "o")}, "bricard")
    assert svg.lstrip().startswith("<") and "</svg>" in svg


@pytest.mark.slow
def test_figures_drawn_in_worker_processes_equal_those_drawn_here():
    """The report's figures are drawn side by side in spawned processes (``Drawing``): the
    same SVG text as drawn in this process, and a figure that raises raises where its SVG
    is read."""
    from reports import figures
    from reports.document import Figure, svg_text

    windows = {"t": np.array([0.5, 1.0, 2.0]), "pos": np.array([1e-16, 2e-16, 4e-16]),
               "energy": np.array([1e-8, 2e-8, 3e-8])}
    entry = {"label": "rattle h=0.01", "integrator": "rattle", "windows": windows,
             "failed": False}
    colors = {"rattle": ("#1f77b4", "o")}
    here = figures.drift([entry], colors, "pendulum")
    with figures.Drawing(jobs=2) as draw:
        assert draw.jobs == 2
        drawn = draw(figures.drift, [entry], colors, "pendulum")
        broken = draw(figures.drift, [{"label": "no windows"}], colors, "pendulum")
        assert svg_text(Figure("drift", drawn)) == here
        with pytest.raises(KeyError):
            svg_text(Figure("broken", broken))
    with figures.Drawing(jobs=1) as draw:
        with pytest.raises(KeyError):
            svg_text(Figure("broken", draw(figures.drift, [{"label": "x"}], colors, "p")))


def test_tick_labels_off_the_decades_are_distinct_and_do_not_crowd():
    """An axis within one decade gets ticks at even steps, which one digit would label
    alike; labels closer than the gap to a decade or to the last label are left out."""
    from reports.figures import _Distinct

    values = [2.6e-3, 2.8e-3, 3.0e-3, 3.2e-3, 3.4e-3, 9.5e-3]
    labels = _Distinct(0.05).format_ticks(values)
    shown = [(x, label) for x, label in zip(values, labels) if label]
    assert [label for _, label in shown] == ["2.6e-03", "3.0e-03", "3.4e-03"]
    assert all(np.log10(b / a) >= 0.05 for (a, _), (b, _) in zip(shown, shown[1:]))
    assert _Distinct(0.05).format_ticks([2e-4, 5e-4]) == ["2e-04", "5e-04"]


def order_table(md: str, problem: str) -> dict[str, list[str]]:
    """The order table of ``problem``'s convergence section, by integrator."""
    part = md[md.index(f"### {problem}: convergence"):]
    rows = [line for line in part.split("\n## ")[0].splitlines()
            if line.startswith("| ") and not line.startswith("| integrator")]
    cells = [[c.strip() for c in re.split(r"(?<!\\)\|", row)[1:-1]] for row in rows]
    return {c[0]: c[1:] for c in cells}


@pytest.mark.slow
def test_orders_are_fitted_over_the_asymptotic_range_and_say_so(tmp_path):
    """A pre-asymptotic coarse point is left out and named; two pairwise orders that
    disagree (3.10 then 1.89) give no order rather than their average; in both reports."""
    db = tmp_path / "driftbench.sqlite"
    with Store(db) as st:
        session = st.begin("unit")
        for h, final in ((0.1, 4e-2), (0.05, 2.5e-4), (0.025, 6.25e-5), (0.0125, 1.5625e-5)):
            st.add(session, run("pendulum", "rattle", h, final=final))
        for h, final in ((0.04, 1e-2), (0.02, 1e-2 / 2 ** 3.10),
                         (0.01, 1e-2 / 2 ** (3.10 + 1.89))):
            st.add(session, run("pendulum", "genalpha", h, final=final))
        st.add(session, run("pendulum", "lobatto3ab3", 0.05, final=1e-6))
    md_path, html_path = build(db, tmp_path)[:2]
    md = md_path.read_text()
    rows = order_table(md, "pendulum")
    assert rows["rattle"] == ["2.00", "2", "h = 0.05..0.0125, 3 points", "7.32, 2.00, 2.00",
                              "0.1 (pre-asymptotic)"]
    assert rows["genalpha"][0].startswith("n/a: no 3 consecutive step sizes whose pairwise "
                                          "orders agree within 0.25")
    assert rows["genalpha"][2:] == ["\\-", "3.10, 1.89",
                                    "0.04 (pairwise orders disagree); 0.02 (pairwise orders "
                                    "disagree); 0.01 (pairwise orders disagree)"]
    assert "fitted over the asymptotic range only" in md
    assert rows["lobatto3ab3"][:4] == ["n/a: 1 step size run, 3 needed", "2", "\\-", "\\-"]
    problem = sections(html_path.read_text())["Problem: pendulum"]
    assert "h = 0.05..0.0125, 3 points" in problem and "0.1 (pre-asymptotic)" in problem


@pytest.mark.slow
def test_a_real_sweep_leaves_its_pre_asymptotic_step_out_of_the_fit(tmp_path, monkeypatch):
    """RATTLE on the pendulum over 10 s: at h = 0.2 (a twelfth of the period) the error is
    not yet in its h^2 range, and the report's order table says so."""
    from benchmarks import run as cli
    from benchmarks.records import CODE_VERSION_ENV

    monkeypatch.setenv(CODE_VERSION_ENV, "test-version")
    argv = ["--problems", "pendulum", "--integrators", "rattle", "--h", "0.2", "0.1", "0.05",
            "0.025", "--t-end", "10", "--jobs", "1", "--repeats", "1", "--out", str(tmp_path)]
    assert cli.main(argv) == 0
    fitted, nominal, span, pairwise, left = order_table(
        (tmp_path / "report.md").read_text(), "pendulum")["rattle"]
    assert left == "0.2 (pre-asymptotic)" and span == "h = 0.1..0.025, 3 points"
    assert float(pairwise.split(", ")[0]) < 1.5 and abs(float(fitted) - 2.0) < 0.1


def test_the_convergence_figure_marks_what_the_fit_left_out():
    """Filled: the three fitted points; hollow: the pre-asymptotic one; hollow and faint:
    the one at round-off; the legend gives the order and how many points it rests on."""
    from reports import figures
    from reports.analysis import fit

    h = 0.04 / 2.0 ** np.arange(5)
    err = np.append(1.0 / 2.0 ** np.cumsum([0.0, 3.10, 1.95, 2.02]), 1e-13)
    c = fit("rattle", h, err, 2.0, 1e-12)
    svg = figures.convergence([c], {"rattle": ("#d62728", "o")}, "t", "basis")
    styles = [s for s in re.findall(r'<use [^>]*style="([^"]*)"', svg) if "#d62728" in s]
    assert sorted(styles) == sorted(["fill: #d62728; stroke: #d62728"] * 3
                                    + ["fill-opacity: 0; stroke: #d62728",
                                       "fill-opacity: 0; stroke: #d62728; stroke-opacity: 0.35"])
    assert "rattle: fitted 1.99 over 3 points, nominal 2" in svg
