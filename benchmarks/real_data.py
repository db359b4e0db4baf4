"""Real DaISy records: mfmjax's one-call path against the peers a practitioner would use.

    pip install sippy-unipi                 # the peers' benchmark-only dependency
    python benchmarks/real_data.py          # mfmjax and every peer, measured in this run
    python benchmarks/real_data.py --no-peers   # mfmjax only (peers from the saved JSON)

Protocol (the peers' module `real_data_peers.py` states the same for them): the first 2/3 of
each record is estimation data, the last 1/3 validation; nothing of the validation third is
seen before the model is fixed. Tasks: heat exchanger (1 -> 1), industrial dryer (3 inputs ->
dry-bulb temperature), glass furnace (3 inputs -> all six outputs: one MISO model per output,
`estimate_outputs`; the record's fit is the mean over outputs), heating system (1 -> 1).
`estimate` is called with `folds=2` (both ends of the estimation data held out in turn).

mfmjax: `Signals` with the default offset rule (`offset=None`), then `mfmjax.estimate(signals,
identify=estimation window, ...)` with its defaults: structure and stage (MFM / SRIVC / output
error) chosen by the mean simulation error on two held-back blocks of the estimation data (its
first and last third, each fitted on the rest); grids n = 1..4, m_k = 0..n (feed-through
included), N, M = 3..5, h per record below (in the record's time unit), delays on the heating
system. Validation: fit % = 100 (1 - ||y - y_sim|| / ||y - mean y||) over the whole validation
third, simulated from the initial-state observer over its first 20 % (eq. 14), as the peers'
least-squares initial state over the same samples.

Times: `cold` is the first call in a fresh process (it compiles; the persistent compilation
cache is off here), `warm` a second identical call. Each record runs in its own process: XLA's
CPU backend keeps a few memory mappings per compiled program alive while the program is
cached, and the whole benchmark in one process (about 300 programs) reached the kernel's
65,530-mapping limit (`vm.max_map_count`) and aborted ("LLVM ERROR: Unable to allocate section
memory"). Saves benchmarks/results/real_data.json.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
import warnings

sys.path.insert(0, os.path.dirname(__file__))
import numpy as np  # noqa: E402
import real_data_peers  # noqa: E402  (sets BLAS threads before NumPy is imported)

import mfmjax  # noqa: E402
from mfmjax.datasets import DAISY, daisy  # noqa: E402

H = {"heat_exchanger": (10, 20, 40, 80), "dryer": (50, 100, 200, 400),
     "glass_furnace": (10, 20, 40, 80), "heating_system": (40, 80, 160, 320)}
N_ORDERS = (1, 2, 3, 4)  # n; m_k = 0..n (feed-through included)
DELAYS = {"heating_system": (0, 2, 4, 6)}  # time units (dt = 2 s): 0..3 samples, as the peers
RESULTS = os.path.join(os.path.dirname(__file__), "results")


def records(name: str) -> list:
    """One Signals per output of the task, with the library's default offset rule."""
    outputs = real_data_peers.TASKS[name]["outputs"]
    return [daisy(name, offset=None, output=o) for o in outputs]


def mfmjax_fit(name: str) -> dict:
    sigs = records(name)
    T, dt, K = sigs[0].n_samples, sigs[0].dt, sigs[0].n_inputs
    cut = (2 * T) // 3
    kw = dict(identify=(sigs[0].t0, sigs[0].t0 + (cut - 1) * dt), folds=2, n=N_ORDERS,
              m=[list(range(max(N_ORDERS) + 1))] * K, N=(3, 4, 5), M=(3, 4, 5), h=H[name],
              delays=[DELAYS[name]] * K if name in DELAYS else None)
    times = []
    for _ in range(2):  # cold, warm
        t0 = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            ests = mfmjax.estimate_outputs(sigs, **kw)
        times.append(time.perf_counter() - t0)
    w0, w1 = sigs[0].t0 + cut * dt, sigs[0].t0 + (T - 1) * dt
    fits, chosen = [], []
    for sig, est in zip(sigs, ests):
        obs = mfmjax.observe(est.model, sig, (w0, w1), observer_window=0.2 * (w1 - w0))
        fits.append(float(mfmjax.fit_percent(np.asarray(sig.y)[cut:], obs.y_sim)))
        chosen.append(dict(output=sig.output_name, n=est.model.n, m=list(est.model.m),
                           delays=[float(d) for d in np.asarray(est.model.delays)],
                           offset=bool(est.model.has_offset), method=est.method,
                           converged=bool(est.converged),
                           **_chosen(est.holdout)))
    return dict(fit=fits, fit_mean=float(np.mean(fits)), cold_s=times[0], warm_s=times[1],
                structure=chosen)


def _chosen(holdout: dict) -> dict:
    """The stage `estimate` chose on the held-back data and its fit there (a rescue returns
    output error from SRIVC's best iterate: the stage is then "srivc", not the method)."""
    for key, value in holdout.items():
        if key.startswith("chosen: "):
            return dict(holdout_stage=key[len("chosen: "):], holdout_fit=value)
    return dict(holdout_stage=None, holdout_fit=None)


def mfmjax_fit_fresh(name: str) -> dict:
    """`mfmjax_fit` in a fresh Python process (see the module docstring)."""
    code = (f"import sys, json; sys.path.insert(0, {os.path.dirname(__file__)!r}); "
            f"import real_data; print(json.dumps(real_data.mfmjax_fit({name!r})))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--no-peers", action="store_true",
                        help="reuse benchmarks/results/real_data_peers.json")
    args = parser.parse_args()
    saved, previous = {}, {}
    path = os.path.join(RESULTS, "real_data_peers.json")
    if args.no_peers and os.path.exists(path):
        with open(path) as fh:
            saved = {r["record"]: r for r in json.load(fh)}
        last = os.path.join(RESULTS, "real_data.json")  # the no-mean-removal variant, if run
        if os.path.exists(last):
            with open(last) as fh:
                previous = {r["record"]: r for r in json.load(fh)}
    rows = []
    for name in DAISY:
        print(f"{name} ...", flush=True)
        row = {"record": name, "description": DAISY[name][7], "mfmjax": mfmjax_fit_fresh(name)}
        if args.no_peers:
            row["peers"] = saved.get(name, {}).get("peers", {})
            row["peers_measured"] = "saved"
            if "peers_no_mean_removal" in previous.get(name, {}):
                row["peers_no_mean_removal"] = previous[name]["peers_no_mean_removal"]
        else:
            row["peers"] = real_data_peers.peers(name)["peers"]
            row["peers_no_mean_removal"] = real_data_peers.peers(name, False)["peers"]
            row["peers_measured"] = "this run"
        best = max(row["peers"], key=lambda p: row["peers"][p]["fit_mean"])
        row["best_peer"] = best
        row["gap"] = row["mfmjax"]["fit_mean"] - row["peers"][best]["fit_mean"]
        rows.append(row)
    peers = list(rows[0]["peers"])
    print(f"\n{'record':<16}{'mfmjax':>8}{'cold s':>8}{'warm s':>8}"
          + "".join(f"{p:>10}" for p in peers) + f"{'best peer':>11}{'gap':>7}")
    for r in rows:
        m = r["mfmjax"]
        print(f"{r['record']:<16}{m['fit_mean']:>8.1f}{m['cold_s']:>8.1f}{m['warm_s']:>8.1f}"
              + "".join(f"{r['peers'][p]['fit_mean']:>10.1f}" for p in peers)
              + f"{r['best_peer']:>11}{r['gap']:>7.1f}")
    if "peers_no_mean_removal" in rows[0]:
        print("\npeers without mean removal (a variant, not the protocol):")
        for r in rows:
            print(f"{r['record']:<16}" + "".join(
                f"{r['peers_no_mean_removal'][p]['fit_mean']:>10.1f}" for p in peers))
    print("\nmfmjax's choices:")
    for r in rows:
        for s in r["mfmjax"]["structure"]:
            print(f"  {r['record']:<16}{s['output']:<10} n={s['n']} m={s['m']} "
                  f"delays={s['delays']} offset={s['offset']} {s['method']}"
                  f"{'' if s['converged'] else ' (NOT CONVERGED)'}")
        if len(r["mfmjax"]["fit"]) > 1:
            print(f"  {'':<16}per output: " + " ".join(f"{f:.1f}" for f in r["mfmjax"]["fit"]))
    os.makedirs(RESULTS, exist_ok=True)
    with open(os.path.join(RESULTS, "real_data.json"), "w") as fh:
        json.dump(rows, fh, indent=1)


if __name__ == "__main__":
    main()
