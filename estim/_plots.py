"""Plots of a fit: measured versus fitted tracks, residuals, loss history (matplotlib)."""

from __future__ import annotations

import os

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from ._fit import FitResult  # noqa: E402

COLOURS = {"bocce": "#8c5a1f", "golf": "#555555", "pingpong": "#f08c1a"}


def _colour(ball: str, i: int) -> str:
    return COLOURS.get(ball, f"C{i}")


def plot_fit(data: dict, result: FitResult, path) -> None:
    """Measured positions (markers; outliers crossed) and the fitted model (lines), x and z."""
    fig, axes = plt.subplots(2, 1, figsize=(8, 6.4), sharex=True)
    for i, (ball, bf) in enumerate(result.balls.items()):
        t, pos = data[ball]
        c = _colour(ball, i)
        n = len(t)
        out = np.abs(bf.residuals[:n]) > 5 * bf.noise_m
        for ax, k, name in ((axes[0], 2, "z"), (axes[1], 0, "x")):
            ok = np.isfinite(pos[:, k])
            ax.plot(t[ok & ~out[:, k]], pos[ok & ~out[:, k], k], "o", ms=2.5, color=c, alpha=0.55,
                    label=f"{ball} measured" if k == 2 else None)
            if np.any(ok & out[:, k]):
                ax.plot(t[ok & out[:, k]], pos[ok & out[:, k], k], "x", ms=6, color="red",
                        label="outliers (robust loss)" if (k == 2 and i == 0) else None)
            ax.plot(bf.model_t[:n], bf.model_position[:n, k], "-", lw=1.3, color=c,
                    label=f"{ball} fit e={bf.values['e']:.3f}" if k == 2 else None)
            ax.set_ylabel(f"{name} [m]")
            ax.grid(alpha=0.25)
    axes[0].set_title("Tracked positions and the fitted hybrid model")
    axes[0].legend(fontsize=7, ncol=2)
    axes[1].set_xlabel("t [s]")
    fig.tight_layout()
    fig.savefig(os.fspath(path), dpi=110)
    plt.close(fig)


def plot_residuals(data: dict, result: FitResult, path) -> None:
    """Residuals (model - measured) in x and z over time, per ball, in millimetres."""
    fig, axes = plt.subplots(len(result.balls), 1, figsize=(8, 2.2 * len(result.balls) + 0.6),
                             sharex=True, squeeze=False)
    for i, (ball, bf) in enumerate(result.balls.items()):
        ax = axes[i, 0]
        t, _ = data[ball]
        n = len(t)
        r = bf.residuals[:n] * 1e3
        for k, name, m in ((0, "x", "."), (2, "z", "+")):
            ok = np.isfinite(data[ball][1][:, k])
            ax.plot(t[ok], r[ok, k], m, ms=3, label=f"{name}")
        band = bf.noise_m * 1e3
        ax.axhspan(-band, band, color="0.85", zorder=0, label="noise level")
        ax.set_ylim(-6 * band, 6 * band)
        ax.set_ylabel(f"{ball}\nresidual [mm]")
        ax.grid(alpha=0.25)
        ax.legend(fontsize=7, loc="upper right", ncol=3)
    axes[0, 0].set_title("Fit residuals, model minus measurement (outliers off scale)")
    axes[-1, 0].set_xlabel("t [s]")
    fig.tight_layout()
    fig.savefig(os.fspath(path), dpi=110)
    plt.close(fig)


def plot_loss_history(result: FitResult, path) -> None:
    """Robust loss per Levenberg-Marquardt iteration, per ball (log scale)."""
    fig, ax = plt.subplots(figsize=(6.4, 3.6))
    for i, (ball, bf) in enumerate(result.balls.items()):
        h = np.asarray(bf.loss_history, dtype=float)
        h = np.where(np.isfinite(h), h, np.nan)
        ax.semilogy(np.arange(1, len(h) + 1), h, "-o", ms=3, color=_colour(ball, i), label=ball)
    ax.set_xlabel("iteration")
    ax.set_ylabel("robust loss (sum of rho(r/s))")
    ax.set_title("Loss history of the fit (full data window)")
    ax.grid(alpha=0.25, which="both")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(os.fspath(path), dpi=110)
    plt.close(fig)
