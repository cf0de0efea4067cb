"""Generate the documentation's reference pages and the README's tables from the registries.

The integrator and problem tables, one page per integrator family and per problem, the
command-line reference and the performance pages are written from the code itself (the
registries, the classes' traits and dataclass fields, the modules' docstrings, the
argument parsers) and from the perf benchmarks' JSON outputs, so that they cannot drift
from what the code does.

Usage::

    python docs/generate.py               # write docs/_generated/ (Sphinx's conf.py runs this)
    python docs/generate.py --readme      # rewrite the README's tables between their markers
    python docs/generate.py --check       # exit 1 when the README's tables are not current
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import importlib
import inspect
import io
import json
import os
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:  # run as a script from anywhere, as conf.py and the test do
    sys.path.insert(0, str(ROOT))

DOCS = ROOT / "docs"
GENERATED = DOCS / "_generated"
README = ROOT / "README.md"
#: Where the perf benchmarks' outputs shown on the performance page are kept (committed:
#: the last measured run of each, with its machine's load).
RESULTS = DOCS / "performance"

#: The README's generated tables, each between a pair of HTML comment markers.
MARKERS = ("integrators", "problems")

#: Human names of the constraint levels in an integrator's ``enforces`` trait.
LEVELS = {"position": "g = 0", "velocity": "G v + g_t = 0"}

#: The perf benchmarks whose JSON outputs the performance pages read, with the command
#: that writes each one.
PERF_OUTPUTS = {
    "efficiency": ("efficiency/efficiency.json",
                   "python -m benchmarks.perf.efficiency --out docs/performance/efficiency"),
    "suite-time": (
        "suite-time/suite_time.json",
        "python -m benchmarks.perf.suite_time quick ci default --out docs/performance/suite-time"),
    "scaling": ("scaling/scaling.json", "python -m benchmarks.perf.scaling --out docs/performance/scaling"),
    "parallel-speedup": ("speedup/parallel_speedup.json",
                         "python -m benchmarks.perf.parallel_speedup --out docs/performance/speedup"),
    "exudyn": ("exudyn/exudyn.json",
               "python -m benchmarks.perf.exudyn --out docs/performance/exudyn"),
}

#: Width the help texts are wrapped to, whatever the terminal that builds the docs.
HELP_COLUMNS = "88"


# --------------------------------------------------------------------------- registries

def integrator_rows() -> list[dict]:
    """One row per registry key of the project's own (not those a plugin or a test
    registered in this process): the class and the traits of the key's preset instance."""
    import integrators

    rows = []
    for key in integrators.keys():
        if integrators.REGISTRY[key][0].split(".", 1)[0] != "integrators":
            continue
        method = integrators.make(key)
        cls = type(method)
        rows.append({
            "key": key, "cls": cls, "module": cls.__module__, "family": method.family,
            "adaptive": method.adaptive, "symplectic": method.symplectic,
            "enforces": tuple(method.enforces), "order": method.nominal_order,
            "preset": integrators.REGISTRY[key][1],
        })
    return rows


def problem_rows() -> list[dict]:
    """One row per built-in problem (not those a file, a module or a plugin registered in
    this process): its module, summary line and parameters."""
    import problems

    rows = []
    for name in problems.names():
        factory = problems.REGISTRY[name]
        # A test may register a problem in this process without a file or module of its
        # own (origin "built-in"): the project's own live in the problems package.
        if problems.origin(name) != "built-in" or not factory.__module__.startswith("problems."):
            continue
        module = importlib.import_module(factory.__module__)
        rows.append({"name": name, "factory": factory, "module": factory.__module__,
                     "summary": first_line(module.__doc__ or factory.__doc__ or ""),
                     "parameters": problems.parameters(name)})
    return rows


def first_line(doc: str) -> str:
    """The first paragraph of a docstring on one line, reST literals as Markdown code."""
    text = " ".join(inspect.cleandoc(doc).split("\n\n")[0].split())
    return text.replace("``", "`")


def enforced(levels: tuple[str, ...]) -> str:
    """The constraint levels of an ``enforces`` trait as equations."""
    return ", ".join(LEVELS.get(level, level) for level in levels) or "neither level exactly"


def order_text(row: dict) -> str:
    """The nominal order; BDF's varies with the step (``nominal_order`` None)."""
    return "variable" if row["order"] is None else str(row["order"])


# --------------------------------------------------------------------------- tables

def integrator_table(link: str = "") -> str:
    """Markdown table of every registered integrator; ``link`` prefixes family page links."""
    lines = ["| key | family | order | step | symplectic | enforces at every step |",
             "|---|---|---|---|---|---|"]
    for r in integrator_rows():
        family = f"[{r['family']}]({link}{page_name(r['module'])}.md)" if link else r["family"]
        lines.append(f"| `{r['key']}` | {family} | {order_text(r)} | "
                     f"{'adaptive' if r['adaptive'] else 'fixed'} | "
                     f"{'yes' if r['symplectic'] else 'no'} | {enforced(r['enforces'])} |")
    return "\n".join(lines)


def problem_table(link: str = "") -> str:
    """Markdown table of every registered problem with its parameter names."""
    lines = ["| problem | what it is | parameters |", "|---|---|---|"]
    for r in problem_rows():
        name = f"[`{r['name']}`]({link}{r['name']}.rst)" if link else f"`{r['name']}`"
        params = ", ".join(f"`{k}`" for k in r["parameters"]) or "none"
        lines.append(f"| {name} | {r['summary']} | {params} |")
    return "\n".join(lines)


def page_name(module: str) -> str:
    """A family page's name: its module's last component."""
    return module.rsplit(".", 1)[-1]


# --------------------------------------------------------------------------- pages

def family_page(module: str, rows: list[dict]) -> str:
    """One integrator family: its keys and traits, options with defaults and presets,
    then the module's and classes' docstrings (equations, order, references)."""
    mod = importlib.import_module(module)
    title = first_line(mod.__doc__ or module).rstrip(".")
    out = [f"# {title}", "", f"Module `{module}`.", "",
           "| key | class | order | step | symplectic | enforces | preset options |",
           "|---|---|---|---|---|---|---|"]
    for r in rows:
        preset = ", ".join(f"`{k}={v}`" for k, v in r["preset"].items()) or "none"
        out.append(f"| `{r['key']}` | `{r['cls'].__name__}` | {order_text(r)} | "
                   f"{'adaptive' if r['adaptive'] else 'fixed'} | "
                   f"{'yes' if r['symplectic'] else 'no'} | {enforced(r['enforces'])} | "
                   f"{preset} |")
    for cls in dict.fromkeys(r["cls"] for r in rows):
        out += ["", f"## Options of `{cls.__name__}`", "",
                "Give them as `key:name=value` (for example "
                f"`{example_option(cls, rows)}`).", "",
                "| option | default |", "|---|---|"]
        for f in dataclasses.fields(cls):
            if f.init:
                out.append(f"| `{f.name}` | `{default_of(f)}` |")
    out += ["", "## Reference", "", "```{eval-rst}", f".. automodule:: {module}", "   :no-index:",
            ""]
    for cls in dict.fromkeys(r["cls"] for r in rows):
        out += [f".. autoclass:: {module}.{cls.__name__}", "   :no-index:", ""]
    out += ["```", ""]
    return "\n".join(out)


def example_option(cls, rows: list[dict]) -> str:
    """``key:name=default`` for the class's first option that is neither a swept setting
    (which a spec may not set beside a sweep of it) nor preset by a registry key."""
    key = next(r for r in rows if r["cls"] is cls)
    options = [f for f in dataclasses.fields(cls) if f.init]
    taken = {"h", "rtol", "atol", *(name for r in rows for name in r["preset"])}
    f = next((f for f in options if f.name not in taken), options[0])
    return f"{key['key']}:{f.name}={default_of(f)}"


def default_of(f: dataclasses.Field) -> object:
    if f.default is not dataclasses.MISSING:
        return f.default
    if f.default_factory is not dataclasses.MISSING:
        return f.default_factory()
    return "required"


def problem_page(r: dict) -> str:
    """One problem, in reST: its parameters with defaults, then its module docstring
    (equations, source, reference) and its factory's docstring. reST, not Markdown,
    because the module docstrings have sections of their own, whose titles docutils keeps
    local to the page only when it parses the page itself."""
    title = f"``{r['name']}``"
    out = [title, "=" * len(title), "",
           f"Module ``{r['module']}``; spec ``{r['name']}:key=value,...``.", "",
           ".. list-table::", "   :header-rows: 1", "", "   * - parameter", "     - default"]
    for k, v in r["parameters"].items():
        out += [f"   * - ``{k}``", f"     - ``{v}``"]
    out += ["", f".. automodule:: {r['module']}", "   :no-index:", "",
            f".. autofunction:: {r['module']}.{r['factory'].__name__}", "   :no-index:", ""]
    return "\n".join(out)


def help_text(module: str) -> str:
    """What ``module``'s ``main(["--help"])`` prints, wrapped to :data:`HELP_COLUMNS`."""
    saved = os.environ.get("COLUMNS")
    os.environ["COLUMNS"] = HELP_COLUMNS
    out = io.StringIO()
    try:
        with contextlib.redirect_stdout(out):
            importlib.import_module(module).main(["--help"])
    except SystemExit:
        pass
    finally:
        if saved is None:
            del os.environ["COLUMNS"]
        else:
            os.environ["COLUMNS"] = saved
    return out.getvalue().rstrip()


def cli_page() -> str:
    """Every subcommand's ``--help``, as its parser prints it."""
    out = ["# Command-line reference", "",
           "Generated from the argument parsers. Each `driftbench SUBCOMMAND` is its module "
           "form, which keeps working and takes the same options.", ""]
    from benchmarks.cli import COMMANDS

    for name, (module, _) in COMMANDS.items():
        form = f"python -m {module.removesuffix('.__main__')}"
        out += [f"## `driftbench {name}`", "", f"Module form: `{form}`.", "", "```text",
                help_text(module).replace(form, f"driftbench {name}"), "```", ""]
    return "\n".join(out)


def performance_page(results: Path = RESULTS) -> str:
    """The perf benchmarks' JSON outputs under ``results`` as tables; where an output is
    absent, the command that writes it."""
    out = ["# Performance", "",
           "Tables on this page are read from the perf benchmarks' JSON outputs under "
           "`docs/performance/` when the documentation is built (the last measured run "
           "of each benchmark, committed); each benchmark's full printout "
           "says how it is judged. Times depend on the machine and its load, which each "
           "output records.", ""]
    for name, (path, command) in PERF_OUTPUTS.items():
        out += [f"## {name}", ""]
        file = results / path
        if not file.is_file():
            out += [f"No `docs/performance/{path}` in this build. Produce it with", "", "```sh",
                    command, "```", "", "then rebuild the documentation (`make docs`).", ""]
            continue
        data = json.loads(file.read_text())
        out += [RENDERERS[name](data), ""]
    return "\n".join(out)


def _efficiency(data: dict) -> str:
    lines = [f"What the harness costs: each family's time per step against a native C "
             f"yardstick of the same algorithm (medians of {data['rounds']} alternating "
             f"rounds; load {data['load']:.2f}; goal at most {data['goal_ratio_per_step']:g}x).",
             "", "| family | driver | problem | us per step | C us per step | x C per step | "
             "x C per solve | steps | C steps | final dq |", "|---|---|---|---|---|---|---|---|---|---|"]
    for r in data.get("rows", []):
        lines.append(f"| `{r['family']}` | {r.get('driver', '-')} | `{r['problem']}` | "
                     f"{r['us_per_step']:.3g} | {r['yardstick_us_per_step']:.3g} | "
                     f"{r['ratio_per_step']:.2f} | {r['ratio_per_solve']:.2f} | {r['steps']} | "
                     f"{r['yardstick_steps']} | {r['final_q_difference']:.1e} |")
    return "\n".join(lines)


def _suite_time(data: list[dict]) -> str:
    lines = ["| suite | wall [s] | budget [s] | load before / after | statuses |",
             "|---|---|---|---|---|"]
    for r in data:
        budget = "none" if r.get("budget_s") is None else f"{r['budget_s']:.0f}"
        statuses = ", ".join(f"{n} {s}" for s, n in sorted(r.get("statuses", {}).items()))
        lines.append(f"| `{r['suite']}` | {r['wall_s']:.1f} | {budget} | "
                     f"{r['load_before']:.2f} / {r['load_after']:.2f} | {statuses} |")
    return "\n".join(lines)


def _scaling(data: dict) -> str:
    lines = ["| problem | N | family | status | us per step | x C | Newton per step | peak MiB |",
             "|---|---|---|---|---|---|---|---|"]
    for p in data.get("points", []):
        def g(x, scale=1.0, spec=".3g"):
            return "-" if x is None else format(scale * x, spec)
        rss = None if p.get("peak_rss") is None else p["peak_rss"] / 2**20
        lines.append(f"| `{p['problem']}` | {p['n']} | {p['family']} | {p['status']} | "
                     f"{g(p.get('wall_per_step'), 1e6)} | {g(p.get('ratio_c'))} | "
                     f"{g(p.get('newton_per_step'), spec='.2f')} | {g(rss, spec='.0f')} |")
    return "\n".join(lines)


def _speedup(data: dict) -> str:
    lines = [f"Suite `{data['suite']}`, {data['runs']} runs, {data['cores']} usable cores.", "",
             "| engine | wall [s] | speed-up | load before / after |", "|---|---|---|---|"]
    for r in data.get("results", []):
        engine = r.get("engine") or r.get("cluster") or f"jobs {r.get('jobs')}"
        lines.append(f"| {engine} | {r['wall_s']:.1f} | {r['speedup']:.2f} | "
                     f"{r.get('load_before', float('nan')):.2f} / "
                     f"{r.get('load_after', float('nan')):.2f} |")
    return "\n".join(lines)


def _exudyn(data: dict) -> str:
    """``genalpha`` against Exudyn's generalized-alpha per problem and N; a comparison that
    did not finish shows its status and no figures."""
    lines = [f"`genalpha` against Exudyn {data['exudyn']}'s generalized-alpha solver, same "
             f"model, `rho_inf` and h (medians of {data['rounds']} alternating rounds; load "
             f"{data['load']:.2f}; goal at most {data['goal_ratio_per_step']:g}x Exudyn per "
             f"step, final states within {data['agreement']:g}). Time per step beyond a "
             "solve's fixed cost; on `rigid-chain` the final states compared are ours in "
             "Exudyn's rigid-body equations, and velocities may differ by Exudyn's "
             "rounding where that is larger.", "",
             "| problem | N | h | status | us per step | Exudyn us per step | x Exudyn per step | "
             "Newton per step | Exudyn Newton per step | final dq | final dv |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in data.get("rows", []):
        if r["status"] != "ok":
            status = str(r["status"]).replace("|", "\\|").replace("\n", " ")
            lines.append(f"| `{r['problem']}` | {r['N']} | {r['h']:g} | {status} | - | - | "
                         f"- | - | - | - | - |")
            continue
        agree = "ok" if r["agree"] else "ok, final states disagree"
        lines.append(f"| `{r['problem']}` | {r['N']} | {r['h']:g} | {agree} | "
                     f"{r['us_per_step']:.3g} | {r['exudyn_us_per_step']:.3g} | "
                     f"{r['ratio_per_step']:.2f} | "
                     f"{r['newton_per_step']:.2f} | {r['exudyn_newton_per_step']:.2f} | "
                     f"{r['final_q_difference']:.1e} | {r['final_v_difference']:.1e} |")
    return "\n".join(lines)


RENDERERS = {"efficiency": _efficiency, "suite-time": _suite_time, "scaling": _scaling,
             "parallel-speedup": _speedup, "exudyn": _exudyn}


def columns_list() -> str:
    """The columns of runs.csv, in order, as one inline list (included by the user guide)."""
    from benchmarks.records import COLUMNS

    return ", ".join(f"`{c}`" for c in COLUMNS) + "\n"


def metrics_table() -> str:
    """The metric columns of runs.csv as their declarations give them
    (:mod:`benchmarks.columns`): definition, which way is better and the drift gate's
    tolerance (included by the metrics guide)."""
    import math

    from benchmarks import columns

    lines = ["| column | definition | better | drift gate |", "|---|---|---|---|"]
    for name in columns.of_part("metrics"):
        c, t = columns.TABLE[name], columns.TABLE[name].tolerance
        if name == "invariant_errors":  # gated invariant by invariant (inv:NAME)
            t = columns.INVARIANT_TOLERANCE
        gate = ("not gated" if t is None else
                f"regresses above {t.factor:g}x the baseline and above {t.floor:g}"
                if t.direction == "lower" else
                f"regresses by {math.log10(t.factor):.1f} digits (counted up to {t.floor:g})")
        definition = c.description.replace("|", "\\|")
        lines.append(f"| `{name}` | {definition} | {c.better or ''} | {gate} |")
    return "\n".join(lines) + "\n"


def suite_table() -> str:
    """The shipped suites: name, budget and the first sentence of each file's description
    (read from the TOML, not loaded: loading resolves every run)."""
    import tomllib

    from benchmarks.suites import SUITE_DIR

    lines = ["| suite | budget [s] | what it is |", "|---|---|---|"]
    for path in sorted(SUITE_DIR.glob("*.toml")):
        data = tomllib.loads(path.read_text())
        what = " ".join(data.get("description", "").split()).split(": ", 1)[0].split(". ")[0]
        budget = data.get("budget", "none")
        lines.append(f"| `{path.stem}` | {budget} | {what.rstrip('.')} |")
    return "\n".join(lines) + "\n"


def changelog_page() -> str:
    """The project's CHANGELOG.md, included as it is; a line saying so where it is absent."""
    if (ROOT / "CHANGELOG.md").is_file():
        return "```{include} ../../CHANGELOG.md\n```\n"
    return "# Changelog\n\nThis checkout has no `CHANGELOG.md`.\n"


# --------------------------------------------------------------------------- writers

def write_docs(target: Path = GENERATED) -> list[Path]:
    """Write every generated page under ``target``; returns the files written."""
    pages: dict[str, str] = {}
    rows = integrator_rows()
    families: dict[str, list[dict]] = {}
    for r in rows:
        families.setdefault(r["module"], []).append(r)
    pages["integrators/index.md"] = "\n".join([
        "# Integrators", "",
        "Generated from the registry (`integrators.REGISTRY`) and each method's traits.", "",
        integrator_table(link="./"), "", "```{toctree}", ":maxdepth: 1", "",
        *[page_name(m) for m in families], "```", ""])
    for module, members in families.items():
        pages[f"integrators/{page_name(module)}.md"] = family_page(module, members)
    problem_list = problem_rows()
    pages["problems/index.md"] = "\n".join([
        "# Problems", "", "Generated from the registry (`problems.REGISTRY`) and each "
        "problem module's docstring.", "", problem_table(link="./"), "", "```{toctree}",
        ":maxdepth: 1", "", *[r["name"] for r in problem_list], "```", ""])
    for r in problem_list:
        pages[f"problems/{r['name']}.rst"] = problem_page(r)
    pages["cli.md"] = cli_page()
    pages["columns.md"] = columns_list()
    pages["metrics.md"] = metrics_table()
    pages["changelog.md"] = changelog_page()
    pages["suites.md"] = suite_table()
    pages["performance.md"] = performance_page()
    for path in target.rglob("*") if target.is_dir() else ():
        # A page of a problem or family no longer registered would be outside every toctree.
        if path.is_file() and path.relative_to(target).as_posix() not in pages:
            path.unlink()
    written = []
    for name, text in pages.items():
        path = target / name
        path.parent.mkdir(parents=True, exist_ok=True)
        if not path.is_file() or path.read_text() != text:  # unchanged files keep Sphinx's cache
            path.write_text(text)
        written.append(path)
    return written


def readme_with_tables(text: str) -> str:
    """``text`` (the README) with each marked table replaced by the current one."""
    tables = {"integrators": integrator_table(), "problems": problem_table()}
    for name in MARKERS:
        begin = f"<!-- {name} table: generated by docs/generate.py -->"
        end = f"<!-- end {name} table -->"
        head, found, rest = text.partition(begin)
        if not found or end not in rest:
            raise SystemExit(f"README.md: no {begin!r} ... {end!r} markers")
        text = f"{head}{begin}\n{tables[name]}\n{end}{rest.split(end, 1)[1]}"
    return text


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python docs/generate.py",
                                description=__doc__.split("\n")[0])
    p.add_argument("--readme", action="store_true", help="rewrite the README's tables")
    p.add_argument("--check", action="store_true",
                   help="exit 1 when the README's tables differ from the registries")
    args = p.parse_args(argv)
    if args.readme or args.check:
        current = README.read_text()
        wanted = readme_with_tables(current)
        if args.check:
            if current != wanted:
                print("README.md: the integrator or problem table is not current; run "
                      "`python docs/generate.py --readme`", file=sys.stderr)
                return 1
            return 0
        README.write_text(wanted)
        return 0
    for path in write_docs():
        print(path.relative_to(ROOT))
    return 0


if __name__ == "__main__":
    sys.exit(main())
