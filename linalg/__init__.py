"""Linear algebra below the integrators: solves with ``S = G M^{-1} G^T`` chosen by structure.

Modules: :mod:`linalg.dense` (the one rank policy, small solves, the dense Schur solver),
:mod:`linalg.krylov` (BiCGSTAB for matrix-free Newton corrections),
:mod:`linalg.pattern` (sparsity patterns, compressed Jacobians), :mod:`linalg.blocks`
(block-diagonal masses: blockwise factors, solves and the whitening of ``G``),
:mod:`linalg.banded`
(banded Cholesky in JAX), :mod:`linalg.sparse` (SuperLU through a callback),
:mod:`linalg.kkt` (a constant mass that is not diagonal: the augmented system ``[[M, G^T],
[G, 0]]`` by a banded ``L D L^T`` in JAX, and ``M`` itself banded) and
:mod:`linalg.schur` (the choice of solver by structure). Every function takes ``G``'s values
or its Jacobian function, its pattern and the mass (or a mass solve) as arguments; nothing
here knows of problems or integrators.
"""

import jax

# Float64 throughout, before any array is created.
jax.config.update("jax_enable_x64", True)
