"""The forest plot of a fit of several clips: each clip's own estimate of a shared
parameter with its 95% interval, the shared value and its band, and the clips' one-by-one
fits for comparison (``estim.fitting._pooled``)."""

from __future__ import annotations

import math

import numpy as np
from matplotlib.figure import Figure

from ..fitting._pooled import PooledResult
from ._plots import _save

__all__ = ["plot_forest"]

Z95 = 1.959963984540054  # two-sided 95% quantile of the normal distribution


def plot_forest(result: PooledResult, path=None) -> Figure:
    """One panel per shared parameter and group, one row per clip.

    Each row shows the clip's own estimate (the other shared values held at theirs; filled,
    red where it disagrees) with its 95% interval, and its one-by-one fit (open grey circle,
    every parameter its own; its interval where the data fixed it). The vertical line and
    band are the shared value and its 95% interval (``SharedFit.stderr``).
    """
    panels = [(sf, n) for sf in result.shared.values() for n in sf.names]
    rows = max(len(sf.clips) for sf, _ in panels)
    fig = Figure(figsize=(4.2 * len(panels), 0.32 * rows + 1.6), layout="tight")
    axes = np.atleast_1d(fig.subplots(1, len(panels), squeeze=False)[0])
    for ax, (sf, name) in zip(axes, panels, strict=True):
        value, se = sf.values[name], sf.stderr[name]
        ax.axvspan(value - Z95 * se, value + Z95 * se, color="C0", alpha=0.18, lw=0,
                   label=f"shared {value:.4f} +- {Z95 * se:.4f} (95%)")
        ax.axvline(value, color="C0", lw=1.2)
        odd = {c for c, n, _, _ in sf.disagree if n == name}
        for k, label in enumerate(sf.clips):
            y = len(sf.clips) - 1 - k
            own, own_se, _ = sf.per_clip[name][label]
            colour = "C3" if label in odd else "k"
            if math.isfinite(own):
                ax.errorbar(own, y, xerr=Z95 * own_se if math.isfinite(own_se) else None, fmt="o", ms=4,
                            color=colour, capsize=2, lw=1, label="own estimate (others shared)" if k == 0 else None)
            alone = result.individual.balls[label]
            a, a_se = alone.values[name], alone.stderr.get(name, math.nan)
            ax.errorbar(a, y + 0.25, xerr=Z95 * a_se if math.isfinite(a_se) else None, fmt="o", ms=4, mfc="none",
                        color="0.55", capsize=2, lw=0.8, label="one-by-one fit" if k == 0 else None)
        ax.set_yticks(range(len(sf.clips)), list(reversed(sf.clips)), fontsize=7)
        ax.set_xlabel(name)
        ax.set_title(f"{sf.group}: {name} over {len(sf.clips)} clips", fontsize=9)
        ax.grid(axis="x", alpha=0.25)
        ax.legend(fontsize=6, loc="upper center", bbox_to_anchor=(0.5, -0.16), ncol=2, frameon=False)
    return _save(fig, path)
