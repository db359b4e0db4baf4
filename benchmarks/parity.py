"""Parity with a previous release: parameters of every path (identify with both output rules,
noisy identify, output_error, scores, search theta and ranking) on the accuracy benchmark's
two systems, saved by one version and compared against another.

    git worktree add /tmp/oldrel <rev>
    PYTHONPATH=/tmp/oldrel python benchmarks/parity.py save /tmp/old.npz
    python benchmarks/parity.py save /tmp/new.npz
    python benchmarks/parity.py compare /tmp/old.npz /tmp/new.npz
"""
import json
import os
import sys
import warnings

import numpy as np

import mfmjax
from mfmjax import ModulatingFunction, Signals, Structure
from mfmjax.datasets import paper_table3_model1, simulated_experiment, third_order_two_input

CASES = [("t3m1", paper_table3_model1, 2.5, 3000, (0, 0), (3, 4, 200.0)),
         ("3rd", third_order_two_input, 0.01, 2000, (1, 0), (4, 5, 2.0))]


def _params(m):
    return np.concatenate([np.asarray(m.a)] + [np.asarray(b) for b in m.b])


def collect():
    warnings.simplefilter("ignore")
    out = {}
    for name, make, dt, T, m, (N, M, h) in CASES:
        true = make()
        sig = simulated_experiment(true, dt=dt, n_samples=T, x0=0.1 * np.ones(true.n))
        lin = Signals(sig.y, sig.u, dt=dt, intersample=sig.intersample, output_rule="foh")
        st, mf = Structure(true.n, m), ModulatingFunction(N, M, h)
        out[name + "_cubic"] = _params(mfmjax.identify(sig, st, mf))
        out[name + "_foh"] = _params(mfmjax.identify(lin, st, mf))
        noisy = simulated_experiment(true, dt=dt, n_samples=T, x0=0.1 * np.ones(true.n),
                                     noise_std=0.01, seed=4)
        est = mfmjax.identify(noisy, st, mf)
        out[name + "_noisy"] = _params(est)
        oe = mfmjax.output_error(noisy, est, max_steps=40)
        out[name + "_oe"] = np.asarray(oe.theta)
        sc = mfmjax.scores(noisy, st, h=h, N=N, M=M)
        out[name + "_scores"] = np.asarray([float(v) for k, v in sc.items() if k != "status"])
        res = mfmjax.search(noisy, n=[true.n], N=[N, N + 1], M=[M], h=[h, 0.9 * h], m=None)
        out[name + "_search_theta"] = np.asarray(res.columns["theta"])
        out[name + "_search_rank"] = np.asarray(res.rank)
    return out


def compare(old_path, new_path):
    a, b = np.load(old_path), np.load(new_path)
    rows = {}
    print(f"{'path':<24}{'norm-wise':>12}{'element-wise':>14}")
    for k in a.files:
        x, y = a[k], b[k]
        if "rank" in k:
            rows[k] = bool(np.array_equal(x, y))
            print(f"{k:<24}{'same' if rows[k] else 'DIFFERENT':>12}")
            continue
        fin = np.isfinite(x) & np.isfinite(y)
        d = np.max(np.abs(x[fin] - y[fin])) / max(np.max(np.abs(x[fin])), 1e-300)
        r = np.max(np.abs(x[fin] - y[fin]) / np.maximum(np.abs(x[fin]), 1e-300))
        rows[k] = {"normwise": float(d), "elementwise": float(r)}
        print(f"{k:<24}{d:>12.1e}{r:>14.1e}")
    path = os.path.join(os.path.dirname(os.path.abspath(__file__)), "results", "parity.json")
    with open(path, "w") as fh:
        json.dump(rows, fh, indent=2)
    print(f"saved {path}")


if __name__ == "__main__":
    if len(sys.argv) == 3 and sys.argv[1] == "save":
        np.savez(sys.argv[2], **collect())
    elif len(sys.argv) == 4 and sys.argv[1] == "compare":
        compare(sys.argv[2], sys.argv[3])
    else:
        sys.exit(__doc__)  # usage (it read any other first word as compare: an IndexError)
