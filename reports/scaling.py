"""The scaling section: cost per step against system size, from the scaling benchmark's output.

``python -m benchmarks.perf.scaling --out DIR`` writes ``DIR/scaling.json``; this module reads
that file only (it imports no integrator or problem) and renders one section: the settings
and what the times include, the plot of time per step against N (one line per family and
the C yardstick), the table of points, the fitted exponents and the bars. The benchmark
writes the section on its own (``scaling.md``, ``scaling.html`` beside its JSON);
``python -m reports --scaling DIR`` adds it to the main report.
"""

from __future__ import annotations

import json
from pathlib import Path

from benchmarks.files import replace_file
from benchmarks.records import Status
from reports import figures
from reports.analysis import fmt
from reports.document import Document, Figure, Para, Table, to_html, to_markdown

SCALING_FILE = "scaling.json"
#: Keys a results file must hold.
REQUIRED = ("settings", "points", "fits", "bars", "load", "baseline_rss")
#: The yardstick's name among the points.
C_NAME = "C"


class ScalingError(ValueError):
    """A scaling results folder that is missing or cannot be read."""


def results_file(path: Path, benchmark: str, required, error: type[ValueError]) -> dict:
    """The JSON object a perf benchmark wrote at ``path`` with the keys ``required``;
    ``error`` (one line) if it is absent, not JSON or lacks one, naming the command that
    writes it (``python -m benchmarks.perf.BENCHMARK --out FOLDER``)."""
    if not path.is_file():
        raise error(f"{path} does not exist: run python -m benchmarks.perf.{benchmark} "
                    f"--out {path.parent} first")
    try:
        data = json.loads(path.read_text())
    except (ValueError, UnicodeDecodeError) as exc:
        raise error(f"{path} is not valid JSON: {exc}") from None
    missing = [key for key in required if not isinstance(data, dict) or key not in data]
    if missing:
        raise error(f"{path} lacks {', '.join(missing)}: not a {benchmark} results file")
    return data


def load(folder) -> dict:
    """The results in ``folder/scaling.json``; :class:`ScalingError` if absent or malformed."""
    return results_file(Path(folder) / SCALING_FILE, "scaling", REQUIRED, ScalingError)


def _us(seconds) -> str:
    return "" if seconds is None else fmt(1e6 * seconds, 4)


def _mib(nbytes) -> str:
    return "" if nbytes is None else f"{nbytes / 2**20:.0f}"


def _processes(k: int) -> str:
    """How many fresh processes each point ran in, and which one is reported."""
    if k == 1:
        return "each point in a fresh process"
    return (f"each point in {k} fresh processes, in {k} rounds over the points, reported by "
            f"its median process (by time per step; the fastest and slowest of the {k} in "
            f"scaling.csv)")


def section(doc: Document, data: dict, draw) -> None:
    """Append the scaling section to ``doc``, its figure drawn by ``draw``
    (:class:`reports.figures.Drawing`)."""
    s, points = data["settings"], data["points"]
    doc.heading(2, "Scaling: cost per step against size")
    steps = ", ".join(f"h = {fmt(h)} on {p}" for p, h in s["h"].items() if p in s["problems"])
    cap = f"{s['memory_limit'] / 2**30:g} GiB" if s["memory_limit"] else "none"
    doc.add(Para(
        f"Every family on {', '.join(s['problems'])} for N = "
        f"{', '.join(map(str, s['n']))}, " + _processes(s.get("processes", 1))
        + f": {s['steps']} steps of "
        f"{steps}; adaptive families at rtol = atol = {fmt(s['rtol'])} over the same horizon, "
        f"per internal step. Time per step is the median wall-clock time of the timed solves "
        f"divided by the steps taken: the compiled loop with its per-step measurement of |g|, "
        f"|G v| and |H - H0| (IDA: its one-step calls, our callbacks and the recording); "
        f"building the case, set-up and compilation are excluded and listed apart. C is the "
        f"plain-C O(N) RATTLE on the chain and on the rigid chain (the step rattle takes "
        f"there and the same bookkeeping, timed by its own clocks). Peak memory is the resident peak of the point's whole process; a process "
        f"that only imports the suite peaks at {_mib(data['baseline_rss'])} MiB. Limits per "
        f"point: {fmt(s['limit'])} s and an address-space cap of {cap}; a family that fails, "
        f"times out or runs out of memory is not run at larger N. 1-minute load average "
        f"{data['load'][0]:.2f} before and {data['load'][1]:.2f} after on "
        f"{data.get('machine', {}).get('cpus', '?')} cores (other processes share them). "
        f"C yardstick: {s.get('c_yardstick', 'not recorded')}."))
    families = list(dict.fromkeys(p["family"] for p in points if p["family"] != C_NAME))
    colors = figures.palette({key: [key] for key in families})
    panels = []
    for problem in s["problems"]:
        lines = []
        for family in families + [C_NAME]:
            done = sorted((p["n"], p["wall_per_step"]) for p in points
                          if p["problem"] == problem and p["family"] == family
                          and p["status"] == Status.OK)
            if family == C_NAME and not done:
                continue
            lines.append({"label": "C (O(N) RATTLE)" if family == C_NAME else family,
                          "key": None if family == C_NAME else family,
                          "n": [n for n, _ in done], "cost": [c for _, c in done]})
        panels.append((problem, lines))
    doc.add(Figure("scaling", draw(figures.scaling, panels, colors),
                   "Time per step against N (log-log): one line per family through its "
                   "finished points (a line ends where its family stopped; the table says "
                   "why), C dashed, and a dotted line of slope 1."))
    rows = []
    for p in points:
        rows.append([p["problem"], str(p["n"]), p["family"], p["status"],
                     "" if p["steps"] is None else str(p["steps"]), _us(p["wall_per_step"]),
                     _us(p["cpu_per_step"]), fmt(p["ratio_c"]),
                     fmt(p["newton_per_step"]), _mib(p["peak_rss"]), fmt(p["setup_s"]),
                     fmt(p["max_pos"]), p["linear_solver"] or "", p["message"]])
    doc.add(Table(["problem", "N", "family", "status", "steps", "us/step (wall)",
                   "us/step (CPU)", "ratio to C", "Newton/step", "peak MiB", "set-up [s]",
                   "max |g|", "linear solver", "message"], rows,
                  "Ratio to C: time per step over the C yardstick's at the same N (wall "
                  "clock). Newton/step: Newton iterations per (internal) step."))
    fit_rows = [[f["problem"], f["family"],
                 "n/a (fewer than two finished points)" if f["exponent"] is None
                 else f"{f['exponent']:.2f}", ", ".join(map(str, f["n"]))]
                for f in data["fits"]]
    doc.add(Table(["problem", "family", "fitted exponent", "N fitted"], fit_rows,
                  f"Least-squares slope of log time per step against log N over the finished "
                  f"points with N >= {s.get('fit_from', '?')} (all finished points where "
                  f"fewer than two reach it); 1 is linear growth."))
    doc.add(Table(["verdict", "bar", "measured"],
                  [[b["verdict"], b["bar"], b["value"]] for b in data["bars"]],
                  "The bars of the scaling issue. NOT MEASURED: the run's options left the "
                  "point out; a point that did not finish fails its bar."
                  + (f" A ratio of two points measured side by side (one process solving "
                     f"both in turn, {s['side_by_side']} rounds) decides its bar; the ratio "
                     f"of the separate processes is given beside it."
                     if data.get("side_by_side") else "")))


def write(data: dict, out: Path) -> list[Path]:
    """The section alone as ``out/scaling.md`` (figure under ``out/figures``) and
    ``out/scaling.html``; returns the paths written."""
    doc = Document("driftbench scaling")
    # One figure: drawn here, as it is submitted.
    section(doc, data, figures.Drawing(jobs=1))
    md, written = to_markdown(doc, out)
    md_path, html_path = out / "scaling.md", out / "scaling.html"
    replace_file(md_path, md)
    replace_file(html_path, to_html(doc))
    return [md_path, html_path, *written]
