"""SUNDIALS IDA driven natively: the residual and iteration matrix compiled into one library
with the stepping loop (``sundials.c``), so that no Python runs between IDA and them.

The residual ``F(t, y, y')`` and the iteration matrix ``dF/dy + cj dF/dy'`` are the same
autodiff-derived functions :mod:`integrators.ida` hands to scikit-sundae; here they are
written as straight-line C (:func:`linalg.codegen.c_function`), compiled with the system's
C compiler together with the driver and linked against the SUNDIALS libraries that
scikit-sundae's wheel ships. IDA is set up with the same calls, in the same order, as
scikit-sundae makes them, so both drivers take the same steps until round-off in the
residuals (C against XLA's code) changes a step-size decision. Python is reached once per
:data:`CHUNK` internal steps, to hand the points to the drift record.

A library is built once per system and formulation and kept under the compile cache's
folder (``$DRIFTBENCH_COMPILE_CACHE/native``, else ``~/.cache/driftbench/native``), named by
the hash of its source and the SUNDIALS build. Where no compiler is found, the system uses
a primitive the code generator does not know, or the SUNDIALS libraries are missing,
:func:`build` raises :class:`NotNative` and the caller keeps scikit-sundae.
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import shlex
import shutil
import subprocess
import tempfile
from functools import cache
from pathlib import Path

import numpy as np

from linalg.codegen import Unsupported, c_function

#: Internal steps handed to Python at a time.
CHUNK = 4096
#: The SUNDIALS libraries the driver links, by the stem of their file names.
LIBRARIES = ("libsundials_core", "libsundials_nvecserial", "libsundials_sunmatrixdense",
             "libsundials_sunlinsoldense", "libsundials_ida")
DRIVER = Path(__file__).with_name("sundials.c")

_double_p = ctypes.POINTER(ctypes.c_double)


class NotNative(RuntimeError):
    """This system cannot run on the native driver (the reason is the message)."""


@cache
def sundials_libraries() -> tuple[Path, ...]:
    """The shared libraries of scikit-sundae's SUNDIALS build, in :data:`LIBRARIES` order."""
    import sksundae

    folder = Path(sksundae.__file__).resolve().parent.parent / "scikit_sundae.libs"
    found = []
    for stem in LIBRARIES:
        matches = sorted(folder.glob(f"{stem}-*.so*")) if folder.is_dir() else []
        if not matches:
            raise NotNative(f"{stem} not found beside scikit-sundae ({folder})")
        found.append(matches[0])
    return tuple(found)


def cache_folder() -> Path:
    setting = os.environ.get("DRIFTBENCH_COMPILE_CACHE", "").strip()
    if setting.lower() == "off":
        return Path(tempfile.gettempdir()) / f"driftbench-native-{os.getuid()}"
    if setting:
        return Path(setting).expanduser() / "native"
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "driftbench" / "native"


def compile_library(source: str) -> Path:
    """The shared library of ``source`` linked against SUNDIALS, built once and kept."""
    libraries = sundials_libraries()
    compiler = os.environ.get("CC") or shutil.which("cc") or shutil.which("gcc")
    if compiler is None:
        raise NotNative("no C compiler (cc or gcc) on PATH")
    key = hashlib.sha256("\n".join([source, compiler, *map(str, libraries)]).encode())
    folder = cache_folder()
    target = folder / f"ida-{key.hexdigest()[:24]}.so"
    if target.exists():
        return target
    folder.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=folder) as work:
        c_file = Path(work) / "ida.c"
        c_file.write_text(source)
        built = Path(work) / target.name
        rpath = f"-Wl,-rpath,{libraries[0].parent}"
        try:
            done = subprocess.run([*shlex.split(compiler), "-O2", "-shared", "-fPIC", "-o",
                                   str(built), str(c_file), *map(str, libraries), rpath, "-lm"],
                                  capture_output=True, text=True)
        except OSError as exc:
            raise NotNative(f"the C compiler {compiler!r} did not start: {exc}") from None
        if done.returncode != 0:
            # The compiler's text names temporary paths: it is not part of the run's
            # record (whose sampling must be the same for the same run), only its first
            # line, without them, is.
            first = next((line for line in done.stderr.splitlines() if "error" in line), "")
            raise NotNative(f"the C compiler failed on the generated code"
                            + (f" ({first.split('error', 1)[1].strip(': ')[:120]})"
                               if first else ""))
        os.replace(built, target)  # atomic: workers building the same library race safely
    return target


def functions(residual, neq: int, jacobian: bool) -> str:
    """C source of the driver's callbacks for ``residual(t, y, yp) -> F`` of ``neq``
    unknowns: ``res`` and ``jac``, the iteration matrix ``dF/dy + cj dF/dy'`` by
    forward-mode autodiff (column-major, as SUNDIALS' dense matrices), or an empty ``jac``
    without ``jacobian`` (IDA then forms it by difference quotients). Raises
    :class:`NotNative` where the code generator has no C form of the system."""
    import jax

    def matrix(t, y, yp, cj):
        return jax.jacfwd(lambda z: residual(t, z, yp + cj * (z - y)))(y)

    vector = (neq,)
    try:
        parts = [c_function(residual, "res", {"t": (), "y": vector, "yp": vector}, "r")]
        parts.append(c_function(matrix, "jac", {"t": (), "y": vector, "yp": vector, "cj": ()},
                                "J", column_major=True) if jacobian else
                     "static void jac(double t, const double *y, const double *yp, double cj,"
                     " double *J) {}\n")
    except Unsupported as exc:
        raise NotNative(f"the system's functions have no C form here: {exc}") from None
    return "#include <math.h>\n" + "".join(parts)


def build(residual, neq: int, jacobian: bool):
    """The library for ``residual(t, y, yp) -> F`` of ``neq`` unknowns, with its autodiff
    iteration matrix when ``jacobian`` (else IDA forms it by difference quotients):
    :func:`functions` compiled with the driver."""
    source = functions(residual, neq, jacobian) + DRIVER.read_text()
    path = compile_library(source)
    try:
        return Library(path)
    except OSError as exc:  # a cache folder on a noexec mount, say
        raise NotNative(f"the compiled driver does not load: {exc.strerror or exc}") from None


class Library:
    """A compiled driver: :meth:`solver` makes a :class:`Solver`."""

    def __init__(self, path: Path):
        lib = ctypes.CDLL(str(path))
        lib.solver_new.restype = ctypes.c_void_p
        lib.solver_new.argtypes = [ctypes.c_int, ctypes.c_double, _double_p, _double_p,
                                   ctypes.c_double, _double_p, _double_p, ctypes.c_int,
                                   ctypes.c_int, ctypes.c_long, ctypes.c_int, ctypes.c_int,
                                   ctypes.c_double, ctypes.c_double, ctypes.c_double,
                                   ctypes.c_double, ctypes.POINTER(ctypes.c_int)]
        lib.solver_steps.restype = ctypes.c_int
        lib.solver_steps.argtypes = [ctypes.c_void_p, ctypes.c_double, ctypes.c_int,
                                     _double_p, _double_p, ctypes.POINTER(ctypes.c_int),
                                     _double_p]
        lib.solver_state.argtypes = [ctypes.c_void_p, _double_p]
        lib.solver_counts.argtypes = [ctypes.c_void_p, ctypes.POINTER(ctypes.c_long)]
        lib.solver_message.restype = ctypes.c_char_p
        lib.solver_message.argtypes = [ctypes.c_void_p]
        lib.solver_free.argtypes = [ctypes.c_void_p]
        self.lib, self.path = lib, path

    def solver(self, **settings) -> "Solver":
        return Solver(self.lib, **settings)


def _p(a: np.ndarray):
    return a.ctypes.data_as(_double_p)


class Solver:
    """One IDA solve: set up at ``(t0, y0, yp0)`` with scikit-sundae's options' meanings."""

    def __init__(self, lib, *, t0, y0, yp0, rtol, atol, algebraic, jacobian, max_order,
                 max_steps, max_nonlin_iters, max_conv_fails, first_step, min_step,
                 max_step, tstop):
        self.lib, self.neq = lib, len(y0)
        y0, yp0, atol = (np.ascontiguousarray(a, dtype=np.float64) for a in (y0, yp0, atol))
        ident = np.ones(self.neq)
        ident[list(algebraic)] = 0.0
        flag = ctypes.c_int(0)
        self._handle = lib.solver_new(self.neq, t0, _p(y0), _p(yp0), rtol, _p(atol),
                                      _p(ident), int(jacobian), max_order, max_steps,
                                      max_nonlin_iters, max_conv_fails, first_step, min_step,
                                      max_step, tstop, ctypes.byref(flag))
        if not self._handle:
            raise RuntimeError(f"IDA did not initialise (flag {flag.value})")
        self.tstop = tstop
        self._t = np.empty(CHUNK)
        self._y = np.empty((CHUNK, self.neq))

    def failure(self, flag: int) -> str:
        """What a negative flag of IDASolve means, in scikit-sundae's words (so that both
        drivers fail with the same message), with SUNDIALS' own text."""
        from sksundae._cy_ida import IDAMESSAGES

        detail = " ".join(self.lib.solver_message(self._handle).decode().split())
        return (f"{IDAMESSAGES.get(flag, 'IDA failed')} (flag {flag})"
                + (f"; SUNDIALS: {detail}" if detail else ""))

    def steps(self, room: int):
        """Up to ``room`` internal steps: ``(t, y, flag, t_now)``, views valid until the
        next call."""
        room = min(room, CHUNK)
        flag, t_now = ctypes.c_int(0), ctypes.c_double(0.0)
        k = self.lib.solver_steps(self._handle, self.tstop, room, _p(self._t), _p(self._y),
                                  ctypes.byref(flag), ctypes.byref(t_now))
        return self._t[:k], self._y[:k], flag.value, t_now.value

    def state(self) -> np.ndarray:
        y = np.empty(self.neq)
        self.lib.solver_state(self._handle, _p(y))
        return y

    def counts(self) -> dict[str, int]:
        """Residual calls, step attempts, IDA's residual and iteration-matrix evaluations."""
        out = (ctypes.c_long * 4)()
        self.lib.solver_counts(self._handle, out)
        return dict(zip(("calls", "trials", "residuals", "jacobians"), out))

    def close(self) -> None:
        if self._handle:
            self.lib.solver_free(self._handle)
            self._handle = None

    __del__ = close
