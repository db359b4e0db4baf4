"""Interactive latency: `identify` at a NEW modulating-function setting, `simulate` of a new model
and `output_error` from a NEW start, warm process, against NumPy/SciPy peers on the same data in
the same process.

Settings are values (issue 12): a new (N, M, h) whose support fits the current kernel bucket
reuses the compiled program, so a user exploring settings pays the run time, not a compile.

- identify peer: `numpy_mfm.identify`, the careful per-candidate NumPy/SciPy MFM (exact kernel
  weights, FFT convolution, Gregory Gram, eq. 12).
- simulate peer: the exact zoh/foh discretisation of each input (`cont2discrete`) filtered with
  `lfilter`, summed (the output-error peer's simulation, from rest; it agrees with `simulate`
  once the start-up transient of the two input-history conventions has decayed).
- output-error peer: SciPy `least_squares` (Levenberg-Marquardt, finite-difference Jacobian)
  on the same free parameters and initial conditions, the exact zoh/foh discretisation of each
  input (`cont2discrete`) simulated with `lfilter` (C loop), started from the same MFM model.

Each latency is the median of the calls; "compile" is the first call's excess over the median.

    python benchmarks/interactive.py [--repeats 20]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time

import numpy as np
from scipy import optimize, signal

import mfmjax
from mfmjax import ModulatingFunction, Structure
from mfmjax.datasets import simulated_experiment, third_order_two_input

HERE = os.path.dirname(os.path.abspath(__file__))
DT, T = 0.01, 3000
STRUCT = Structure(3, (1, 0))


def _timed(fn):
    t0 = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - t0


def settings(count, rng):
    """Distinct (N, M, h) with supports of 200..250 samples: one kernel bucket (256)."""
    return [(int(rng.integers(3, 8)), int(rng.integers(3, 8)), float(h))
            for h in rng.permutation(np.linspace(2.0, 2.5, count))]


def scipy_output_error(y, u, dt, modes, model, max_nfev=2000):
    """SciPy peer: output-error fit of a_0..a_{n-1}, b (a_n = 1) and the n initial conditions
    of the filter (`lfilter`'s zi of the free response) by `least_squares(method="lm")`."""
    n = model.n
    m = [b.shape[0] - 1 for b in model.b]
    theta0 = np.concatenate([np.asarray(model.a)[:n]] + [np.asarray(b) for b in model.b])

    def parts(theta):
        a = np.concatenate([theta[:n], [1.0]])[::-1]  # descending powers for scipy
        pos, bs = n, []
        for mk in m:
            bs.append(theta[pos : pos + mk + 1][::-1])
            pos += mk + 1
        return a, bs

    def simulate(theta, zi):
        a, bs = parts(theta)
        out = np.zeros(len(y))
        den = None
        for k, bk in enumerate(bs):
            A, B, C, D = signal.tf2ss(bk, a)
            Ad, Bd, Cd, Dd, _ = signal.cont2discrete((A, B, C, D), dt, method=modes[k])
            num, den = signal.ss2tf(Ad, Bd, Cd, Dd)
            out += signal.lfilter(num[0], den, u[:, k])
        free = signal.lfilter(np.zeros(n + 1), den, np.zeros(len(y)), zi=zi)[0]
        return out + free

    scale = np.maximum(np.abs(theta0), 1e-8)

    def residual(z):
        return y - simulate(theta0 + scale * z[: theta0.size], z[theta0.size :])

    z0 = np.zeros(theta0.size + n)
    z0[theta0.size :] = np.linalg.lstsq(  # initial conditions for the start (linear in zi)
        np.stack([simulate(theta0, e) - simulate(theta0, np.zeros(n)) for e in np.eye(n)], 1),
        y - simulate(theta0, np.zeros(n)), rcond=None)[0]
    sol = optimize.least_squares(residual, z0, method="lm", max_nfev=max_nfev, xtol=1e-10,
                                 ftol=1e-10)
    return theta0 + scale * sol.x[: theta0.size], float(np.sum(sol.fun**2) * dt), sol.status


def scipy_simulate(model, u, dt, modes):
    """SciPy peer of `simulate` from rest: per input the exact zoh/foh discretisation
    (`tf2ss`, `cont2discrete`, `ss2tf`) filtered with `lfilter` (C loop), summed."""
    a = np.asarray(model.a)[::-1]
    out = np.zeros(u.shape[0])
    for k, bk in enumerate(model.b):
        A, B, C, D = signal.tf2ss(np.asarray(bk)[::-1], a)
        Ad, Bd, Cd, Dd, _ = signal.cont2discrete((A, B, C, D), dt, method=modes[k])
        num, den = signal.ss2tf(Ad, Bd, Cd, Dd)
        out += signal.lfilter(num[0], den, u[:, k])
    return out


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeats", type=int, default=20,
                    help="new settings per entry point (at least 3: the accuracy check uses "
                         "the fourth setting)")
    args = ap.parse_args()
    if args.repeats < 3:
        ap.error("--repeats must be at least 3")
    rng = np.random.default_rng(0)
    true = third_order_two_input()
    # white output noise (std 0.05 on an O(1) output): noise-free data make G singular, which
    # the library's KKT solve handles but the peer's eq. (12) closed form does not
    clean = simulated_experiment(true, dt=DT, n_samples=T, seed=2, noise_std=0.05)
    noisy = clean
    y, u = np.asarray(clean.y), np.asarray(clean.u)
    modes = clean.intersample
    grid = settings(args.repeats + 1, rng)

    # -- identify: new settings, warm process ---------------------------------------------
    _, first = _timed(lambda: mfmjax.identify(clean, STRUCT, ModulatingFunction(*grid[0])).a
                      .block_until_ready())
    lib = [_timed(lambda s=s: mfmjax.identify(clean, STRUCT, ModulatingFunction(*s)).a
                  .block_until_ready())[1] for s in grid[1:]]
    repeat = [_timed(lambda: mfmjax.identify(clean, STRUCT, ModulatingFunction(*grid[1])).a
                     .block_until_ready())[1] for _ in grid[1:]]
    from numpy_mfm import identify as np_identify

    peer = [_timed(lambda s=s: np_identify(y, u, DT, modes, 3, (1, 0), *s))[1] for s in grid[1:]]
    est = mfmjax.identify(clean, STRUCT, ModulatingFunction(*grid[3]))
    ref = np_identify(y, u, DT, modes, 3, (1, 0), *grid[3])
    lib_theta = np.concatenate([np.asarray(est.a)] + [np.asarray(b) for b in est.b])
    agree = float(np.max(np.abs(lib_theta - ref) / np.abs(ref)))
    med = {k: statistics.median(v) for k, v in (("new", lib), ("repeat", repeat), ("peer", peer))}
    print(f"identify, T={T}, n=3, m=(1,0), {len(lib)} new settings (N, M, h) in one bucket")
    print(f"  {'':<34}{'median ms':>12}")
    print(f"  {'mfmjax, new setting':<34}{med['new'] * 1e3:>12.2f}")
    print(f"  {'mfmjax, repeated setting':<34}{med['repeat'] * 1e3:>12.2f}")
    print(f"  {'NumPy peer (numpy_mfm)':<34}{med['peer'] * 1e3:>12.2f}")
    print(f"  first call (compile + run) {first:.2f} s; new/peer = {med['new'] / med['peer']:.2f}"
          f"; max rel. parameter difference to the peer {agree:.1e}")

    # -- simulate: a new model each call, against the SciPy peer ---------------------------------
    models = [mfmjax.identify(clean, STRUCT, ModulatingFunction(*s)) for s in grid[1:]]
    mfmjax.simulate(models[0], u, dt=DT).block_until_ready()
    sim = [_timed(lambda m=m: mfmjax.simulate(m, u, dt=DT).block_until_ready())[1] for m in models]
    sim_peer = [_timed(lambda m=m: scipy_simulate(m, u, DT, modes))[1] for m in models]
    y_lib = np.asarray(mfmjax.simulate(models[0], u, dt=DT))
    y_peer = scipy_simulate(models[0], u, DT, modes)
    # the peer's filters start with zero input history; `simulate` holds the inputs before the
    # first sample at their first value (foh): compared after that start-up transient decays
    half = T // 2
    sim_agree = float(np.max(np.abs(y_lib[half:] - y_peer[half:])) / np.max(np.abs(y_peer)))
    sm = {"lib": statistics.median(sim), "peer": statistics.median(sim_peer)}
    print(f"\nsimulate, T={T}, {len(models)} models (a new model each call)")
    print(f"  {'mfmjax simulate':<34}{sm['lib'] * 1e3:>12.2f} ms")
    print(f"  {'SciPy peer (cont2discrete+lfilter)':<34}{sm['peer'] * 1e3:>12.2f} ms")
    print(f"  lib/peer = {sm['lib'] / sm['peer']:.2f}; max |y - y_peer| / max |y_peer| over the "
          f"second half = {sim_agree:.1e}")

    # -- output_error: new starts vs a repeated start, and the SciPy peer ----------------------
    starts = [mfmjax.identify(noisy, STRUCT, ModulatingFunction(*s)) for s in grid]
    _, oe_first = _timed(lambda: mfmjax.output_error(noisy, starts[0]))
    oe_new = [_timed(lambda m=m: mfmjax.output_error(noisy, m))[1] for m in starts[1:6]]
    oe_rep = [_timed(lambda: mfmjax.output_error(noisy, starts[1]))[1] for _ in range(5)]
    fits = [mfmjax.output_error(noisy, m) for m in starts[1:6]]
    peer_runs = [_timed(lambda m=m: scipy_output_error(np.asarray(noisy.y), np.asarray(noisy.u),
                                                       DT, modes, m)) for m in starts[1:6]]
    E_lib = statistics.median(f.E for f in fits)
    E_peer = statistics.median(r[0][1] for r in peer_runs)
    oe = {"new": statistics.median(oe_new), "repeat": statistics.median(oe_rep),
          "peer": statistics.median(r[1] for r in peer_runs)}
    print("\noutput_error, same record, 5 new starts")
    print(f"  {'mfmjax, new start':<34}{oe['new']:>12.3f} s")
    print(f"  {'mfmjax, repeated start':<34}{oe['repeat']:>12.3f} s")
    print(f"  {'SciPy least_squares peer':<34}{oe['peer']:>12.3f} s")
    print(f"  first call {oe_first:.1f} s; new/repeat = {oe['new'] / oe['repeat']:.2f} (target <= 3); "
          f"new/peer = {oe['new'] / oe['peer']:.2f}; median E: mfmjax {E_lib:.6g}, peer {E_peer:.6g}")
    out = dict(
        T=T, dt=DT, identify=dict(first_call_s=first, new_setting_ms=med["new"] * 1e3,
                                  repeated_setting_ms=med["repeat"] * 1e3,
                                  numpy_peer_ms=med["peer"] * 1e3,
                                  ratio_new_to_peer=med["new"] / med["peer"],
                                  max_rel_param_diff_to_peer=agree),
        simulate=dict(ms=sm["lib"] * 1e3, scipy_peer_ms=sm["peer"] * 1e3,
                      ratio_to_peer=sm["lib"] / sm["peer"], max_rel_diff_to_peer=sim_agree),
        output_error=dict(first_call_s=oe_first, new_start_s=oe["new"], repeated_start_s=oe["repeat"],
                          scipy_peer_s=oe["peer"], ratio_new_to_repeat=oe["new"] / oe["repeat"],
                          ratio_new_to_peer=oe["new"] / oe["peer"], median_E=E_lib,
                          median_E_peer=E_peer),
    )
    os.makedirs(os.path.join(HERE, "results"), exist_ok=True)
    path = os.path.join(HERE, "results", "interactive.json")
    with open(path, "w") as fh:
        json.dump(out, fh, indent=2)
    print(f"saved {path}")


if __name__ == "__main__":
    main()
