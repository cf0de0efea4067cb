"""What every test shares: float64 JAX, set once before any test module builds an array;
the persistent compilation cache; XLA's options but the one-kernel flag
(:func:`integrators.loop.xla_options`); one BLAS thread
(:func:`benchmarks.pool.one_blas_thread`) and one XLA intra-op thread
(:func:`benchmarks.pool.one_xla_thread`);
and the ``slow`` marker's meaning.

``make test`` runs everything. ``pytest -m "not slow"`` is the quick subset: it leaves out
the long verification runs (long horizons, large problems, whole studies) and the tests
that start process pools, clusters, drawing processes, compiled yardsticks or whole suites
in subprocesses, but for the short end-to-end checks of a user's mistakes (one line, exit
status 2, results kept), which a contributor should see fail first.

The tests compile through the same persistent cache as the suite
(:mod:`benchmarks.compilation`: ``$DRIFTBENCH_COMPILE_CACHE``, else the per-user folder),
so a second ``make test`` and the test files after the first reuse what was compiled. No
test depends on its state: an entry read back is the executable that would be compiled.
"""

import os

import jax

jax.config.update("jax_enable_x64", True)

from benchmarks import compilation, pool  # noqa: E402  (after float64 is set)
from integrators.loop import kernel_environment, xla_options  # noqa: E402

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
