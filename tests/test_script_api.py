"""The Python API called from a plain script, without an ``if __name__ == "__main__"``
guard: no worker process (the runs' or the report's drawing) runs the script again."""

from __future__ import annotations

import math
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

SCRIPT = """\
from benchmarks.api import sweep
runs = sweep(["pendulum"], ["rattle"], h=[0.02, 0.01], t_end=0.5, out="results/mine",
             report=True, repeats=1)
print("SWEEP DONE")
print(runs[["problem", "integrator", "h", "status", "max_pos_residual", "rel_energy_error"]])
"""


@pytest.mark.slow
def test_unguarded_script_finishes_and_writes_its_report(tmp_path):
    """The README's example as ``python file.py``: exits 0 with its table, runs the sweep
    once (a worker that imported the script would run it again, and the second sweep
    would find the store "being written by another invocation") and writes the report
    with its figures, which are drawn in worker processes."""
    script = tmp_path / "example.py"
    script.write_text(SCRIPT)
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    done = subprocess.run([sys.executable, str(script)], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    assert done.stdout.count("SWEEP DONE") == 1
    assert "Traceback" not in done.stderr
    out = tmp_path / "results" / "mine"
    assert (out / "report.md").is_file() and (out / "report.html").is_file()
    assert list((out / "figures").glob("*.svg"))
    assert done.stdout.count(" ok ") == 2, done.stdout


@pytest.mark.slow
def test_a_drawing_process_that_dies_fails_its_figure_and_the_next_is_drawn():
    """A drawing worker that dies fails the figure it was drawing, with its exit code,
    where that figure is read; the next figure gets a fresh worker."""
    from reports import figures

    with figures.Drawing(jobs=2) as draw:
        died = draw(os._exit, 3)
        with pytest.raises(RuntimeError, match="exit code 3"):
            died.result(timeout=120)
        assert draw(math.fsum, [0.1] * 10).result(timeout=120) == 1.0
