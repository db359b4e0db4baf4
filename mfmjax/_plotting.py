"""Figures (matplotlib, optional): the on-line prediction plot of the paper's Fig. 3 and 5."""

from __future__ import annotations

import numpy as np


def _pyplot():
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        raise ValueError("plotting needs matplotlib: pip install 'mfmjax[plot]'") from None
    return plt


def plot_online(series: dict, models: list[dict], path, *, title: str = "", ylabel: str = "y",
                end: float | None = None) -> None:
    """Measured and predicted output; the intervals in which each model predicted on
    alternating blue/yellow backgrounds (green: before the first model); operating points as
    dotted lines (the paper's Fig. 3 and 5). Written as a PNG to `path`."""
    plt = _pyplot()
    t, y, y_pred = series["t"], series["y"], series["y_pred"]
    fig, ax = plt.subplots(figsize=(10, 4), dpi=100)
    t_end = float(t[-1]) if end is None and t.size else end
    if models:
        ax.axvspan(float(t[0]) if t.size else 0.0, models[0]["sim_start"], color="#cfe8cf",
                   lw=0, label="identifying model 1")
    for i, rec in enumerate(models):
        stop = rec["sim_end"] if rec["sim_end"] is not None else t_end
        ax.axvspan(rec["sim_start"], stop, color=("#d6e4f5", "#f7efc6")[i % 2], lw=0)
    for time in sorted({rec["operating_point_time"] for rec in models}):
        ax.axvline(time, color="k", ls=":", lw=1.0)
    ax.plot(t, y, lw=1.1, color="#1f3b73", label="measured")
    ax.plot(t, y_pred, lw=1.1, color="#d2501e", label="predicted")
    ax.set_xlabel("time [s]")
    ax.set_ylabel(ylabel)
    if title:
        ax.set_title(title)
    ax.set_xlim(float(t[0]) if t.size else 0.0, t_end or 1.0)
    ax.legend(loc="best", fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def plot_inputs(t, u, names, path, *, extra=None, extra_name: str = "", title: str = "") -> None:
    """The inputs (and an unmeasured disturbance such as the pull rate) stacked (Fig. 2 and 4)."""
    plt = _pyplot()
    rows = u.shape[1] + (extra is not None)
    fig, axes = plt.subplots(rows, 1, figsize=(10, 1.8 * rows + 0.6), dpi=100, sharex=True)
    axes = np.atleast_1d(axes)
    for k in range(u.shape[1]):
        axes[k].plot(t, u[:, k], lw=1.0)
        axes[k].set_ylabel(names[k])
    if extra is not None:
        axes[-1].plot(t, extra, lw=1.0, color="#7a3b8f")
        axes[-1].set_ylabel(extra_name)
    axes[-1].set_xlabel("time [s]")
    if title:
        axes[0].set_title(title)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
