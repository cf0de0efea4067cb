"""What every test shares: float64 JAX, set once before any test module builds an array,
and the ``slow`` marker's meaning.

``make test`` runs everything. ``pytest -m "not slow"`` is the quick subset: it leaves out
the long verification runs (long horizons, large problems, whole studies) and the tests
that start process pools, clusters or whole suites in subprocesses.
"""

import jax

jax.config.update("jax_enable_x64", True)
