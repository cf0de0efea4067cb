"""The integrator contract: frozen options, ``prepare`` then ``solve``, a bounded trajectory.

An integrator is a frozen dataclass whose fields are all of its options; what ran is
exactly ``asdict(integrator)``. ``prepare(case, grid)`` does all set-up (compilation,
solver construction) and returns a zero-argument ``solve`` that the runner times on its own.
``solve`` returns a :class:`Trajectory` whose size does not depend on the number of steps:
per-window maxima of the residuals and of the energy error, and a bounded set of sampled
states. Failure is data: a run that cannot go on ends with a status and a message.
"""

from __future__ import annotations

import enum
import math
from dataclasses import asdict, dataclass, field
from typing import Callable, ClassVar

import numpy as np

from linalg.schur import KINDS
from linalg.sparse import FALLBACK_MAX
from problems.case import Case
from problems.source import located


class Status(enum.StrEnum):
    """How a run ended (docs/design.md, section 6); the values are what runs.csv and the store
    hold, and a member compares equal to its value."""

    OK = "ok"
    #: A numerical failure; the message says what and where.
    FAILED = "failed"
    #: Killed at its time limit.
    TIMEOUT = "timeout"
    #: A defect or bad input; the message says which.
    ERROR = "error"
    #: Not run; the message says why.
    SKIPPED = "skipped"


class Failure(enum.IntEnum):
    """Why a step of our compiled loops failed: the integer code a step returns, with its
    message (:attr:`message`). ``NONE`` (0) is a step that did not fail.

    The codes are data inside the compiled loops (``jnp.where`` on them, never Python
    branching on values), so one vocabulary serves the fixed-step loop
    (:mod:`integrators.loop`), the diffrax-driven loop (:mod:`integrators.baumgarte`) and
    manual stepping (:class:`integrators.fixed.Stepper`). Messages with ``{...}`` fields
    are formatted by the loop that knows their values.
    """

    NONE = 0, ""
    NEWTON = 1, "the stage equations did not converge (Newton)"
    NON_FINITE = 2, "the state became non-finite"
    SINGULAR = 3, ("G M^-1 G^T could not be solved with: not finite, or numerically singular "
                   "(redundant constraints or a singular configuration) with more than "
                   f"{FALLBACK_MAX} constraints on the superlu path; linear_solver=dense or "
                   "banded handles a singular one")
    UNDERFLOW = 4, "the step size underflowed: attempts were rejected until h reached round-off"
    SOLVER = 5, "the diffrax solver reported an unsuccessful step"
    MAX_STEPS = 6, "max_steps = {max_steps} accepted steps were reached before t_end = {t_end:g}"

    def __new__(cls, code: int, message: str):
        member = int.__new__(cls, code)
        member._value_ = code
        member.message = message
        return member

#: Work counters every run reports (zero where a method has no such work).
COUNTERS = ("n_steps", "n_rejected", "n_f_evals", "n_jac_evals", "n_newton", "n_lin_solves")


@dataclass(frozen=True)
class Grid:
    """What to record over the horizon ``[t0, t_end]``.

    Parameters
    ----------
    t0, t_end : float
        The horizon.
    n_windows : int
        Number of windows over which maxima of ``|g|``, ``|G v + g_t|`` and ``|H - H0|``
        are kept (the drift series).
    n_samples : int
        Number of states kept, evenly spread over the steps. A prepared solve of the
        fixed-step loop holds buffers of this many ``q`` and ``v`` from one call to the
        next (:mod:`integrators.loop`); a solve copies back only the rows it uses.
    """

    t0: float
    t_end: float
    n_windows: int = 1000
    n_samples: int = 2000


@dataclass
class Trajectory:
    """What a solve returns: bounded in size whatever the number of steps.

    ``windows`` maps ``"t"`` (window end times), ``"pos"``, ``"vel"``, ``"energy"`` and one
    entry per declared invariant (``"inv:NAME"``) to arrays of per-window maxima; windows no
    step reached are dropped. ``samples`` holds ``"t"``, ``"q"`` and ``"v"``. ``sampling``
    says where residuals were measured (``"every step"``, ``"every internal step"`` or a
    dense output grid). ``linear_solver`` names the linear algebra that ran (``"dense"``, or
    the structured solver chosen from the sparsity of the constraints, see
    :mod:`linalg.schur`) and ``pattern_nnz`` the number of structural nonzeros of
    the constraint Jacobian ``G`` (``None`` where no pattern was needed).
    """

    status: str
    message: str
    t_final: float
    q_final: np.ndarray
    v_final: np.ndarray
    windows: dict[str, np.ndarray]
    samples: dict[str, np.ndarray]
    counts: dict[str, int]
    sampling: str = "every step"
    fail_step: int | None = None
    fail_time: float | None = None
    extra: dict[str, float] = field(default_factory=dict)
    linear_solver: str = "dense"
    pattern_nnz: int | None = None


@dataclass(frozen=True)
class Integrator:
    """Base class: subclasses add their options as dataclass fields.

    What a method *is*, as data that tests and reports can ask for (its traits):

    Class attributes
    ----------------
    family : str
        The family the method belongs to (the README's integrator table).
    adaptive : bool
        Whether the method controls its own step (``rtol``/``atol``) or takes ``h``.
    symplectic : bool
        Whether a step is a symplectic map of the constrained flow for a conservative
        system with scleronomic constraints (then energy errors stay bounded over
        exponentially long times, for small enough ``h``).
    enforces : tuple of str
        The constraint levels held at every step to the solver's tolerance: ``"position"``
        (``g = 0``) and ``"velocity"`` (``G v + g_t = 0``); empty where drift is only
        damped. A property where it depends on an option (the formulation).
    nominal_order : int or None
        The order of the global error for smooth solutions (convergence plots and fits);
        ``None`` where no single order applies. A property where it depends on an option.
    """

    family: ClassVar[str] = ""
    adaptive: ClassVar[bool] = False
    symplectic: ClassVar[bool] = False
    enforces: ClassVar[tuple[str, ...]] = ()
    nominal_order: ClassVar[int | None] = None

    #: The constraint levels of :attr:`enforces`.
    LEVELS: ClassVar[tuple[str, ...]] = ("position", "velocity")

    def __post_init__(self):
        # An adaptive method's ``atol`` defaults to NaN, which stands for "equal to rtol".
        atol = getattr(self, "atol", None)
        if isinstance(atol, float) and math.isnan(atol):
            object.__setattr__(self, "atol", self.rtol)

    def options(self) -> dict[str, object]:
        """Every option of this integrator (what ran)."""
        return asdict(self)

    #: Whether :meth:`prepare_ensemble` runs the lanes in one compiled loop (``True``) or
    #: one after another.
    batched: ClassVar[bool] = False

    def prepare(self, case: Case, grid: Grid) -> Callable[[], Trajectory]:
        raise NotImplementedError

    def prepare_ensemble(self, case: Case, grid: Grid, q0s: np.ndarray, v0s: np.ndarray
                         ) -> Callable[[], list[Trajectory]]:
        """Set up an ensemble: the case from each of the consistent initial states
        ``(q0s[i], v0s[i])``; ``solve()`` returns one :class:`Trajectory` per lane.

        Here the lanes are prepared and solved one after another (:attr:`batched` is
        ``False``); methods with a compiled loop run them in one (``True``).
        """
        solves = [self.prepare(case.with_initial(q, v), grid) for q, v in zip(q0s, v0s)]
        return lambda: [solve() for solve in solves]

    def check_choice(self, option: str, choices) -> None:
        """Raise ``ValueError`` unless the value of ``option`` is one of ``choices`` (names)."""
        value = getattr(self, option)
        if value not in choices:
            raise ValueError(f"{type(self).__name__}: {option} = {value!r} is not one of "
                             f"{', '.join(choices)}")

    def check(self) -> None:
        """Validate the options; raise ``ValueError`` naming the bad one and where the class
        is defined."""
        cls = type(self)
        h = getattr(self, "h", None)
        if h is not None and not (np.isfinite(h) and h > 0):
            raise ValueError(located(f"{cls.__name__}: h = {h} must be positive and finite", cls))
        for name in ("rtol", "atol", "newton_tol"):
            tol = getattr(self, name, None)
            if tol is not None and not (0 < tol < 1):
                raise ValueError(located(f"{cls.__name__}: {name} = {tol} must lie in (0, 1)",
                                         cls))
        limit = getattr(self, "newton_max_iter", None)
        if limit is not None and not limit >= 1:
            raise ValueError(located(f"{cls.__name__}: newton_max_iter = {limit} must be >= 1",
                                     cls))
        if hasattr(self, "linear_solver"):
            # Refused here, before any run: at the first step it would make every run of
            # a suite an error.
            self.check_choice("linear_solver", KINDS)
