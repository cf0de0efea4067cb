"""Flexible spacecraft: box hub with two solar panels, reduced in hybrid coordinates.

Modules
-------
:mod:`~studies.flexible.mesh`
    Structured triangular meshes of rectangular shell parts.
:mod:`~studies.flexible.shell`
    Flat-shell element matrices (six degrees of freedom per node) and sparse assembly.
:mod:`~studies.flexible.spacecraft`
    The finite-element model of the seed's spacecraft and its free-free modes.
:mod:`~studies.flexible.modal`
    The four modal sets and their hybrid-coordinate reduced models.
:mod:`~studies.flexible.study`
    Plate verification, the Table 1 analogue and the trial-strategy sweep.

The entry point for other parts of the project is :func:`reduced_model`.
"""

from __future__ import annotations

from functools import lru_cache

from .modal import MODAL_SETS, HybridModel, Substructures, reduce
from .spacecraft import SpacecraftDesign, build_spacecraft

__all__ = ["MODAL_SETS", "HybridModel", "SpacecraftDesign", "reduced_model", "substructures"]


@lru_cache(maxsize=4)
def substructures(design: SpacecraftDesign = SpacecraftDesign()) -> Substructures:
    """The assembled finite-element model of a design with its component-mode cache.

    Cached per design, so that every reduced model of one design shares one
    assembly and one set of component eigen-solutions.
    """
    return Substructures(build_spacecraft(design))


@lru_cache(maxsize=32)
def _reduced(modal_set: str, n_modes, design: SpacecraftDesign, options: tuple) -> HybridModel:
    return reduce(substructures(design), modal_set, n_modes, **dict(options))


def reduced_model(modal_set: str = "system", n_modes: int | tuple[int, int] | None = None,
                  synthesis_modes: tuple[int, int] | None = None, **mesh_options) -> HybridModel:
    """Reduced model of the spacecraft in hybrid coordinates.

    Parameters
    ----------
    modal_set : {"system", "craig-bampton", "macneal-rubin", "component"}
        Which of the seed's modal sets spans the deformation (see
        :mod:`studies.flexible.modal` for the equations of each).
    n_modes : int, (int, int) or None
        Retained normal modes. ``"system"``: the number of system modes
        (default 20, the seed's). The component sets: a pair (hub, per
        panel), or the total, shared 12 : 8 : 8 between hub and panels;
        default the seed's 12 hub and 8 per-panel modes.
    synthesis_modes : (int, int), optional
        ``"system"`` only: the (hub, per-panel) fixed-interface modes of the
        Craig-Bampton basis the system modes are synthesised from (default
        :data:`studies.flexible.modal.SYNTHESIS_MODES`).
    **mesh_options
        Fields of :class:`~studies.flexible.spacecraft.SpacecraftDesign`,
        e.g. ``element_size`` (m, default 0.125) or ``panel_span`` (m,
        default 1.5).

    Returns
    -------
    HybridModel
        ``M`` and ``K`` of order ``6 + k`` in the coordinates
        ``[x, y, z, theta_x, theta_y, theta_z, eta_1 ... eta_k]`` (hub frame
        origin translation, small rotations, deformation coordinates), with
        ``K`` zero on the rigid block; ``origin``, ``total_mass``,
        ``inertia`` (about ``origin``) and the free-free elastic frequencies
        ``f_hz``. Its arrays are read-only: the model is cached and shared
        between callers.

    Examples
    --------
    >>> model = reduced_model("system", 20, element_size=0.25)  # doctest: +SKIP
    >>> model.M.shape  # doctest: +SKIP
    (26, 26)
    """
    if modal_set not in MODAL_SETS:
        raise ValueError(f"unknown modal set {modal_set!r}; choose from {MODAL_SETS}")
    options = ()
    if synthesis_modes is not None:
        if modal_set != "system":
            raise ValueError("synthesis_modes applies to the 'system' modal set only")
        options = (("synthesis_modes", tuple(synthesis_modes)),)
    key = tuple(n_modes) if isinstance(n_modes, (tuple, list)) else n_modes
    return _reduced(modal_set, key, SpacecraftDesign(**mesh_options), options)
