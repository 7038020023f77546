"""Energy / conservation plots (matplotlib, Agg backend)."""

from __future__ import annotations

import os
from pathlib import Path

import matplotlib
import numpy as np
from matplotlib.figure import Figure

from abmpm.io.atomic import atomic_write


def _get(series: dict, *names: str):
    for n in names:
        if n in series and series[n] is not None:
            return np.asarray(series[n], dtype=np.float64)
    return None


def _relative_change(a: np.ndarray) -> np.ndarray:
    ref = a[0] if a.size else 1.0
    scale = abs(ref) if abs(ref) > 0 else max(float(np.max(np.abs(a))) if a.size else 1.0, 1e-300)
    return (a - ref) / scale


def plot_energy(series: dict, path: str | os.PathLike, title: str | None = None) -> None:
    """Plot kinetic energy vs time and the relative change of mass and |momentum|.

    ``series`` keys (lists or arrays of equal length): ``time`` (or ``t``),
    ``kinetic_energy`` (or ``ke``), optional ``potential_energy``, ``mass``
    (or ``total_mass``), ``momentum`` (either (T,3) vectors or |p| values, also
    ``momentum_norm``). Missing series are skipped. The PNG is written atomically.
    """
    matplotlib.use("Agg", force=False)

    t = _get(series, "time", "t")
    ke = _get(series, "kinetic_energy", "ke", "kinetic")
    pe = _get(series, "potential_energy", "pe")
    mass = _get(series, "mass", "total_mass")
    mom = _get(series, "momentum_norm", "momentum", "p")
    if mom is not None and mom.ndim == 2:
        mom = np.linalg.norm(mom, axis=1)
    n = max((len(s) for s in (ke, mass, mom, pe) if s is not None), default=0)
    if t is None:
        t = np.arange(n, dtype=np.float64)

    fig = Figure(figsize=(8, 6), dpi=100)
    ax1, ax2 = fig.subplots(2, 1, sharex=True)
    if ke is not None:
        ax1.plot(t[: len(ke)], ke, color="tab:red", lw=1.5, label="kinetic")
    if pe is not None:
        ax1.plot(t[: len(pe)], pe, color="tab:blue", lw=1.0, label="potential")
        if ke is not None and len(ke) == len(pe):
            ax1.plot(t[: len(ke)], ke + pe, color="k", lw=1.0, ls="--", label="total")
    ax1.set_ylabel("energy [J]")
    ax1.grid(True, alpha=0.3)
    if ax1.lines:
        ax1.legend(loc="best", fontsize=8)
    ax1.set_title(title or "Energy and conservation")

    if mass is not None:
        ax2.plot(t[: len(mass)], _relative_change(mass), color="tab:green", lw=1.5,
                 label=r"$\Delta m / m_0$")
    if mom is not None:
        ax2.plot(t[: len(mom)], _relative_change(mom), color="tab:purple", lw=1.2,
                 label=r"$\Delta |p| / |p_0|$")
    ax2.set_xlabel("time [s]")
    ax2.set_ylabel("relative change")
    ax2.grid(True, alpha=0.3)
    ax2.ticklabel_format(axis="y", style="sci", scilimits=(-3, 3), useOffset=False)
    if ax2.lines:
        ax2.legend(loc="best", fontsize=8)
    fig.tight_layout()
    with atomic_write(Path(path)) as tmp:
        fig.savefig(tmp, format="png")
