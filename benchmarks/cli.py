"""``driftbench``: the suite's one command, with a subcommand per tool.

``driftbench run``
    Run a sweep or a suite and write its report (``python -m benchmarks.run``).
``driftbench report``
    Rebuild the report from a results store (``python -m reports``).
``driftbench check``
    The drift-regression gate (``python -m benchmarks.check``).
``driftbench cache``
    The persistent compile cache: where it is, its size, clearing it
    (``python -m benchmarks.compilation``).

Each subcommand takes the same options as its module form (``driftbench run --help``) and
exits with the same status: 0 when every run finished as planned, 1 when a run ended in
``error`` or ``timeout`` or the gate failed, 2 for bad input, 130 when interrupted.
"""

from __future__ import annotations

import importlib
import signal
import sys
from importlib import metadata

from benchmarks.records import EXIT_INPUT

#: Subcommand -> (module with ``main(argv) -> int``, one line of help).
COMMANDS: dict[str, tuple[str, str]] = {
    "run": ("benchmarks.run", "run a sweep or a suite and write its report"),
    "report": ("reports.__main__", "rebuild report.md and report.html from a results store"),
    "check": ("benchmarks.check", "compare a suite's drift against a baseline (the gate)"),
    "cache": ("benchmarks.compilation", "show or clear the persistent compile cache"),
}


def usage() -> str:
    width = max(map(len, COMMANDS))
    lines = ["usage: driftbench {" + ",".join(COMMANDS) + "} [options]", "",
             "Integrators for constrained mechanical systems, compared on one footing.", "",
             "subcommands:"]
    lines += [f"  {name:<{width}}  {text}" for name, (_, text) in COMMANDS.items()]
    lines += ["", "driftbench SUBCOMMAND --help shows a subcommand's options."]
    return "\n".join(lines)


def version() -> str:
    try:
        return metadata.version("driftbench")
    except metadata.PackageNotFoundError:  # run from a checkout that is not installed
        return "unknown"


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if not argv or argv[0] in ("-h", "--help"):
        print(usage(), file=sys.stdout if argv else sys.stderr)
        return 0 if argv else EXIT_INPUT
    if argv[0] == "--version":
        print(f"driftbench {version()}")
        return 0
    name, rest = argv[0], argv[1:]
    if name not in COMMANDS:
        print(f"error: unknown subcommand {name!r}; one of {', '.join(COMMANDS)} "
              f"(see driftbench --help)", file=sys.stderr)
        return EXIT_INPUT
    module = importlib.import_module(COMMANDS[name][0])
    return module.main(rest)


def entry() -> None:
    """The console script: as ``python -m benchmarks.run``, shutting down is not to be
    interrupted by a second Ctrl-C once the command has finished."""
    code = main()
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    sys.exit(code)
