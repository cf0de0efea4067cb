r"""Verification and the seed's modal-set comparison, as tables.

* :func:`plate_verification`: square plates (side :math:`a`, :math:`h/a = 0.01`,
  :math:`\nu = 0.3`) against classical frequency parameters
  :math:`\lambda = \omega a^2 \sqrt{\rho h / D}`: the cantilever against
  Leissa (1969) (3.492, 8.525, 21.43, 27.33, 31.11), the simply supported
  plate against the exact :math:`\lambda_{mn} = \pi^2 (m^2 + n^2)`, the free
  plate against its six rigid-body zeros and Leissa's first elastic values
  (13.468, 19.596, 24.270), and the free hub box against six zeros.
* :func:`fe_modes`, :func:`fe_convergence`: the full model's free-free
  spectrum and its mesh convergence.
* :func:`table1`: the analogue of the seed's Table 1, the first six non-zero
  frequencies of each modal set's reduced model next to the full model's.
* :func:`modal_convergence`, :func:`plot_modal_convergence`: the seed's trial
  strategy (Section 4, step 1), error against the number of retained modes.

Reduced-model frequencies are compared with the full model's index by index
in ascending order: for Rayleigh-Ritz models the :math:`j`-th reduced
eigenvalue bounds the :math:`j`-th full one from above, so that pairing is
the one the bound speaks about.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pandas as pd

from .mesh import merge, box, plate
from .modal import MODAL_SETS, Substructures, reduce, split_modes
from .shell import ShellSection, assemble, node_dofs
from .spacecraft import SpacecraftDesign, SpacecraftFE, build_spacecraft, free_vibration, frequencies_hz

CANTILEVER_CLASSICAL = (3.492, 8.525, 21.43, 27.33, 31.11)
"""Leissa (1969), square plate clamped on one edge, nu = 0.3: first five lambda."""
FREE_PLATE_CLASSICAL = (13.468, 19.596, 24.270)
"""Leissa (1969), completely free square plate, nu = 0.3: first three elastic lambda."""
PLATE_MESHES = (4, 8, 16, 24, 32)
"""Elements per side of the square-plate verification meshes (two triangles per cell)."""
PLATE_SECTION = ShellSection(E=70e9, nu=0.3, rho=2700.0, h=0.01)
"""Verification plate: 1 m square, 10 mm thick (thin: a/h = 100)."""
N_TABLE = 6
"""Non-zero frequencies compared in Table 1, as in the seed."""
COMPONENT_SWEEP = (7, 14, 28, 56, 84)
"""Total retained component modes in the trial strategy (split 12 : 8 : 8 as the seed's 28)."""
SYSTEM_SWEEP = (6, 8, 10, 15, 20, 30, 40)
"""Retained system modes in the trial strategy."""


def _plate_lambda(n: int, fixed) -> np.ndarray:
    """Frequency parameters of the 1 m square plate with the given dofs fixed (callable of the mesh)."""
    mesh = plate(1.0, 1.0, n, n)
    K, M = assemble(mesh, PLATE_SECTION)
    fixed_dofs = fixed(mesh)
    free = np.setdiff1d(np.arange(K.shape[0]), fixed_dofs)
    n_modes = 9 if fixed_dofs.size == 0 else 6
    shift = -1.0 if fixed_dofs.size == 0 else 0.0
    omega2, _ = free_vibration(K[free][:, free], M[free][:, free], n_modes, shift)
    scale = np.sqrt(PLATE_SECTION.areal_mass / PLATE_SECTION.D)
    return np.sign(omega2) * np.sqrt(np.abs(omega2)) * scale


def cantilever_plate(n: int) -> np.ndarray:
    """First five lambda of the square plate clamped (all six dofs) along ``x = 0``, ``n x n`` mesh."""
    def clamped(mesh):
        return node_dofs(np.flatnonzero(np.isclose(mesh.nodes[:, 0], 0.0)))
    return _plate_lambda(n, clamped)[:5]


def simply_supported_plate(n: int) -> np.ndarray:
    """First six lambda of the simply supported square plate, ``n x n`` mesh.

    On every edge ``w = 0``, the in-plane displacements are held and so is
    the rotation that would tilt the edge along itself (the "hard" support
    of a shear-deformable plate, whose thin limit is the classical one).
    """
    def supported(mesh):
        x, y = mesh.nodes[:, 0], mesh.nodes[:, 1]
        edge_x = np.flatnonzero(np.isclose(x, 0.0) | np.isclose(x, 1.0))
        edge_y = np.flatnonzero(np.isclose(y, 0.0) | np.isclose(y, 1.0))
        return np.unique(np.concatenate([node_dofs(edge_x, (0, 1, 2, 3)), node_dofs(edge_y, (0, 1, 2, 4))]))
    return _plate_lambda(n, supported)


def free_plate(n: int) -> np.ndarray:
    """First nine lambda of the completely free square plate (six rigid-body, then elastic)."""
    return _plate_lambda(n, lambda mesh: np.array([], dtype=np.int64))


def simply_supported_exact() -> np.ndarray:
    r"""First six exact :math:`\lambda_{mn} = \pi^2(m^2 + n^2)` of the simply supported square plate."""
    m, n = np.meshgrid(np.arange(1, 5), np.arange(1, 5))
    return np.sort((np.pi**2 * (m**2 + n**2)).ravel())[:6]


def free_box_hz(element_size: float = 0.5, design: SpacecraftDesign = SpacecraftDesign()) -> np.ndarray:
    """First seven free-free frequencies (Hz) of the hub box alone (six rigid-body, then elastic)."""
    nx, ny, nz, _ = replace(design, element_size=element_size).intervals()
    mesh = merge({"hub": box(*design.hub_size, nx, ny, nz)})
    K, M = assemble(mesh, design.section)
    omega2, _ = free_vibration(K, M, 7, -(2.0 * np.pi * 0.05) ** 2)
    return frequencies_hz(omega2)


def plate_verification(meshes=PLATE_MESHES) -> pd.DataFrame:
    """Mesh-convergence table of the plate and box checks.

    Returns
    -------
    pandas.DataFrame
        Columns ``case, mode, mesh, value, classical, rel_error``; ``value``
        and ``classical`` are frequency parameters for the plates and Hz for
        the box; ``rel_error`` is ``value / classical - 1``, left empty where
        the classical value is a rigid-body zero. The cantilever and simply
        supported rows also carry a Richardson extrapolation from the two
        finest meshes (assuming second-order convergence), mesh
        ``"extrapolated"``.
    """
    rows = []
    cases = {
        "cantilever": (cantilever_plate, CANTILEVER_CLASSICAL),
        "simply-supported": (simply_supported_plate, simply_supported_exact()),
        "free-free-plate": (free_plate, np.concatenate([np.zeros(6), FREE_PLATE_CLASSICAL])),
    }
    for case, (solve, classical) in cases.items():
        values = {n: solve(n) for n in meshes}
        for n in meshes:
            rows += [(case, j + 1, f"{n}x{n}", v, c) for j, (v, c) in enumerate(zip(values[n], classical))]
        if case != "free-free-plate" and len(meshes) >= 2:
            n1, n2 = meshes[-2], meshes[-1]
            extrapolated = (n2**2 * values[n2] - n1**2 * values[n1]) / (n2**2 - n1**2)
            rows += [(case, j + 1, "extrapolated", v, c) for j, (v, c) in enumerate(zip(extrapolated, classical))]
    for size in (0.5, 0.25):
        for j, v in enumerate(free_box_hz(size)):
            rows.append(("free-free-box", j + 1, f"h={size}m", v, 0.0 if j < 6 else np.nan))
    df = pd.DataFrame(rows, columns=["case", "mode", "mesh", "value", "classical"])
    with np.errstate(divide="ignore", invalid="ignore"):
        df["rel_error"] = np.where(df["classical"] > 0, df["value"] / df["classical"] - 1.0, np.nan)
    return df


def fe_modes(fe: SpacecraftFE, n_elastic: int = 26, shift_hz: float = 0.05) -> pd.DataFrame:
    """Free-free frequencies of the full model, six rigid-body ones included.

    Returns
    -------
    pandas.DataFrame
        Columns ``mode, f_hz``.
    """
    omega2, _ = free_vibration(fe.K, fe.M, 6 + n_elastic, -(2.0 * np.pi * shift_hz) ** 2)
    f = frequencies_hz(omega2)
    return pd.DataFrame({"mode": np.arange(1, f.size + 1), "f_hz": f})


def fe_convergence(sizes=(0.5, 0.25, 0.125, 1.0 / 12.0), n_elastic: int = 10,
                   design: SpacecraftDesign = SpacecraftDesign()) -> pd.DataFrame:
    """Elastic free-free frequencies of the full model on a sequence of meshes.

    Returns
    -------
    pandas.DataFrame
        Columns ``element_size, n_dof, mode, f_hz, rel_change``, where
        ``mode`` counts elastic modes only and ``rel_change`` is the change
        from the next coarser mesh.
    """
    rows = []
    previous = None
    for size in sizes:
        fe = build_spacecraft(replace(design, element_size=size))
        f = fe_modes(fe, n_elastic)["f_hz"].to_numpy()[6:]
        change = f / previous - 1.0 if previous is not None else np.full(f.size, np.nan)
        rows += [(size, fe.n_dof, j + 1, f[j], change[j]) for j in range(f.size)]
        previous = f
    return pd.DataFrame(rows, columns=["element_size", "n_dof", "mode", "f_hz", "rel_change"])


def _compare(modal_set: str, f_red: np.ndarray, f_fe: np.ndarray, n: int = N_TABLE) -> pd.DataFrame:
    return pd.DataFrame({
        "modal_set": modal_set,
        "mode": np.arange(1, n + 1),
        "f_hz": f_red[:n],
        "f_fe_hz": f_fe[:n],
        "rel_error": f_red[:n] / f_fe[:n] - 1.0,
    })


def table1(sub: Substructures, f_fe_elastic: np.ndarray) -> pd.DataFrame:
    """The Table 1 analogue with the seed's default mode counts.

    Parameters
    ----------
    sub : Substructures
    f_fe_elastic : numpy.ndarray
        Elastic free-free frequencies of the full model (Hz), ascending.

    Returns
    -------
    pandas.DataFrame
        Columns ``modal_set, mode, f_hz, f_fe_hz, rel_error``.
    """
    return pd.concat([_compare(s, reduce(sub, s).f_hz, f_fe_elastic) for s in MODAL_SETS], ignore_index=True)


def modal_convergence(sub: Substructures, f_fe_elastic: np.ndarray,
                      component_sweep=COMPONENT_SWEEP, system_sweep=SYSTEM_SWEEP) -> pd.DataFrame:
    """The seed's trial strategy: first six frequencies as retained modes are added.

    Returns
    -------
    pandas.DataFrame
        Columns ``modal_set, n_modes, n_hub, n_panel, n_dof, mode, f_hz,
        f_fe_hz, rel_error``; ``n_modes`` is the number of retained normal
        modes (component elastic modes of hub and both panels, or system
        modes), ``n_dof`` the order of the reduced model including the six
        rigid coordinates and, for Craig-Bampton, the constraint modes.
    """
    frames = []
    for s in MODAL_SETS:
        for n in (system_sweep if s == "system" else component_sweep):
            model = reduce(sub, s, n)
            n_hub, n_panel = (0, 0) if s == "system" else split_modes(n)
            df = _compare(s, model.f_hz, f_fe_elastic)
            df.insert(1, "n_modes", n)
            df.insert(2, "n_hub", n_hub)
            df.insert(3, "n_panel", n_panel)
            df.insert(4, "n_dof", model.M.shape[0])
            frames.append(df)
    return pd.concat(frames, ignore_index=True)


def convergence_summary(convergence: pd.DataFrame) -> pd.DataFrame:
    """Largest relative error over the compared modes, per set and retained-mode count."""
    return (convergence.assign(abs_error=convergence["rel_error"].abs())
            .groupby(["modal_set", "n_modes", "n_dof"], as_index=False, sort=False)["abs_error"].max()
            .rename(columns={"abs_error": "max_abs_rel_error"}))


def plot_modal_convergence(convergence: pd.DataFrame, path: Path) -> None:
    """Plot the trial strategy: largest error of the first six frequencies against retained modes and model order."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    summary = convergence_summary(convergence)
    fig, axes = plt.subplots(1, 2, figsize=(10, 4), sharey=True)
    floor = 1e-12
    for s, marker in zip(MODAL_SETS, "osD^"):
        d = summary[summary["modal_set"] == s]
        err = np.maximum(d["max_abs_rel_error"], floor)
        axes[0].semilogy(d["n_modes"], err, marker=marker, label=s)
        axes[1].semilogy(d["n_dof"], err, marker=marker, label=s)
    axes[0].set_xlabel("retained normal modes (component sets: hub + both panels)")
    axes[1].set_xlabel("order of the reduced model (6 rigid + deformation coordinates)")
    axes[0].set_ylabel(f"max |relative error|, first {N_TABLE} elastic frequencies")
    for ax in axes:
        ax.grid(True, which="both", alpha=0.3)
    axes[0].axhline(0.05, color="grey", ls=":", lw=1)
    axes[1].axhline(0.05, color="grey", ls=":", lw=1)
    axes[0].legend()
    fig.suptitle(f"Modal-set convergence against the full model (errors floored at {floor:g} for the log scale)")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def set_ordering(table: pd.DataFrame) -> list[tuple[str, float]]:
    """Modal sets from largest to smallest worst-case error in a Table 1 frame."""
    worst = table.assign(e=table["rel_error"].abs()).groupby("modal_set")["e"].max()
    return sorted(worst.items(), key=lambda kv: -kv[1])


SEED_TABLE1 = {
    "component": (0.76, 0.81, 1.52, 1.89, 2.16, 2.35),
    "craig-bampton": (0.59, 0.64, 1.80, 2.36, 2.36, 2.43),
    "system": (0.54, 0.58, 1.83, 2.37, 2.38, 2.45),
    "fe": (0.55, 0.55, 2.32, 2.37, 2.65, 2.65),
}
"""The seed's Table 1 (Hz), for reference in reports; the seed has no MacNeal-Rubin row."""

SEED_ORDERING = "component modes worst, Craig-Bampton close, system modes closest"
"""The seed's reading of its Table 1."""

__all__ = [
    "CANTILEVER_CLASSICAL", "FREE_PLATE_CLASSICAL", "SEED_ORDERING", "SEED_TABLE1",
    "cantilever_plate", "convergence_summary", "fe_convergence", "fe_modes", "free_box_hz", "free_plate",
    "modal_convergence", "plate_verification", "plot_modal_convergence", "set_ordering",
    "simply_supported_exact", "simply_supported_plate", "table1",
]
