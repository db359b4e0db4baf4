"""Noise-free identification accuracy: the cubic output rule against the piecewise-linear rule.

Prints a table and saves benchmarks/results/identify_accuracy.json. Also prints the time of
one identify call, compile apart from run (no peer here: the throughput comparison against a
NumPy/SciPy loop belongs to the search benchmark).

    python benchmarks/identify_accuracy.py
"""

from __future__ import annotations

import json
import os
import time

import numpy as np

import mfmjax
from mfmjax import ModulatingFunction, Signals, Structure
from mfmjax.datasets import paper_table3_model1, simulated_experiment, third_order_two_input

CASES = [
    ("paper Table 3 model 1 (n=2, m=0,0; foh+zoh)", paper_table3_model1, 2.5, 3000, (0, 0),
     (3, 4, 200.0)),
    ("3rd order, 2 inputs (m=1,0; foh+zoh)", third_order_two_input, 0.01, 2000, (1, 0),
     (4, 5, 2.0)),
]


def params(model):
    return np.concatenate([np.asarray(model.a)] + [np.asarray(b) for b in model.b])


def main():
    rows = []
    print(f"{'system':<48}{'dt':>7}{'cubic rule':>13}{'pw-linear':>13}{'ratio':>9}")
    for name, make, dt, T, m, (N, M, h) in CASES:
        true = make()
        sig = simulated_experiment(true, dt=dt, n_samples=T, x0=0.1 * np.ones(true.n))
        lin = Signals(sig.y, sig.u, dt=dt, intersample=sig.intersample, output_rule="foh")
        st, mf = Structure(true.n, m), ModulatingFunction(N, M, h)
        err = {}
        for label, s in (("cubic", sig), ("foh", lin)):
            est = mfmjax.identify(s, st, mf)
            err[label] = float(np.max(np.abs(params(est) - params(true)) / np.abs(params(true))))
        print(f"{name:<48}{dt:>7g}{err['cubic']:>13.2e}{err['foh']:>13.2e}"
              f"{err['foh'] / err['cubic']:>9.0f}")
        rows.append(dict(system=name, dt=dt, samples=T, N=N, M=M, h=h,
                         max_rel_error_cubic=err["cubic"], max_rel_error_piecewise_linear=err["foh"]))
    # timing: first call (compile + run) and warm calls
    true = third_order_two_input()
    sig = simulated_experiment(true, dt=0.01, n_samples=8000)
    st = Structure(3, (1, 0))
    t0 = time.perf_counter()
    mfmjax.identify(sig, st, ModulatingFunction(4, 5, 2.0)).a.block_until_ready()
    first = time.perf_counter() - t0
    reps = 20
    t0 = time.perf_counter()
    for k in range(reps):
        mfmjax.identify(sig, st, ModulatingFunction(4, 5, 2.0 - 0.01 * k, h_max=2.0)).a.block_until_ready()
    warm = (time.perf_counter() - t0) / reps
    print(f"\nidentify, T=8000, n=3, m=(1,0): first call {first:.2f} s (compile), "
          f"warm {warm * 1e3:.1f} ms/call")
    os.makedirs(os.path.join(os.path.dirname(__file__), "results"), exist_ok=True)
    out = os.path.join(os.path.dirname(__file__), "results", "identify_accuracy.json")
    with open(out, "w") as fh:
        json.dump(dict(accuracy=rows, first_call_s=first, warm_call_s=warm), fh, indent=2)
    print(f"saved {out}")


if __name__ == "__main__":
    main()
