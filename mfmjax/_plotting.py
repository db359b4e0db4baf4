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


# -- analysis figures (compare, residuals, step, Bode; see mfmjax._analysis) --------------------


def plot_compare(cmp, path) -> None:
    """Measured vs simulated output on the window, the fit % in the legend (MATLAB compare)."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(9, 3.5), dpi=100)
    ax.plot(cmp.t, cmp.y, lw=1.0, color="#1f3b73", label=f"measured {cmp.output_name}")
    fit = "fit undefined" if not np.isfinite(cmp.fit) else f"fit {cmp.fit:.1f} %"
    ax.plot(cmp.t, cmp.y_sim, lw=1.0, color="#d2501e", label=f"simulated ({fit})")
    ax.set_xlabel("time")
    ax.set_ylabel(cmp.output_name)
    ax.legend(loc="best", fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def plot_residuals(res, path) -> None:
    """Auto-correlation of the residuals and cross-correlation with each input, 99 % bounds."""
    plt = _pyplot()
    K = len(res.input_names)
    fig, axes = plt.subplots(1 + K, 1, figsize=(8, 2.4 * (1 + K) + 0.4), dpi=100)
    axes = np.atleast_1d(axes)
    ax = axes[0]
    ax.stem(res.lags, res.auto, basefmt=" ")
    ax.axhspan(-res.auto_bound, res.auto_bound, color="#d6e4f5", lw=0, zorder=0)
    ax.set_title(f"auto-correlation of the residuals of {res.output_name}: "
                 f"{'white' if res.white else 'NOT white'} (99 %)", fontsize=9)
    ax.set_xlabel("lag")
    for k, name in enumerate(res.input_names):
        ax = axes[1 + k]
        ok = res.independent[k]
        ax.stem(res.cross_lags, res.cross[k], basefmt=" ")
        if np.isfinite(res.cross_bound[k]):
            ax.axhspan(-res.cross_bound[k], res.cross_bound[k], color="#d6e4f5", lw=0, zorder=0)
        verdict = "undefined" if ok is None else ("independent" if ok else "NOT independent")
        ax.set_title(f"cross-correlation with {name}: {verdict} (99 %)", fontsize=9)
        ax.set_xlabel("lag (positive: input leads)")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def plot_step(step, path) -> None:
    """Step response of each input, with its 99 % band when the response carries one."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(8, 3.5), dpi=100)
    for k, name in enumerate(step.input_names):
        (line,) = ax.plot(step.t, step.y[k], lw=1.2, label=f"step of {name}")
        if step.std is not None:
            ax.fill_between(step.t, step.lower[k], step.upper[k], color=line.get_color(),
                            alpha=0.25, lw=0, label="99 % band" if k == 0 else None)
    ax.set_xlabel("time")
    ax.set_ylabel(step.output_name)
    ax.set_title("step response" + ("" if step.std is not None else " (no covariance: no band)"),
                 fontsize=9)
    ax.legend(loc="best", fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def plot_bode(fr, path) -> None:
    """Bode magnitude (dB) and phase (deg) per input, with 99 % bands when available."""
    plt = _pyplot()
    fig, (am, ap) = plt.subplots(2, 1, figsize=(8, 5.5), dpi=100, sharex=True)
    for k, name in enumerate(fr.input_names):
        (line,) = am.semilogx(fr.w, fr.mag_db[k], lw=1.2, label=name)
        ap.semilogx(fr.w, fr.phase_deg[k], lw=1.2, color=line.get_color())
        if fr.mag_db_std is not None:
            z = 2.5758293035489004
            am.fill_between(fr.w, fr.mag_db[k] - z * fr.mag_db_std[k],
                            fr.mag_db[k] + z * fr.mag_db_std[k], color=line.get_color(),
                            alpha=0.25, lw=0, label="99 % band" if k == 0 else None)
            ap.fill_between(fr.w, fr.phase_deg[k] - z * fr.phase_deg_std[k],
                            fr.phase_deg[k] + z * fr.phase_deg_std[k], color=line.get_color(),
                            alpha=0.25, lw=0)
    am.set_ylabel("magnitude [dB]")
    ap.set_ylabel("phase [deg]")
    ap.set_xlabel("frequency [rad per time unit]")
    am.set_title("Bode diagram" + ("" if fr.mag_db_std is not None else
                                   " (no covariance: no band)"), fontsize=9)
    am.legend(loc="best", fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
