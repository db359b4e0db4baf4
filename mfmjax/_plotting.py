"""Figures (matplotlib, optional): the on-line prediction plot of the paper's Fig. 3 and 5."""

from __future__ import annotations

import numpy as np

# both figures share these horizontal margins (fractions of the width), so that their time axes
# line up when the inputs figure is shown above or below the prediction figure
LEFT, RIGHT = 0.08, 0.98


def _pyplot():
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        raise ValueError("plotting needs matplotlib: pip install 'mfmjax[plot]'") from None
    return plt


def broken_at_switches(y_pred, model_number):
    """`y_pred` with NaN inserted where the predicting model changes: (index map, values) such
    that a line plot shows a gap at each switch instead of a vertical jump."""
    y_pred = np.asarray(y_pred, dtype=np.float64)
    mn = np.asarray(model_number)
    cut = np.flatnonzero(mn[1:] != mn[:-1]) + 1  # first sample of each new model
    return np.insert(np.arange(y_pred.size, dtype=np.float64), cut, np.nan), np.insert(
        y_pred, cut, np.nan)


def plot_online(series: dict, models: list[dict], path, *, title: str = "", ylabel: str = "y",
                end: float | None = None, start: float | None = None,
                xlabel: str = "time") -> None:
    """Measured and predicted output; the intervals in which each model predicted on
    alternating blue/yellow bands labelled with the model number (green: before the first
    model); operating points as dotted lines labelled p1, p2, ... (the paper's Fig. 3 and 5).
    The predicted line is broken where the model changes. Written as a PNG to `path`."""
    plt = _pyplot()
    t, y, y_pred = series["t"], series["y"], series["y_pred"]
    fig, ax = plt.subplots(figsize=(10, 4), dpi=100)
    t0 = (float(t[0]) if t.size else 0.0) if start is None else start
    t_end = float(t[-1]) if end is None and t.size else end
    # only what falls on the time axis (a resumed run plots its own series with every model:
    # the earlier bands were out of view but in the legend)
    right = t_end if t_end is not None else np.inf
    if models and models[0]["sim_start"] > t0:  # ("identifying model 1" from the record's
        # start read as model 1's window, which the table gives, e.g. 100-500)
        w = models[0].get("ident_window")
        ax.axvspan(t0, models[0]["sim_start"], color="#cfe8cf", lw=0,
                   label="no model yet" + (f" (model 1 fitted on {w[0]:g} to {w[1]:g})"
                                           if w is not None else ""))
    shown = 0
    for i, rec in enumerate(models):
        stop = rec["sim_end"] if rec["sim_end"] is not None else t_end
        if (stop is not None and stop <= t0) or rec["sim_start"] >= right:
            continue
        ax.axvspan(rec["sim_start"], stop, color=("#d6e4f5", "#f7efc6")[i % 2], lw=0,
                   label="model k predicts (band k)" if shown == 0 else None)
        ax.text((max(rec["sim_start"], t0) + min(stop, right)) / 2, 0.97, str(rec["model"]),
                transform=ax.get_xaxis_transform(), ha="center", va="top", fontsize=8,
                color="#333333")
        shown += 1
    ops = {}
    for rec in models:
        if t0 <= rec["operating_point_time"] <= right:
            ops.setdefault(rec["operating_point_time"], rec["operating_point"])
    for k, (time, label) in enumerate(sorted(ops.items())):
        ax.axvline(time, color="k", ls=":", lw=1.0, label="operating point" if k == 0 else None)
        ax.text(time, 0.90, f" {label}", transform=ax.get_xaxis_transform(), fontsize=8,
                ha="left", va="top", fontweight="bold", zorder=5,  # above the data lines (p1
                bbox=dict(facecolor="white", alpha=0.8, lw=0, pad=1))  # was drawn under them)
    ax.plot(t, y, lw=1.1, color="#1f3b73", label="measured")
    if "model_number" in series and len(t):
        idx, yp = broken_at_switches(y_pred, series["model_number"])
        tp = np.interp(idx, np.arange(t.size), t)  # NaN indices stay NaN
        ax.plot(tp, yp, lw=1.1, color="#d2501e", label="predicted")
    else:
        ax.plot(t, y_pred, lw=1.1, color="#d2501e", label="predicted")
    ax.set_xlabel(xlabel)  # the data's time unit is the caller's to name
    ax.set_ylabel(ylabel)
    if title:
        ax.set_title(title, fontsize=10)
    ax.set_xlim(t0, t_end or 1.0)
    ax.legend(loc="lower left", fontsize=7, ncol=3, framealpha=0.9)
    fig.subplots_adjust(left=LEFT, right=RIGHT, bottom=0.13, top=0.91)
    fig.savefig(path)
    plt.close(fig)


def plot_inputs(t, u, names, path, *, extra=None, extra_name: str = "", title: str = "",
                xlim=None, xlabel: str = "time") -> None:
    """The inputs (and an unmeasured disturbance such as the pull rate) stacked (Fig. 2 and 4),
    on the time axis `xlim` (default: the data's) with the prediction figure's margins."""
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
    axes[-1].set_xlabel(xlabel)
    axes[-1].set_xlim(*(xlim if xlim is not None else (float(t[0]), float(t[-1]))))
    if title:
        axes[0].set_title(title, fontsize=10)
    fig.subplots_adjust(left=LEFT, right=RIGHT, bottom=0.09, top=0.94, hspace=0.12)
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
    verdict = "undefined" if res.white is None else "white" if res.white else "NOT white"
    ax.set_title(f"auto-correlation of the residuals of {res.output_name}: {verdict} (99 %)",
                 fontsize=9)
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


def plot_bode(fr, path, nyquist=None) -> None:
    """Bode magnitude (dB) and phase (deg) per input, with 99 % bands when available; the
    data's Nyquist frequency marked and the band above it shaded when given."""
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
    note = ""
    if nyquist is not None:
        for ax in (am, ap):
            if nyquist <= fr.w[-1]:  # beyond the grid its line and legend entry were
                # clipped out of view: the title says where it is instead
                ax.axvline(nyquist, color="0.3", ls="--", lw=0.9,
                           label="Nyquist of the data (pi/dt)" if ax is am else None)
                ax.axvspan(max(nyquist, fr.w[0]), fr.w[-1], color="0.85", alpha=0.5, lw=0,
                           label="above it: not in the data" if ax is am else None)
        am.set_xlim(fr.w[0], fr.w[-1])
        if nyquist > fr.w[-1]:
            note = f"; Nyquist of the data (pi/dt) at {nyquist:.3g}, above this grid"
    am.set_ylabel("magnitude [dB]")
    ap.set_ylabel("phase [deg]")
    ap.set_xlabel("frequency [rad per time unit]")
    am.set_title("Bode diagram" + ("" if fr.mag_db_std is not None else
                                   " (no covariance: no band)") + note, fontsize=9)
    am.legend(loc="best", fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
