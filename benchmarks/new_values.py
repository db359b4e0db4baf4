"""A new value that fixes no shape, in a warm process: time and programs compiled.

    python benchmarks/new_values.py [--runs 2] [--compare DIR]

In a fresh process (no persistent compilation cache), each entry point is called once on a
1200-sample two-input record (third-order system, 1 % output noise, dt = 0.05), then again
with one value changed: the same system sampled at dt = 0.051 (every kernel still in its
bucket), a model of the same orders built from coefficients instead of identified, refine's
tolerances, estimate's SRIVC tolerance, the on-line identifier's column names, a 1100-sample
record and a new T_ob for `moving_final_states` and `cramer_rao`, new exponents for the eager
`phi` and `kernel_weights`. The second
call's wall time and the programs it compiled (JAX's compile log, `tests/jaxlog.py`) are
printed; `--compare DIR` alternates every run with the mfmjax package in DIR (e.g. a
`git worktree` of an earlier commit). Saves benchmarks/results/new_values.json.
"""

from __future__ import annotations

import json

import numpy as np
from fresh_process import alternated, arguments

CHILD = r"""
import json, sys, time, warnings
sys.path.insert(0, TESTS)
import numpy as np, jax
jax.config.update("jax_enable_x64", True)
from jaxlog import compiles
import mfmjax
from mfmjax import ModulatingFunction, OnlineConfig, OnlineIdentifier, Signals, Structure
from mfmjax.datasets import simulated_experiment, switching_experiment, third_order_two_input
warnings.simplefilter("ignore")
st, mf = Structure(3, [1, 1]), ModulatingFunction(4, 5, 2.6)
def record(dt):
    return simulated_experiment(third_order_two_input(), dt=dt, n_samples=1200, seed=3,
                                noise_std=0.01)
base, other = record(0.05), record(0.051)
head = Signals(np.asarray(base.y)[:1100], np.asarray(base.u)[:1100], dt=0.05,
               intersample=base.intersample)
grid = dict(n=(2, 3), m=[(0, 1), (0, 1)], N=(4, 5), M=5, h=(2.4, 2.6))
small = dict(h=(2.6,), n=(2, 3), N=(4,), M=(5,))
t, y, u, _ = switching_experiment()
def online(names):
    cfg = OnlineConfig(dt=1.0, n_inputs=2, n=(2,), intersample=("foh", "zoh"), n_reident=6,
                       output_name=names[0], input_names=names[1:])
    ident = OnlineIdentifier(cfg)
    for c0 in range(0, len(t), 250):
        ident.update(t[c0:c0 + 250], y[c0:c0 + 250], u[c0:c0 + 250])
    return ident.mse()
def given(sig):
    m = mfmjax.identify(sig, st, mf)
    return mfmjax.Model.from_coefficients(np.asarray(m.a), [np.asarray(b) for b in m.b],
                                          intersample=sig.intersample)
jobs = {
  "identify, new dt": lambda s: mfmjax.identify(s, st, mf).a,
  "observe, new dt": lambda s: mfmjax.observe(mfmjax.identify(s, st, mf), s).E,
  "simulate, new dt": lambda s: mfmjax.simulate(mfmjax.identify(s, st, mf), s.u, dt=float(s.dt)),
  "search, new dt": lambda s: mfmjax.search(s, **grid).row(0)["E"],
  "output_error, new dt": lambda s: mfmjax.output_error(s, mfmjax.identify(s, st, mf)).theta,
  "estimate, new dt": lambda s: mfmjax.estimate(s, **small).model.a,
}
out = {}
for name, job in jobs.items():
    jax.block_until_ready(job(base))
    t0 = time.perf_counter()
    with compiles() as names:
        jax.block_until_ready(job(other))
    out[name] = dict(s=time.perf_counter() - t0, programs=len(names))
pairs = {
  "observe, model given not identified": (
      lambda: mfmjax.observe(mfmjax.identify(base, st, mf), base).E,
      lambda: mfmjax.observe(given(base), base).E),
  "refine, new rtol/atol": (
      lambda: mfmjax.refine(base, mfmjax.identify(base, st, mf), vary=("h",), max_steps=5).value,
      lambda: mfmjax.refine(base, mfmjax.identify(base, st, mf), vary=("h",), max_steps=5,
                            rtol=1e-5, atol=1e-7).value),
  "estimate, new SRIVC tol": (lambda: mfmjax.estimate([base, base], **small)[0].model.a,
                              lambda: mfmjax.estimate([base, base], **small, tol=1e-7)[0].model.a),
  "on-line run, new column names": (lambda: online(("y", "u1", "u2")),
                                    lambda: online(("temperature", "valve", "pump"))),
  "moving_final_states, new length and T_ob": (
      lambda: mfmjax.moving_final_states(given(base), base, 45.0, [50.0, 59.0]),
      lambda: mfmjax.moving_final_states(given(base), head, 46.0, [53.0, 54.95])),
  "cramer_rao, new experiment length": (
      lambda: mfmjax.cramer_rao(given(base), base.u, np.zeros(3), dt=0.05, sigma=0.01)[1],
      lambda: mfmjax.cramer_rao(given(base), head.u, np.zeros(3), dt=0.05, sigma=0.01)[1]),
  "phi and kernel_weights, new N, M": (
      lambda: [mfmjax.phi(np.linspace(0, 2, 41), ModulatingFunction(3, 4, 2.0), 1),
               mfmjax.kernel_weights(ModulatingFunction(3, 4, 2.0), 1, 0.05, "foh", 0.0, 48)],
      lambda: [mfmjax.phi(np.linspace(0, 2, 41), ModulatingFunction(5, 6, 2.0), 1),
               mfmjax.kernel_weights(ModulatingFunction(5, 6, 2.0), 1, 0.05, "foh", 0.0, 48)]),
}
for name, (first, second) in pairs.items():
    jax.block_until_ready(first())
    t0 = time.perf_counter()
    with compiles() as names:
        jax.block_until_ready(second())
    out[name] = dict(s=time.perf_counter() - t0, programs=len(names))
print(json.dumps(out))
"""


def main():
    args = arguments("new_values")
    rows = alternated(args, CHILD, lambda r: print(f"  {r['label']} run {r['run'] + 1} done",
                                                   flush=True))
    labels = sorted({r["label"] for r in rows}, key=lambda x: x != "this")
    jobs = [k for k in rows[0] if k not in ("label", "run")]
    print(f"\n{'second call':38s}" + "".join(f" | {lab + ' s':>11s} {'programs':>8s}"
                                             for lab in labels))
    table = {}
    for job in jobs:
        cells, table[job] = "", {}
        for lab in labels:
            rs = [r[job] for r in rows if r["label"] == lab]
            s = [r["s"] for r in rs]
            table[job][lab] = dict(s=s, programs=[r["programs"] for r in rs])
            cells += f" | {np.min(s):5.2f}-{np.max(s):5.2f} {max(r['programs'] for r in rs):8d}"
        print(f"{job:38s}{cells}")
    with open(args.json, "w") as fh:
        json.dump(dict(runs=args.runs, compare=args.compare, rows=rows, table=table), fh, indent=1)
    print(f"saved {args.json}")


if __name__ == "__main__":
    main()
