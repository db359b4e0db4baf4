"""`mfmjax demo`: the paper's case study on the simulated glass forehearth (section 5-6).

Runs the on-line identifier with Table 1's settings on both experiments, prints tables like the
paper's Tables 2-5 and the prediction MSE, writes Fig. 2-5-style PNGs and a JSON of all results.
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


def run_experiment(experiment: int, horizon: float | None = None, seed: int = 0) -> dict:
    """Simulate one experiment and run Algorithm 1 on it: (data, identifier, timings)."""
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
        output_name=data["names"][0], input_names=data["names"][1:],
    )
    ident = OnlineIdentifier(config)
    t1 = time.perf_counter()
    S = config.samples
    for c0 in range(0, data["t"].size, S):
        ident.update(data["t"][c0 : c0 + S], data["y"][c0 : c0 + S], data["u"][c0 : c0 + S])
    return {"data": data, "ident": ident, "delay": delay, "simulate_s": t_sim,
            "online_s": time.perf_counter() - t1}


def paper_tables(models: list[dict], end: float | None) -> str:
    """The paper's Tables 2-3 (model properties, then parameters) for one experiment."""
    lines = [f"{'Model nr':>8} {'Op. point':>9} {'Ident. time [s]':>16} {'Sim. time [s]':>14} "
             f"{'N':>3} {'M':>3} {'h [s]':>6}"]
    for r in models:
        stop = r["sim_end"] if r["sim_end"] is not None else end
        lines.append(f"{r['model']:>8} {r['operating_point']:>9} "
                     f"{r['ident_window'][0]:>7.0f}-{r['ident_window'][1]:<8.0f} "
                     f"{r['sim_start']:>6.0f}-{stop:<7.0f} {r['N']:>3} {r['M']:>3} {r['h']:>6.0f}")
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


def demo(out: str = "mfmjax-demo", horizon: float | None = None) -> dict:
    from ._plotting import plot_inputs, plot_online

    os.makedirs(out, exist_ok=True)
    results = {"paper_mse": PAPER_MSE, "experiments": []}
    print("mfmjax demo: on-line identification and prediction of a glass forehearth zone")
    print("(the paper's Algorithm 1 with Table 1's settings; simulated plant, see "
          "mfmjax.datasets.forehearth)\n")
    for ex in (1, 2):
        _say(f"[{ex}/2] experiment {ex}: simulating the forehearth and running Algorithm 1 ...")
        r = run_experiment(ex, horizon)
        ident, data = r["ident"], r["data"]
        mse = ident.mse()
        end = ident._end()
        pull = data["pull"]
        print(f"Experiment {ex}: pull rate {pull[0]:.0f} -> {pull[-1]:.0f} t/24h over "
              f"{data['t'][-1]:.0f} s; input-1 delay {data['delay'].min():.0f}-"
              f"{data['delay'].max():.0f} s (identifier uses {r['delay']:.0f} s)")
        print(paper_tables(ident.models, end))
        shown = f"{mse:.4f} degC^2" if math.isfinite(mse) else "undefined (no prediction yet)"
        print(f"mean square prediction error: {shown} (paper: {PAPER_MSE[ex]})\n")
        fig_in = os.path.join(out, f"experiment{ex}_inputs.png")
        fig_pred = os.path.join(out, f"experiment{ex}_prediction.png")
        plot_inputs(data["t"], data["u"], ["prev. zone [degC]", "pressure [mbar]"], fig_in,
                    extra=pull, extra_name="pull [t/24h]",
                    title=f"Experiment {ex}: system inputs and glass pull rate (cf. Fig. {2 * ex})")
        plot_online(ident.series(), ident.models, fig_pred, ylabel="zone temperature [degC]",
                    title=f"Experiment {ex}: on-line prediction, MSE {mse:.3f} (cf. Fig. {2 * ex + 1})",
                    end=end)
        results["experiments"].append({
            "experiment": ex, "mse": mse if math.isfinite(mse) else None, "models": ident.models,
            "intervals": ident.events, "delay_used": r["delay"],
            "delay_range": [float(data["delay"].min()), float(data["delay"].max())],
            "figures": [fig_in, fig_pred], "simulate_s": r["simulate_s"],
            "online_s": r["online_s"],
        })
        if not math.isfinite(mse):  # strict JSON has no NaN: say why the value is missing
            results["experiments"][-1]["mse_note"] = (
                "null: no prediction yet (the first model is identified after n_start "
                "intervals and predicts from the interval after it); use a longer horizon")
    path = os.path.join(out, "results.json")
    from ._persist import atomic_write, json_safe

    text = json.dumps(json_safe(results), indent=1, allow_nan=False) + "\n"
    atomic_write(path, text.encode())
    print(f"wrote {out}/experiment{{1,2}}_inputs.png, experiment{{1,2}}_prediction.png, "
          "results.json")
    return results
