"""First-call cost: every figure from a fresh process, without / cold / warm persistent cache.

    python benchmarks/cold_start.py [--quick]

Modes (each a new Python process): `no cache` (MFMJAX_NO_COMPILE_CACHE=1: compile everything,
as before the cache), `cold` (an empty cache directory: compile and write), `warm` (the same
directory, a second process: read the programs back). Jobs:

- `mfmjax demo` (CLI, the full demo: two on-line runs on the simulated forehearth);
- `mfmjax search` (CLI) of an 810-candidate grid (n 1..2, m_k <= n - 1, N, M 3..5, 18 h)
  on a 3000-sample two-input record written to CSV (`mfmjax.datasets`, 1 % output noise),
  `--score J`; the CLI still simulates every candidate (E, fit), the NumPy peer does not;
- `mfmjax identify` (CLI) of one model on the same CSV;
- in-library `mfmjax.output_error` first call (after import, data and the MFM start from
  `identify`, timed apart) on the same CSV, from the identify job's model, and a second call
  in the same process (warm process);
- in-library `mfmjax.refine(vary=("h",), max_steps=5)` first call (after import, data and the
  MFM start, timed apart) on the same CSV, and a second call (warm process); no peer;
- `mfmjax online` (CLI) on the forehearth's experiment 1 (`mfmjax dataset forehearth`, 8001
  samples, paper-mode Algorithm 1, input-1 delay 265 s);
- in-library `mfmjax.search(score="J", simulate=False)` first call (after import and data
  set-up, timed separately) on the 14,464-candidate grid of `search_throughput.py` (T = 8000,
  K = 2, N, M 3..8, 16 h, n 1..4, every m_k <= n - 1) and on its 760-candidate quick grid, and a
  second call in the same process (warm process).

Peers, same run, each in a fresh process: the shared-work NumPy/SciPy search
(`numpy_shared_peer.py`) on the CLI search job (import + CSV read + run) and on both library
grids (whole-grid time), the per-candidate NumPy peer (`numpy_mfm.identify`) on the
identify job, and SciPy's `least_squares` output error (`interactive.scipy_output_error`, from
the NumPy MFM start) on the output-error job; the demo and the on-line identifier have no
peer. Prints a table and ratios; saves benchmarks/results/cold_start.json (with `--jobs`,
a subset, to cold_start_<jobs>.json). `--quick` skips the 14,464-candidate grid.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time

import numpy as np

from mfmjax._persist import json_safe

HERE = os.path.dirname(os.path.abspath(__file__))
T_CLI = 3000
CLI_GRID = dict(n="1:2", N="3:5", M="3:5", h=[float(v) for v in np.linspace(40, 250, 18)])
IDENTIFY = dict(n=2, m=(1, 1), N=4, M=4, h=120.0)
MODES = ("no cache", "cold", "warm")
JOBS = ("demo", "search", "identify", "output_error", "refine", "online", "lib")


def lib_grid(quick: bool) -> dict:
    """search_throughput.py's grid (quick: its 760-candidate one)."""
    hs = np.linspace(40, 250, 4 if quick else 16)
    NM = range(3, 6) if quick else range(3, 9)
    return dict(n=(1, 2, 3, 4), N=tuple(NM), M=tuple(NM), h=tuple(float(v) for v in hs))


# -- children (run in fresh processes) --------------------------------------------------------


def child_lib(quick: bool) -> dict:
    t0 = time.perf_counter()
    import mfmjax

    if os.environ.get("JAX_COMPILATION_CACHE_DIR"):
        mfmjax.enable_compile_cache()
    sys.path.insert(0, HERE)
    from search_throughput import noisy

    t1 = time.perf_counter()
    sig = noisy(8000)
    t2 = time.perf_counter()
    grid = lib_grid(quick)
    res = mfmjax.search(sig, score="J", simulate=False, **grid)
    t3 = time.perf_counter()
    res2 = mfmjax.search(sig, score="J", simulate=False, **grid)
    t4 = time.perf_counter()
    assert len(res2) == len(res)
    return {"import_s": t1 - t0, "data_s": t2 - t1, "first_s": t3 - t2, "second_s": t4 - t3,
            "candidates": len(res), "compile_s_reported": res.compile_s}


def child_peer(job: str, csv: str | None) -> dict:
    t0 = time.perf_counter()
    sys.path.insert(0, HERE)
    import numpy_shared_peer as peer

    t1 = time.perf_counter()
    if job == "cli":
        data = np.loadtxt(csv, delimiter=",", skiprows=1)
        y, u, dt, modes = data[:, 1], data[:, 2:], 1.0, ("foh", "zoh")
        lo, hi = (int(v) for v in CLI_GRID["N"].split(":"))
        n_lo, n_hi = (int(v) for v in CLI_GRID["n"].split(":"))
        grid = dict(n=range(n_lo, n_hi + 1), N=range(lo, hi + 1), M=range(lo, hi + 1),
                    h=CLI_GRID["h"])
    else:
        from search_throughput import noisy  # data set-up, not counted in run_s

        sig = noisy(8000)
        y, u, dt, modes = np.asarray(sig.y), np.asarray(sig.u), sig.dt, sig.intersample
        grid = lib_grid(job == "small")
    t2 = time.perf_counter()
    res = peer.search(y, u, dt, modes, **grid)
    t3 = time.perf_counter()
    return {"import_s": t1 - t0, "data_s": t2 - t1, "run_s": t3 - t2,
            "candidates": int(len(res["n"]))}


def child_peer_identify(csv: str) -> dict:
    t0 = time.perf_counter()
    sys.path.insert(0, HERE)
    import numpy_mfm

    data = np.loadtxt(csv, delimiter=",", skiprows=1)
    theta = numpy_mfm.identify(data[:, 1], data[:, 2:], 1.0, ("foh", "zoh"), IDENTIFY["n"],
                               list(IDENTIFY["m"]), IDENTIFY["N"], IDENTIFY["M"], IDENTIFY["h"])
    assert np.all(np.isfinite(theta))
    return {"run_s": time.perf_counter() - t0}


def _csv_signals(csv: str):
    data = np.loadtxt(csv, delimiter=",", skiprows=1)
    return data[:, 1], data[:, 2:]


def _first_and_second(csv: str, fit) -> dict:
    """Import mfmjax (its cache on when the parent set a folder), read the CSV, the MFM start
    (`identify`), then `fit(mfmjax, signals, start)` twice: the seconds of each stage and the
    two results."""
    t0 = time.perf_counter()
    import mfmjax

    if os.environ.get("JAX_COMPILATION_CACHE_DIR"):
        mfmjax.enable_compile_cache()
    t1 = time.perf_counter()
    y, u = _csv_signals(csv)
    sig = mfmjax.Signals(y, u, dt=1.0, intersample=("foh", "zoh"))
    start = mfmjax.identify(sig, mfmjax.Structure(IDENTIFY["n"], IDENTIFY["m"]),
                            mfmjax.ModulatingFunction(IDENTIFY["N"], IDENTIFY["M"],
                                                      IDENTIFY["h"]))
    t2 = time.perf_counter()
    first = fit(mfmjax, sig, start)
    t3 = time.perf_counter()
    second = fit(mfmjax, sig, start)
    t4 = time.perf_counter()
    return {"import_s": t1 - t0, "data_s": t2 - t1, "first_s": t3 - t2,
            "second_s": t4 - t3}, first, second


def child_oe(csv: str) -> dict:
    times, fit, again = _first_and_second(csv, lambda mfmjax, sig, start: mfmjax.output_error(
        sig, start))
    assert fit.converged and np.array_equal(fit.theta, again.theta)
    return dict(times, E=float(fit.E))


def child_refine(csv: str) -> dict:
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # max_steps reached: the steps are what is timed
        times, r, again = _first_and_second(csv, lambda mfmjax, sig, start: mfmjax.refine(
            sig, start, vary=("h",), max_steps=5))
    assert np.array_equal(r.path, again.path)
    return dict(times, steps=r.steps, h=r.settings["h"])


def child_peer_oe(csv: str) -> dict:
    from types import SimpleNamespace

    t0 = time.perf_counter()
    sys.path.insert(0, HERE)
    import numpy_mfm
    from interactive import scipy_output_error

    t1 = time.perf_counter()
    y, u = _csv_signals(csv)
    n, m = IDENTIFY["n"], list(IDENTIFY["m"])
    theta = numpy_mfm.identify(y, u, 1.0, ("foh", "zoh"), n, m, IDENTIFY["N"], IDENTIFY["M"],
                               IDENTIFY["h"])
    a = theta[: n + 1] / theta[n]
    b = [theta[n + 1 + sum(mk + 1 for mk in m[:k]):][: m[k] + 1] / theta[n] for k in range(2)]
    start = SimpleNamespace(n=n, a=a, b=b)
    t2 = time.perf_counter()
    _, E, status = scipy_output_error(y, u, 1.0, ("foh", "zoh"), start)
    t3 = time.perf_counter()
    assert status > 0, status
    return {"import_s": t1 - t0, "data_s": t2 - t1, "run_s": t3 - t2, "E": E}


# -- parent -----------------------------------------------------------------------------------


def _env(mode: str | None, cache: str | None) -> dict:
    env = {k: v for k, v in os.environ.items()
           if k not in ("JAX_COMPILATION_CACHE_DIR", "MFMJAX_NO_COMPILE_CACHE")}
    if mode == "no cache":
        env["MFMJAX_NO_COMPILE_CACHE"] = "1"
    elif mode is not None:
        env["JAX_COMPILATION_CACHE_DIR"] = cache
    return env


def _run(cmd, env, cwd) -> tuple[float, str]:
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, env=env, cwd=cwd, capture_output=True, text=True, timeout=1800)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed:\n{proc.stderr[-3000:]}")
    return wall, proc.stdout


def _child(args: list[str], env, cwd) -> tuple[float, dict]:
    wall, out = _run([sys.executable, os.path.abspath(__file__), "--child", *args], env, cwd)
    line = [v for v in out.splitlines() if v.startswith("RESULT ")][-1]
    return wall, json.loads(line[len("RESULT "):])


def _dir_size(path: str) -> tuple[int, float]:
    files = [os.path.join(path, f) for f in os.listdir(path)] if os.path.isdir(path) else []
    files = [f for f in files if f.endswith("-cache")]
    return len(files), sum(os.path.getsize(f) for f in files) / 1e6


def write_csv(path: str) -> None:
    import mfmjax
    from mfmjax.datasets import paper_table3_model1, simulated_experiment

    sig = simulated_experiment(paper_table3_model1(), dt=1.0, n_samples=T_CLI, seed=1)
    y = np.asarray(sig.y)
    y = y + 0.01 * np.std(y) * np.random.default_rng(2).standard_normal(T_CLI)
    t = np.arange(T_CLI) * 1.0
    np.savetxt(path, np.column_stack([t, y, np.asarray(sig.u)]), delimiter=",",
               header="time,y,u1,u2", comments="")
    del mfmjax


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="skip the 14,464-candidate grid")
    ap.add_argument("--child", nargs="+", help=argparse.SUPPRESS)
    ap.add_argument("--jobs", default=",".join(JOBS),
                    help=f"comma-separated subset of {','.join(JOBS)} (default: all)")
    args = ap.parse_args()
    jobs = args.jobs.split(",")
    if not set(jobs) <= set(JOBS):
        ap.error(f"--jobs: unknown {sorted(set(jobs) - set(JOBS))}; choose from {JOBS}")
    if args.child:
        kind = args.child[0]
        if kind == "lib":
            res = child_lib(args.child[1] == "small")
        elif kind == "peer":
            res = child_peer(args.child[1], args.child[2] if len(args.child) > 2 else None)
        elif kind == "oe":
            res = child_oe(args.child[1])
        elif kind == "refine":
            res = child_refine(args.child[1])
        elif kind == "peer_oe":
            res = child_peer_oe(args.child[1])
        else:
            res = child_peer_identify(args.child[1])
        print("RESULT " + json.dumps(res))
        return

    exe = shutil.which("mfmjax")
    cli = [exe] if exe else [sys.executable, "-c",
                             "import sys; from mfmjax._cli import main; sys.exit(main())"]
    work = tempfile.mkdtemp(prefix="mfmjax-cold-")
    csv = os.path.join(work, "record.csv")
    write_csv(csv)
    search_cmd = cli + ["search", csv, "--output", "y", "--inputs", "u1,u2", "--time", "time",
                        "--intersample", "foh,zoh", "--n", CLI_GRID["n"],
                        "--N", CLI_GRID["N"], "--M", CLI_GRID["M"],
                        "--h", ",".join(f"{v:g}" for v in CLI_GRID["h"]), "--score", "J",
                        "--top", "3"]
    identify_cmd = cli + ["identify", csv, "--output", "y", "--inputs", "u1,u2", "--time",
                          "time", "--intersample", "foh,zoh", "--n", str(IDENTIFY["n"]),
                          "--m", ",".join(map(str, IDENTIFY["m"])), "--N", str(IDENTIFY["N"]),
                          "--M", str(IDENTIFY["M"]), "--h", str(IDENTIFY["h"])]
    demo_cmd = cli + ["demo", "--out", os.path.join(work, "demo")]
    fh1 = os.path.join(work, "forehearth1.csv")
    online_cmd = cli + ["online", fh1, "--output", "zone_temperature", "--inputs",
                        "previous_zone_temperature,mixture_pressure", "--time", "time",
                        "--delays", "265,0"]
    out = {"machine": {"cpus": os.cpu_count(), "load_start": os.getloadavg()},
           "jobs": {}, "notes": []}
    rows = []

    def cli_job(name, cmd):
        res = {}
        cache = os.path.join(work, f"cache-{name}")
        for mode in MODES:
            wall, stdout = _run(cmd, _env(mode, cache), work)
            res[mode] = {"wall_s": wall}
            if name == "search":
                res[mode]["first_line"] = stdout.splitlines()[0]
            if mode == "cold":
                res["cache_files"], res["cache_mb"] = _dir_size(cache)
            print(f"  {name:<10} {mode:<9} {wall:7.2f} s", flush=True)
        return res

    def lib_job(label, child, cache_name, note):
        """A library child in each mode (first and second call), one cache folder."""
        res = {}
        cache = os.path.join(work, cache_name)
        for mode in MODES:
            wall, r = _child(child, _env(mode, cache), work)
            res[mode] = dict(r, wall_s=wall)
            if mode == "cold":
                res["cache_files"], res["cache_mb"] = _dir_size(cache)
            print(f"  {label:<6} {mode:<9} first {r['first_s']:7.2f} s  second "
                  f"{r['second_s']:6.3f} s  import {r['import_s']:5.2f} s  ({note(r)})",
                  flush=True)
        return res

    print("CLI jobs (wall time of a new process, import included):", flush=True)
    if "demo" in jobs:
        out["jobs"]["demo"] = cli_job("demo", demo_cmd)
    if "search" in jobs:
        out["jobs"]["search_cli_810"] = cli_job("search", search_cmd)
        wall, r = _child(["peer", "cli", csv], _env(None, None), work)
        out["jobs"]["search_cli_810"]["numpy_shared_peer"] = dict(r, wall_s=wall)
        print(f"  {'peer':<10} {'search':<9} {wall:7.2f} s ({r['candidates']} candidates, run "
              f"{r['run_s']:.2f} s)", flush=True)
    if "identify" in jobs:
        out["jobs"]["identify_cli"] = cli_job("identify", identify_cmd)
        wall, r = _child(["peer_identify", csv], _env(None, None), work)
        out["jobs"]["identify_cli"]["numpy_per_candidate_peer"] = dict(r, wall_s=wall)
        print(f"  {'peer':<10} {'identify':<9} {wall:7.2f} s", flush=True)
    if "online" in jobs:
        _run(cli + ["dataset", "forehearth", "--experiment", "1", "-o", fh1], _env(None, None),
             work)
        out["jobs"]["online_cli"] = cli_job("online", online_cmd)

    if "output_error" in jobs:
        print("in-library output_error, first call in a new process:", flush=True)
        res = lib_job("oe", ["oe", csv], "cache-oe", lambda r: f"start {r['data_s']:.2f} s")
        wall, r = _child(["peer_oe", csv], _env(None, None), work)
        res["scipy_least_squares_peer"] = dict(r, wall_s=wall)
        print(f"  oe     peer      run   {r['run_s']:7.2f} s  import {r['import_s']:5.2f} s "
              f"(E {r['E']:.6g} against {res['warm']['E']:.6g})", flush=True)
        out["jobs"]["output_error_lib"] = res

    if "refine" in jobs:
        print("in-library refine, first call in a new process:", flush=True)
        out["jobs"]["refine_lib"] = lib_job("refine", ["refine", csv], "cache-refine",
                                            lambda r: f"{r['steps']} steps")

    print("in-library search, first call in a new process:", flush=True)
    for grid in (() if "lib" not in jobs else ("small",) if args.quick else ("small", "big")):
        res = lib_job(grid, ["lib", grid], f"cache-lib-{grid}",
                      lambda r: f"{r['candidates']} candidates")
        wall, r = _child(["peer", grid], _env(None, None), work)
        res["numpy_shared_peer"] = dict(r, wall_s=wall)
        print(f"  {grid:<6} peer      run   {r['run_s']:7.2f} s  import {r['import_s']:5.2f} s "
              f"({r['candidates']} candidates)", flush=True)
        out["jobs"][f"search_lib_{res['cold']['candidates']}"] = res
    out["machine"]["load_end"] = os.getloadavg()

    # table
    print(f"\n{'job':<28}{'no cache':>10}{'cold':>10}{'warm':>10}{'peer':>10}"
          f"{'warm/peer':>11}{'cold/peer':>11}")
    for key, res in out["jobs"].items():
        if key.startswith("search_lib"):
            vals = [res[m]["first_s"] for m in MODES]
            peer = res["numpy_shared_peer"]["run_s"]
            label = f"search {res['cold']['candidates']} (1st call)"
        elif key == "refine_lib":
            vals = [res[m]["first_s"] for m in MODES]
            peer = float("nan")
            label = "refine (1st call)"
        elif key == "output_error_lib":
            vals = [res[m]["first_s"] for m in MODES]
            peer = res["scipy_least_squares_peer"]["run_s"]
            label = "output_error (1st call)"
        else:
            vals = [res[m]["wall_s"] for m in MODES]
            p = res.get("numpy_shared_peer") or res.get("numpy_per_candidate_peer")
            peer = p["wall_s"] if p else float("nan")
            label = {"demo": "mfmjax demo (CLI)", "search_cli_810": "mfmjax search 810 (CLI)",
                     "identify_cli": "mfmjax identify (CLI)",
                     "online_cli": "mfmjax online (CLI)"}[key]
        res["ratio_warm_to_peer"] = vals[2] / peer
        res["ratio_cold_to_peer"] = vals[1] / peer
        rows.append((label, *vals, peer))
        print(f"{label:<28}" + "".join(f"{v:>10.2f}" for v in vals) + f"{peer:>10.2f}"
              f"{vals[2] / peer:>11.2f}{vals[1] / peer:>11.2f}")
    if "output_error_lib" in out["jobs"]:
        r = out["jobs"]["output_error_lib"]["warm"]
        print(f"output_error: warm process (second call) {r['second_s']:.3f} s")
    for key, res in out["jobs"].items():
        if key.startswith("search_lib"):
            c = res["cold"]["candidates"]
            print(f"search {c}: warm process (second call) {res['warm']['second_s']:.3f} s = "
                  f"{c / res['warm']['second_s']:.0f} candidates/s")
    out["notes"] = [
        "CLI rows and the identify peer: wall time of a new process (interpreter + imports "
        "+ work); search_lib rows: the first search call after import and data set-up; "
        "its peer: the NumPy whole-grid run time (import and data excluded).",
        "demo, online and refine have no NumPy peer.",
        "output_error rows: the first output_error call after import, data and the MFM start "
        "(identify); its peer: SciPy least_squares from the NumPy MFM start (run time).",
        "the CLI search computes E and fit for every candidate (simulation); the peer J only.",
    ]
    name = "cold_start" + ("" if set(jobs) == set(JOBS) else "_" + "_".join(jobs))
    path = os.path.join(HERE, "results", name + ".json")
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with open(path, "w") as fh:
        json.dump(json_safe(out), fh, indent=2, allow_nan=False)  # no NaN: null
    print(f"saved {path}")
    shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
