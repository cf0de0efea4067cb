"""The ``driftbench`` console command: each subcommand is its module's ``main``."""

import subprocess
import sys
from pathlib import Path

import pytest

from benchmarks import cli

ROOT = Path(__file__).resolve().parents[1]


def test_subcommands_are_the_modules_mains(capsys):
    assert cli.main(["run", "--list"]) == 0
    listing = capsys.readouterr().out
    assert "pendulum" in listing and "[built-in]" in listing


def test_unknown_subcommand_is_one_line_and_status_2(capsys):
    assert cli.main(["rn"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "unknown subcommand 'rn'" in err[0]


def test_help_and_version(capsys):
    assert cli.main(["--help"]) == 0
    out = capsys.readouterr().out
    assert all(name in out for name in cli.COMMANDS)
    assert cli.main([]) == 2
    assert cli.main(["--version"]) == 0
    assert capsys.readouterr().out.startswith("driftbench ")


def test_subcommand_options_pass_through():
    with pytest.raises(SystemExit) as exit_:
        cli.main(["cache", "--no-such-option"])
    assert exit_.value.code == 2


@pytest.mark.slow
def test_installed_script_runs():
    script = Path(sys.executable).with_name("driftbench")
    if not script.exists():
        pytest.skip("the package is not installed in this environment (make venv installs it)")
    done = subprocess.run([str(script), "run", "--list"], capture_output=True, text=True,
                          cwd=ROOT, timeout=120)
    assert done.returncode == 0, done.stderr
    assert "pendulum" in done.stdout
