"""mfmjax's XLA compile options against XLA's defaults: compile time and warm run time per entry point.

    python benchmarks/compile_options.py [--repeats 2] [--xla-flags=FLAGS ...] [--json PATH]

mfmjax compiles its programs with `xla_cpu_use_fusion_emitters=False` (`mfmjax/_jit.py`);
`MFMJAX_XLA_DEFAULTS=1` compiles them with XLA's own defaults. Each (setting, repeat) is a fresh
Python process without a persistent cache; in it every entry point runs once (first call:
XLA compile time summed from JAX's monitoring events, and wall time) and then `WARM` more times
(median warm time). Entry points, on one 3000-sample two-input record (1 % output noise;
`mfmjax.datasets`): `identify`, `search` (248 candidates, n 1..4), `simulate`, `observe`, `srivc`,
`output_error`, `estimate` (two orders, one (N, M, h)). Prints the table and the ratios
(options / defaults; < 1 is better) and saves benchmarks/results/compile_options.json.
`--xla-flags=FLAGS` (repeatable) adds a setting per string: mfmjax's options with `XLA_FLAGS` set to it for the
whole process (e.g. "--xla_backend_optimization_level=0"), compared with mfmjax's options.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
WARM = 5
SETTINGS = {"mfmjax options": "0", "XLA defaults": "1"}


def child() -> dict:
    import collections
    import time

    import jax

    jax.config.update("jax_enable_x64", True)
    from jax._src import monitoring

    compile_s = collections.Counter()

    def listen(event, duration, **_):
        if event == "/jax/core/compile/backend_compile_duration":
            compile_s["now"] += duration

    monitoring.register_event_duration_secs_listener(listen)
    import mfmjax
    from mfmjax import ModulatingFunction, Signals, Structure
    from mfmjax.datasets import simulated_experiment, third_order_two_input

    rec = simulated_experiment(third_order_two_input(), dt=0.01, n_samples=3000,
                               x0=[0.1, 0.2, 0.3], noise_std=0.01, seed=3)
    sig = Signals(rec.y, rec.u, dt=0.01, intersample=("foh", "zoh"))
    mf, st = ModulatingFunction(4, 4, 1.5), Structure(3, [1, 0])
    model = mfmjax.identify(sig, st, mf)
    jobs = {
        "identify": lambda: mfmjax.identify(sig, st, mf).a,
        "search": lambda: mfmjax.search(sig, n=(1, 2, 3, 4), N=(4, 5), M=(4, 5), h=(1.5, 2.0),
                                        m=[(0, 1, 2), (0, 1, 2)]).row(0)["E"],
        "simulate": lambda: mfmjax.simulate(model, rec.u, dt=0.01),
        "observe": lambda: mfmjax.observe(model, sig).E,
        "srivc": lambda: mfmjax.srivc(sig, model).model.a,
        "output_error": lambda: mfmjax.output_error(sig, model).model.a,
        "estimate": lambda: mfmjax.estimate(sig, h=(1.5,), n=(2, 3), N=(4,), M=(4,),
                                            m=[(0, 1), (0,)]).model.a,
    }
    out = {}
    for name, job in jobs.items():
        compile_s["now"] = 0.0
        t0 = time.perf_counter()
        jax.block_until_ready(job())
        first = time.perf_counter() - t0
        comp = compile_s["now"]
        warm = []
        for _ in range(WARM):
            t0 = time.perf_counter()
            jax.block_until_ready(job())
            warm.append(time.perf_counter() - t0)
        out[name] = dict(first_s=first, compile_s=comp, warm_ms=1e3 * float(np.median(warm)))
    return out


def _ratio(a: float, b: float) -> str:
    return f"{a / b:.2f}" if b > 0 else "-"


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--xla-flags", action="append", default=[], metavar="FLAGS")
    ap.add_argument("--json", default=os.path.join(HERE, "results", "compile_options.json"))
    ap.add_argument("--child", action="store_true")
    args = ap.parse_args()
    if args.child:
        print(json.dumps(child()))
        return
    settings = {label: (flag, "") for label, flag in SETTINGS.items()}
    settings.update({flags: ("0", flags) for flags in args.xla_flags})
    runs = {k: [] for k in settings}
    for rep in range(args.repeats):
        for label, (flag, xla_flags) in settings.items():  # alternate: the load drifts
            env = dict(os.environ, MFMJAX_XLA_DEFAULTS=flag, MFMJAX_NO_COMPILE_CACHE="1",
                       XLA_FLAGS=xla_flags)
            env.pop("JAX_COMPILATION_CACHE_DIR", None)
            res = subprocess.run([sys.executable, __file__, "--child"], env=env, check=True,
                                 capture_output=True, text=True)
            runs[label].append(json.loads(res.stdout.strip().splitlines()[-1]))
            print(f"  repeat {rep + 1}: {label} done", flush=True)
    out = args.json
    os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
    with open(out, "w") as fh:  # raw runs first: the table below is derived from them
        json.dump(dict(repeats=args.repeats, warm_calls=WARM, runs=runs), fh, indent=1)
    names = list(runs["mfmjax options"][0])
    med = {label: {n: {k: float(np.median([r[n][k] for r in rs])) for k in rs[0][n]}
                   for n in names} for label, rs in runs.items()}
    a, b = med["mfmjax options"], med["XLA defaults"]
    print(f"\nmedian of {args.repeats} fresh processes per setting (no persistent cache)")
    print(f"{'entry point':14s} | {'compile s':>17s} | {'first call s':>17s} | {'warm ms':>19s} | "
          f"ratio compile / first / warm")
    print(f"{'':14s} | {'options  defaults':>17s} | {'options  defaults':>17s} | "
          f"{'options   defaults':>19s} |")
    for n in names:
        x, y = a[n], b[n]
        print(f"{n:14s} | {x['compile_s']:7.2f} {y['compile_s']:9.2f} | {x['first_s']:7.2f} "
              f"{y['first_s']:9.2f} | {x['warm_ms']:8.2f} {y['warm_ms']:10.2f} | "
              f"{_ratio(x['compile_s'], y['compile_s'])} / {_ratio(x['first_s'], y['first_s'])} / "
              f"{_ratio(x['warm_ms'], y['warm_ms'])}")
    tot = {label: sum(m[n]["first_s"] for n in names) for label, m in med.items()}
    print(f"{'all first calls':14s} | {'':17s} | {tot['mfmjax options']:7.2f} "
          f"{tot['XLA defaults']:9.2f} | ratio {tot['mfmjax options'] / tot['XLA defaults']:.2f}")
    for flags in args.xla_flags:  # each against mfmjax's options without it
        x = med[flags]
        comp = {label: sum(m[n]["compile_s"] for n in names) for label, m in
                ((flags, x), ("mfmjax options", a))}
        print(f"\nXLA_FLAGS={flags!r} / without (compile; warm per entry point): "
              f"all compiles {comp[flags]:.2f} / {comp['mfmjax options']:.2f} s = "
              f"{_ratio(comp[flags], comp['mfmjax options'])}; " + ", ".join(
                  f"{n} {_ratio(x[n]['compile_s'], a[n]['compile_s'])} / "
                  f"{_ratio(x[n]['warm_ms'], a[n]['warm_ms'])}" for n in names))
    with open(out, "w") as fh:
        json.dump(dict(repeats=args.repeats, warm_calls=WARM, runs=runs, median=med), fh, indent=1)


if __name__ == "__main__":
    main()
