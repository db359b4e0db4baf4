"""Real DaISy records: structure search on the first two thirds, fit % on the held-back third.

    python benchmarks/real_data.py

For each record: `mfmjax.search` (score BIC, offset term, delays where they matter) on the first
2/3 of the samples; the best model is then validated on the last 1/3: initial state from the
initial-state observer over the first 20 % of that third (eq. 14), simulation over all of it, and
fit % = 100 (1 - ||y - y_sim|| / ||y - mean y||). For context, the same split with a least-squares
FIR model (30 lags per input + constant: a peer that needs no state) is printed too. Saves
benchmarks/results/real_data.json.
"""

from __future__ import annotations

import json
import os
import time
import warnings

import numpy as np

import mfmjax
from mfmjax.datasets import DAISY, daisy

SETUPS = {  # grids in time units of each record; lag-0 effects -> m_k up to n (feed-through)
    "heat_exchanger": dict(n=(1, 2, 3), h=(10, 20, 40, 80), feedthrough=False, delays=None),
    "dryer": dict(n=(1, 2, 3), h=(50, 100, 200, 400), feedthrough=True, delays=None),
    "glass_furnace": dict(n=(1, 2, 3), h=(10, 20, 40, 80), feedthrough=True, delays=None),
    "heating_system": dict(n=(1, 2, 3), h=(40, 80, 160, 320), feedthrough=False,
                           delays=[(0, 2, 4, 6)]),
}
FIR_LAGS = 30


def fir_fit(y, u, cut):
    T, K = u.shape
    X = np.column_stack([np.roll(u[:, k], lag) for k in range(K) for lag in range(FIR_LAGS)]
                        + [np.ones(T)])[FIR_LAGS:]
    Y, c = y[FIR_LAGS:], cut - FIR_LAGS
    theta = np.linalg.lstsq(X[:c], Y[:c], rcond=None)[0]
    return float(mfmjax.fit_percent(Y[c:], X[c:] @ theta))


def main():
    warnings.simplefilter("ignore")
    rows = []
    for name, st in SETUPS.items():
        sig = daisy(name)
        T, K, dt = sig.n_samples, sig.n_inputs, sig.dt
        cut = (2 * T) // 3
        part = mfmjax.Signals(sig.y[:cut], sig.u[:cut], dt=dt, intersample=sig.intersample,
                              offset=True)
        m = [list(range(max(st["n"]) + 1))] * K if st["feedthrough"] else None
        a = time.perf_counter()
        res = mfmjax.search(part, n=st["n"], N=(3, 4, 5), M=(3, 4, 5), h=st["h"], m=m,
                            delays=st["delays"], score="bic")
        seconds = time.perf_counter() - a
        best, r = res.best(), res.row(0)
        full = mfmjax.Signals(sig.y, sig.u, dt=dt, intersample=sig.intersample, offset=True)
        w0, w1 = cut * dt, (T - 1) * dt
        obs = mfmjax.observe(best, full, (w0, w1), observer_window=0.2 * (w1 - w0))
        fit = float(mfmjax.fit_percent(np.asarray(sig.y)[cut:], obs.y_sim))
        rows.append({
            "dataset": name, "description": DAISY[name][7], "samples": T, "dt": dt,
            "ident_samples": cut, "candidates": len(res), "search_s": seconds,
            "n": r["n"], "m": r["m"], "N": r["N"], "M": r["M"], "h": r["h"],
            "delays": r["delays"], "fit_ident": r["fit"], "fit_validation": fit,
            "fir_fit_validation": fir_fit(np.asarray(sig.y), np.asarray(sig.u), cut),
            "status": r["status"],
        })
    print(f"{'dataset':<15}{'T':>6}{'cands':>7}{'n':>3}{'m':>9}{'N':>3}{'M':>3}{'h':>6}"
          f"{'delays':>8}{'fit id %':>10}{'fit val %':>11}{'FIR val %':>11}{'search s':>10}")
    for r in rows:
        print(f"{r['dataset']:<15}{r['samples']:>6}{r['candidates']:>7}{r['n']:>3}"
              f"{','.join(map(str, r['m'])):>9}{r['N']:>3}{r['M']:>3}{r['h']:>6g}"
              f"{','.join(f'{d:g}' for d in r['delays']):>8}{r['fit_ident']:>10.1f}"
              f"{r['fit_validation']:>11.1f}{r['fir_fit_validation']:>11.1f}{r['search_s']:>10.1f}")
    os.makedirs(os.path.join(os.path.dirname(__file__), "results"), exist_ok=True)
    with open(os.path.join(os.path.dirname(__file__), "results", "real_data.json"), "w") as fh:
        json.dump(rows, fh, indent=1)


if __name__ == "__main__":
    main()
