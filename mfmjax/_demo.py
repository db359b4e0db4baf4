"""`mfmjax demo`: the paper's case study on the simulated glass forehearth (section 5-6).

Runs the on-line identifier (Table 1's settings; improved mode by default, `mode="paper"` for
Algorithm 1 as stated) on both experiments, prints tables like the paper's Tables 2-5, the
input-1 delays against the simulator's and the prediction MSE, writes Fig. 2-5-style PNGs and
a JSON of all results.
"""

from __future__ import annotations

import json
import math
import os
import sys
import time

import numpy as np

PAPER_MSE = {1: 0.2841, 2: 0.2028}


def _say(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def run_experiment(experiment: int, horizon: float | None = None, seed: int = 0,
                   mode: str = "paper", **settings) -> dict:
    """Simulate one experiment (disturbances from `seed`) and run the on-line identifier on it
    in `mode` ("paper": Algorithm 1 as stated; "improved"), `settings` passed to OnlineConfig:
    (data, identifier, timings, per-interval update times in s)."""
    from . import datasets
    from ._online import OnlineConfig, OnlineIdentifier

    t0 = time.perf_counter()
    data = datasets.forehearth(experiment, seed=seed)
    if horizon is not None:
        keep = data["t"] <= horizon
        data = {**data, **{k: data[k][keep] for k in ("t", "y", "u", "pull", "delay")}}
    t_sim = time.perf_counter() - t0
    # the transport delay of input 1 is known at the start of the experiment (from the pull
    # rate of the operating point); it is kept for the whole run, as the pull is not measured
    delay = float(np.round(data["delay"][0]))
    config = OnlineConfig(
        dt=1.0, n_inputs=2, intersample=data["intersample"], delays=(delay, 0.0),
        output_name=data["names"][0], input_names=data["names"][1:], mode=mode, **settings,
    )
    ident = OnlineIdentifier(config)
    t1 = time.perf_counter()
    S = config.samples
    times = []
    for c0 in range(0, data["t"].size, S):
        t2 = time.perf_counter()
        ident.update(data["t"][c0 : c0 + S], data["y"][c0 : c0 + S], data["u"][c0 : c0 + S])
        times.append(time.perf_counter() - t2)
    return {"data": data, "ident": ident, "delay": delay, "simulate_s": t_sim,
            "online_s": time.perf_counter() - t1, "update_s": times}


def paper_tables(models: list[dict], end: float | None) -> str:
    """The paper's Tables 2-3 (model properties, then parameters) for one experiment."""
    lines = [f"{'Model nr':>8} {'Op. point':>9} {'Ident. time [s]':>16} {'Sim. time [s]':>14} "
             f"{'N':>3} {'M':>3} {'h [s]':>6}"]
    for r in models:
        stop = r["sim_end"] if r["sim_end"] is not None else end
        # a model accepted in the last closed interval has predicted nothing yet: "(next)"
        # (it read 3000-3000, a span of zero shown as a real one)
        shown = "(next)" if stop is None or stop <= r["sim_start"] else f"{stop:.0f}"
        lines.append(f"{r['model']:>8} {r['operating_point']:>9} "
                     f"{r['ident_window'][0]:>7.0f}-{r['ident_window'][1]:<8.0f} "
                     f"{r['sim_start']:>6.0f}-{shown:<7} {r['N']:>3} {r['M']:>3} {r['h']:>6.0f}")
    n_max = max((r["n"] for r in models), default=2)
    m_max = [max((r["m"][k] for r in models), default=0) for k in range(2)]
    head = [f"a_{i}" for i in range(n_max + 1)]
    head += [f"b_{k + 1}{j}" for k in range(2) for j in range(m_max[k] + 1)]
    lines += ["", f"{'Model nr':>8} " + " ".join(f"{h:>10}" for h in head) + f" {'offset':>10}"]
    for r in models:
        vals = [r["a"][i] if i <= r["n"] else None for i in range(n_max + 1)]
        for k in range(2):
            vals += [r["b"][k][j] if j <= r["m"][k] else None for j in range(m_max[k] + 1)]
        cells = ["—" if v is None else f"{v:.4g}" for v in vals]
        lines.append(f"{r['model']:>8} " + " ".join(f"{c:>10}" for c in cells)
                     + f" {r['offset']:>10.4g}")
    return "\n".join(lines)


def residence_time(record: dict, k: int = 0) -> float:
    r"""Mean residence time of input k's path in an on-line model record: the first moment of
    its impulse response, $d_k + a_1/a_0 - b_{k1}/b_{k0}$ ($-G'(0)/G(0)$ of
    $G(s) = B_k(s) e^{-s d_k} / A(s)$); NaN where the static gain is 0 or undefined. For the
    forehearth it is comparable with the transport delay x/v (the mean time a tracer takes),
    plus the thermocouple's 20 s lag, while the dead time d_k alone absorbs the dispersion."""
    a, b = record["a"], record["b"][k]
    if len(a) < 2 or a[0] == 0 or b[0] == 0:
        return math.nan
    return record["delays"][k] + a[1] / a[0] - (b[1] / b[0] if len(b) > 1 else 0.0)


SENSOR_LAG = 20.0  # s, the zone thermocouple's lag (a sensor datasheet value, taken as known)
TRANSIT_PECLET = (25.0, 40.0, 60.0, 100.0, 160.0)  # grid of the transit kernel's Peclet number
TRANSIT_CROWN = (150.0, 250.0, 400.0, 600.0, 900.0)  # s, grid of the crown lag (input 2 path)
TRANSIT_WINDOW = 2500.0  # s of output fitted (the newest), at least TRANSIT_MIN_WINDOW
TRANSIT_MIN_WINDOW = 1500.0
TRANSIT_TREND = 4  # Legendre polynomials over the window: the unmeasured pull rate's effect


def transit_kernel(theta: float, peclet: float, n: int, dt: float = 1.0) -> np.ndarray:
    r"""Advection-dispersion transit-time density (inverse Gaussian: mean `theta` s, variance
    $2\theta^2/Pe$), sampled at the centres of `n` intervals of `dt` and normalised to sum 1."""
    tau = (np.arange(n) + 0.5) * dt
    lam = theta * peclet / 2.0
    k = np.sqrt(lam / (2 * np.pi * tau**3)) * np.exp(-lam * (tau - theta) ** 2
                                                     / (2 * theta**2 * tau))
    return k / k.sum()


def _lag(x: np.ndarray, T: float, dt: float) -> np.ndarray:
    from scipy.signal import lfilter

    a = math.exp(-dt / T)
    return lfilter([1 - a], [1, -a], x - x[0]) + x[0]


def transport_delay_estimate(y, u, end: int, guess: float, dt: float = 1.0) -> dict:
    r"""Grey-box estimate of input 1's transport delay (the glass's mean transit time, s) from
    the samples before index `end` only (causal), searched within `guess` +-50 %.

    Model of the zone (the forehearth's physics, its constants unknown): the output is
    $c + \text{trend} + g_1\,S\,K_{\theta,Pe}\,u_1 + g_2\,S\,C_{T_c}\,R_{\theta,Pe}\,u_2$, where
    $K$ is the advection-dispersion transit-time density (inverse Gaussian, mean $\theta$),
    $R = 1 - \int K$ its survival function (the burners heat the glass all along the zone, so the
    glass at the thermocouple has been heated for its whole transit), $C$ the crown's
    first-order lag $T_c$, $S$ the thermocouple's known 20 s lag, and the trend Legendre
    polynomials of degree < 4 over the window (the unmeasured pull rate). $\theta$ (5 s grid,
    then 1 s), $Pe$ and $T_c$ on grids; $c$, trend, $g_1$, $g_2$ by least squares on the newest
    2500 s (1500 s at least). $\theta$ is the first moment of the transport part of the input-1
    path, the sensor lag excluded: the quantity the simulator calls its delay (x/v).
    **Returns:** {"delay", "peclet", "crown", "gain1", "window"}; delay NaN with too little
    history or when the best delay of the 5 s grid is one of its ends (no interior minimum)."""
    from scipy import fft as sfft

    fn = "transport_delay_estimate()"
    if not (isinstance(guess, (int, float)) and math.isfinite(guess) and guess > 0):
        raise ValueError(f"{fn}: guess must be a finite delay > 0 s (got {guess!r})")
    if not 0 < end <= len(y):
        raise ValueError(f"{fn}: end must be in 1..len(y)={len(y)} (got {end}); it is the "
                         "index after the newest sample used")
    lo, hi = 0.5 * guess, 1.5 * guess
    hist = math.ceil(2.5 * hi / dt)  # the kernel's reach (its tail beyond is < 1e-3 at Pe >= 25)
    w = min(round(TRANSIT_WINDOW / dt), end - hist)
    if w < round(TRANSIT_MIN_WINDOW / dt):
        return {"delay": math.nan, "peclet": math.nan, "crown": math.nan, "gain1": math.nan,
                "window": None}
    seg = slice(end - w - hist, end)
    u = np.asarray(u, dtype=np.float64)
    u1 = _lag(u[seg, 0], SENSOR_LAG, dt)
    u2 = _lag(u[seg, 1], SENSOR_LAG, dt)
    yw = np.asarray(y, dtype=np.float64)[end - w : end]
    tt = np.linspace(-1.0, 1.0, w)
    Q, _ = np.linalg.qr(np.polynomial.legendre.legvander(tt, TRANSIT_TREND - 1))

    def proj(x):
        return x - Q @ (Q.T @ x)

    yr = proj(yw)
    nf = sfft.next_fast_len(w + 2 * hist, real=True)  # linear convolutions: no wrap-around
    F1 = sfft.rfft(u1, nf)
    F2 = [sfft.rfft(_lag(u2, T, dt), nf) for T in TRANSIT_CROWN]
    eps2 = 2 * np.finfo(np.float64).eps  # lstsq's default cut-off for a 2 x 2 system

    def fits(pairs):  # (sse, crown, g1) of the best crown lag of each (theta, Pe), batched
        k = np.stack([transit_kernel(th, pe, hist, dt) for th, pe in pairs])
        x1 = proj(sfft.irfft(F1 * sfft.rfft(k, nf), nf)[:, hist : hist + w].T).T
        S = sfft.rfft(1.0 - np.cumsum(k, axis=1), nf) * dt
        best = np.full((len(pairs), 3), [math.inf, math.nan, math.nan])
        for Tc, F in zip(TRANSIT_CROWN, F2):
            x2 = proj(sfft.irfft(F * S, nf)[:, hist : hist + w].T).T
            g12 = np.einsum("bt,bt->b", x1, x2)
            G = np.stack([np.stack([np.einsum("bt,bt->b", x1, x1), g12], -1),
                          np.stack([g12, np.einsum("bt,bt->b", x2, x2)], -1)], -2)
            r = np.stack([x1 @ yr, x2 @ yr], -1)
            c = np.einsum("bij,bj->bi", np.linalg.pinv(G, rcond=eps2), r)
            sse = yr @ yr - np.einsum("bi,bi->b", c, r)
            better = sse < best[:, 0]  # strictly: the first crown lag wins a tie, as min() does
            best[better] = np.stack([sse, np.full_like(sse, Tc), c[:, 0]], -1)[better]
        return best

    def search(thetas, pes):  # the first (theta-major) least sse, as min() over the grid
        pairs = [(th, pe) for th in thetas for pe in pes]
        best = np.concatenate([fits(pairs[i : i + 64]) for i in range(0, len(pairs), 64)])
        i = int(np.argmin(best[:, 0]))
        return (float(best[i, 0]), float(best[i, 1]), float(best[i, 2])), *pairs[i]

    grid = np.arange(lo, hi + 1e-9, 5.0)
    _, th, pe = search(grid, TRANSIT_PECLET)
    if th in (grid[0], grid[-1]):  # no interior minimum: the data do not determine the delay
        return {"delay": math.nan, "peclet": pe, "crown": math.nan, "gain1": math.nan,
                "window": [float((end - w) * dt), float(end * dt)]}
    (_, Tc, g1), th, pe = search(np.arange(max(lo, th - 4), min(hi, th + 4) + 1e-9, 1.0), (pe,))
    return {"delay": float(th), "peclet": pe, "crown": Tc, "gain1": g1,
            "window": [float((end - w) * dt), float(end * dt)]}


def delay_table(models: list[dict], data: dict, guess: float | None = None) -> list[dict]:
    """Per accepted model: the operating point, when it starts predicting, the input-1 dead time
    in use, its residence time, the grey-box transport delay estimated from the data before
    that time (`transport_delay_estimate` around `guess`; NaN without `guess` or `y`, `u`) and
    the simulator's true transport delay then (s)."""
    rows = []
    for r in models:
        true = float(np.interp(r["sim_start"], data["t"], data["delay"]))
        transport = math.nan
        if guess is not None and "y" in data:
            end = int(np.searchsorted(data["t"], r["sim_start"], side="right"))
            dt = float(data["t"][1] - data["t"][0])
            transport = transport_delay_estimate(data["y"], data["u"], end, guess, dt)["delay"]
        rows.append({"model": r["model"], "operating_point": r["operating_point"],
                     "sim_start": r["sim_start"], "delay": r["delays"][0],
                     "residence": residence_time(r, 0), "transport": transport,
                     "true_delay": true})
    return rows


def format_delay_table(rows: list[dict]) -> str:
    lines = [f"{'Model':>8} {'Op. point':>9} {'from [s]':>9} {'dead time [s]':>14} "
             f"{'residence [s]':>14} {'transport [s]':>14} {'true delay [s]':>15}"]
    for r in rows:
        res = "-" if not math.isfinite(r["residence"]) else f"{r['residence']:.0f}"
        tr = "-" if not math.isfinite(r.get("transport", math.nan)) else f"{r['transport']:.0f}"
        lines.append(f"{r['model']:>8} {r['operating_point']:>9} {r['sim_start']:>9.0f} "
                     f"{r['delay']:>14.0f} {res:>14} {tr:>14} {r['true_delay']:>15.0f}")
    return "\n".join(lines)


def demo(out: str = "mfmjax-demo", horizon: float | None = None, mode: str = "improved") -> dict:
    """Run both experiments in `mode` ("improved", default, or "paper"), print the tables and
    MSE, write the figures and results.json to `out`."""
    from ._plotting import plot_inputs, plot_online

    if mode not in ("paper", "improved"):
        raise ValueError(f"demo(): unknown mode {mode!r}; use 'paper' or 'improved'")
    os.makedirs(out, exist_ok=True)
    results = {"paper_mse": PAPER_MSE, "mode": mode, "experiments": []}
    print("mfmjax demo: on-line identification and prediction of a glass forehearth zone")
    if mode == "paper":
        print("(the paper's Algorithm 1 with Table 1's settings; simulated plant, see "
              "mfmjax.datasets.forehearth)\n")
    else:
        print("(improved mode: Algorithm 1 with delay tracking, forecast-ranked models and a "
              "noise-tied operating-point test; --mode paper for the paper's; simulated plant, "
              "see mfmjax.datasets.forehearth)\n")
    for ex in (1, 2):
        _say(f"[{ex}/2] experiment {ex}: simulating the forehearth and running Algorithm 1 "
             f"({mode} mode) ...")
        r = run_experiment(ex, horizon, mode=mode)
        ident, data = r["ident"], r["data"]
        mse = ident.mse()
        end = ident._end()
        pull = data["pull"]
        tracked = mode == "improved" and "delay" in ident.state.config.improvements
        print(f"Experiment {ex}: pull rate {pull[0]:.0f} -> {pull[-1]:.0f} t/24h over "
              f"{data['t'][-1]:.0f} s; input-1 delay {data['delay'].min():.0f}-"
              f"{data['delay'].max():.0f} s (identifier starts from {r['delay']:.0f} s"
              f"{', tracked' if tracked else ', kept'})")
        print(paper_tables(ident.models, end))
        delays = delay_table(ident.models, data, guess=r["delay"])
        print("\n" + format_delay_table(delays))
        why = None if math.isfinite(mse) else (  # say why (it did not), and what helps:
            f"{ident.why_no_prediction()}; a longer --horizon lets "  # (a model accepted in
            + ("its first model predict" if ident.models else  # the last interval was told
               "the plant reach an operating point"))  # to wait for an operating point)
        shown = f"{mse:.4f} degC^2" if why is None else f"undefined ({why})"
        print(f"mean square prediction error: {shown} (paper: {PAPER_MSE[ex]})\n")
        fig_in = os.path.join(out, f"experiment{ex}_inputs.png")
        fig_pred = os.path.join(out, f"experiment{ex}_prediction.png")
        span = (float(data["t"][0]), float(end if end is not None else data["t"][-1]))
        plot_inputs(data["t"], data["u"], ["prev. zone [degC]", "pressure [mbar]"], fig_in,
                    extra=pull, extra_name="pull [t/24h]", xlim=span, xlabel="time [s]",
                    title=f"Experiment {ex}: system inputs and glass pull rate (not measured) "
                          f"(cf. Fig. {2 * ex})")
        mse_txt = f"MSE {mse:.3f} degC$^2$" if math.isfinite(mse) else "no prediction yet"
        plot_online(ident.series(), ident.models, fig_pred, ylabel="zone temperature [degC]",
                    title=f"Experiment {ex}, {mode} mode: on-line prediction, {mse_txt} "
                          f"(paper {PAPER_MSE[ex]}; cf. Fig. {2 * ex + 1})",
                    start=span[0], end=span[1], xlabel="time [s]")
        upd = np.asarray(r["update_s"]) * 1e3
        results["experiments"].append({
            "experiment": ex, "mse": mse if math.isfinite(mse) else None, "models": ident.models,
            "intervals": ident.events, "delay_used": r["delay"], "delays": delays,
            "delay_range": [float(data["delay"].min()), float(data["delay"].max())],
            "figures": [fig_in, fig_pred], "simulate_s": r["simulate_s"],
            "online_s": r["online_s"], "update_ms_median": float(np.median(upd)),
        })
        if why is not None:  # strict JSON has no NaN: say why the value is missing, as
            # printed (it blamed n_start where no operating point had been detected)
            results["experiments"][-1]["mse_note"] = f"null: {why}"
    path = os.path.join(out, "results.json")
    from ._persist import atomic_write, json_safe

    text = json.dumps(json_safe(results), indent=1, allow_nan=False) + "\n"
    atomic_write(path, text.encode())
    print(f"wrote {out}/experiment{{1,2}}_inputs.png, experiment{{1,2}}_prediction.png, "
          "results.json")
    return results
