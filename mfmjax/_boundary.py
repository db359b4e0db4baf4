"""Argument checks shared by the public functions (run before anything is traced).

Every checker takes the public function's name `fn` and the argument's `name`, and raises a
`ValueError` (wrong value) or `TypeError` (wrong kind) whose message names the function, the
argument, the value received and the fix, e.g.
"search(): n must be an integer >= 1 (got n=2.5); give whole orders such as n=(1, 2, 3)".
A bool is never taken as a number. JAX tracers (values under jit/vmap/grad) pass through the
value checks untouched: only their types and shapes are checked.
"""

from __future__ import annotations

import math
import numbers
import os
import sys

import jax
import numpy as np

X64_FIX = 'call jax.config.update("jax_enable_x64", True) before using mfmjax'


def require_x64(fn: str) -> None:
    """Refuse to run with JAX's float64 mode off (every result would silently be float32)."""
    if not jax.config.jax_enable_x64:
        raise RuntimeError(
            f"{fn}(): JAX float64 mode is off (jax_enable_x64=False), so every result would be "
            f"float32 (about 20 % parameter error); {X64_FIX}"
        )


def is_traced(x) -> bool:
    return isinstance(x, jax.core.Tracer)


def _show(value) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def number(fn: str, name: str, value, *, lo=None, hi=None, lo_open: bool = False,
           hi_open: bool = False, fix: str = "", traced: bool = False):
    """A finite real number (not a bool, str or array of several values) in [lo, hi].

    Returns a Python float (or the tracer itself when `traced` allows one)."""
    if traced and is_traced(value):
        return value
    if is_traced(value):
        raise TypeError(f"{fn}(): {name} is traced (inside jax.jit/jax.vmap/jax.grad), but it "
                        f"must be a concrete number here (it sets a length, a grid or a "
                        f"check on the host); pass it from outside the transformation"
                        f"{'; ' + fix if fix else ''}")
    if isinstance(value, (bool, np.bool_)) or isinstance(value, (str, bytes)):
        raise TypeError(f"{fn}(): {name} must be a number, got {type(value).__name__} "
                        f"{_show(value)}{'; ' + fix if fix else ''}")
    if isinstance(value, (np.ndarray, jax.Array)):
        if value.size != 1 or value.dtype == bool or not np.issubdtype(value.dtype, np.number):
            raise TypeError(f"{fn}(): {name} must be one number, got an array of shape "
                            f"{value.shape} ({value.dtype})")
        value = np.asarray(value).reshape(())[()]  # a NumPy scalar (a JAX one is no Real)
    if not isinstance(value, numbers.Real):
        raise TypeError(f"{fn}(): {name} must be a real number, got {type(value).__name__} "
                        f"{_show(value)}")
    v = float(value)
    bounds = ""
    if lo is not None:
        bounds += f" {'>' if lo_open else '>='} {lo:g}"
    if hi is not None:
        bounds += f"{' and' if lo is not None else ''} {'<' if hi_open else '<='} {hi:g}"
    ok = math.isfinite(v)
    if ok and lo is not None:
        ok = v > lo if lo_open else v >= lo
    if ok and hi is not None:
        ok = v < hi if hi_open else v <= hi
    if not ok:
        what = f"{bounds.strip()} and finite" if bounds else "a finite number"
        raise ValueError(f"{fn}(): {name} must be {what} (got {name}={v:g})"
                         f"{'; ' + fix if fix else ''}")
    return v


def integer(fn: str, name: str, value, *, lo=None, hi=None, fix: str = "") -> int:
    """A whole number (an int, or a float with an integral value; never a bool) in [lo, hi]."""
    if isinstance(value, (np.ndarray, jax.Array)) and value.size == 1 and np.issubdtype(
            value.dtype, np.integer):
        value = int(value.reshape(())[()])
    v = number(fn, name, value, fix=fix)
    if v != int(v):
        raise ValueError(f"{fn}(): {name} must be an integer (got {name}={v:g})"
                         f"{'; ' + fix if fix else ''}")
    v = int(v)
    if (lo is not None and v < lo) or (hi is not None and v > hi):
        rng = (f">= {lo}" if hi is None else f"in [{lo}, {hi}]") if lo is not None else f"<= {hi}"
        raise ValueError(f"{fn}(): {name} must be an integer {rng} (got {name}={v})"
                         f"{'; ' + fix if fix else ''}")
    return v


def values(fn: str, name: str, value, *, allow_empty: bool = False) -> list:
    """A scalar or a flat sequence as a list (a string or a nested sequence is refused)."""
    if isinstance(value, (str, bytes)):
        raise TypeError(f"{fn}(): {name} must be a number or a sequence of numbers, got the "
                        f"string {_show(value)}")
    if isinstance(value, (np.ndarray, jax.Array)):
        if value.ndim > 1:
            raise ValueError(f"{fn}(): {name} must be a number or a flat sequence, got an "
                             f"array of shape {value.shape}")
        out = list(np.asarray(value).reshape(-1))
    elif isinstance(value, (list, tuple, range)):
        out = list(value)
    else:
        out = [value]
    if not out and not allow_empty:
        raise ValueError(f"{fn}(): the {name} grid is empty (got {name}={_show(value)}); give "
                         "at least one value")
    return out


def numbers_(fn: str, name: str, value, **kw) -> list[float]:
    """A number or a non-empty flat sequence of numbers, each checked by `number(**kw)`."""
    return [number(fn, f"{name}[{i}]" if isinstance(value, (list, tuple, np.ndarray))
                   else name, v, **kw) for i, v in enumerate(values(fn, name, value))]


def integers(fn: str, name: str, value, **kw) -> list[int]:
    """An integer or a non-empty flat sequence of integers, each checked by `integer(**kw)`."""
    return [integer(fn, f"{name}[{i}]" if isinstance(value, (list, tuple, np.ndarray))
                    else name, v, **kw) for i, v in enumerate(values(fn, name, value))]


def window(fn: str, name: str, value):
    """None or a time window (start, end): two finite numbers with start < end."""
    if value is None:
        return None
    if any(is_traced(x) for x in jax.tree.leaves(value)):
        raise TypeError(f"{fn}(): {name} is traced (inside jax.jit/jax.vmap/jax.grad); a window "
                        "fixes how many samples are used, so give concrete times (start, end)")
    if isinstance(value, (str, bytes)) or not isinstance(
            value, (list, tuple, np.ndarray, jax.Array)):
        raise TypeError(f"{fn}(): {name} must be a pair (start, end) of times, got "
                        f"{type(value).__name__} {_show(value)}; e.g. {name}=(0.0, 100.0)")
    vals = list(np.asarray(value).reshape(-1)) if not isinstance(value, (list, tuple)) \
        else list(value)
    if len(vals) != 2:
        raise ValueError(f"{fn}(): {name} must be a pair (start, end) of times, got "
                         f"{len(vals)} value(s) {_show(value)}; e.g. {name}=(0.0, 100.0)")
    w0 = number(fn, f"{name}[0]", vals[0])
    w1 = number(fn, f"{name}[1]", vals[1])
    if not w0 < w1:
        raise ValueError(f"{fn}(): {name} must have start < end (got {name}=({w0:g}, {w1:g}))")
    return w0, w1


def array(fn: str, name: str, value, *, ndim=None, finite: bool = True,
          fix: str = "remove or interpolate non-finite samples first"):
    """A real array (not bool, str or complex) of `ndim` (int or tuple of allowed ndims).

    Returns a float64 numpy array, or the value itself when it is a tracer (dtype and ndim are
    checked; finiteness is not)."""
    if value is None:
        raise TypeError(f"{fn}(): {name} is missing (got None); give an array of samples")
    if isinstance(value, (str, bytes)):
        raise TypeError(f"{fn}(): {name} must be an array of numbers, got the string "
                        f"{_show(value)}")
    traced = is_traced(value)
    if traced or isinstance(value, (np.ndarray, jax.Array)):
        dtype = value.dtype
    else:
        try:
            dtype = np.asarray(value).dtype
        except (ValueError, TypeError):
            raise TypeError(f"{fn}(): {name} must be a rectangular array of numbers "
                            f"(got {_show(value)})") from None
    if np.issubdtype(dtype, np.bool_):
        raise TypeError(f"{fn}(): {name} is a bool array; booleans are not samples, convert "
                        f"them explicitly (e.g. {name}.astype(float))")
    if not (np.issubdtype(dtype, np.integer) or np.issubdtype(dtype, np.floating)):
        raise TypeError(f"{fn}(): {name} must hold real numbers, got dtype {dtype}")
    shape = np.shape(value)
    allowed = (ndim,) if isinstance(ndim, int) else ndim
    if allowed is not None and len(shape) not in allowed:
        want = " or ".join(f"{d}-D" for d in allowed)
        raise ValueError(f"{fn}(): {name} must be {want}, got shape {shape}")
    if traced:
        return value
    arr = np.asarray(value, dtype=np.float64)
    if finite and not np.all(np.isfinite(arr)):
        bad = np.argwhere(~np.isfinite(arr))[0]
        where = f" at index {tuple(int(i) for i in bad)}" if arr.ndim else ""
        raise ValueError(f"{fn}(): {name} has a NaN or inf value{where}; {fix}")
    return arr


def choice(fn: str, name: str, value, options) -> str:
    """One of a few option strings."""
    if not isinstance(value, str) or value not in options:
        raise ValueError(f"{fn}(): unknown {name} {_show(value)}; use one of {tuple(options)}")
    return value


def min_support(fn: str, h, dt: float, name: str = "h") -> None:
    """A modulating function's support must cover at least 2 sampling intervals."""
    if is_traced(h):
        return
    hv = np.asarray(h, dtype=np.float64)
    if hv.size and float(np.min(hv)) < 2 * dt * (1 - 1e-12):
        raise ValueError(
            f"{fn}(): {name}={float(np.min(hv)):g} is shorter than 2 sampling intervals "
            f"(dt={dt:g}); h must cover at least 2 samples (h >= {2 * dt:g}), or the "
            "quadrature cannot resolve the modulating function"
        )


# -- argument checks of the public verbs whose bodies live elsewhere (one call at their top) ---


# what to do instead, for the public functions whose work runs on the host (`eager_only`)
EAGER_FIX = {
    "search": "for several records call it once per record, or lay experiments end to end "
              "with Signals.concatenate",
    "estimate": "for a batch of records pass a list: estimate([sig1, sig2, ...], ...)",
    "refine": "under jax.grad or jax.vmap use scores, which traces",
    "compare": "under jax.jit or jax.vmap use observe, which traces",
    "residuals": "under jax.jit or jax.vmap use observe, which traces",
    "output_error": "for a batch of records pass a list, output_error([sig1, sig2, ...], "
                    "starts), or use srivc, which traces",
    "step_response": "under jax.jit, jax.vmap or jax.grad use simulate, which traces",
    "frequency_response": "under jax.jit, jax.vmap or jax.grad evaluate B_k(jw)/A(jw) from "
                          "model.a and model.b with jnp.polyval",
    "cramer_rao": "it returns NumPy standard deviations; compute it outside the transformation",
    "to_scipy": "export a concrete model",
    "to_control": "export a concrete model",
    "save_model": "save a concrete model",
    "Signals.concatenate": "concatenate concrete records before the transformation",
    "Model.from_coefficients": "build the Model from concrete coefficients, then put traced "
                               "ones in with equinox.tree_at (a, b, offset)",
    "update": "feed concrete samples (the on-line identifier's buffers live on the host)",
    "resample": "resample concrete samples before the transformation",
}


def eager_only(fn: str, *values, fix: str | None = None) -> None:
    """TypeError naming `fn` and what to do instead (`fix`, default `EAGER_FIX[fn]`) when a
    leaf of `values` (records, models, settings) is traced: `fn` plans, decides or draws on
    the host, so `jax.jit`/`jax.vmap`/`jax.grad` cannot run it (JAX's
    TracerArrayConversionError or ConcretizationTypeError came from inside the host code)."""
    if any(is_traced(x) for v in values for x in jax.tree.leaves(v)):
        raise TypeError(f"{fn}() runs on the host (its grid, decisions or bookkeeping), so it "
                        f"cannot take traced values inside jax.jit/jax.vmap/jax.grad; call it on "
                        f"concrete values: {fix or EAGER_FIX[fn]}")


def _signals_arg(fn: str, signals):
    from ._signals import Signals

    if not isinstance(signals, Signals):
        raise TypeError(f"{fn}(): signals must be a Signals (mfmjax.Signals(y, u, dt=...)), got "
                        f"{type(signals).__name__}{swap_hint(fn, signals)}")
    return signals


def swap_hint(fn: str, value) -> str:
    """For a Model given where a record goes, or a record where a model goes: the public
    function's argument order (some take the record first, some the model), else ''."""
    import inspect

    from ._model import Model
    from ._signals import Signals

    if not isinstance(value, (Model, Signals)):
        return ""
    import mfmjax

    target = getattr(mfmjax, fn, None)
    if not callable(target):
        return ""
    first = [p for p in inspect.signature(target).parameters][:2]
    return f"; arguments swapped? the order is {fn}({', '.join(first)}, ...)"


def model_delays(fn: str, model) -> None:
    """A model's delays are dead times: finite and >= 0 (a model edited by hand, e.g. with
    `eqx.tree_at`, can carry others: its simulation read future samples, status ok)."""
    if is_traced(model.delays):
        return
    d = np.asarray(model.delays, dtype=np.float64)
    if not np.all(np.isfinite(d) & (d >= 0)):
        raise ValueError(f"{fn}(): model.delays must be finite and >= 0 (dead times), got "
                         f"{d.tolist()}; a negative delay would read future inputs")


def same_inputs(fn: str, model, signals) -> None:
    """A model evaluated or refined on `signals` must have their number of inputs and dead
    times for delays (`model_delays`)."""
    model_delays(fn, model)
    if model.n_inputs != signals.n_inputs:
        raise ValueError(f"{fn}(): the model has {model.n_inputs} inputs but the signals have "
                         f"{signals.n_inputs}; pass the inputs the model was identified with")


def start_layout(fn: str, model, signals) -> None:
    """A start model of an estimator: the signals' inputs and offset term (else the offset
    would fit a b coefficient's slot, or be dropped)."""
    same_inputs(fn, model, signals)
    if model.has_offset != signals.offset:
        raise ValueError(f"{fn}(): model.has_offset={model.has_offset} but signals.offset="
                         f"{signals.offset}; identify the start on these signals, or give "
                         f"Signals(..., offset={model.has_offset})")


def window_list(identify) -> list:
    """`identify=` as a list of (t0, t1) windows: one window, or a list of them."""
    return [identify] if np.isscalar(identify[0]) else list(identify)


def start_notes(fn: str, model, signals) -> None:
    """Warn (public entry points only) where the start model says otherwise than the signals
    about what the fit takes from them. Its delays are used: where they differ from delays the
    signals were given (nonzero), a start built with delays 0 fitted a wrong model silently
    (a = [0.77, 1.27] for [2, 3] with the record's 0.5 s dead time); signals at zero delays
    and a start with delays from a search's grid is the usual path: not said. The signals'
    intersample rules are used: zoh data declared nowhere in `Signals` (foh by default) with a
    zoh start fitted a = [4.2, 5.7] for [2, 3], "converged" (an audit of 2026-11-28)."""
    import warnings

    if not (is_traced(model.delays) or is_traced(signals.delays)):
        d_model, d_sig = np.asarray(model.delays), np.asarray(signals.delays)
        if np.any(d_sig != 0) and not np.array_equal(d_model, d_sig):
            warnings.warn(f"{fn}(): the start model's delays {d_model.tolist()} are used, not "
                          f"the signals' own {d_sig.tolist()}; give the start the record's "
                          "delays (Model.from_coefficients(..., delays=...), or identify it on "
                          "these signals) if those are the plant's", stacklevel=user_stacklevel())
    if tuple(model.intersample) != tuple(signals.intersample):
        warnings.warn(f"{fn}(): the fit uses the signals' intersample rules "
                      f"{list(signals.intersample)}, not the start model's "
                      f"{list(model.intersample)}; declare the data's rule where they were "
                      "read (Signals(..., intersample=...): 'zoh' for inputs held between "
                      "samples)", stacklevel=user_stacklevel())


def _eta(fn: str, eta) -> None:
    if eta is not None and not is_traced(eta):
        nonzero_eta(fn, array(fn, "eta", eta, ndim=1, fix="give a finite constraint vector"))


def nonzero_eta(fn: str, eta) -> None:
    """eta^T theta = 1 (eq. 11) has no solution for eta = 0: every candidate came back flagged
    (nonfinite, a_n_zero, unstable), the cause unsaid."""
    if eta.size and not np.any(np.asarray(eta)):
        raise ValueError(f"{fn}(): eta is all zeros, so the constraint eta^T theta = 1 (eq. 11) "
                         "has no solution; give a nonzero constraint vector (default: ones with "
                         "the offset's entry 0)")


def check_identify(signals, structure, mf, eta=None, delay_max=None,
                   fn: str = "identify") -> None:
    """identify() (or `fn`): x64, argument kinds, eta finite, h covering at least 2 samples."""
    from ._modulating import ModulatingFunction

    require_x64(fn)
    _signals_arg(fn, signals)
    if not isinstance(mf, ModulatingFunction):
        raise TypeError(f"{fn}(): mf must be a ModulatingFunction, got {type(mf).__name__}")
    min_support(fn, mf.h, signals.host_dt, "mf.h")
    _eta(fn, eta)
    if delay_max is not None:
        number(fn, "delay_max", delay_max, lo=0)


def _grid_numbers(fn, name, value, **kw):
    if value is None:
        raise TypeError(f"{fn}(): {name} is required (got None)")
    return numbers_(fn, name, value, **kw)


def per_input_lists(fn: str, name: str, value, K: int) -> None:
    """Refuse a flat list of several numbers for `m` or `delays`: one list per input is the
    form, and delays=(0, 5) on two inputs read as 0 on one and 5 on the other, where "try 0
    and 5" was as likely meant (on one input it was refused by count, the fix unsaid)."""
    if not isinstance(value, (list, tuple)):
        return  # (refused as a non-sequence by the caller)
    if len(value) > 1 and all(np.ndim(v) == 0 and not isinstance(v, (str, bytes))
                              for v in value):
        flat = [v.item() if hasattr(v, "item") else v for v in value]
        raise ValueError(
            f"{fn}(): {name}={flat} is a flat list; give one list per input ({K}): e.g. "
            f"{name}=[{tuple(flat)}{', ...' if K > 1 else ''}] to try "
            f"{' and '.join(map(str, flat))} on the first input"
            + (f", or {name}={[(v,) for v in flat]} for one value per input" if len(flat) == K
               else ""))


def check_search(signals, *, n, N, M, h, m, delays, score, validate, observer_window, eta,
                 chunk_size, simulate, progress, identify=None, fn: str = "search") -> None:
    """search() (or `fn`, e.g. estimate, which checks its grid as search does): every grid
    and option checked for kind and range before anything is built."""
    require_x64(fn)
    signals = _signals_arg(fn, signals)
    eager_only(fn, signals, n, N, M, h, m, delays, validate, observer_window, eta)
    integers(fn, "n", n, lo=1, fix="orders are whole numbers, e.g. n=(1, 2, 3)")
    for name, val in (("N", N), ("M", M)):
        integers(fn, name, val, lo=1, fix=f"give whole exponents, e.g. {name}=(3, 4, 5) (the "
                 "search's moments need polynomial modulating functions; identify and refine "
                 "take real exponents)")
    hs = _grid_numbers(fn, "h", h, fix="give modulating-function widths in the record's time "
                       "unit")  # the sign is checked by the grid builder
    if min(hs) > 0:
        min_support(fn, np.asarray(hs), signals.host_dt)
    K = signals.n_inputs
    for name, value in (("m", m), ("delays", delays)):
        per_input_lists(fn, name, value, K)
    if m is not None:
        if isinstance(m, (str, bytes)) or not isinstance(m, (list, tuple)):
            raise TypeError(f"{fn}(): m must list, per input, the numerator orders to try "
                            f"(e.g. m=[[0, 1]] for one input), got {_show(m)}")
        for k, mk in enumerate(m):
            integers(fn, f"m[{k}]", mk, lo=0)
    if delays is not None:
        if isinstance(delays, (str, bytes)) or not isinstance(delays, (list, tuple)):
            raise TypeError(f"{fn}(): delays must list, per input, the delays to try "
                            f"(e.g. delays=[[0.0, 1.5]] for one input), got {_show(delays)}")
        if len(delays) != K:
            raise ValueError(f"{fn}(): delays needs one list per input ({K}), got {len(delays)}")
        for k, dk in enumerate(delays):
            numbers_(fn, f"delays[{k}]", dk)  # the sign is checked by the grid builder
    choice(fn, "score", score, ("E", "J", "fit", "aic", "bic"))
    window(fn, "validate", validate)
    if identify is not None:
        if isinstance(identify, (str, bytes)) or not isinstance(identify, (list, tuple)) or \
                not identify:
            raise TypeError(f"{fn}(): identify must be a window (t0, t1) or a list of windows, "
                            f"got {_show(identify)}")
        wins = window_list(identify)
        for w in wins:
            window(fn, "identify", w)
        ordered = sorted((float(a), float(b)) for a, b in wins)
        for (a0, a1), (b0, b1) in zip(ordered, ordered[1:]):
            if b0 <= a1:  # both ends included: a shared sample overlaps too
                raise ValueError(f"{fn}(): the identify windows ({a0:.15g}, {a1:.15g}) and "
                                 f"({b0:.15g}, {b1:.15g}) overlap: the Gram would count their "
                                 "common samples twice (and a hold-out block could lie inside "
                                 "the fitted data); give disjoint windows or merge them")
    if observer_window is not None:
        number(fn, "observer_window", observer_window, lo=0, lo_open=True)
    _eta(fn, eta)
    integer(fn, "chunk_size", chunk_size, lo=1)
    if not isinstance(simulate, (bool, np.bool_)):
        raise TypeError(f"{fn}(): simulate must be True or False, got {_show(simulate)}")
    if progress is not None and not callable(progress):
        raise TypeError(f"{fn}(): progress must be a function progress(done, total) or None")


def check_scores(signals, structure, *, h, N, M, delays, eta, validate, observer_window, h_max,
                 delay_max) -> None:
    """scores(): settings may be tracers (under grad/jit); concrete ones are checked."""
    from ._structure import Structure

    fn = "scores"
    require_x64(fn)
    signals = _signals_arg(fn, signals)
    if not isinstance(structure, Structure):
        raise TypeError(f"{fn}(): structure must be a Structure, got {type(structure).__name__}")
    for name, val in (("N", N), ("M", M)):
        if not is_traced(val):  # as identify: phi^(i) must vanish at both ends for i < n
            number(fn, name, val, lo=structure.n,
                   fix=f"phi^(i) must vanish at both ends for i < n = {structure.n}")
    if not is_traced(h):
        number(fn, "h", h, lo=0, lo_open=True)
        min_support(fn, h, signals.host_dt)
    if delays is not None and not is_traced(delays):
        array(fn, "delays", delays, ndim=(0, 1))
    _eta(fn, eta)
    window(fn, "validate", validate)
    if observer_window is not None:
        number(fn, "observer_window", observer_window, lo=0, lo_open=True)
    if h_max is not None:
        number(fn, "h_max", h_max, lo=0, lo_open=True)
    if delay_max is not None:
        number(fn, "delay_max", delay_max, lo=0)


def _steps_tolerances(fn, max_steps, rtol, atol) -> None:
    integer(fn, "max_steps", max_steps, lo=0, fix="give the most solver steps, e.g. 40")
    number(fn, "rtol", rtol, lo=0, lo_open=True)
    number(fn, "atol", atol, lo=0, lo_open=True)


SETTINGS = ("h", "N", "M", "delays")


def check_refine(signals, *, score, vary, bounds, validate, observer_window, max_steps, rtol,
                 atol, top) -> None:
    """refine(): `vary` a sequence of names (never a bare string), finite bounds, steps >= 1."""
    fn = "refine"
    require_x64(fn)
    eager_only(fn, _signals_arg(fn, signals))
    choice(fn, "score", score, ("E", "J"))
    if isinstance(vary, (str, bytes)):
        raise TypeError(f"{fn}(): vary must be a sequence of names, not the string "
                        f"{_show(vary)}; write vary=({vary!r},)")
    if not isinstance(vary, (list, tuple, set, frozenset)) or not vary:
        raise ValueError(f"{fn}(): vary must name some of {SETTINGS} (got {_show(vary)})")
    for v in vary:
        if not isinstance(v, str) or v not in SETTINGS:
            raise ValueError(f"{fn}(): vary must name some of {SETTINGS} (unknown vary entry "
                             f"{_show(v)})")
    if bounds is not None:
        if not isinstance(bounds, dict):
            raise TypeError(f"{fn}(): bounds must be a dict such as {{'h': (lo, hi)}}, got "
                            f"{type(bounds).__name__}")
        for key, val in bounds.items():
            choice(fn, "bound", key, SETTINGS)
            if isinstance(val, (str, bytes)) or not isinstance(val, (list, tuple)) \
                    or len(val) != 2:
                raise ValueError(f"{fn}(): bounds[{key!r}] must be a pair (lo, hi), got "
                                 f"{_show(val)}")
            for side, b in zip(("lo", "hi"), val):
                array(fn, f"bounds[{key!r}] {side}", b, ndim=(0, 1), fix="give finite bounds")
            if key == "h":
                min_support(fn, val[0], signals.host_dt, "bounds['h'] lo")
            if key == "delays" and np.any(np.asarray(val[0], dtype=np.float64) < 0):
                raise ValueError(f"{fn}(): bounds['delays'] lo must be >= 0 (got "
                                 f"{_show(val[0])}): a delay is a dead time; its box starts "
                                 "at 0 at the lowest")
    window(fn, "validate", validate)
    if observer_window is not None:
        number(fn, "observer_window", observer_window, lo=0, lo_open=True)
    _steps_tolerances(fn, max_steps, rtol, atol)
    integer(fn, "top", top, lo=1)


def check_output_error(signals, *, window_, max_steps, rtol, atol) -> None:
    fn = "output_error"
    require_x64(fn)
    _signals_arg(fn, signals)
    window(fn, "window", window_)
    _steps_tolerances(fn, max_steps, rtol, atol)


def user_stacklevel() -> int:
    """`warnings.warn`'s stacklevel, from the function that calls this, of the first frame
    outside mfmjax (and equinox): a warning points at the user's line through any chain of
    library calls."""
    import equinox

    # equinox's frames too: a method of a Module is called through its bound-method wrapper
    roots = tuple(os.path.dirname(os.path.abspath(m.__file__)) for m in (sys.modules[__package__],
                                                                       equinox))
    frame, level = sys._getframe(1), 1
    while frame is not None and os.path.abspath(frame.f_code.co_filename).startswith(roots):
        frame, level = frame.f_back, level + 1
    return level


def check_rank(fn: str, i, count: int) -> int:
    """A rank 0 .. count-1 (SearchResult.best / row)."""
    if count == 0:
        raise ValueError(f"{fn}(): the search result is empty; widen the grid")
    return integer(fn, "i", i, lo=0, hi=count - 1,
                   fix=f"ranks run from 0 (best) to {count - 1}")


def check_modulating(N, M, h, h_max) -> None:
    """ModulatingFunction(): N, M, h are numbers or arrays of numbers (or tracers), never a bool,
    str, None or an empty sequence; their values are checked by the constructor itself."""
    fn = "ModulatingFunction"
    require_x64(fn)
    for name, val in (("N", N), ("M", M), ("h", h)):
        if is_traced(val):
            continue
        if isinstance(val, (list, tuple)):
            raise TypeError(f"{fn}(): {name} must be a number or an array, got a "
                            f"{type(val).__name__} {_show(val)}; e.g. {name}=3")
        if isinstance(val, (np.ndarray, jax.Array)):
            arr = array(fn, name, val, finite=False)
            if arr.size == 0:
                raise ValueError(f"{fn}(): {name} is empty; give a number")
        elif isinstance(val, (bool, np.bool_)) or not isinstance(val, numbers.Real):
            raise TypeError(f"{fn}(): {name} must be a number, got {type(val).__name__} "
                            f"{_show(val)}")
    if h_max is not None:
        number(fn, "h_max", h_max, lo=0, lo_open=True)


def check_cramer_rao(model, u, x0, dt, sigma, length) -> None:
    """cramer_rao(): a Model, finite u and x0, dt > 0, 0 < sigma <= 1e150 (sigma^2 must not
    overflow), length an integer in [1, T]."""
    from ._model import Model

    fn = "cramer_rao"
    require_x64(fn)
    if not isinstance(model, Model):
        raise TypeError(f"{fn}(): model must be a Model, got {type(model).__name__}"
                        f"{swap_hint(fn, model)}")
    from ._signals import Signals

    if isinstance(u, Signals):  # (it said "u must hold real numbers, got dtype object")
        raise TypeError(f"{fn}(): u must be the experiment's inputs (T, K), got a Signals: "
                        "pass signals.u")
    if not is_traced(u):
        u = array(fn, "u", u, ndim=(1, 2))
    K = model.n_inputs
    shape = np.shape(u)
    if (shape[1] if len(shape) == 2 else 1) != K or shape[0] < 1:
        raise ValueError(
            f"{fn}(): u must have shape (T, {K}) for this model (time-major, one column per "
            f"input), got {shape}" + ("; transpose it (u.T)" if shape[0] == K else ""))
    if not is_traced(x0):
        array(fn, "x0", x0, ndim=1)
    if np.shape(x0) != (model.n,):
        raise ValueError(f"{fn}(): x0 must have shape ({model.n},) (the model's state), got "
                         f"{np.shape(x0)}")
    number(fn, "dt", dt, lo=0, lo_open=True)
    number(fn, "sigma", sigma, lo=0, lo_open=True, hi=1e150,
           fix="give the output noise's standard deviation")
    if length is not None:
        integer(fn, "length", length, lo=1, hi=int(np.shape(u)[0]))
