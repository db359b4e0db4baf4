"""Monte Carlo under white output noise: MFM, MFM + output error, SRIVC (JAX) and a NumPy SRIVC.

    python benchmarks/noise_montecarlo.py [--quick] [--runs R] [--systems a,b]

Systems: the paper's Table 3 model 1 (n = 2, 2 inputs: foh, zoh; dt = 2.5 s, 2000 samples), a
4th-order SISO system with lightly damped poles (zeta = 0.1 at 1 rad/s, zeta = 0.2 at 3 rad/s;
dt = 0.05 s, 2000 samples), and (issue 14) a 4th-order lightly damped system with a
right-half-plane zero, $9(1 - s/2) / ((s^2 + 0.1 s + 1)(s^2 + 0.6 s + 9))$ (zeta 0.05 and 0.1),
sampled 100x faster than its fastest pole (dt = 2 pi / 300 s), a PRBS input held (zoh), 7500
samples. White output noise at SNR 20 dB and 10 dB (power ratio of the clean output's variance
to the noise variance), 100 runs each (`--quick`: 10). Methods, on the same realisations in the
same process: plain MFM (`identify`, eq. 12); MFM + `output_error`; `mfmjax.srivc` from the MFM
estimate; the NumPy/SciPy SRIVC peer (benchmarks/srivc_peer.py, `cont2discrete` + `lfilter`)
from the same MFM estimate. Per method: largest normalised bias |mean - true| / |true| over the
parameters, std / CRB (min, median, max; `cramer_rao` at the truth and noise level), failures
(non-finite, not converged, any parameter more than 10 CRB std off), ms per fit warm, compile
s, ratios to the NumPy SRIVC peer; then the whole batch of realisations through `jax.vmap(srivc)`
(one compiled call) and as a list (`srivc(records, starts)`: chunks on a thread per core),
each the median of 3 calls after a compiling one, against as many sequential NumPy SRIVC
fits, and the known-structure pipeline (the MFM start and SRIVC from it) vmapped in one
compiled call; then (issue 14 item 4) `mfmjax.estimate` with its default selection and stages on the
whole batch of records (a list of `Signals`: every stage one compiled call per structure),
over the grid `estimate_grid`
(orders n-1..n, numerator orders m_k..m_k+1 per input, the system's N and M, h and 0.75 h):
its structure choice (records that did not choose the true structure count as failures), bias,
std / CRB, failures, and time per record warm (the batch run twice; the first is compile +
run) against 10 records one at a time. `--no-estimate` skips it. One process per system
(XLA's CPU memory mappings grow with every compiled program). Saves
benchmarks/results/noise_montecarlo.json.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
import warnings

# tiny matrices: threaded BLAS only contends (a 6x6 scipy expm took 20 ms with OpenBLAS threads
# on this loaded 2-core machine, 9 us with one); set before numpy loads, for the NumPy peers
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from scipy.signal import max_len_seq  # noqa: E402

import mfmjax  # noqa: E402
from mfmjax import ModulatingFunction, Structure  # noqa: E402
from mfmjax.datasets import paper_table3_model1, simulated_experiment  # noqa: E402

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import srivc_peer  # noqa: E402

SYSTEMS = {
    "table3_model1": dict(model=paper_table3_model1, dt=2.5, T=2000, structure=Structure(2, (0, 0)),
                          mf=ModulatingFunction(3, 4, 200.0)),
    "fourth_order_lightly_damped": dict(
        model=lambda: mfmjax.Model.from_coefficients(
            np.polymul([1, 0.2, 1], [1, 1.2, 9])[::-1], [[9.0]], intersample=("foh",)),
        dt=0.05, T=2000, structure=Structure(4, (0,)), mf=ModulatingFunction(4, 5, 8.0)),
    "fourth_order_rhp_zero_prbs": dict(
        model=lambda: mfmjax.Model.from_coefficients(
            np.polymul([1, 0.1, 1], [1, 0.6, 9])[::-1], [[9.0, -4.5]], intersample=("zoh",)),
        dt=2 * np.pi / 300, T=7500, structure=Structure(4, (1,)),
        mf=ModulatingFunction(5, 5, 8.0), prbs=8),
}


def _prbs_experiment(true, dt, T, hold):
    """A maximum-length binary sequence (10 bits, +-1), each level held `hold` samples (zoh)."""
    levels = 2.0 * max_len_seq(10)[0] - 1.0
    u = np.resize(np.repeat(levels, hold), T)[:, None]
    y = np.asarray(mfmjax.simulate(true, u, dt=dt))
    return mfmjax.Signals(y, u, dt=dt, intersample=true.intersample)


def _params(model):
    return np.concatenate([np.asarray(model.a)[: model.n]] + [np.asarray(b) for b in model.b])


def _timed(fn):
    a = time.perf_counter()
    out = jax.block_until_ready(fn())
    return out, time.perf_counter() - a


def _warm(fn, repeats=3):
    """(result, median time of `repeats` calls): the batch timings (after a compiling call)."""
    times = []
    for _ in range(repeats):
        out, t = _timed(fn)
        times.append(t)
    return out, float(np.median(times))


def estimate_grid(spec):
    """The grid `estimate` searches in this benchmark: around the true structure and MF."""
    st, mf = spec["structure"], spec["mf"]
    return dict(n=(st.n - 1, st.n), m=[[mk, mk + 1] for mk in st.m], N=(float(mf.N),),
                M=(float(mf.M),), h=(0.75 * float(mf.h), float(mf.h)))


def _true_part(model, true):
    """The coefficients of `model` that the true structure has (a_0..a_{n-1}, b_k0..b_km_k)."""
    return np.concatenate([np.asarray(model.a)[: true.n]]
                          + [np.asarray(b)[: mk + 1] for b, mk in zip(model.b, true.m)])


def run_estimate(spec, true, sigs, crb, truth):
    """`mfmjax.estimate` (default selection and stages) on the batch of records."""
    grid = estimate_grid(spec)
    ests, t_first = _timed(lambda: mfmjax.estimate(sigs, **grid))
    ests, t_warm = _timed(lambda: mfmjax.estimate(sigs, **grid))
    few = sigs[:10]
    for sig in few:  # the one-record programs compiled, then timed
        mfmjax.estimate(sig, **grid)
    _, t_seq = _timed(lambda: [mfmjax.estimate(sig, **grid) for sig in few])
    # the true structure, or one that nests it (extra numerator coefficients): its true-structure
    # coefficients are compared; a structure that does not nest the truth is a failure
    nests = [e.model.n == true.n and all(a >= b for a, b in zip(e.model.m, true.m)) for e in ests]
    right = [e.model.n == true.n and tuple(e.model.m) == tuple(true.m) for e in ests]
    x = np.asarray([_true_part(e.model, true) for e, ok in zip(ests, nests) if ok])
    finite = np.all(np.isfinite(x), axis=1)
    conv = np.asarray([e.converged for e, ok in zip(ests, nests) if ok])
    off = ~finite | np.any(np.abs(x - truth) > 10 * crb, axis=1)
    ratio = x[finite].std(0, ddof=1) / crb
    methods = {}
    for e in ests:
        methods[e.method] = methods.get(e.method, 0) + 1
    return {"grid": {k: list(np.ravel(v).tolist()) if k != "m" else v for k, v in grid.items()},
            "wrong_structure": int(len(ests) - sum(nests)),
            "over_parameterised": int(sum(nests) - sum(right)), "methods": methods,
            "bias": (np.abs(x[finite].mean(0) - truth) / np.abs(truth)).tolist(),
            "std_over_crb": [float(ratio.min()), float(np.median(ratio)), float(ratio.max())],
            "nonfinite": int(np.sum(~finite)), "not_converged": int(np.sum(~conv)),
            "off_10crb": int(np.sum(off)), "batch_s_first": t_first, "batch_s_warm": t_warm,
            "ms_per_record_batch": 1e3 * t_warm / len(sigs),
            "ms_per_record_one_at_a_time": 1e3 * t_seq / len(few)}


_PIPELINES: dict = {}  # one jitted pipeline per system (its second SNR compiles nothing)


def run_system(name, spec, snr_db, runs, with_estimate=True):
    true = spec["model"]()
    if spec.get("prbs"):
        clean = _prbs_experiment(true, spec["dt"], spec["T"], spec["prbs"])
    else:
        clean = simulated_experiment(true, dt=spec["dt"], n_samples=spec["T"], seed=11)
    sd = float(np.std(clean.y)) / 10 ** (snr_db / 20)
    rng = np.random.default_rng(1000 + int(snr_db))
    est = {k: [] for k in ("mfm", "oe", "srivc", "srivc_peer")}
    times = {k: [] for k in est}
    conv = {k: [] for k in est}
    codes, sigs, starts = {}, [], []
    for _ in range(runs):
        y = np.asarray(clean.y) + sd * rng.standard_normal(spec["T"])
        sig = mfmjax.Signals(y, clean.u, dt=spec["dt"], intersample=clean.intersample)
        m0, t = _timed(lambda: mfmjax.identify(sig, spec["structure"], spec["mf"]))
        est["mfm"].append(_params(m0)), times["mfm"].append(t), conv["mfm"].append(True)
        r, t = _timed(lambda: mfmjax.output_error(sig, m0))
        codes[r.result] = codes.get(r.result, 0) + 1
        est["oe"].append(np.asarray(r.theta)), times["oe"].append(t)
        conv["oe"].append(r.result == "successful")
        f, t = _timed(lambda: mfmjax.srivc(sig, m0))
        est["srivc"].append(np.asarray(f.theta)), times["srivc"].append(t)
        conv["srivc"].append(bool(f.converged))
        a = time.perf_counter()
        g = srivc_peer.fit(sig, m0)
        times["srivc_peer"].append(time.perf_counter() - a)
        est["srivc_peer"].append(g["theta"]), conv["srivc_peer"].append(g["status"] == 0)
        sigs.append(sig), starts.append(m0)
    names, crb = mfmjax.cramer_rao(true, clean.u, jnp.zeros(true.n), dt=spec["dt"], sigma=sd)
    truth = _params(true)
    crb = np.asarray(crb)[: truth.size]

    def stats(key):
        x = np.asarray(est[key])
        finite = np.all(np.isfinite(x), axis=1)
        off = ~finite | np.any(np.abs(x - truth) > 10 * crb, axis=1)
        ratio = x[finite].std(0, ddof=1) / crb
        warm = times[key][1:] if len(times[key]) > 1 else times[key]
        return {"mean": x[finite].mean(0).tolist(), "std": x[finite].std(0, ddof=1).tolist(),
                "bias": (np.abs(x[finite].mean(0) - truth) / np.abs(truth)).tolist(),
                "std_over_crb": [float(ratio.min()), float(np.median(ratio)), float(ratio.max())],
                "nonfinite": int(np.sum(~finite)), "not_converged": int(np.sum(~np.asarray(
                    conv[key]))), "off_10crb": int(np.sum(off)),
                "ms_warm": 1e3 * float(np.median(warm)),
                "compile_s": max(times[key][0] - float(np.median(warm)), 0.0)}

    out = {"system": name, "snr_db": snr_db, "runs": runs, "names": list(names),
           "true": truth.tolist(), "crb": crb.tolist(), "oe_codes": codes}
    out.update({k: stats(k) for k in est})
    out["mfm_s_per_run"] = float(np.mean(times["mfm"]))
    out["oe_s_per_run"] = float(np.mean(times["oe"]))
    # the whole batch: one vmapped call (compile, then warm) against sequential NumPy fits
    stack = lambda trees: jax.tree.map(lambda *x: jnp.stack(x), *trees)  # noqa: E731
    batched = jax.vmap(lambda s, m: mfmjax.srivc(s, m))
    # the default offset rule's note is static metadata that can differ between records: stack
    # the unlabelled copies (what the library's own programs see)
    bs, bm = stack([sig.unlabelled() for sig in sigs]), stack(starts)
    fb, t_first = _timed(lambda: batched(bs, bm))
    fb, t_batch = _warm(lambda: batched(bs, bm))
    same = float(np.max(np.abs(np.asarray(fb.theta) - np.asarray(est["srivc"]))
                        / np.abs(truth)))
    # the list of records: chunks of records in one compiled call each, on a thread per core
    fl, l_first = _timed(lambda: mfmjax.srivc(sigs, starts))
    fl, t_list = _warm(lambda: mfmjax.srivc(sigs, starts))
    same_list = float(np.max(np.abs(np.asarray([f.theta for f in fl]) - np.asarray(est["srivc"]))
                             / np.abs(truth)))
    a = time.perf_counter()
    for sig, m0 in zip(sigs, starts):
        srivc_peer.fit(sig, m0)
    t_seq = time.perf_counter() - a
    # the known-structure pipeline in one compiled call: the MFM start and SRIVC from it,
    # vmapped over the records (stacked with their offset flag explicit and dt a number, which
    # `identify` needs for its kernel length)
    pipeline = _PIPELINES.setdefault(name, jax.jit(jax.vmap(lambda s: mfmjax.srivc(
        s, mfmjax.identify(s, spec["structure"], spec["mf"], delay_max=0.0)))))
    ps = stack([mfmjax.Signals(sig.y, sig.u, dt=spec["dt"], intersample=sig.intersample,
                               offset=sigs[0].offset) for sig in sigs])
    fp, p_first = _timed(lambda: jax.block_until_ready(pipeline(ps)))
    fp, t_pipe = _warm(lambda: jax.block_until_ready(pipeline(ps)))
    same_pipe = float(np.max(np.abs(np.asarray(fp.theta) - np.asarray(est["srivc"]))
                             / np.abs(truth)))
    out["batch"] = {"records": runs, "vmap_s": t_batch, "vmap_compile_s": t_first - t_batch,
                    "numpy_sequential_s": t_seq, "speedup": t_seq / t_batch,
                    "max_rel_diff_vs_single": same, "list_s": t_list,
                    "list_compile_s": l_first - t_list, "list_speedup": t_seq / t_list,
                    "list_max_rel_diff_vs_single": same_list, "pipeline_s": t_pipe,
                    "pipeline_compile_s": p_first - t_pipe, "pipeline_speedup": t_seq / t_pipe,
                    "pipeline_not_converged": int(np.sum(~np.asarray(fp.converged))),
                    "pipeline_max_rel_diff_vs_single": same_pipe}
    if with_estimate:
        out["estimate"] = run_estimate(spec, true, sigs, crb, truth)
        out["estimate"]["vs_numpy_srivc_sequential"] = t_seq / out["estimate"]["batch_s_warm"]
    return out


METHODS = (("mfm", "MFM"), ("oe", "MFM+OE"), ("srivc", "SRIVC jax"), ("srivc_peer", "SRIVC np"))


def print_case(r):
    peer = r["srivc_peer"]
    print(f"\n{r['system']}, SNR {r['snr_db']:g} dB, {r['runs']} runs (output-error codes "
          f"{r['oe_codes']})")
    print(f"{'method':<11}{'bias':>9}{'std/CRB min':>12}{'med':>6}{'max':>7}{'nonfin':>7}"
          f"{'notconv':>8}{'>10CRB':>7}{'ms/fit':>9}{'compile s':>10}{'bias/SR':>8}"
          f"{'time/SR':>8}")
    for key, label in METHODS:
        m = r[key]
        lo, med, hi = m["std_over_crb"]
        print(f"{label:<11}{max(m['bias']):>9.2e}{lo:>12.2f}{med:>6.2f}{hi:>7.2f}"
              f"{m['nonfinite']:>7}{m['not_converged'] if key != 'mfm' else '-':>8}"
              f"{m['off_10crb']:>7}{m['ms_warm']:>9.1f}{m['compile_s']:>10.1f}"
              f"{max(m['bias']) / max(peer['bias']):>8.2f}{m['ms_warm'] / peer['ms_warm']:>8.2f}")
    b = r["batch"]
    print(f"batch of {b['records']}: vmap(srivc) {b['vmap_s']:.2f} s warm (compile "
          f"{b['vmap_compile_s']:.1f} s) vs {b['numpy_sequential_s']:.2f} s sequential NumPy "
          f"SRIVC: {b['speedup']:.1f}x (max |batched - single| / |true| = "
          f"{b['max_rel_diff_vs_single']:.1e})")
    print(f"  the list srivc(records, starts) (threads, one per core): {b['list_s']:.2f} s warm "
          f"(compile {b['list_compile_s']:.1f} s): {b['list_speedup']:.1f}x (max |list - "
          f"single| / |true| = {b['list_max_rel_diff_vs_single']:.1e})")
    print(f"  MFM start + SRIVC in one vmapped call: {b['pipeline_s']:.2f} s warm (compile "
          f"{b['pipeline_compile_s']:.1f} s): {b['pipeline_speedup']:.1f}x the sequential NumPy "
          f"fits (which start from the MFM estimates), not converged "
          f"{b['pipeline_not_converged']} (max |pipeline - single| / |true| = "
          f"{b['pipeline_max_rel_diff_vs_single']:.1e})")
    if "estimate" in r:
        e = r["estimate"]
        lo, med, hi = e["std_over_crb"]
        print(f"estimate (defaults) on the batch: methods {e['methods']}, wrong structure "
              f"{e['wrong_structure']}, over-parameterised {e['over_parameterised']} (the true "
              f"structure's coefficients compared), bias {max(e['bias']):.2e} "
              f"({max(e['bias']) / max(peer['bias']):.2f}x SRIVC np), std/CRB "
              f"{lo:.2f}/{med:.2f}/{hi:.2f}, nonfinite {e['nonfinite']}, "
              f"not converged {e['not_converged']}, >10 CRB {e['off_10crb']}")
        print(f"  {e['ms_per_record_batch']:.0f} ms per record in the batch (warm; first call "
              f"{e['batch_s_first']:.1f} s), {e['ms_per_record_one_at_a_time']:.0f} ms one at a "
              f"time; the batch vs sequential NumPy SRIVC fits (known structure): "
              f"{e['vs_numpy_srivc_sequential']:.2f}x")


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--runs", type=int)
    ap.add_argument("--systems", help="comma-separated names (default: all)")
    ap.add_argument("--no-estimate", action="store_true", help="skip the batched estimate")
    ap.add_argument("--json", help="where to save the results (default: benchmarks/results)")
    args = ap.parse_args()
    runs = args.runs or (10 if args.quick else 100)
    names = args.systems.split(",") if args.systems else list(SYSTEMS)
    warnings.simplefilter("ignore")
    t0 = time.perf_counter()
    out = []
    path = args.json or os.path.join(os.path.dirname(__file__), "results",
                                     "noise_montecarlo.json")
    if len(names) > 1:  # one process per system: XLA's CPU memory mappings grow per program
        import subprocess
        import tempfile

        for name in names:
            with tempfile.NamedTemporaryFile(suffix=".json") as tmp:
                cmd = [sys.executable, __file__, "--systems", name, "--runs", str(runs),
                       "--json", tmp.name] + (["--no-estimate"] if args.no_estimate else [])
                subprocess.run(cmd, check=True)
                with open(tmp.name) as fh:
                    out += json.load(fh)["results"]
        names = []
    for name in names:
        for snr in (20.0, 10.0):
            r = run_system(name, SYSTEMS[name], snr, runs, not args.no_estimate)
            out.append(r)
            print_case(r)
    total = time.perf_counter() - t0
    print(f"\nwhole benchmark: {total:.0f} s")
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with open(path, "w") as fh:
        json.dump({"results": out, "runtime_s": total, "argv": sys.argv[1:]}, fh, indent=1)


if __name__ == "__main__":
    main()
