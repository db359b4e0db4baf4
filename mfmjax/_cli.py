"""Command line: `mfmjax identify|demo ...`. User errors print one line and exit with code 2."""

from __future__ import annotations

import argparse
import json
import sys
import warnings

import numpy as np


class _UserError(Exception):
    pass


class _Parser(argparse.ArgumentParser):
    def error(self, message):  # one line, exit 2, no usage dump
        raise _UserError(f"{self.prog}: {message}")


def _floats(text: str, name: str) -> list[float]:
    try:
        return [float(v) for v in text.split(",") if v.strip() != ""]
    except ValueError:
        raise _UserError(f"--{name}: expected comma-separated numbers, got {text!r}") from None


def _ints(text: str, name: str) -> list[int]:
    vals = _floats(text, name)
    if any(v != int(v) for v in vals):
        raise _UserError(f"--{name}: expected integers, got {text!r}")
    return [int(v) for v in vals]


def _add_data_args(p: argparse.ArgumentParser):
    p.add_argument("file", help="CSV file with a header row")
    p.add_argument("--output", required=True, help="output column name")
    p.add_argument("--inputs", default="", help="input column names, comma separated")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--time", help="time column name (uniform sampling)")
    g.add_argument("--dt", type=float, help="sampling interval (when there is no time column)")
    p.add_argument("--intersample", help="per input: zoh or foh (default foh)")
    p.add_argument("--delays", help="per input transport delay in time units "
                   "(search: one grid per input separated by ';')")
    p.add_argument("--offset", action="store_true", help="add a constant offset term")
    p.add_argument("--names", help="column names for a file without header (comma separated)")


def _load_signals(args):
    from ._signals import Signals

    inputs = [c.strip() for c in args.inputs.split(",") if c.strip()]
    kwargs = {}
    if args.intersample:
        kwargs["intersample"] = [s.strip() for s in args.intersample.split(",")]
    if args.delays:
        kwargs["delays"] = _floats(args.delays, "delays")
    if args.time is None and args.dt is None:
        raise _UserError("give --time COLUMN or --dt SECONDS")
    return Signals.from_csv(
        args.file,
        output=args.output,
        inputs=inputs,
        time=args.time,
        dt=args.dt,
        offset=args.offset,
        names=[c.strip() for c in args.names.split(",")] if args.names else None,
        **kwargs,
    )


def _cmd_identify(args):
    import mfmjax

    sig = _load_signals(args)
    m = _ints(args.m, "m") if args.m else [0] * sig.n_inputs
    structure = mfmjax.Structure(args.n, m).for_inputs(sig.n_inputs)
    mf = mfmjax.ModulatingFunction(args.N, args.M, args.h)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = mfmjax.identify(sig, structure, mf)
    report = _refine_report(sig, model, bool(args.delays)) if args.refine else None
    if args.save:
        from ._persist import save_model

        save_model(report["model"] if report else model, args.save)
    if args.json:
        out = model.to_dict()
        if report:
            out["refined"] = {k: v for k, v in report.items() if k != "model"}
        print(json.dumps(out))
    else:
        print(f"{args.file}: {sig.n_samples} samples, dt={sig.dt:g}, K={sig.n_inputs}")
        print(model.summary())
        if report:
            _print_report(report)


def _refine_report(sig, model, vary_delays: bool) -> dict:
    """refine (h, N, M[, delays]) by BFGS on E, then output-error LM on the parameters."""
    import mfmjax

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        vary = ("h", "N", "M") + (("delays",) if vary_delays else ())
        r = mfmjax.refine(sig, model, vary=vary)
        oe = mfmjax.output_error(sig, r.model)
    E0 = float(mfmjax.performance_index(model, sig))
    E1 = float(mfmjax.performance_index(r.model, sig))
    return {
        "model": oe.model, "settings": r.settings, "start_settings": r.start_settings,
        "refine_result": r.result, "refine_steps": r.steps, "E_mfm": E0, "E_refined": E1,
        "E_output_error": oe.E, "output_error_result": oe.result,
        "parameters": {name: {"value": float(v), "std_error": float(e)}
                       for name, v, e in zip(oe.names, oe.theta, oe.std_errors)},
    }


def _print_report(rep: dict) -> None:
    s = rep["settings"]
    delays = ",".join(f"{d:.4g}" for d in s["delays"]) if s["delays"] else "-"
    print(f"\nrefined settings (BFGS on E: {rep['refine_result']}, {rep['refine_steps']} steps): "
          f"N={s['N']:.4g} M={s['M']:.4g} h={s['h']:.5g} delays={delays}")
    print(f"E (eq. 17): MFM {rep['E_mfm']:.6g} -> refined settings {rep['E_refined']:.6g} -> "
          f"output error {rep['E_output_error']:.6g} ({rep['output_error_result']})")
    print(f"{'parameter':<10}{'output error':>16}{'std. error':>14}")
    for name, p in rep["parameters"].items():
        print(f"{name:<10}{p['value']:>16.6e}{p['std_error']:>14.3e}")


def _cmd_demo(args):
    from ._demo import demo

    if args.horizon is not None and args.horizon < 2500:
        raise _UserError("--horizon: at least 2500 s (the first model needs 8 intervals)")
    demo(args.out, args.horizon)


def _online_config(args, K: int, dt: float, names):
    from ._online import OnlineConfig

    kwargs = {}
    if args.config:
        try:
            import tomllib
        except ImportError:  # Python 3.10
            import tomli as tomllib

        try:
            with open(args.config, "rb") as fh:
                kwargs = tomllib.load(fh)
        except OSError as err:
            raise _UserError(f"--config: cannot read {args.config}: {err.strerror}") from None
        except tomllib.TOMLDecodeError as err:
            raise _UserError(f"--config: {args.config} is not valid TOML ({err})") from None
        kwargs = kwargs.get("online", kwargs)
    if args.delays:
        kwargs["delays"] = _floats(args.delays, "delays")
    if args.intersample:
        kwargs["intersample"] = [s.strip() for s in args.intersample.split(",")]
    known = set(OnlineConfig.__dataclass_fields__) - {"dt", "n_inputs"}
    bad = sorted(set(kwargs) - known)
    if bad:
        raise _UserError(f"--config: unknown setting(s) {bad}; known: {sorted(known)}")
    kwargs.setdefault("input_names", names[1])
    kwargs.setdefault("output_name", names[0])
    return OnlineConfig(dt=dt, n_inputs=K, **kwargs)


def _cmd_online(args):
    import os

    from ._online import OnlineIdentifier, model_table
    from ._signals import read_csv

    cols = read_csv(args.file, [c.strip() for c in args.names.split(",")] if args.names else None)
    inputs = [c.strip() for c in args.inputs.split(",") if c.strip()]
    for c in [args.output, *inputs] + ([args.time] if args.time else []):
        if c not in cols:
            raise _UserError(f"{args.file}: no column {c!r}; columns are {sorted(cols)}")
    if not inputs:
        raise _UserError("--inputs: the on-line identifier needs at least one input")
    y = cols[args.output]
    u = np.column_stack([cols[c] for c in inputs])
    if args.time:
        t = cols[args.time]
        dt = float(np.median(np.diff(t))) if t.size > 1 else 1.0
    elif args.dt:
        dt = args.dt
        t = np.arange(y.size) * dt
    else:
        raise _UserError("give --time COLUMN or --dt SECONDS")
    if args.checkpoint and os.path.exists(args.checkpoint):
        ident = OnlineIdentifier.load(args.checkpoint)
        st = ident.state
        if ident.state.config.n_inputs != u.shape[1]:
            raise _UserError("--checkpoint: it was written for a different number of inputs")
        done = float(st.t0) + (int(st.n_seen) - 0.5) * st.config.dt
        keep = t > done  # continue after the samples the checkpoint has seen
        t, y, u = t[keep], y[keep], u[keep]
    else:
        ident = OnlineIdentifier(_online_config(args, u.shape[1], dt, (args.output, inputs)))
    chunk = max(ident.state.config.samples, 1)
    progress = _Progress("online") if not args.json else None
    for c0 in range(0, t.size, chunk):
        ident.update(t[c0 : c0 + chunk], y[c0 : c0 + chunk], u[c0 : c0 + chunk])
        if progress is not None:
            progress(min(c0 + chunk, t.size), t.size)
    if args.checkpoint:
        ident.save(args.checkpoint)
    mse = ident.mse()
    res = {"mse": mse if np.isfinite(mse) else None, "models": ident.models,
           "intervals": len(ident.events)}
    if args.plot:
        from ._plotting import plot_online

        plot_online(ident.series(), ident.models, args.plot, ylabel=args.output,
                    title=f"on-line prediction, MSE {mse:.4g}")
        res["plot"] = args.plot
    if args.json:
        print(json.dumps(res))
    else:
        print(model_table(ident.models, end=ident._end()))
        print(f"\nmean square prediction error: {mse:.6g} over {len(ident.events)} intervals")


def _cmd_dataset(args):
    from .datasets import forehearth

    if args.name != "forehearth":
        raise _UserError(f"dataset: unknown dataset {args.name!r}; available: forehearth")
    d = forehearth(args.experiment, seed=args.seed)
    cols = ["time", *d["names"]] + (["pull_rate"] if args.with_pull else [])
    data = np.column_stack([d["t"], d["y"], d["u"]] + ([d["pull"]] if args.with_pull else []))
    try:
        with open(args.o, "w") as fh:
            fh.write(",".join(cols) + "\n")
            for row in data:
                fh.write(",".join(repr(float(v)) for v in row) + "\n")
    except OSError as err:
        raise _UserError(f"-o: cannot write {args.o}: {err.strerror}") from None
    print(f"wrote {args.o}: {data.shape[0]} samples at 1 s, columns {', '.join(cols)} "
          f"(input-1 delay {d['delay'].min():.0f}-{d['delay'].max():.0f} s)")


def _grid(text: str, name: str, integer: bool = False) -> list:
    """'a:b' (inclusive integer range) or 'a,b,c' (list)."""
    text = text.strip()
    if ":" in text:
        parts = text.split(":")
        if len(parts) != 2:
            raise _UserError(f"--{name}: expected a range a:b or a list a,b,c, got {text!r}")
        lo, hi = (_ints(v, name)[0] if v.strip() else None for v in parts)
        if lo is None or hi is None:
            raise _UserError(f"--{name}: expected a range a:b, got {text!r}")
        if hi < lo:
            raise _UserError(f"--{name}: empty range {text!r} (the end is below the start)")
        return list(range(lo, hi + 1))
    vals = _ints(text, name) if integer else _floats(text, name)
    if not vals:
        raise _UserError(f"--{name}: empty grid")
    return vals


def _per_input_grid(text, name, K, integer):
    parts = text.split(";")
    if len(parts) == 1:
        parts = parts * K
    if len(parts) != K:
        raise _UserError(f"--{name}: give one grid per input separated by ';' ({K} inputs)")
    return [_grid(p, name, integer) for p in parts]


class _Progress:
    """A text progress bar on stderr, shown once a search has run for more than ~1.5 s."""

    def __init__(self, label: str):
        import time

        self.label, self.t0, self.shown = label, time.perf_counter(), False

    def __call__(self, done: int, total: int):
        import time

        if not self.shown and time.perf_counter() - self.t0 < 1.5 and done < total:
            return
        self.shown = True
        width = 30
        fill = int(width * done / max(total, 1))
        sys.stderr.write(f"\r{self.label} [{'#' * fill}{'.' * (width - fill)}] {done}/{total}")
        if done >= total:
            sys.stderr.write("\n")
        sys.stderr.flush()


def _cmd_search(args):
    import mfmjax

    grid_delays = args.delays
    args.delays = None
    sig = _load_signals(args)
    K = sig.n_inputs
    kwargs = dict(
        n=_grid(args.n, "n", True),
        N=_grid(args.N, "N"),
        M=_grid(args.M, "M"),
        h=_grid(args.h, "h"),
        score=args.score,
    )
    if args.m:
        kwargs["m"] = _per_input_grid(args.m, "m", K, True)
    if grid_delays:
        kwargs["delays"] = _per_input_grid(grid_delays, "delays", K, False)
    if args.validate:
        window = _floats(args.validate, "validate")
        if len(window) != 2:
            raise _UserError("--validate: expected T0,T1")
        kwargs["validate"] = tuple(window)
    result = mfmjax.search(sig, progress=_Progress("search"), **kwargs)
    report = None
    if args.refine:
        best = result.best()
        sig_best = _with_delays(sig, best.delays)
        report = _refine_report(sig_best, best, bool(grid_delays))
    if args.save:
        from ._persist import save_model

        save_model(report["model"] if report else result.best(), args.save)
    if args.json:
        out = result.to_dict(top=args.top)
        if report:
            out["refined"] = {k: v for k, v in report.items() if k != "model"}
        print(json.dumps(out))
    else:
        print(f"{len(result)} candidates, ranked by {args.score} "
              f"(compile {result.compile_s:.1f} s, run {result.run_s:.1f} s)")
        print(result.table(args.top))
        if report:
            _print_report(report)


def _with_delays(sig, delays):  # a Signals with other delays
    import equinox as eqx

    return eqx.tree_at(lambda q: q.delays, sig, delays)


def _cmd_validate(args):
    import mfmjax

    model = mfmjax.load_model(args.model)
    sig = _load_signals(args)
    window = tuple(_floats(args.window, "window")) if args.window else None
    if window is not None and len(window) != 2:
        raise _UserError("--window: expected T0,T1")
    obs = mfmjax.observe(model, sig, window)
    k0 = 0 if window is None else round((window[0] - sig.t0) / sig.dt)
    y = np.asarray(sig.y)[k0 : k0 + obs.y_sim.shape[0]]
    fit = float(mfmjax.fit_percent(y, obs.y_sim))
    res = {"E": float(obs.E), "fit": fit, "x0": [float(v) for v in np.asarray(obs.x_initial)],
           "x_final": [float(v) for v in np.asarray(obs.x_final)],
           "window": [sig.t0 + k0 * sig.dt, sig.t0 + (k0 + len(y) - 1) * sig.dt]}
    if args.plot:
        _plot_validation(sig, k0, y, np.asarray(obs.y_sim), fit, args.plot)
        res["plot"] = args.plot
    if args.json:
        print(json.dumps(res))
    else:
        print(f"window        {res['window'][0]:g} .. {res['window'][1]:g}")
        print(f"E (eq. 17)    {res['E']:.6e}")
        print(f"fit           {fit:.2f} %")
        print("x0            " + " ".join(f"{v:.6e}" for v in res["x0"]))


def _plot_validation(sig, k0, y, y_sim, fit, path):
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        raise _UserError("--plot needs matplotlib: pip install 'mfmjax[plot]'") from None
    t = sig.t0 + sig.dt * (k0 + np.arange(len(y)))
    fig, ax = plt.subplots(figsize=(8, 3.5), dpi=100)
    ax.plot(t, y, lw=1.2, label=f"measured {sig.output_name}")
    ax.plot(t, y_sim, lw=1.0, ls="--", label=f"simulated (fit {fit:.1f} %)")
    ax.set_xlabel("time")
    ax.set_ylabel(sig.output_name)
    ax.legend(loc="best")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def main(argv=None) -> int:
    parser = _Parser(prog="mfmjax", description="Modulating Function Method identification")
    sub = parser.add_subparsers(dest="command", parser_class=_Parser)
    p = sub.add_parser("identify", help="identify one model from a CSV record")
    _add_data_args(p)
    p.add_argument("--n", type=int, required=True, help="output order n")
    p.add_argument("--m", help="numerator orders per input, comma separated (default 0)")
    p.add_argument("--N", type=float, required=True, help="modulating function exponent N")
    p.add_argument("--M", type=float, required=True, help="modulating function exponent M")
    p.add_argument("--h", type=float, required=True, help="modulating function width h")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--save", help="write the model to this JSON file")
    p.add_argument("--refine", action="store_true", help="refine h, N, M (and delays) by "
                   "gradient, then the parameters by output error, with standard errors")
    p.set_defaults(func=_cmd_identify)
    p = sub.add_parser("search", help="batched search over orders and MF settings")
    _add_data_args(p)
    p.add_argument("--n", default="1:3", help="output orders, range a:b or list (default 1:3)")
    p.add_argument("--m", help="numerator orders, one grid per input separated by ';' "
                   "(default 0..n-1)")
    p.add_argument("--N", default="3:5", help="exponent N grid (default 3:5)")
    p.add_argument("--M", default="3:5", help="exponent M grid (default 3:5)")
    p.add_argument("--h", required=True, help="widths h, list a,b,c")
    p.add_argument("--score", default="E", choices=["E", "J", "fit", "aic", "bic"])
    p.add_argument("--validate", help="T0,T1 validation window (default: whole record)")
    p.add_argument("--top", type=int, default=10, help="rows to print")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--save", help="write the best model to this JSON file")
    p.add_argument("--refine", action="store_true", help="refine the best candidate's settings "
                   "by gradient, then its parameters by output error")
    p.set_defaults(func=_cmd_search)
    p = sub.add_parser("validate", help="E, fit % and observed x0 of a saved model on a record")
    _add_data_args(p)
    p.add_argument("--model", required=True, help="model JSON written by identify --save")
    p.add_argument("--window", help="T0,T1 (default: the whole record)")
    p.add_argument("--plot", help="write measured vs simulated output to this PNG")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=_cmd_validate)
    p = sub.add_parser("online", help="on-line identification and prediction (Algorithm 1)")
    _add_data_args(p)
    p.add_argument("--config", help="TOML file of OnlineConfig settings (e.g. interval = 250)")
    p.add_argument("--plot", help="write the prediction figure (paper's Fig. 3) to this PNG")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--checkpoint", help="resume from this state file if it exists; save to it")
    p.set_defaults(func=_cmd_online)
    p = sub.add_parser("dataset", help="write a built-in simulated dataset to CSV")
    p.add_argument("name", help="forehearth")
    p.add_argument("--experiment", type=int, default=1, choices=[1, 2])
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--with-pull", action="store_true", help="add the (unmeasured) pull rate")
    p.add_argument("-o", required=True, help="CSV file to write")
    p.set_defaults(func=_cmd_dataset)
    p = sub.add_parser("demo", help="run the built-in demonstration")
    p.add_argument("--out", default="mfmjax-demo", help="directory for the PNGs and JSON "
                   "(default ./mfmjax-demo)")
    p.add_argument("--horizon", type=float, help="stop each experiment after this many seconds")
    p.set_defaults(func=_cmd_demo)
    try:
        args = parser.parse_args(argv)
        if args.command is None:
            raise _UserError("mfmjax: give a command: identify, search, validate, online, "
                             "dataset, demo (see --help)")
        for name in ("N", "M"):
            val = getattr(args, name, None)
            if isinstance(val, float) and val == int(val):
                setattr(args, name, int(val))
        args.func(args)
    except (_UserError, ValueError, TypeError, OSError) as err:
        msg = str(err).splitlines()[0] if str(err) else type(err).__name__
        print(f"error: {msg}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
