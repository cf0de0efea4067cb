"""What every test shares: float64 JAX, set once before any test module builds an array;
the persistent compilation cache; XLA's options but the one-kernel flag
(:func:`integrators.loop.xla_options`); one BLAS thread
(:func:`benchmarks.pool.one_blas_thread`) and one XLA intra-op thread
(:func:`benchmarks.pool.one_xla_thread`);
and the ``slow`` marker's meaning.

``make test`` runs everything. ``pytest -m "not slow"`` is the quick subset: it leaves out
the long verification runs (long horizons, large problems, whole studies) and the tests
that start process pools, clusters or whole suites in subprocesses.

The tests compile through the same persistent cache as the suite
(:mod:`benchmarks.compilation`: ``$DRIFTBENCH_COMPILE_CACHE``, else the per-user folder),
so a second ``make test`` and the test files after the first reuse what was compiled, and
each test's programs are kept whole (:func:`kept_programs`). No test depends on their
state: an entry read back is the executable that would be compiled.
"""

import hashlib
import os
from pathlib import Path

import jax
import pytest

jax.config.update("jax_enable_x64", True)

from benchmarks import compilation, pool  # noqa: E402  (after float64 is set)
from integrators.loop import kernel_environment, xla_options  # noqa: E402
from linalg.compiled import keeping  # noqa: E402

# XLA reads its flags when JAX starts its CPU client, at the first computation: the tests
# compile as the suite's workers do (without the one-kernel flag, which only changes how
# the time loops run), which takes a third less time to compile.
os.environ.update(kernel_environment(options=xla_options(kernel=False)))
compilation.enable()
# One BLAS thread per test process, as in the suite's workers: two test workers on two
# cores would otherwise each spin a second OpenBLAS thread in every dense solve.
pool.one_blas_thread()
# And one XLA intra-op thread: with two, a large vmapped ensemble's LAPACK calls can deadlock.
pool.one_xla_thread()


def _test_code() -> str:
    """Hash of the code a test may compile beyond :data:`compilation.CODE_PACKAGES`: the
    tests themselves, the harness and the examples."""
    digest = hashlib.sha256()
    base = Path(__file__).resolve().parent.parent
    for package in ("tests", "benchmarks", "examples"):
        for path in sorted((base / package).rglob("*")):
            if not path.is_file() or "__pycache__" in path.parts:
                continue
            digest.update(str(path.relative_to(base)).encode())
            digest.update(path.read_bytes())
    return digest.hexdigest()


_TEST_CODE = _test_code()


@pytest.fixture(autouse=True)
def kept_programs(request):
    """Each test's programs kept whole (:func:`linalg.compiled.keeping`), named by the
    test and the hash of all the code it runs: a second ``make test`` on unchanged code
    loads them instead of tracing and lowering each again. They go to a folder of their
    own beside the suite's kept programs, under a bound of its own, so that the tests
    never push a user's suite programs out. A test is deterministic (its
    random draws are seeded), so the programs it compiles are the same in every session;
    the runs inside it that keep their own programs (:func:`benchmarks.execute.execute`)
    use their own scope."""
    where = compilation.programs()
    with keeping(None if where is None else where / "tests",
                 compilation.identity("test", request.node.nodeid, _TEST_CODE)):
        yield
