"""Command line: `mfmjax identify|search|validate|report|online|dataset|demo ...`.

A user error (a bad option, file or value) prints one line on stderr and exits with code 2; an
unexpected internal error prints one line with a bug-report hint and exits with code 1. No
traceback reaches the user in either case (set MFMJAX_TRACEBACK=1 to see it for a bug report).
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import math
import os
import re
import sys
import time
import warnings

import numpy as np


class _UserError(Exception):
    pass


class _Parser(argparse.ArgumentParser):
    def __init__(self, *args, **kwargs):  # no abbreviations: `--delay 2` was taken as --delays
        super().__init__(*args, **{"allow_abbrev": False, **kwargs})

    def error(self, message):  # one line, exit 2, no usage dump
        raise _UserError(f"{self.prog}: {message}")


def _floats(text: str, name: str) -> list[float]:
    try:
        vals = [float(v) for v in text.split(",") if v.strip() != ""]
    except ValueError:
        raise _UserError(f"--{name}: expected comma-separated numbers, got {text!r}") from None
    bad = [v for v in vals if not math.isfinite(v)]
    if bad:
        raise _UserError(f"--{name}: {bad[0]:g} is not a finite number (got {text!r})")
    return vals


def _number(name: str, *, lo: float | None = None, lo_open: bool = False, integer: bool = False):
    """An argparse `type=`: a finite number (a whole one when `integer`) >= lo (> lo)."""
    bound = "" if lo is None else f" {'>' if lo_open else '>='} {lo:g}"
    what = f"{'an integer' if integer else 'a finite number'}{bound}"

    def convert(text: str):
        try:
            v = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}") from None
        ok = math.isfinite(v) and (not integer or v == int(v))
        if ok and lo is not None:
            ok = v > lo if lo_open else v >= lo
        if not ok:
            raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}")
        return int(v) if integer else v

    convert.__name__ = name  # argparse names the type in its own messages
    return convert


def _window(text: str, name: str) -> tuple[float, float]:
    """T0,T1: two finite times with T0 < T1."""
    vals = _floats(text, name)
    if len(vals) != 2:
        raise _UserError(f"--{name}: expected T0,T1 (two numbers), got {text!r}")
    if not vals[0] < vals[1]:
        raise _UserError(f"--{name}: T0 must be below T1 (got {text!r})")
    return vals[0], vals[1]


def _print_json(obj) -> None:
    from ._persist import json_safe

    print(json.dumps(json_safe(obj), allow_nan=False))


def _ints(text: str, name: str) -> list[int]:
    vals = _floats(text, name)
    if any(v != int(v) for v in vals):
        raise _UserError(f"--{name}: expected integers, got {text!r}")
    return [int(v) for v in vals]


def _add_model_args(p: argparse.ArgumentParser):
    """The saved model of `validate` and `report`: `MODEL FILE` or `FILE --model MODEL`."""
    p.add_argument("model", nargs="?", help="model JSON written by save_model / --save")
    p.add_argument("--model", dest="model_option", metavar="MODEL",
                   help="the model JSON, given as an option instead (FILE --model MODEL)")


def _model_path(args) -> str:
    if (args.model is None) == (args.model_option is None):
        raise _UserError("give the model JSON once: MODEL FILE, or FILE --model MODEL")
    return args.model if args.model is not None else args.model_option


def _add_data_args(p: argparse.ArgumentParser, *, online: bool = False):
    """The record's arguments; `online`: those it does not take (offset, --resample,
    --detrend) are hidden and refused by `_cmd_online`."""
    p.add_argument("file", help="CSV file with a header row")
    p.add_argument("--output", required=True, help="output column name")
    p.add_argument("--inputs", default="", help="input column names, comma separated")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--time", help="time column name (uniform sampling)")
    g.add_argument("--dt", type=_number("dt", lo=0, lo_open=True),
                   help="sampling interval (when there is no time column)")
    p.add_argument("--intersample", help="per input, comma-separated: zoh or foh; one value "
                   "for every input (default foh)")
    p.add_argument("--delays", help="per input transport delay in time units "
                   "(search: one grid per input separated by ';')")
    p.add_argument("--names", help="column names for a file without header (comma separated)")
    hide = (lambda text: argparse.SUPPRESS) if online else (lambda text: text)
    # (argparse's usage line fails on a group whose members are all hidden)
    g = p if online else p.add_mutually_exclusive_group()
    g.add_argument("--offset", action="store_true", default=None, help=hide("add a constant "
                   "offset term (default: decided from the data, see Signals(offset=None))"))
    g.add_argument("--no-offset", dest="offset", action="store_false",
                   help=hide("no offset term, whatever the data"))
    p.add_argument("--resample", type=_number("resample", lo=0, lo_open=True), metavar="DT",
                   help=hide("read a non-uniform --time column onto a uniform grid of step DT (inputs "
                   "by --intersample, the output linearly; mfmjax.resample)"))
    p.add_argument("--detrend", choices=("linear", "constant"),
                   help=hide("remove the least-squares line (or the mean) of the output and of each "
                   "input, fitted on --identify-window where the command has one (else the "
                   "whole record; validate and report reuse the lines saved with the model) "
                   "and removed from the whole record; the model is then for deviations from "
                   "them and has no offset term unless --offset (mfmjax.detrend, "
                   "Trend.apply)"))


def _add_window_args(p: argparse.ArgumentParser):
    p.add_argument("--identify-window", help="T0,T1: identify on these samples only "
                   "(default: the whole record)")
    p.add_argument("--validate-window", help="T0,T1: simulate the model there (state from the "
                   "observer over its first 20 %%) and report fit %% (data not fitted on)")


def _record_window(text: str, name: str, sig) -> tuple[float, float]:
    """A --NAME T0,T1 option that must lie inside the record (half a sample of slack)."""
    w = _window(text, name)
    end = sig.t0 + (sig.n_samples - 1) * sig.dt
    if w[0] < sig.t0 - 0.5 * sig.dt or w[1] > end + 0.5 * sig.dt:
        raise _UserError(f"--{name} {w[0]:.15g},{w[1]:.15g} must lie inside the record "
                         f"[{sig.t0:.15g}, {end:.15g}]")
    return w


def _identify_part(args, sig):
    """The identification window as (t0, t1), or None for the whole record."""
    if not args.identify_window:
        return None
    return _record_window(args.identify_window, "identify-window", sig)


def _observer_window(given, w, sig, option: str | None) -> float:
    """The initial-state observer's length on window `w` (`option`'s, None: the record):
    `given` (--observer-window), else the first `OBSERVER_FRACTION` (20 %) of the window, the
    rule of `estimate`'s hold-out blocks and of the CLI's validation lines (an observer over
    the whole window fits the state to the very data it scores: a flattering fit)."""
    from ._observers import MIN_WINDOW
    from ._selection import OBSERVER_FRACTION as share

    if given is not None:  # checked here, in the CLI's terms (the library names its argument)
        samples = round(given / sig.dt) + 1
        if samples < MIN_WINDOW or given > (w[1] - w[0]) * (1 + 1e-12):
            where = f"{option} {w[0]:.15g},{w[1]:.15g}" if option else "the record"
            raise _UserError(f"--observer-window {given:g} must hold at least {MIN_WINDOW} "
                             f"samples (>= {(MIN_WINDOW - 1) * sig.dt:g} at dt = {sig.dt:g}) "
                             f"and fit inside {where} ({w[1] - w[0]:g} long)")
        return given
    if round(share * (w[1] - w[0]) / sig.dt) + 1 < MIN_WINDOW:
        what = (f"{option} {w[0]:.15g},{w[1]:.15g}" if option else
                f"the record ({sig.n_samples} samples)")
        raise _UserError(f"{what} is too short: its first {share:.0%} (the initial-state "
                         f"observer) needs at least {MIN_WINDOW} samples; widen it to at least "
                         f"{(MIN_WINDOW - 1) * sig.dt / share:g}, or give --observer-window"
                         f" (windows are times, not sample numbers: dt = {sig.dt:g})")
    return share * (w[1] - w[0])


def _whole(sig) -> tuple[float, float]:
    return (sig.t0, sig.t0 + (sig.n_samples - 1) * sig.dt)


def _check_validation_window(args, sig) -> None:
    """--validate-window inside the record and long enough for its observer, before the fit
    (it was checked after the search, whose --save file was then written by a failed run)."""
    if args.validate_window:
        w = _record_window(args.validate_window, "validate-window", sig)
        _observer_window(None, w, sig, "--validate-window")


TIME_NAMES = ("t", "time", "Time", "TIME", "timestamp", "Timestamp", "datetime", "date")


# column names of a sample counter (DaISy files number their samples in a column "k")
INDEX_NAMES = ("k", "n", "i", "idx", "index", "Index", "sample", "samples", "Sample", "nr", "no")


def _time_column_note(args, sig) -> None:
    """On stderr: --dt gives the times while the file has a column that looks like its own
    time (a logging gap in it went unseen: the samples after it were shifted); --time names
    a sample counter (its step 1 made the model's time unit one sample, unsaid)."""
    if args.time in INDEX_NAMES and sig.dt == 1.0 and float(sig.t0).is_integer():
        print(f"note: --time {args.time} counts samples (step 1), so the model's time unit is "
              "one sample: its coefficients, delays and h are per sample; give --dt STEP "
              "instead (without --time) for the record's own time unit", file=sys.stderr)
    if args.dt is None or args.time is not None or args.names:
        return
    try:
        with open(args.file, encoding="utf-8-sig") as fh:  # the header row only
            header = [c.strip().strip('"') for c in fh.readline().lstrip("# ").split(",")]
    except (OSError, UnicodeDecodeError):
        return
    used = {args.output, *_columns(args)}
    found = [c for c in header if c in TIME_NAMES and c not in used]
    if found:
        print(f"note: --dt {args.dt:g} gives the sample times; the file's column {found[0]!r} "
              f"is not read (--time {found[0]} reads it and checks that it is uniform)",
              file=sys.stderr)


def _validation_report(args, sig, model) -> dict | None:
    """fit % and E of `model` on --validate-window, the state from the initial-state observer
    over the window's first 20 % (eq. 14, 17)."""
    if not args.validate_window:
        return None
    import mfmjax

    w = _record_window(args.validate_window, "validate-window", sig)
    ident = _identify_part(args, sig)
    # windows that only touch (0,30 and 30,45: one shared sample) are adjacent, not flagged
    overlap = ident is None or (w[0] < ident[1] and ident[0] < w[1])
    from ._observers import observation
    from ._status import Status

    ob = _observer_window(None, w, sig, "--validate-window")
    # the model's failure is not the user's: the model is still printed, the status says why
    obs = observation(model, sig, w, observer_window=ob)
    status = int(obs.status)
    if status & (Status.OVERFLOW | Status.UNOBSERVABLE):
        failed = ("the model's state is not observable on this window"
                  if status & Status.UNOBSERVABLE else  # (a singular M0 sets OVERFLOW too)
                  "the model's response overflows float64 on this window (an unstable model: "
                  "see its status)")
        return {"window": list(w), "fit": None, "E": None, "observer_window": ob,
                "overlaps_identification": bool(overlap), "failed": failed}
    a = round((w[0] - sig.t0) / sig.dt)
    y = np.asarray(sig.y)[a: a + obs.y_sim.shape[0]]
    return {"window": list(w), "fit": float(mfmjax.fit_percent(y, obs.y_sim)),
            "E": float(obs.E), "observer_window": ob,
            "overlaps_identification": bool(overlap)}


def _print_validation(v: dict | None) -> None:
    if v is not None and v.get("failed"):
        print(f"validation on [{v['window'][0]:.15g}, {v['window'][1]:.15g}]: none, {v['failed']}")
    elif v is not None:
        print(f"validation on [{v['window'][0]:.15g}, {v['window'][1]:.15g}]: fit {v['fit']:.2f} %  "
              f"E {v['E']:.4e}  (state from the observer over the first "
              f"{v['observer_window']:g}" + (
                  "; WARNING: the window overlaps the identification data)"
                  if v["overlaps_identification"] else ")"))


def _columns(args) -> list[str]:
    """The input column names; refuses an input that is the output, the time or a repeat."""
    inputs = [c.strip() for c in args.inputs.split(",") if c.strip()]
    for c in inputs:
        if c == args.output:
            raise _UserError(f"--inputs: {c!r} is also the output (--output {args.output}); an "
                             "output given as an input makes the model degenerate: drop it")
        if c == args.time:
            raise _UserError(f"--inputs: {c!r} is also the time column (--time {args.time})")
        if inputs.count(c) > 1:
            raise _UserError(f"--inputs: {c!r} is given twice; list each input once")
    if args.time is not None and args.time == args.output:
        raise _UserError(f"--time: {args.time!r} is also the output (--output {args.output})")
    return inputs


def _load_signals(args, saved=None):
    """(record as the arguments read it, the `Trend` --detrend removed or None). `saved`: the
    identification data's lines saved with the model (`_saved_lines`), removed instead of
    lines fitted on this file."""
    from ._signals import Signals

    inputs = _columns(args)
    kwargs = {}
    if args.intersample:
        kwargs["intersample"] = _intersample(args, len(inputs))
    if args.delays:
        kwargs["delays"] = _floats(args.delays, "delays")
    if args.time is None and args.dt is None:
        raise _UserError("give --time COLUMN or --dt STEP (the sampling interval, in the "
                         "data's time unit)")
    if getattr(args, "resample", None) is not None:
        if args.time is None:
            raise _UserError(f"--resample {args.resample:g}: needs --time COLUMN (the sample "
                             "times to read the record at), not --dt")
        kwargs["resample"] = args.resample
    sig = Signals.from_csv(
        args.file,
        output=args.output,
        inputs=inputs,
        time=args.time,
        dt=args.dt,
        offset=args.offset,
        names=[c.strip() for c in args.names.split(",")] if args.names else None,
        **kwargs,
    )
    _time_column_note(args, sig)
    if getattr(args, "detrend", None):
        from ._prepare import detrend

        part = _identify_part(args, sig) if getattr(args, "identify_window", None) else None
        if saved is not None:  # validate/report: the model's own lines
            trend = saved
            sig = trend.apply(sig, offset=bool(args.offset))
            if trend.kind == "linear" and _another_clock(args, sig, trend.t0):
                # the lines are read at this file's times: from 0 under --dt (the DaISy
                # heater's hold-out file: fit 58.3 % under --dt 2, 21.5 % under --time time)
                print(f"warning: --detrend linear: the model's lines start at t={trend.t0:.15g} "
                      f"and are evaluated at this file's times, which start at "
                      f"t={sig.t0:.15g}" + (" (--dt: the first row is t=0)" if args.time is None
                                            else "") +
                      ": the result depends on where the file's times put it on those lines; "
                      "give --time COLUMN with times on the identification record's clock (in "
                      "both commands), or use --detrend constant", file=sys.stderr)
        elif part is None:
            sig, trend = detrend(sig, args.detrend, offset=bool(args.offset))
        else:  # the lines from the identification data only, removed from the whole record:
            # fitted over the whole file they also saw the --validate-window's data
            trend = detrend(sig.window(*part), args.detrend, offset=bool(args.offset))[1]
            sig = trend.apply(sig, offset=bool(args.offset))
        lines = [(sig.output_name, trend.y_level, trend.y_slope)] + list(
            zip(sig.input_names, trend.u_level, trend.u_slope))
        text = ", ".join(f"{n} {float(c):.6g}" + (f"{float(s):+.6g}*(t-{trend.t0:.15g})"
                                                    if trend.kind == "linear" else "")
                         for n, c, s in lines)
        where = (" (the model's identification data's, saved with it)" if saved is not None
                 else f" (fitted on --identify-window {part[0]:.15g},{part[1]:.15g})" if part
                 else " (fitted on this file: the model file holds no lines of this kind)"
                 if hasattr(args, "model") else "")
        print(f"note: --detrend {args.detrend}: removed {text}{where}; the model is for "
              "deviations from these lines", file=sys.stderr)
        return sig, trend
    return sig, None


def _saved_record(path: str):
    """The `record` of a model file (how its identification data were read), or None;
    `load_model` has read and checked the file."""
    with open(path, "rb") as fh:
        return json.loads(fh.read().decode("utf-8")).get("record")


def _saved_lines(path: str, args):
    """The lines --detrend removed from the model's identification data (`save_model`'s
    record), when this command detrends the same way; else None."""
    from ._prepare import Trend

    if not getattr(args, "detrend", None):
        return None
    saved = _saved_record(path)
    trend = saved.get("trend") if isinstance(saved, dict) else None
    if not isinstance(trend, dict) or trend.get("kind") != args.detrend:
        return None
    return Trend.from_dict(trend)


def _offset_note(sig) -> None:
    """The default offset rule's decision and why (`Signals.offset_note`), on stderr as the
    detrend note: the model it shapes is printed without it (a heater record whose rule could
    not decide the term came back 35-43 % off with status ok and nothing said)."""
    from ._signals import DETRENDED

    if sig.offset_note and DETRENDED not in sig.offset_note:  # --detrend said it
        print(f"note: {sig.offset_note}", file=sys.stderr)


def _no_inputs_note(args) -> None:
    """On stderr: without --inputs the model is the output's alone (its free response), while
    the file may hold the inputs the user meant (a forgotten --inputs gave an autonomous model
    of the DaISy dryer's y1 with nothing said)."""
    if _columns(args):
        return
    from ._signals import read_csv

    names = [c.strip() for c in args.names.split(",")] if args.names else None
    unused = [c for c in read_csv(args.file, names, used=()) if c not in (args.output, args.time)]
    if unused:
        print(f"note: no --inputs: a model of {args.output} alone (its free response from the "
              f"observed initial state); the file's columns {', '.join(unused)} are not used "
              "(give --inputs to model their effect)", file=sys.stderr)


def _writable_folder(option: str, path) -> None:
    """Said before the run, not after it (a long stream's work was lost; validate printed
    `[Errno 2] No such file or directory`)."""
    folder = os.path.dirname(os.path.abspath(path)) if path else None
    if folder and not (os.path.isdir(folder) and os.access(folder, os.W_OK)):
        raise _UserError(f"{option} {path}: the folder {folder} does not exist or is not "
                         "writable; create it or give another path")


def _check_outputs(args) -> None:
    """The output paths of any command, before it runs (--save's folder was checked after
    the search, whose table was then lost)."""
    if getattr(args, "save", None):
        _writable_folder("--save", args.save)
    if getattr(args, "plot", None):
        if os.path.isdir(args.plot) or args.plot.endswith(("/", os.sep)):  # matplotlib wrote
            # the hidden file FOLDER/.png.png while the JSON named FOLDER/.png
            raise _UserError(f"--plot {args.plot}: it is a folder; give a file name, e.g. "
                             f"{os.path.join(args.plot, 'validation.png')}")
        if not os.path.splitext(args.plot)[1]:
            args.plot += ".png"  # what matplotlib writes; the JSON said "out" for out.png
        _writable_folder("--plot", args.plot)
    if getattr(args, "func", None) is _cmd_report and os.path.exists(args.o) and not \
            os.path.isdir(args.o):
        raise _UserError(f"-o {args.o}: a file of that name exists; report writes a folder of "
                         "figures: give a new or existing folder")


def _names_note(model, sig, path: str) -> None:
    """On stderr after the results: the saved model's column names differ from the data's (a
    heating system's model validated on a heat exchanger's columns gave fit -4857 % with
    nothing said). Models without names of their own (y, u1, ...) are not compared, unless
    the file says they are a CSV's columns (`_record`: columns really named y, u1, u2, given
    as u2, u1, gave fit 69 % against 99 % unsaid)."""
    saved = _saved_record(path)
    from_file = isinstance(saved, dict) and "columns" in saved
    default = not from_file and model.output_name == "y" and model.input_names == tuple(
        f"u{k + 1}" for k in range(model.n_inputs))
    if not default and (model.output_name, tuple(model.input_names)) != (
            sig.output_name, tuple(sig.input_names)):
        print(f"note: the model was identified from {model.output_name} <- "
              f"{', '.join(model.input_names)}; these data are {sig.output_name} <- "
              f"{', '.join(sig.input_names)}: check the columns and their order", file=sys.stderr)


def _record(args, sig, trend) -> dict:
    """How the identification data were read, saved with the model (`save_model`): with
    --detrend, the lines removed (validate and report remove the same ones), the file, its
    time column (None: --dt) and first time: the clock the lines are on (`_another_clock`)."""
    out = {"dt": sig.host_dt, "detrend": getattr(args, "detrend", None),
           "columns": [sig.output_name, *sig.input_names]}  # the CSV's own names
    if trend is None:
        return out
    return {**out, "trend": trend.to_dict(), "file": os.path.abspath(args.file),
            "time": args.time, "start": float(sig.t0)}


def _another_clock(args, sig, lines_t0: float) -> bool:
    """Whether this file's times may not be the identification record's clock, on which the
    saved linear lines were fitted: the same file read from another first time; another
    file where either command read no time column (--dt counts from 0 in each file), or whose
    times start before the lines do (a hold-out log whose clock restarts at 0: fit -788 %,
    unsaid, a review); a record saved before 2026-11-28 (no clock saved): --dt, or times
    before the lines' start."""
    saved = _saved_record(_model_path(args)) or {}
    before = float(sig.t0) < lines_t0 - 0.5 * sig.host_dt
    if "time" not in saved:
        return args.time is None or before
    try:
        same = os.path.samefile(saved.get("file", ""), args.file)
    except OSError:
        same = False
    if same:  # (an earlier stretch of the same record is on its clock)
        return float(sig.t0) != saved.get("start")
    return args.time is None or saved["time"] is None or before


def _record_note(path: str, args, sig) -> None:
    """On stderr: the data given to validate/report were read unlike the model's
    identification data (saved by identify/search --save): --detrend differs (a model of
    detrended data on the raw record gave fit -23434 % with nothing said), or the sampling
    step differs tenfold or more (a time column in minutes against seconds)."""
    saved = _saved_record(path)
    if not isinstance(saved, dict):
        return
    was, now = saved.get("detrend"), getattr(args, "detrend", None)
    if was != now:
        print("note: the model was identified on data read "
              + (f"with --detrend {was} (the model is for deviations from those lines)"
                 if was else "without --detrend")
              + f"; these data are read {f'with --detrend {now}' if now else 'as they are'}: "
              + (f"give --detrend {was} as then" if was else "drop --detrend"), file=sys.stderr)
    dt = saved.get("dt")
    if isinstance(dt, (int, float)) and dt > 0 and max(dt / sig.host_dt, sig.host_dt / dt) >= 10:
        print(f"note: the model was identified on data sampled at dt={dt:g}; these data have "
              f"dt={sig.host_dt:g}: if their time columns are in different units (s and min), "
              "convert one: the model's coefficients and delays are in its data's time unit; "
              f"if --time names a sample counter, read the file with --dt {dt:g} instead (the "
              "fit below compares the model on a time axis it was not made for)",
              file=sys.stderr)


def _intersample(args, K: int) -> list[str]:
    """--intersample as one rule per input: one value is every input's (`--intersample zoh`
    on three inputs, as the record line advises, was refused: "needs one entry per input")."""
    rules = [v.strip() for v in args.intersample.split(",")]
    return rules * K if len(rules) == 1 else rules


def _model_settings_note(args, model) -> None:
    """On stderr: --delays or --intersample given to validate/report differ from the saved
    model's, which are used (they were ignored without a word)."""
    for option, given, own in (
            ("--delays", args.delays and _floats(args.delays, "delays"),
             [float(v) for v in np.asarray(model.delays)]),
            ("--intersample", args.intersample and _intersample(args, len(model.intersample)),
             list(model.intersample))):
        if given and list(given) != own:
            print(f"note: {option} {','.join(map(str, given))} is not used: the model's own "
                  f"({','.join(f'{v:g}' if isinstance(v, float) else v for v in own)}) are, "
                  "as it was identified with them", file=sys.stderr)
    if getattr(args, "offset", None) is not None and bool(args.offset) != model.has_offset:
        print(f"note: --{'offset' if args.offset else 'no-offset'} is not used: the model "
              f"{'has' if model.has_offset else 'has no'} offset term of its own, which is "
              "used as identified", file=sys.stderr)


def _cmd_identify(args):
    import mfmjax

    full, trend = _load_signals(args)
    ident = _identify_part(args, full)
    _check_validation_window(args, full)
    sig = full if ident is None else full.window(*ident)
    m = _ints(args.m, "m") if args.m else [0] * sig.n_inputs
    structure = mfmjax.Structure(args.n, m).for_inputs(sig.n_inputs)
    mf = mfmjax.ModulatingFunction(args.N, args.M, args.h)
    with warnings.catch_warnings(record=True) as caught:  # the status is in the summary
        warnings.simplefilter("always")
        model = mfmjax.identify(sig, structure, mf)
    report = _refine_report(sig, model, bool(args.delays)) if args.refine else None
    validation = _validation_report(args, full, report["model"] if report else model)
    cov = report.pop("covariance", None) if report else None  # saved for report's bands
    joint = report.pop("joint_covariance", None) if report else None  # (with the delays')
    if args.save:
        from ._analysis import usable_covariance, usable_joint
        from ._persist import save_model

        saved = report["model"] if report else model
        save_model(saved, args.save, covariance=usable_covariance(saved, cov),
                   joint_covariance=usable_joint(saved, joint), record=_record(args, sig, trend))
    _offset_note(full)  # after the work: a user error stays one line
    _no_inputs_note(args)
    for w in caught:  # what the status alone does not say (the inputs that are dependent)
        if str(w.message).startswith("identify(): the inputs"):
            print(f"warning: {_first_line(w.message)}", file=sys.stderr)
    if args.json:
        out = model.to_dict()
        if report:
            # the model validated and saved (the top level is the MFM estimate it started from)
            out["refined"] = {**{k: v for k, v in report.items() if k != "model"},
                              "model": report["model"].to_dict()}
        if validation:
            out["validation"] = validation
        _print_json(out)
    else:
        print(f"{args.file}: {_record_text(args, sig)}")
        print(model.summary())
        if report and "summary" in report:
            print("\n" + report["summary"])
        elif report:
            _print_report(report)
        _print_validation(validation)


def _record_text(args, sig) -> str:
    """The record as read: samples, step, inputs and how each is read between samples (the
    rule changes the model: the DaISy dryer's b_10 moves 28 % between zoh and foh)."""
    text = f"{sig.n_samples} samples, dt={sig.dt:g}, K={sig.n_inputs}"
    if sig.n_inputs:
        text += f", inputs read as {','.join(sig.intersample)} between samples"
        if not args.intersample:
            text += " (the default; --intersample zoh for inputs held between samples)"
    return text


def _refine_report(sig, model, vary_delays: bool) -> dict:
    """refine (h, N, M[, delays]) by BFGS on E, then output-error LM on the parameters; E of
    eq. 17 of the three models (NaN for a model whose state cannot be observed on the data,
    e.g. an unstable one: the report was lost to an error that advised a shorter window)."""
    import mfmjax

    def E(m) -> float:
        try:
            return float(mfmjax.performance_index(m, sig))
        except ValueError:
            return float("nan")

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        vary = ("h", "N", "M") + (("delays",) if vary_delays else ())
        r = mfmjax.refine(sig, model, vary=vary)
    said = [str(w.message) for w in caught if str(w.message).startswith("refine(): ")]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        # delays fitted here count in the std errors (as known they came out 0.43-0.52 of
        # the estimates' spread on a 10 dB record)
        oe = mfmjax.output_error(sig, r.model, delay_uncertainty=vary_delays)
    return {
        "model": oe.model, "settings": r.settings, "start_settings": r.start_settings,
        "refine_result": r.result, "refine_steps": r.steps, "refine_warnings": said,
        "refine_improved": r.improved, "E_mfm": E(model),
        # eq. 17 as the two before it (output error's own criterion, its fitted x0's squared
        # residuals, was printed under that name)
        "E_refined": E(r.model), "E_output_error": E(oe.model), "output_error_result": oe.result,
        "output_error_converged": oe.converged, "output_error_stabilised": oe.stabilised,
        # what OutputErrorFit.summary() says and the warnings silenced above said
        "output_error_unstable": bool(int(oe.model.status) & int(mfmjax.Status.UNSTABLE)),
        "undetermined": [n for n, e in zip(oe.names, oe.std_errors) if not math.isfinite(e)],
        "parameters": {name: {"value": float(v), "std_error": float(e)}
                       for name, v, e in zip(oe.names, oe.theta, oe.std_errors)},
        "covariance": oe.covariance, "joint_covariance": oe.joint_covariance,
        "delay_std_errors": _delay_std_json(oe.delay_std_errors),
    }


def _delay_std_json(errors):
    """Each input's delay std error for JSON: null where none was counted (none fitted, or
    all of them 0), and null for an input whose delay was not."""
    if errors is None or not np.any(np.isfinite(errors)):
        return None
    return [float(v) if math.isfinite(v) else None for v in errors]


def _print_report(rep: dict) -> None:
    s = rep["settings"]
    delays = ",".join(f"{d:.4g}" for d in s["delays"]) if s["delays"] else "-"
    print(f"\nrefined settings (BFGS on E: {rep['refine_result']}, {rep['refine_steps']} steps"
          f"{'' if rep['refine_improved'] else ', no improvement: the start kept'}): "
          f"N={s['N']:.4g} M={s['M']:.4g} h={s['h']:.5g} delays={delays}")
    for text in rep["refine_warnings"]:  # (they were silenced: a stall read "successful")
        print(f"note: {text}")
    E = [f"{rep[k]:.6g}" if math.isfinite(rep[k]) else "undefined"
         for k in ("E_mfm", "E_refined", "E_output_error")]
    print(f"E (eq. 17) on the data fitted, the state observed over all of them: MFM {E[0]} -> "
          f"refined settings {E[1]} -> output error {E[2]} ({rep['output_error_result']})")
    if "undefined" in E:
        print("note: E is undefined where the model's state cannot be observed on the data "
              "(an unstable model: see its status)")
    if not rep["output_error_converged"]:
        print(f"WARNING: output error NOT CONVERGED ({rep['output_error_result']}); the parameters "
              "below are its best iterate and their standard errors are not trustworthy")
    if rep["output_error_stabilised"]:
        print("note: the refined MFM model was unstable; its right-half-plane poles were mirrored "
              "before the output-error fit")
    if rep["output_error_unstable"]:
        print("WARNING: the output-error model is UNSTABLE (a root of A(s) with Re >= 0): "
              "validate it before use")
    if rep["undetermined"]:
        print(f"WARNING: NOT DETERMINED by the data (infinite std error, the value is "
              f"arbitrary): {', '.join(rep['undetermined'])}")
    print(f"{'parameter':<10}{'output error':>16}{'std. error':>14}")
    for name, p in rep["parameters"].items():
        print(f"{name:<10}{p['value']:>16.6e}{p['std_error']:>14.3e}")
    if rep["delay_std_errors"] is not None:
        for k, (d, e) in enumerate(zip(s["delays"], rep["delay_std_errors"])):
            if e is not None:
                print(f"{'delay ' + str(k + 1):<10}{d:>16.6e}{e:>14.3e}")
        print("note: the delays were fitted by refine; the standard errors include their "
              "uncertainty")


def _cmd_demo(args):
    from ._demo import demo

    demo(args.out, args.horizon, args.mode)


def _toml_settings(args) -> dict:
    """The settings of --config (a table [online] or top-level keys), finite numbers only."""
    if not args.config:
        return {}
    try:
        import tomllib
    except ImportError:  # Python 3.10
        import tomli as tomllib

    try:
        with open(args.config, "rb") as fh:
            doc = tomllib.load(fh)
    except OSError as err:
        raise _UserError(f"--config: cannot read {args.config}: {err.strerror}") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as err:
        raise _UserError(f"--config: {args.config} is not valid TOML ({err})") from None
    doc = doc.get("online", doc)
    if not isinstance(doc, dict):
        raise _UserError(f"--config: [online] in {args.config} must be a table of settings")
    for key, val in doc.items():
        for v in val if isinstance(val, list) else [val]:
            if isinstance(v, float) and not math.isfinite(v):
                raise _UserError(f"--config: {key} = {val} in {args.config}: every number must "
                                 "be finite")
    return dict(doc)


def _online_config(args, K: int, dt: float, names):
    """(OnlineConfig from --config, --delays, --intersample, the keys given explicitly)."""
    from ._online import OnlineConfig

    kwargs = _toml_settings(args)
    replaced = []  # said once the config is valid (a user error stays one line)
    for key, option, value in (
            ("delays", "--delays", args.delays and _floats(args.delays, "delays")),
            ("intersample", "--intersample", args.intersample and _intersample(args, K))):
        if value:
            if key in kwargs and list(np.atleast_1d(kwargs[key])) != list(value):
                replaced.append(f"note: {option} replaces {key} = {kwargs[key]} of --config")
            kwargs[key] = value
    from_columns = {"output_name", "input_names"}  # --output and --inputs name them
    known = set(OnlineConfig.__dataclass_fields__) - {"dt", "n_inputs"} - from_columns
    named = sorted(set(kwargs) & from_columns)
    if named:
        raise _UserError(f"--config: {', '.join(named)} come from --output and --inputs (the "
                         "CSV's columns); drop them from the config")
    bad = sorted(set(kwargs) - known)
    if bad:
        raise _UserError(f"--config: unknown setting(s) {bad}; known: {sorted(known)}" + (
            "; dt comes from --time COLUMN or --dt STEP" if "dt" in bad else ""))
    given = sorted(kwargs)
    kwargs.setdefault("input_names", names[1])
    kwargs.setdefault("output_name", names[0])
    try:
        config = OnlineConfig(dt=dt, n_inputs=K, **kwargs)
    except (OverflowError, ZeroDivisionError) as err:  # arithmetic on an extreme value
        raise _UserError(f"--config: a setting is out of range ({err})") from None
    except ValueError as err:
        if args.time and "whole number" in str(err):  # a jittered time column
            raise _UserError(f"{err}; dt={dt:g} is the median step of --time {args.time}: "
                             "give --dt with the sampling interval if the steps jitter, or "
                             "set interval in --config in the time column's unit (a "
                             "multiple of dt)") from None
        raise
    _check_memory(config)
    for note in replaced:
        print(note, file=sys.stderr)  # it did so without a word
    return config, given


# Measured: the on-line identifier's peak RSS (Table 1 settings scaled with T, n = 2, K = 2,
# through the first identification) grew by 922 MB when T went from 2,500 to 25,000 samples
# (ring buffer +180,000 samples x 3 signals x 8 bytes = 4.3 MB): 213-216 times the buffer's
# bytes in two runs (benchmarks/online_work_memory.py), rounded up here. The fixed ~0.5 GB of
# compiled programs is not counted.
_WORK_PER_BUFFER = 256


def _available_memory() -> int | None:
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None


def _check_memory(config) -> None:
    """Refuse a configuration whose buffers cannot fit in memory, before allocating anything:
    the ring buffer holds `config.buffer` samples of the output and K inputs (8 bytes each), and
    identification needs about `_WORK_PER_BUFFER` times that; refused above the memory
    available now (MemAvailable), or above 2**31 buffered samples when that is unknown."""
    samples = config.buffer
    need = samples * (config.n_inputs + 1) * 8 * _WORK_PER_BUFFER
    avail = _available_memory()
    if (avail is not None and need > avail) or samples > 2**31:
        have = "unknown" if avail is None else f"{avail / 2**30:.1f} GiB"
        raise _UserError(
            f"--config: interval = {config.interval:g} (dt = {config.dt:g}) needs a buffer of "
            f"{samples:,} samples and about {need / 2**30:.3g} GiB of memory (available: "
            f"{have}); use a shorter interval or a coarser dt"
        )


def _cmd_online(args):
    from ._online import OnlineIdentifier, load_with_extra, model_table
    from ._signals import read_csv

    given = [flag for flag, on in (("--offset/--no-offset", args.offset is not None),
                                   ("--resample", args.resample is not None),
                                   ("--detrend", args.detrend is not None)) if on]
    if given:  # shared with identify/search, not read here: refused rather than ignored
        raise _UserError(f"{given[0]}: online does not take it: it reads the record's samples "
                         "as they are, uniformly sampled, and its --config TOML sets the model "
                         "form (offset = true/false); resample or detrend the CSV first "
                         "(mfmjax.resample, mfmjax.detrend)")
    cols = read_csv(args.file, [c.strip() for c in args.names.split(",")] if args.names else None)
    inputs = _columns(args)
    for c in [args.output, *inputs] + ([args.time] if args.time else []):
        if c not in cols:
            raise _UserError(f"{args.file}: no column {c!r}; columns are {sorted(cols)}")
    if not inputs:
        raise _UserError("--inputs: the on-line identifier needs at least one input")
    y = cols[args.output]
    u = np.column_stack([cols[c] for c in inputs])
    if args.time:
        t = cols[args.time]
        if not np.all(np.isfinite(t)):
            raise _UserError(f"--time: column {args.time!r} has a NaN or inf time")
        if t.size < 2:
            raise _UserError(f"--time: column {args.time!r} has {t.size} row(s), too few to "
                             "read the sampling interval from; give more samples")
        back = np.flatnonzero(np.diff(t) <= 0)
        if back.size:  # said here by row, not as a negative dt or an update() chunk sample
            i = int(back[0]) + 1
            raise _UserError(f"--time: column {args.time!r} does not increase at data row "
                             f"{i + 1} (t={t[i]:.15g} after t={t[i - 1]:.15g}); sort the file "
                             "by time and drop repeated rows")
        dt = float(np.median(np.diff(t)))
    elif args.dt:
        dt = args.dt
        t = np.arange(y.size) * dt
    else:
        raise _UserError("give --time COLUMN or --dt STEP (the sampling interval, in the "
                         "data's time unit)")
    _writable_folder("--checkpoint", args.checkpoint)
    rows = np.arange(t.size)  # each sample's data row (0-based), for update()'s errors
    before = {"sse": 0.0, "count": 0, "intervals": 0, "predicted": 0}
    resumed = partial = False
    if args.checkpoint and os.path.exists(args.checkpoint):
        state, extra = load_with_extra(args.checkpoint)
        _check_resume(args, state.config, u.shape[1], dt, (args.output, inputs))
        ident = OnlineIdentifier(state=state)
        ident.models = list(extra.get("models", []))
        resumed = "prediction" in extra  # written by this command: it holds the errors so far
        partial = not resumed and int(state.n_closed) > 0  # written by OnlineIdentifier.save
        if resumed:
            before = {k: extra["prediction"].get(k) for k in before}  # (no "predicted"
            # in a checkpoint written before 2026-11-28: unknown)
        done = float(state.t0) + (int(state.n_seen) - 0.5) * state.config.dt
        keep = t > done  # continue after the samples the checkpoint has seen
        t, y, u, rows = t[keep], y[keep], u[keep], rows[keep]
    else:
        config, _ = _online_config(args, u.shape[1], dt, (args.output, inputs))
        ident = OnlineIdentifier(config)
    chunk = max(ident.state.config.samples, 1)
    progress = _Progress("online") if not args.json else None
    for c0 in range(0, t.size, chunk):
        try:
            ident.update(t[c0 : c0 + chunk], y[c0 : c0 + chunk], u[c0 : c0 + chunk])
        except ValueError as err:  # t[j] of the chunk: said as the file's data row (it read
            # "t[0] = 700.5" for data row 702, an audit)
            raise _UserError(re.sub(r"\bt\[(\d+)\]", lambda m: f"the time at data row "
                                    f"{int(rows[c0 + int(m.group(1))]) + 1}", str(err))) from None
        if progress is not None:
            progress(min(c0 + chunk, t.size), t.size)
    s = ident.series()
    run = dict(ident.prediction)  # this call's squared errors (the wrapper's running sums)
    total = {k: None if before[k] is None or run[k] is None else before[k] + run[k]
             for k in run}
    if args.checkpoint:  # the whole run's sums go on with the state, for the next resume
        ident.prediction = total
        ident.save(args.checkpoint)
    mse = total["sse"] / total["count"] if total["count"] else math.nan
    mse_run = run["sse"] / run["count"] if run["count"] else math.nan
    if resumed:
        scope = (f"the whole run: {before['intervals']} intervals before the checkpoint and "
                 f"{run['intervals']} in this call")
    elif partial:
        scope = (f"the {run['intervals']} intervals of this call only (the checkpoint holds no "
                 "earlier prediction errors)")
    else:
        scope = f"{run['intervals']} intervals"
    if total["predicted"] is not None and total["count"]:  # the MSE is over these alone
        scope += (f" ({total['predicted']} of them predicted)" if not resumed else
                  f" ({total['predicted']} of the {total['intervals']} predicted)")
    res = {"mse": mse, "mse_scope": scope, "mse_this_call": mse_run, "models": ident.models,
           "intervals": total["intervals"]}
    why = None
    if not total["count"]:  # say what held the first model back (the last interval's reason)
        why = ident.why_no_prediction()
        res["mse_note"] = why
    if args.plot:
        from ._plotting import plot_online

        plot_online(s, ident.models, args.plot, ylabel=args.output,
                    xlabel=args.time or "time (units of --dt)",  # the CSV column names the unit
                    title=f"on-line prediction, MSE {mse_run:.4g}"
                    + (" (this call; whole run in the text output)" if resumed else ""))
        res["plot"] = args.plot
    if args.json:
        _print_json(res)
    else:
        print(model_table(ident.models, end=ident._end()))  # (no unit: the CSV's own)
        shown = "undefined (no prediction yet)" if not total["count"] else f"{mse:.6g}"
        print(f"\nmean square prediction error: {shown} over {scope}")
        if why:
            print(why)


def _check_resume(args, config, K: int, dt: float, names) -> None:
    """Refuse a command line that contradicts the checkpoint it resumes (naming both)."""
    ck = args.checkpoint
    if config.n_inputs != K:
        raise _UserError(f"--checkpoint: {ck} was written for {config.n_inputs} input(s), "
                         f"--inputs gives {K}")
    if abs(config.dt - dt) > 1e-9 * config.dt:
        raise _UserError(f"--checkpoint: {ck} was written for dt={config.dt:g}, the data has "
                         f"dt={dt:g}")
    if (config.output_name, tuple(config.input_names)) != (names[0], tuple(names[1])):
        raise _UserError(
            f"--checkpoint: {ck} was written for output {config.output_name!r} and inputs "
            f"{list(config.input_names)}, the command line gives {names[0]!r} and {names[1]}"
        )
    if not (args.config or args.delays or args.intersample):
        return
    new, given = _online_config(args, K, config.dt, names)
    for key in given:
        old, now = getattr(config, key), getattr(new, key)
        if old != now:
            opt = f"--{key}" if key in ("delays", "intersample") else f"--config {key}"
            raise _UserError(
                f"--checkpoint: {ck} was written with {key}={_show(old)}, {opt} gives "
                f"{key}={_show(now)}; drop {opt} to resume, or start a new checkpoint file"
            )


def _show(v) -> str:
    if isinstance(v, tuple):
        return ",".join(_show(x) for x in v)
    return f"{v:g}" if isinstance(v, float) else str(v)


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
          f"(input-1 delay {d['delay'].min():.0f}-{d['delay'].max():.0f} s; the inputs are "
          f"read with --intersample {','.join(d['intersample'])}: the pressure is held)")


def _grid(text: str, name: str, integer: bool = False) -> list:
    """'a:b' (inclusive integer range) or 'a,b,c' (list)."""
    text = text.strip()
    if ":" in text:
        parts = text.split(":")
        if len(parts) != 2:
            raise _UserError(f"--{name}: expected a range a:b or a list a,b,c, got {text!r}")
        ends = [_ints(v, name) if v.strip() else [] for v in parts]
        if any(len(e) != 1 for e in ends):
            raise _UserError(f"--{name}: expected a range a:b of two integers, got {text!r}")
        lo, hi = ends[0][0], ends[1][0]
        if hi < lo:
            raise _UserError(f"--{name}: empty range {text!r} (the end is below the start)")
        if hi - lo >= _MAX_RANGE:
            raise _UserError(f"--{name}: the range {text!r} has {hi - lo + 1:,} values; at most "
                             f"{_MAX_RANGE:,} (a grid that size is not a search)")
        return list(range(lo, hi + 1))
    vals = _ints(text, name) if integer else _floats(text, name)
    if not vals:
        raise _UserError(f"--{name}: empty grid")
    return vals


_MAX_RANGE = 10_000  # values in one a:b range: refused above, before building the list


def _delays_grid_note(text, K: int) -> None:
    """A single --delays grid with several inputs is searched for each of them, where
    identify reads a list as one delay per input (and refuses a single value): say so."""
    if text and K > 1 and ";" not in text:
        values = text.split(",")
        each = f" ({';'.join(values)})" if len(values) == K else ""
        print(f"note: --delays {text} is searched as one grid for each of the {K} inputs; "
              f"for a delay per input, as identify reads it, give one grid per input separated "
              f"by ';'{each}", file=sys.stderr)


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
        self.label, self.t0, self.shown = label, time.perf_counter(), False

    def __call__(self, done: int, total: int):
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
    if args.estimate and (args.validate or args.score is not None):
        raise _UserError("--estimate ranks the structures by E on blocks held back from "
                         "--identify-window (--holdout); --validate and --score rank the plain "
                         "search: give them without --estimate")
    args.score = args.score or "E"
    sig, trend = _load_signals(args)
    _check_validation_window(args, sig)
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
    if args.validate:  # inside the record: checked before the observer that depends on it
        kwargs["validate"] = _record_window(args.validate, "validate", sig)
    if args.estimate and args.refine:
        raise _UserError("--estimate and --refine are two ways to improve the winner; give one")
    if args.estimate and args.observer_window is not None:
        raise _UserError("--observer-window sets the observer of the search's E; --estimate "
                         "ranks on its hold-out blocks with their own (their first 20 %)")
    if args.holdout is not None and not args.estimate:
        raise _UserError("--holdout is the share held back by --estimate; add --estimate")
    report = None
    ident = _identify_part(args, sig)
    held_back = (args.validate_window and ident is not None and not args.validate
                 and not args.estimate and args.score != "J")
    if held_back:  # the ranking must not see the window the validation line calls held back
        kwargs["validate"] = ident
    if not args.estimate:  # E and fit % as `validate` measures them: the state observed over
        # the first 20 % of the window they are measured on (the whole record without one)
        option = ("--validate" if args.validate else
                  "--identify-window (where the search ranks by E)" if held_back else None)
        w = kwargs.get("validate") or _whole(sig)
        try:
            kwargs["observer_window"] = _observer_window(args.observer_window, w, sig, option)
        except _UserError:
            if option or args.observer_window is not None:
                raise
            # a whole record too short for a 20 % observer: the observer over all of it (the
            # search's own default), as before 2026-11-27, said on stderr
            kwargs["observer_window"] = w[1] - w[0]
            print(f"note: the record is too short for an initial-state observer over its first "
                  f"20 %; E is measured with the state observed over all of it "
                  f"({sig.n_samples} samples)", file=sys.stderr)
    if args.estimate:  # mfmjax.estimate's path: its search table, ranked on held-back data
        kwargs.pop("score")
        kwargs.pop("validate", None)
        started = time.perf_counter()
        with warnings.catch_warnings(record=True) as caught:  # estimate's own warnings
            warnings.simplefilter("always")
            est = mfmjax.estimate(sig, identify=ident, **kwargs, **(
                {} if args.holdout is None else {"holdout": args.holdout}))
        estimate_s = time.perf_counter() - started
        for text in dict.fromkeys(str(w.message) for w in caught  # estimate's, each once
                                  if str(w.message).startswith("estimate(")):
            _one_line_warning(text, UserWarning, "", 0)
        result = est.search
        report = {"model": est.model, "method": est.method, "converged": est.converged,
                  "srivc_status": est.srivc.describe() if est.srivc is not None else "not run",
                  "selection": est.selection, "summary": est.summary(),
                  "n": est.model.n, "m": list(est.model.m), "notes": list(est.notes),
                  "parameters": {k: {"value": float(v), "std_error": float(e)} for k, v, e in
                                 zip(est.names, _free_values(est.model), est.std_errors)},
                  "delay_std_errors": _delay_std_json(est.delay_std_errors),
                  "covariance": est.covariance, "joint_covariance": est.joint_covariance}
    else:
        result = mfmjax.search(sig, progress=_Progress("search"), identify=ident, **kwargs)
    if args.refine:  # on the data the search fitted (its identification window)
        best = result.best()
        sig_best = _with_delays(sig if ident is None else sig.window(*ident), best.delays)
        report = _refine_report(sig_best, best, bool(grid_delays))
    cov = report.pop("covariance", None) if report else None  # saved for report's bands
    joint = report.pop("joint_covariance", None) if report else None  # (with the delays')
    validation = _validation_report(args, sig, report["model"] if report else result.best())
    if args.estimate and validation and validation.get("fit") is not None:
        held = [v for k, v in est.holdout.items() if k.startswith("chosen: ")]
        fit = validation["fit"]
        if held and math.isfinite(held[0]) and 100.0 - fit > 2.0 * (100.0 - held[0]):
            # (the DaISy dryer: hold-out fit 56.3 %, validation 6.05 %, nothing said)
            validation["note"] = (
                f"the validation fit ({fit:.1f} %) leaves more than twice the relative error "
                f"of the fit on the held-back estimation data ({held[0]:.1f} %): the data "
                "after the estimation window differ from it (another operating point, a "
                "disturbance, a drift); the model is valid for the estimation data's regime")
            print(f"note: {validation['note']}", file=sys.stderr)
    if args.save:  # after everything that can fail: a failed command writes no file
        from ._analysis import usable_covariance, usable_joint
        from ._persist import save_model

        saved = report["model"] if report else result.best()
        save_model(saved, args.save, covariance=usable_covariance(saved, cov),
                   joint_covariance=usable_joint(saved, joint), record=_record(args, sig, trend))
    if not args.estimate:  # estimate's notes say it, with its own decision
        _offset_note(sig)  # after the work: a user error stays one line
    _no_inputs_note(args)
    _delays_grid_note(grid_delays, K)
    if held_back:
        print(f"note: candidates ranked by {args.score} on --identify-window {ident[0]:.15g},"
              f"{ident[1]:.15g}, not on the --validate-window data (give --validate to rank on "
              "another window)", file=sys.stderr)
    if args.json:
        out = result.to_dict(top=args.top)
        if validation:
            out["validation"] = validation
        if args.estimate:
            out["score"] = "holdout E"  # the table of estimate: ranked on held-back data
            # the whole call's time, as the text output prints (the search's compile_s and
            # run_s were a part of it, and read as all of it)
            out["estimate_s"] = estimate_s
            out["search_compile_s"], out["search_run_s"] = out.pop("compile_s"), out.pop("run_s")
        else:
            out["observer_window"] = kwargs["observer_window"]
        if report:
            key = "estimated" if "summary" in report else "refined"
            out[key] = {**{k: v for k, v in report.items() if k not in ("model", "summary")},
                        "model": report["model"].to_dict()}  # the model validated and saved
        _print_json(out)
    else:
        # estimate's time is the whole call's (its last search's compile/run is a part of it)
        print(f"{args.file}: {_record_text(args, sig)}")
        print(f"{len(result)} candidates, ranked by "
              f"{'E on held-back data' if args.estimate else args.score} " + (
                  f"(estimate {estimate_s:.1f} s: search, SRIVC and output error)"
                  if args.estimate else
                  f"(compile {result.compile_s:.1f} s, run {result.run_s:.1f} s)"))
        if not args.estimate:
            w = kwargs.get("validate") or _whole(sig)
            print(f"E and fit % on [{w[0]:.15g}, {w[1]:.15g}], the state from the observer over the "
                  f"first {kwargs['observer_window']:g}")
        print(result.table(args.top))
        if report and "summary" in report:  # (rank 1 read as the model returned, which a
            # stage after MFM or another structure's hold-out score can replace)
            print(f"\nreturned: {report['method']} n={report['n']} m={report['m']} (the "
                  "table ranks the MFM candidates; the stages after MFM were compared on "
                  "held-back data, below)")
            print(report["summary"])
        elif report:
            _print_report(report)
        _print_validation(validation)


def _free_values(model):
    from ._output_error import free_parameters

    return free_parameters(model)[1]


def _with_delays(sig, delays):  # a Signals with other delays
    import equinox as eqx

    return eqx.tree_at(lambda q: q.delays, sig, delays)


def _cmd_validate(args):
    import mfmjax

    model = mfmjax.load_model(_model_path(args))
    sig, trend = _load_signals(args, _saved_lines(_model_path(args), args))
    window = _record_window(args.window, "window", sig) if args.window else None
    ob = _observer_window(args.observer_window, window or _whole(sig), sig,
                          window and "--window")
    obs = mfmjax.observe(model, sig, window, observer_window=ob)
    k0 = 0 if window is None else round((window[0] - sig.t0) / sig.dt)
    y = np.asarray(sig.y)[k0 : k0 + obs.y_sim.shape[0]]
    constant = bool(np.ptp(y) == 0)  # fit % divides by the output's variation about its mean
    fit = None if constant else float(mfmjax.fit_percent(y, obs.y_sim))
    res = {"E": float(obs.E), "fit": fit, "x0": [float(v) for v in np.asarray(obs.x_initial)],
           "x_final": [float(v) for v in np.asarray(obs.x_final)],
           "window": [sig.t0 + k0 * sig.dt, sig.t0 + (k0 + len(y) - 1) * sig.dt],
           "observer_window": ob}
    if constant:
        res["fit_note"] = (f"undefined: the measured {sig.output_name} is constant on the "
                           "window, and fit % is relative to its variation about the mean")
    if args.plot:
        _plot_validation(sig, k0, y, np.asarray(obs.y_sim), fit, args.plot,
                         _plotted_name(sig.output_name, trend))
        res["plot"] = args.plot
    if args.json:
        _print_json(res)
    else:
        print(f"window        {res['window'][0]:.15g} .. {res['window'][1]:.15g}")
        print(f"E (eq. 17)    {res['E']:.6e}")
        print(f"fit           {res['fit_note'] if constant else f'{fit:.2f} %'}")
        print(f"observer      the first {ob:g} of the window (x0 from those samples only)")
        print("x0            " + " ".join(f"{v:.6e}" for v in res["x0"]))
    _names_note(model, sig, _model_path(args))
    _model_settings_note(args, model)
    _record_note(_model_path(args), args, sig)


def _plotted_name(name: str, trend) -> str:
    """The output's name in a figure: with --detrend, as the deviation from the removed line
    it is (compare.png read "T_degC" over -70..0 for a plate near 140 degC)."""
    if trend is None:
        return name
    line = f"{float(trend.y_level):.6g}" if trend.kind == "constant" else "its line"
    return f"{name} - {line} (deviation)"


def _plot_validation(sig, k0, y, y_sim, fit, path, name):
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        raise _UserError("--plot needs matplotlib: pip install 'mfmjax[plot]'") from None
    t = sig.t0 + sig.dt * (k0 + np.arange(len(y)))
    fig, ax = plt.subplots(figsize=(8, 3.5), dpi=100)
    ax.plot(t, y, lw=1.2, label=f"measured {name}")
    label = "fit undefined" if fit is None else f"fit {fit:.1f} %"
    ax.plot(t, y_sim, lw=1.0, ls="--", label=f"simulated ({label})")
    ax.set_xlabel("time")
    ax.set_ylabel(name)
    ax.legend(loc="best")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def _cmd_report(args):
    """compare.png, residuals.png, step.png, bode.png and report.json for a model on a record."""
    import mfmjax

    from . import _analysis as an

    args.model = _model_path(args)
    model = mfmjax.load_model(args.model)
    cov, note = an.saved_covariance(args.model, model)  # the joint one where it was saved
    sig, trend = _load_signals(args, _saved_lines(args.model, args))
    window = _record_window(args.window, "window", sig) if args.window else None
    ob = _observer_window(args.observer_window, window or _whole(sig), sig,
                          window and "--window")
    # residuals first: it checks --lags before observing (a warning of the observer would
    # otherwise precede the one-line error)
    res = an.residuals(model, sig, window, observer_window=ob, lags=args.lags)
    cmp = an.compare(model, sig, window, observer_window=ob)
    if trend is not None:  # the curves are deviations from the removed line: said on the axis
        cmp = dataclasses.replace(cmp, output_name=_plotted_name(cmp.output_name, trend))
    step = an.step_response(model, covariance=cov)
    bode = an.frequency_response(model, covariance=cov)
    os.makedirs(args.o, exist_ok=True)
    files = {}
    nyquist = math.pi / float(sig.dt)  # the data's: a model says nothing reliable above it
    for name, obj in (("compare", cmp), ("residuals", res), ("step", step), ("bode", bode)):
        files[name] = os.path.join(args.o, f"{name}.png")
        obj.plot(files[name], **({"nyquist": nyquist} if name == "bode" else {}))
    rep = {"model": args.model, "data": args.file,
           "window": [float(cmp.t[0]), float(cmp.t[-1])],
           "fit": None if not math.isfinite(cmp.fit) else cmp.fit, "observer_window": ob,
           "residuals": res.to_dict(), "bands": cov is not None, "bands_note": note,
           "nyquist": nyquist,
           "figures": files}
    from ._persist import atomic_write, json_safe

    path = os.path.join(args.o, "report.json")
    atomic_write(path, (json.dumps(json_safe(rep), indent=1, allow_nan=False) + "\n").encode())
    print(cmp.summary())
    print(f"(the state from the initial-state observer over the first {ob:g} of the window)")
    print(res.summary())
    print(note)
    print(f"wrote {', '.join(os.path.basename(f) for f in files.values())} and report.json "
          f"to {args.o}")
    _names_note(model, sig, args.model)
    _model_settings_note(args, model)
    _record_note(args.model, args, sig)


def main(argv=None) -> int:
    parser = _Parser(prog="mfmjax", description="Modulating Function Method identification")
    parser.add_argument("--no-compile-cache", action="store_true", help="do not use the "
                        "persistent compilation cache (mfmjax.enable_compile_cache)")
    sub = parser.add_subparsers(dest="command", parser_class=_Parser)
    p = sub.add_parser("identify", help="identify one model from a CSV record")
    _add_data_args(p)
    p.add_argument("--n", type=_number("n", lo=1, integer=True), required=True,
                   help="output order n")
    p.add_argument("--m", help="numerator orders per input, comma separated (default 0)")
    p.add_argument("--N", type=_number("N"), required=True,
                   help="modulating function exponent N")
    p.add_argument("--M", type=_number("M"), required=True,
                   help="modulating function exponent M")
    p.add_argument("--h", type=_number("h"), required=True,
                   help="modulating function width h (time units)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--save", help="write the model to this JSON file")
    p.add_argument("--refine", action="store_true", help="refine h, N, M (and delays) by "
                   "gradient, then the parameters by output error, with standard errors")
    _add_window_args(p)
    p.set_defaults(func=_cmd_identify)
    p = sub.add_parser("search", help="batched search over orders and MF settings")
    _add_data_args(p)
    p.add_argument("--n", default="1:3", help="output orders, range a:b or list (default 1:3)")
    p.add_argument("--m", help="numerator orders, one grid per input separated by ';' "
                   "(default 0..n-1; with --estimate 0..n, feed-through included)")
    p.add_argument("--N", default="3:5", help="exponent N grid (default 3:5)")
    p.add_argument("--M", default="3:5", help="exponent M grid (default 3:5)")
    p.add_argument("--h", required=True, help="widths h, list a,b,c")
    p.add_argument("--score", default=None, choices=["E", "J", "fit", "aic", "bic"],
                   help="ranking score (default E; not with --estimate)")
    p.add_argument("--validate", help="T0,T1 validation window (default: whole record)")
    p.add_argument("--observer-window", type=_number("observer-window", lo=0, lo_open=True),
                   help="length of the initial-state observer from the start of the window E "
                   "is measured on (default: its first 20 %%; the --validate-window line keeps "
                   "its own first 20 %%)")
    p.add_argument("--top", type=_number("top", lo=1, integer=True), default=10,
                   help="rows to print")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--save", help="write the best model to this JSON file")
    p.add_argument("--refine", action="store_true", help="refine the best candidate's settings "
                   "by gradient, then its parameters by output error")
    p.add_argument("--estimate", action="store_true", help="mfmjax.estimate's path: structure "
                   "chosen on held-back data, SRIVC (and output error), standard errors")
    p.add_argument("--holdout", type=_number("holdout", lo=0, lo_open=True),
                   help="with --estimate: the share of the estimation data held back "
                   "(0.05 to 0.5, default 1/3)")
    _add_window_args(p)
    p.set_defaults(func=_cmd_search)
    p = sub.add_parser("validate", help="E, fit %% and observed x0 of a saved model on a record")
    _add_model_args(p)
    _add_data_args(p)
    p.add_argument("--window", help="T0,T1 (default: the whole record)")
    p.add_argument("--observer-window", type=_number("observer-window", lo=0, lo_open=True),
                   help="length of the initial-state observer from the window start "
                   "(default: the first 20 %% of the window)")
    p.add_argument("--plot", help="write measured vs simulated output to this PNG")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=_cmd_validate)
    p = sub.add_parser("report", help="compare, residual, step and Bode figures and "
                       "report.json of a saved model on a record")
    _add_model_args(p)
    _add_data_args(p)
    p.add_argument("-o", required=True, help="directory for the PNGs and report.json")
    p.add_argument("--window", help="T0,T1 validation window (default: the whole record)")
    p.add_argument("--observer-window", type=_number("observer-window", lo=0, lo_open=True),
                   help="length of the initial-state observer from the window start "
                   "(default: the first 20 %% of the window)")
    p.add_argument("--lags", type=_number("lags", lo=1, integer=True), default=25,
                   help="correlation lags of the residual tests (default 25)")
    p.set_defaults(func=_cmd_report)
    p = sub.add_parser("online", help="on-line identification and prediction (Algorithm 1)")
    _add_data_args(p, online=True)
    p.add_argument("--config", help="TOML file of OnlineConfig settings (e.g. interval = 250)")
    p.add_argument("--plot", help="write the prediction figure (paper's Fig. 3) to this PNG")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--checkpoint", help="resume from this state file if it exists; save to it")
    p.set_defaults(func=_cmd_online)
    p = sub.add_parser("dataset", help="write a built-in simulated dataset to CSV")
    p.add_argument("name", help="forehearth")
    p.add_argument("--experiment", type=int, default=1, choices=[1, 2])
    p.add_argument("--seed", type=_number("seed", lo=0, integer=True), default=0)
    p.add_argument("--with-pull", action="store_true", help="add the (unmeasured) pull rate")
    p.add_argument("-o", required=True, help="CSV file to write")
    p.set_defaults(func=_cmd_dataset)
    p = sub.add_parser("demo", help="run the built-in demonstration")
    p.add_argument("--out", default="mfmjax-demo", help="directory for the PNGs and JSON "
                   "(default ./mfmjax-demo)")
    p.add_argument("--horizon", type=_number("horizon", lo=2500),
                   help="stop each experiment after this many seconds (>= 2500: the first "
                   "model needs 8 intervals of 250 s)")
    p.add_argument("--mode", choices=["improved", "paper"], default="improved",
                   help="improved (default: delay tracking, forecast-ranked models) or paper "
                   "(Algorithm 1 exactly as the paper states it)")
    p.set_defaults(func=_cmd_demo)
    try:
        argv = list(sys.argv[1:] if argv is None else argv)
        no_cache = "--no-compile-cache" in argv  # accepted before or after the command
        argv = [a for a in argv if a != "--no-compile-cache"]
        # a value that starts with a minus ("--delays -5,0", "--x0 -1,2"): argparse took it
        # for an option ("expected one argument"); glued to its option it reaches the checks
        for i in range(len(argv) - 1, 0, -1):
            if re.match(r"-[\d.]", argv[i]) and argv[i - 1].startswith("--") \
                    and "=" not in argv[i - 1] and argv[i - 1] != "--":  # ("--": file names)
                argv[i - 1:i + 1] = [f"{argv[i - 1]}={argv[i]}"]
        args = parser.parse_args(argv)
        if args.command is None:
            raise _UserError("mfmjax: give a command: identify, search, validate, report, online, "
                             "dataset, demo (see --help)")
        for name, val in vars(args).items():  # argparse turns a value "--" into []
            if isinstance(val, list):
                raise _UserError(f"--{name}: expected a value, got {val!r}")
        for name in ("N", "M"):
            val = getattr(args, name, None)
            if isinstance(val, float) and abs(val) < 2**53 and val == int(val):
                setattr(args, name, int(val))
        from ._cache import disable_compile_cache, enable_compile_cache

        if no_cache:
            disable_compile_cache()
        else:
            try:
                enable_compile_cache()
            except (ValueError, OSError) as err:  # an unwritable cache folder (or another
                # process pruning it) must not stop the command
                print(f"warning: {_first_line(err)}", file=sys.stderr)
        with warnings.catch_warnings():
            warnings.showwarning = functools.partial(_one_line_warning, command=args.command)
            # its own note says which of --delays/--intersample the model's replace
            warnings.filterwarnings("ignore", message=r"observe\(\): the signals' intersample")
            # and its names note says when the columns differ from the model's (`_names_note`)
            warnings.filterwarnings("ignore", message=r"observe\(\): the record's inputs")
            _quiet_jax_callback_log()
            _check_outputs(args)
            args.func(args)
    except (_UserError, ValueError, TypeError, OSError) as err:
        print(f"error: {_first_line(err)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("error: interrupted", file=sys.stderr)
        return 130
    except MemoryError:
        print("error: out of memory; use a shorter record, a smaller grid or a shorter "
              "interval", file=sys.stderr)
        return 2
    except Exception as err:
        if os.environ.get("MFMJAX_TRACEBACK"):
            raise
        data_error = _runtime_check_message(err)  # a value check inside jit (eqx.error_if)
        if data_error is not None:
            print(f"error: {data_error}", file=sys.stderr)
            return 2
        print(f"error: internal error ({type(err).__name__}: {_first_line(err)[:200]}); this "
              "is a bug in mfmjax: please report it with the command line (run again with "
              "MFMJAX_TRACEBACK=1 for the traceback)", file=sys.stderr)
        return 1
    return 0


def _first_line(err: BaseException) -> str:
    lines = [ln.strip() for ln in str(err).splitlines() if ln.strip()]
    return lines[0] if lines else type(err).__name__


def _runtime_check_message(err: BaseException) -> str | None:
    """The message of an `eqx.error_if` check that failed inside a jitted program, if any."""
    import re

    found = re.search(r"EquinoxRuntimeError: ([^\n]+)", str(err))
    return found.group(1).strip() if found else None


def _one_line_warning(message, category, filename, lineno, file=None, line=None, *,
                      command=None):
    """A library warning on one line, its Python spelling of a window in the command's option
    (it advised "window=(t_start, t_end)" on the command line)."""
    text = " ".join(str(message).split())
    option = "--window" if command in ("validate", "report") else "--validate-window"
    text = text.replace("(window=(t_start, t_end))", f"({option} T0,T1)")
    print(f"warning: {text}", file=sys.stderr)


def _quiet_jax_callback_log() -> None:
    """A failed value check inside jit logs its own traceback through this logger: the CLI
    reports the check's message instead (one line)."""
    import logging

    logging.getLogger("jax._src.callback").setLevel(logging.CRITICAL)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
