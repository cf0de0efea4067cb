"""Test-only integrators, a problem and studies that misbehave on purpose (fault injection).

Loaded by the batch and every worker when the environment variable
``DRIFTBENCH_TEST_PLUGINS`` names this file (``benchmarks.executors.PLUGIN_ENV``); never
registered otherwise. Each fault is the smallest thing that reproduces one way a real run
goes wrong:

- ``test-hang``: ``solve`` never returns (a Newton iteration stuck in compiled code);
- ``test-kill``: the process is killed by ``SIGKILL`` (the out-of-memory killer);
- ``test-abort``: the process aborts (``SIGABRT``, a failed assertion in a C extension);
- ``test-raise``: ``solve`` raises (a defect);
- ``test-nan``: ``solve`` claims success with a NaN state (a method that hides a blow-up);
- ``test-offset-pendulum:dx=...``: the pendulum released from ``(L + dx, 0)``, so that a
  parameter makes the initial values inconsistent;
- studies ``test-study`` (a table and a figure) and ``test-study-raise``.
"""

from __future__ import annotations

import os
import signal
import time
from dataclasses import dataclass
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pandas as pd

import integrators
import problems
from benchmarks import batch
from integrators.base import Integrator, Status, Trajectory
from problems.case import make_case
from problems.mechanics import System


@dataclass(frozen=True)
class Hang(Integrator):
    h: float = 0.1

    def prepare(self, case, grid):
        def solve():
            while True:
                time.sleep(0.1)

        return solve


@dataclass(frozen=True)
class Kill(Integrator):
    h: float = 0.1

    def prepare(self, case, grid):
        return lambda: os.kill(os.getpid(), signal.SIGKILL)


@dataclass(frozen=True)
class Abort(Integrator):
    h: float = 0.1

    def prepare(self, case, grid):
        return os.abort


@dataclass(frozen=True)
class Raise(Integrator):
    h: float = 0.1

    def prepare(self, case, grid):
        def solve():
            raise RuntimeError("injected fault in solve")

        return solve


@dataclass(frozen=True)
class ReturnNaN(Integrator):
    h: float = 0.1

    def prepare(self, case, grid):
        n = case.system.n

        def solve():
            t = np.array([case.t0, case.t_end])
            nan = np.array([0.0, np.nan])
            return Trajectory(Status.OK, "", case.t_end, np.full(n, np.nan), np.full(n, np.nan),
                              {"t": t, "pos": nan, "vel": nan, "energy": nan},
                              {"t": t, "q": np.full((2, n), np.nan), "v": np.full((2, n), np.nan)},
                              {"n_steps": 1})

        return solve


for _key, _cls in (("test-hang", Hang), ("test-kill", Kill), ("test-abort", Abort),
                   ("test-raise", Raise), ("test-nan", ReturnNaN)):
    integrators.register(_key, f"{__name__}:{_cls.__name__}")


@problems.register("test-offset-pendulum")
def offset_pendulum(dx: float = 0.0, t_end: float = 1.0):
    """A unit pendulum released at rest from ``(1 + dx, 0)``: inconsistent unless dx = 0."""
    system = System(n=2, m=1, mass=np.ones(2), potential=lambda q: 9.81 * q[1],
                    constraints=lambda q, t: jnp.array([q[0] ** 2 + q[1] ** 2 - 1.0]))
    return make_case("test-offset-pendulum", system, [1.0 + dx, 0.0], [0.0, 0.0],
                     (0.0, t_end), dict(dx=dx), energy_scale=9.81)


def good_study(out: Path) -> dict[str, pd.DataFrame]:
    (out / "curve.svg").write_text('<svg xmlns="http://www.w3.org/2000/svg"></svg>')
    return {"numbers": pd.DataFrame({"k": [1, 2], "value": [0.5, 0.25]})}


def raising_study(out: Path) -> dict[str, pd.DataFrame]:
    raise RuntimeError("injected fault in a study")


batch.STUDIES.update({"test-study": f"{__name__}:good_study",
                       "test-study-raise": f"{__name__}:raising_study"})
