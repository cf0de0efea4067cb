"""Linear algebra below the integrators: solves with ``S = G M^{-1} G^T`` chosen by structure.

Modules: :mod:`linalg.dense` (the one rank policy, small solves, the dense Schur solver),
:mod:`linalg.pattern` (sparsity patterns, compressed Jacobians), :mod:`linalg.blocks`
(block-diagonal masses: blockwise factors, solves and the whitening of ``G``),
:mod:`linalg.banded`
(banded Cholesky in JAX), :mod:`linalg.sparse` (SuperLU through a callback) and
:mod:`linalg.schur` (the choice of solver by structure). Every function takes ``G``'s values
or its Jacobian function, its pattern and the mass (or a mass solve) as arguments; nothing
here knows of problems or integrators.
"""

import jax

# Float64 throughout, before any array is created.
jax.config.update("jax_enable_x64", True)
