r"""On-line adaptive identification and output prediction: the paper's Algorithm 1.

An explicit-state machine (`method.md` section 8): `init(config) -> OnlineState` and
`update(state, t, y, u) -> (OnlineState, OnlineOutputs)`, fed chunks of any size. Time is cut
into intervals of width `interval` (T); when an interval closes:

1. **Statistics**: the interval is *valid* if all its samples and their variances are finite
   (a sample beyond about 1e154 makes its interval invalid, like a NaN); *steady* if the
   variance of the output and of every input over it is below a threshold (default: `steady_rel`
   times the variance of that signal over all valid intervals so far, a data-scaled default;
   or absolute `steady_var`). An **operating point** is the onset of a steady run (a steady
   interval after a non-steady one, or the first interval); its time is the interval's start.
   The input-output correlation of the interval is $\max_k |\rho(y, u_k(t - \tau_k))|$.
2. **Prediction** (Step 5 of the previous interval): the current model's final state at the
   previous interval end comes from the final-state observer over `T_obfin` (eq. 15), and the
   output of the interval just closed is simulated from it with the measured inputs. It uses no
   output sample after the previous interval end; it is emitted when the interval closes.
3. **Step 3** (no model yet, an operating point in the last `n_start` intervals, at least
   `n_start` intervals seen, the correlation test passed in one of them): the batched search over
   the candidate set on the last `n_start` intervals; the candidate with least E (eq. 17, simulated
   from its initial-state-observer estimate over `T_obinit`) becomes model 1.
4. **Step 4** (a model exists and an operating point lies in the last `n_reident` intervals):
   E_current of the current model and E of every candidate identified on the last `n_reident`
   intervals (same window, each from its own initial-state observer); the least is E_reident, and
   the model is replaced if E_reident < E_current.

Every step is recorded (`OnlineOutputs.events`), every accepted model too (`OnlineOutputs.models`,
the columns of the paper's Tables 2-5). Memory is bounded: a ring buffer of
max(n_start T, n_reident T, T_obfin + T + max delay) samples and per-interval statistics for the
last max(n_start, n_reident) intervals. Choices where the paper is silent: selecting the first
model by its observer-initialised E (MFM needs no zero initial condition), the onset definition
of an operating point, and the data-scaled variance threshold.

`OnlineConfig(mode="improved")` (issue 17) keeps this machine and changes what the paper leaves
open or what fails on the forehearth (each change named in `IMPROVEMENTS`, measured on its own
by `benchmarks/forehearth_modes.py --ablation`): longer windows with wider modulating functions,
delays searched on a grid around the value in use, candidates ranked by their forecast of an
interval they were not fitted on, a damping check, a minimum relative improvement before a
model is replaced, a noise-tied operating-point test, and re-identification when a prediction
misses by far more than the noise. `mode="paper"` (the default) is Algorithm 1 as stated.
"""

from __future__ import annotations

import functools
import json
import math
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from . import _boundary as _b
from ._boundary import require_x64
from ._jit import jit
from ._model import Model, plain_number
from ._observers import observe_forced
from ._padded import padded_forced
from ._quadrature import edge_padded
from ._search import check_eta_reaches, plan_search, run_plan, structures, validate_candidate
from ._signals import INTERSAMPLE, Signals
from ._status import Status, describe

FORMAT, VERSION = "mfmjax-online", 1
IMPROVEMENTS = ("window", "delay", "refine", "rank", "damping", "hold", "steady",
                "alarm", "spikes")  # in order
REFINE_STEPS = 4  # improved "refine": golden-section steps (the bracket shrinks to 0.618^4)
ALARM = 100.0  # improved "alarm": re-identify when a prediction's MSE > 100 noise variances
NOISE_FACTOR = 4.0  # improved steady test: the variance threshold is at least 4 noise variances
HYSTERESIS = 2.0  # improved onset: the interval before a steady one exceeded 2x its threshold
TOP_RANK = 16  # candidates (best E on the fit window) ranked on the longer window
MAX_BUFFER_GIB = 1.0  # largest ring buffer OnlineConfig accepts (allocation-sized nonsense)


def _tuple(x, cast):
    return tuple(cast(v) for v in (x if isinstance(x, (list, tuple)) else [x]))


class OnlineConfig(eqx.Module):
    """Settings of Algorithm 1 (defaults: the paper's Table 1, time in seconds).

    **Arguments:**

    - `dt`: sampling interval; `n_inputs`: K.
    - `interval` (T), `n_start`, `n_reident`, `T_obfin`, `T_obinit`, `tr_corr`: Table 1.
    - `n`, `m`, `N`, `M`, `h`: the candidate set of the re-identification (a search grid; default
      the orders and MF settings of the paper's Tables 2-5: n in {2, 3}, m_k in {0, 1},
      N in {3, 5}, M in {4, 6}, h in {50, 100}: 64 candidates).
    - `delays`: known input delays; `intersample`, `smooth`, `output_rule`, `offset` (a constant
      term in the model, default True: plant data are not deviation variables), `eta`: as in
      `Signals` / `search` (default: ones with the offset left out, `default_eta`; paper
      mode: the paper's ones, the offset included).
    - `steady_rel`: an interval is steady when each signal's variance over it is below
      `steady_rel` times that signal's variance over all valid intervals so far; `steady_var`
      (output, then each input) replaces this by absolute thresholds.
    - `mode`: `"paper"` (default: Algorithm 1 as the paper states it) or `"improved"`, which
      applies the changes listed in `improvements` (default: all of `IMPROVEMENTS`):
      `"window"`: `n_reident` 12 (3000 s windows: they keep the last set-point step, the
      only excitation of the controller's input) and h in {50, 100, 200} unless given,
      re-identification triggered in the n_reident/2 intervals after an operating point;
      `"delay"`: the delays of the inputs with a nonzero `delays` entry are searched on a grid
      of step `delay_step` within `delay_span` of the value in use at every identification;
      `"refine"`: the winner's tracked delays then refined by golden-section search within
      +-`delay_step`/2 (REFINE_STEPS steps) on its observer-initialised E of the newest window;
      `"rank"`: candidates are fitted on the `n_reident` intervals before the one just closed,
      and they and the current model are ranked by their Step-5 forecast of that interval (data
      none was fitted on); the winner's settings are fitted again on the newest window;
      `"damping"`: candidates with a pole of damping ratio below `min_damping` are refused;
      `"hold"`: a model is replaced only when E_reident < (1 - `min_improvement`) E_current;
      `"steady"`: the steadiness threshold is at least NOISE_FACTOR times each signal's
      measured noise variance, and an operating point needs the interval before it to exceed
      HYSTERESIS times its threshold; `"alarm"`: an interval whose prediction MSE exceeds
      ALARM times the output's measured noise variance (an RMS error of 10 noise standard
      deviations) triggers a re-identification as an operating point does; `"spikes"`: an
      output sample whose `spike_scores` exceed OUTLIER_Z is replaced in the buffer by the
      median of the OUTLIER_SIDE samples on each side once the OUTLIER_SIDE after it have
      arrived, before later statistics, identifications and predictions read it (the measured
      value stays in the outputs and the MSE; the event's `cleaned` names it; the inputs are
      not cleaned: a short pulse or PRBS bit is excitation).
    """

    dt: float = eqx.field(static=True)
    n_inputs: int = eqx.field(static=True)
    interval: float = eqx.field(static=True)
    n_start: int = eqx.field(static=True)
    n_reident: int = eqx.field(static=True)
    T_obfin: float = eqx.field(static=True)
    T_obinit: float = eqx.field(static=True)
    tr_corr: float = eqx.field(static=True)
    n: tuple = eqx.field(static=True)
    m: tuple = eqx.field(static=True)
    N: tuple = eqx.field(static=True)
    M: tuple = eqx.field(static=True)
    h: tuple = eqx.field(static=True)
    delays: tuple = eqx.field(static=True)
    intersample: tuple = eqx.field(static=True)
    smooth: tuple = eqx.field(static=True)
    output_rule: str = eqx.field(static=True)
    offset: bool = eqx.field(static=True)
    eta: tuple | None = eqx.field(static=True)
    steady_rel: float = eqx.field(static=True)
    steady_var: tuple | None = eqx.field(static=True)
    output_name: str = eqx.field(static=True)
    input_names: tuple = eqx.field(static=True)
    mode: str = eqx.field(static=True)
    improvements: tuple = eqx.field(static=True)
    delay_step: float = eqx.field(static=True)
    delay_span: float = eqx.field(static=True)
    min_damping: float = eqx.field(static=True)
    min_improvement: float = eqx.field(static=True)

    def __init__(
        self, *, dt: float, n_inputs: int, interval: float = 250.0, n_start: int = 8,
        n_reident: int | None = None, T_obfin: float = 500.0, T_obinit: float = 1000.0,
        tr_corr: float = 0.5, n=(2, 3), m=None, N=(3, 5), M=(4, 6), h=None,
        delays=None, intersample="foh", smooth=False, output_rule: str = "cubic",
        offset: bool = True, eta=None, steady_rel: float = 0.1, steady_var=None,
        output_name: str = "y", input_names=None, mode: str = "paper", improvements=None,
        delay_step: float = 10.0, delay_span: float = 60.0,
        min_damping: float = 0.5, min_improvement: float = 0.1,
    ):
        fn = "OnlineConfig"
        _b.require_x64(fn)
        mode = _b.choice(fn, "mode", mode, ("paper", "improved"))
        if isinstance(improvements, str):
            improvements = (improvements,)
        elif improvements is not None and not isinstance(improvements, (list, tuple)):
            raise TypeError(f"OnlineConfig(): improvements must be a list of names from "
                            f"{IMPROVEMENTS}, got {improvements!r}")
        if improvements is None:
            improvements = IMPROVEMENTS if mode == "improved" else ()
        elif mode == "paper" and len(improvements):
            raise ValueError("OnlineConfig(): improvements need mode='improved' (paper mode is "
                             f"Algorithm 1 as stated), got improvements={improvements!r}")
        improvements = _tuple(improvements, str) if len(improvements) else ()
        bad = [v for v in improvements if v not in IMPROVEMENTS]
        if bad:
            raise ValueError(f"OnlineConfig(): unknown improvements {bad}; choose from "
                             f"{list(IMPROVEMENTS)}")
        wide = "window" in improvements  # 3000 s re-identification windows, h up to 200 s
        n_reident = (12 if wide else 4) if n_reident is None else n_reident
        h = ((50.0, 100.0, 200.0) if wide else (50.0, 100.0)) if h is None else h
        K = _b.integer(fn, "n_inputs", n_inputs, lo=1, fix="the on-line identifier needs inputs")
        dt = _b.number(fn, "dt", dt, lo=0, lo_open=True, fix="give the sampling interval")
        interval = _b.number(fn, "interval", interval, lo=0, lo_open=True)
        S = interval / dt
        if not (abs(S - round(S)) < 1e-9 * S and round(S) >= 16):
            raise ValueError(
                f"OnlineConfig(): interval ({interval:g}) must be a whole number (>= 16) of "
                f"samples dt={dt:g}"
            )
        n_start = _b.integer(fn, "n_start", n_start, lo=1)
        n_reident = _b.integer(fn, "n_reident", n_reident, lo=1)
        for name, v in (("T_obfin", T_obfin), ("T_obinit", T_obinit)):
            v = _b.number(fn, name, v)
            if not 8 * dt <= v:
                raise ValueError(f"OnlineConfig(): {name} must span at least 8 samples (got {v})")
        T_obfin, T_obinit = float(T_obfin), float(T_obinit)
        for name, count in (("n_start", n_start), ("n_reident", n_reident)):
            if T_obinit > count * interval:
                raise ValueError(
                    f"OnlineConfig(): T_obinit ({T_obinit:g}) must fit in the identification "
                    f"window of {name} intervals ({name} * interval = {count * interval:g}); "
                    f"raise {name} or lower T_obinit"
                )
        tr_corr = _b.number(fn, "tr_corr", tr_corr)
        if not 0 <= tr_corr <= 1:
            raise ValueError(f"OnlineConfig(): tr_corr must lie in [0, 1] (got {tr_corr})")
        steady_rel = _b.number(fn, "steady_rel", steady_rel)
        if not steady_rel > 0:
            raise ValueError(f"OnlineConfig(): steady_rel must be > 0 (got {steady_rel})")
        samples = round(S)
        self.dt, self.n_inputs, self.interval = dt, K, float(interval)
        self.n_start, self.n_reident = n_start, n_reident
        self.T_obfin, self.T_obinit, self.tr_corr = T_obfin, T_obinit, tr_corr
        self.n = tuple(_b.integers(fn, "n", n, lo=1, fix="orders are whole numbers, e.g. "
                                   "n=(2, 3)"))
        if m is not None and (isinstance(m, (str, bytes)) or not isinstance(m, (list, tuple))
                              or not all(isinstance(mk, (list, tuple)) for mk in m)):
            # a flat list (m=[0, 1]) would read as one fixed order per input: refused
            raise TypeError(f"OnlineConfig(): m must list, per input, the numerator orders to try "
                            f"(e.g. m=[[0, 1]] * {K}, one list per input), got {m!r}")
        self.m = (tuple(tuple(_b.integers(fn, f"m[{k}]", mk, lo=0)) for k, mk in enumerate(m))
                  if m is not None else tuple((0, 1) for _ in range(K)))
        if len(self.m) != K:
            raise ValueError(f"OnlineConfig(): m needs one list of orders per input ({K})")
        if not structures(self.n, self.m, K):  # (accepted; nothing to identify)
            raise ValueError(f"OnlineConfig(): no structure in n={list(self.n)}, m="
                             f"{[list(mk) for mk in self.m]}: every numerator order must be "
                             "at most n (m_k <= n); lower m or raise n")
        self.N = tuple(float(v) for v in _b.integers(fn, "N", N, lo=1, hi=19))
        self.M = tuple(float(v) for v in _b.integers(fn, "M", M, lo=1, hi=19))
        if not any(a >= min(self.n) and b >= min(self.n) for a in self.N for b in self.M):
            raise ValueError(
                f"OnlineConfig(): every candidate has N < n or M < n (n={list(self.n)}, "
                f"N={list(self.N)}, M={list(self.M)}); widen N and M (they must be >= n)"
            )
        self.h = tuple(_b.numbers_(fn, "h", h, lo=0, lo_open=True,
                                   fix="give modulating-function widths in time units"))
        _b.min_support(fn, np.asarray(self.h), dt)
        self.delays = (tuple(_b.numbers_(fn, "delays", delays, lo=0))
                       if delays is not None else (0.0,) * K)
        self.intersample = _tuple(intersample, str) * (K if not isinstance(
            intersample, (list, tuple)) else 1)
        for v in (smooth if isinstance(smooth, (list, tuple)) else [smooth]):
            if not isinstance(v, (bool, np.bool_)):  # "false" or "no" would read as True
                raise TypeError(f"OnlineConfig(): smooth must be True or False (or one per "
                                f"input), got {smooth!r}")
        self.smooth = _tuple(smooth, bool) * (K if not isinstance(smooth, (list, tuple)) else 1)
        for name, v in (("delays", self.delays), ("intersample", self.intersample),
                        ("smooth", self.smooth)):
            if len(v) != K:
                raise ValueError(f"OnlineConfig(): {name} needs one entry per input ({K})")
        if any(mode not in INTERSAMPLE for mode in self.intersample):
            bad = [mode for mode in self.intersample if mode not in INTERSAMPLE]
            raise ValueError(f"OnlineConfig(): intersample must be one of {INTERSAMPLE} per "
                             f"input, got {bad[0]!r}")
        if max(self.h) + max(self.delays) >= n_reident * interval / 2:
            raise ValueError(
                "OnlineConfig(): h + delay must be below half the re-identification window "
                f"({n_reident * interval / 2:g}); lower h or raise n_reident"
            )
        self.output_rule = _b.choice(fn, "output_rule", output_rule, ("cubic", "foh"))
        if not isinstance(offset, (bool, np.bool_)):  # "false" would read as True
            raise TypeError(f"OnlineConfig(): offset must be True or False, got {offset!r}")
        self.offset = bool(offset)
        p = parameter_count(self)
        # the first identification's window (n_start intervals) must leave the search enough
        # valid samples (as `identify` requires): h = 600 on a 500-sample window passed here
        # and raised at the first identification, at every retry (the state does not advance)
        from ._gram import MIN_VALID
        from ._quadrature import kernel_length

        first = n_start * interval / dt
        support = kernel_length(max(self.h) + max(self.delays), dt) - 1
        if first - support < max(MIN_VALID, 2 * p):
            raise ValueError(
                f"OnlineConfig(): h + delay ({max(self.h) + max(self.delays):g}) leaves "
                f"{max(int(first - support), 0)} valid samples of the first identification "
                f"window (n_start x interval = {n_start * interval:g}), fewer than the "
                f"{max(MIN_VALID, 2 * p)} the search needs; lower h or raise n_start")
        if eta is not None:
            eta = _b.array(fn, "eta", eta, ndim=1, fix="give a finite constraint vector")
            _b.nonzero_eta(fn, eta)
            if eta.shape != (p,):
                raise ValueError(
                    f"OnlineConfig(): eta must have one entry per parameter of the largest "
                    f"candidate ({p}: a_0..a_nmax, each input's b, the offset), got {eta.size}"
                )
            check_eta_reaches("OnlineConfig", eta, structures(self.n, self.m, K), self.offset)
        self.eta = tuple(float(v) for v in eta) if eta is not None else None
        self.steady_rel = steady_rel
        self.steady_var = (tuple(_b.numbers_(fn, "steady_var", steady_var, lo=0))
                           if steady_var is not None else None)
        if self.steady_var is not None and len(self.steady_var) != K + 1:
            raise ValueError(f"OnlineConfig(): steady_var needs {K + 1} values (output, inputs)")
        self.output_name = str(output_name)
        self.input_names = (_tuple(input_names, str) if input_names is not None
                            else tuple(f"u{k + 1}" for k in range(K)))
        if len(self.input_names) != K:
            raise ValueError(f"OnlineConfig(): input_names needs one name per input ({K}), got "
                             f"{list(self.input_names)}")
        self.mode = mode
        self.improvements = tuple(v for v in IMPROVEMENTS if v in improvements)
        self.delay_step = _b.number(fn, "delay_step", delay_step, lo=0, lo_open=True)
        self.delay_span = _b.number(fn, "delay_span", delay_span, lo=0)
        if self.delay_span / self.delay_step > 50:
            raise ValueError(f"OnlineConfig(): delay_span / delay_step must be <= 50 (a grid of "
                             f"at most 101 delays), got {delay_span:g} / {delay_step:g}")
        self.min_damping = _b.number(fn, "min_damping", min_damping, lo=0, hi=1)
        self.min_improvement = _b.number(fn, "min_improvement", min_improvement, lo=0, hi=1,
                                         hi_open=True)
        buffer = self.buffer
        gib = buffer * (K + 1) * 8 / 2**30
        if gib > MAX_BUFFER_GIB:
            S = self.samples  # which setting makes the buffer: the windows, or T_obfin
            windows = max(self.n_start, self.n_reident + int("rank" in self.improvements)) * S
            cause = (f"T_obfin={T_obfin:g} ({round(T_obfin / dt) + 1:.3g} samples) sets it; "
                     "lower T_obfin" if buffer > windows else
                     f"interval={interval:g} is {samples:.3g} samples of dt={dt:g}; use a "
                     "coarser dt, a shorter interval or fewer intervals (n_start, n_reident)")
            raise ValueError(
                f"OnlineConfig(): the sample buffer would hold {buffer:.3g} samples per signal "
                f"({gib:.3g} GiB, limit {MAX_BUFFER_GIB:g} GiB): {cause}"
            )

    # derived sizes (samples)
    @property
    def samples(self) -> int:  # per interval
        return round(self.interval / self.dt)

    @property
    def n_max(self) -> int:
        return max(self.n)

    @property
    def span_bound(self) -> float:  # h + delay < this (checked): fixes the compiled shapes
        return self.n_reident * self.interval / 2

    def window_bound(self, intervals: int) -> int:
        """Samples an identification window of `intervals` intervals is padded to: the longest
        window (max(n_start, n_reident) intervals), or half of it (rounded up) for a window
        that fits in half: two programs serve every window, none pays more than twice its own
        length (paper mode's 8- and 4-interval windows keep their length)."""
        longest = max(self.n_start, self.n_reident)
        half = -(-longest // 2)
        return (half if intervals <= half else longest) * self.samples

    @property
    def margin(self) -> int:  # input history the delayed inputs may need before a window
        return math.ceil(self.span_bound / self.dt) + 1

    @property
    def ob_final(self) -> int:
        return round(self.T_obfin / self.dt) + 1

    @property
    def buffer(self) -> int:  # improved "rank" fits on the n_reident intervals before the last
        S, extra = self.samples, int("rank" in self.improvements)
        return max(self.n_start * S, (self.n_reident + extra) * S, self.ob_final + S + self.margin)

    @property
    def history(self) -> int:  # intervals of statistics kept
        return max(self.n_start, self.n_reident + int("rank" in self.improvements))

    def to_dict(self) -> dict:
        return {f: getattr(self, f) for f in self.__dataclass_fields__}


class OnlineState(eqx.Module):
    """Everything Algorithm 1 carries from one update to the next (fixed-size numpy leaves)."""

    config: OnlineConfig = eqx.field(static=True)
    t0: np.ndarray  # time of sample 0 (NaN before the first update)
    n_seen: np.ndarray  # samples received (index of the next sample)
    buf_y: np.ndarray  # (L,) ring buffer, sample i at i % L
    buf_u: np.ndarray  # (L, K)
    stream: np.ndarray  # (3, K+1): count, mean, M2 of each signal over valid intervals
    noise: np.ndarray  # (2, K+1): valid intervals, mean per-interval noise variance estimate
    iv: np.ndarray  # (R, 5): valid, steady, onset, correlation, level (max var / threshold)
    n_closed: np.ndarray  # intervals closed
    model: dict  # current model (padded arrays) and its bookkeeping
    op_count: np.ndarray  # operating points used so far


def _empty_model(config: OnlineConfig) -> dict:
    K, nm = config.n_inputs, config.n_max
    z = lambda *s: np.zeros(s)  # noqa: E731
    return {
        "exists": np.asarray(False), "a": z(nm + 1), "b": z(K, nm + 1), "offset": z(),
        "n": np.asarray(0), "m": np.zeros(K, dtype=np.int64), "N": z(), "M": z(), "h": z(),
        "number": np.asarray(0), "op": np.asarray(0), "op_time": np.asarray(np.nan),
        "delays": np.asarray(config.delays, dtype=np.float64),
    }


def init(config: OnlineConfig) -> OnlineState:
    """A fresh on-line identifier (no data, no model)."""
    require_x64("online.init")
    if not isinstance(config, OnlineConfig):
        raise TypeError("init(): config must be an OnlineConfig")
    K, L = config.n_inputs, config.buffer
    return OnlineState(
        config=config, t0=np.asarray(np.nan), n_seen=np.asarray(0),
        buf_y=np.full(L, np.nan), buf_u=np.full((L, K), np.nan),
        stream=np.zeros((3, K + 1)), noise=np.zeros((2, K + 1)),
        iv=np.zeros((config.history, 5)),
        n_closed=np.asarray(0), model=_empty_model(config), op_count=np.asarray(0),
    )


class OnlineOutputs(eqx.Module):
    """What one `update` produced: the samples of the intervals it closed with their predictions
    (`y_pred` NaN and `model_number` 0 where no model predicted), one event per closed interval
    and a record per accepted model (the columns of the paper's Tables 2-5)."""

    t: np.ndarray
    y: np.ndarray
    y_pred: np.ndarray
    model_number: np.ndarray
    events: tuple
    models: tuple


# -- compiled kernels (one compilation per config) ------------------------------------------


def _window_signals(config: OnlineConfig, y, u, t0: float) -> Signals:
    """A window's record as the compiled programs take it: checked under the signals' names
    (a NaN is reported by column name), then unlabelled, so other names compile nothing (the
    labelled window went into `_predict` and `_score`: a run under other column names compiled
    them again)."""
    return Signals(
        y, u, dt=config.dt, t0=t0, intersample=config.intersample, delays=config.delays,
        offset=config.offset, smooth=config.smooth, output_rule=config.output_rule,
        output_name=config.output_name, input_names=config.input_names,
    ).unlabelled()


def _plan_for(config: OnlineConfig, intervals: int):
    """The candidate grid checked and compiled once for a window of `intervals` intervals."""
    return _plan_grid(config, intervals, tuple((float(d),) for d in config.delays))


@functools.lru_cache(maxsize=256)
def _plan_grid(config: OnlineConfig, intervals: int, delays: tuple, h: tuple | None = None):
    """The candidate grid with a grid of delays per input (`delays`: one tuple per input) and
    MF widths `h` (default config.h) for a window of `intervals` intervals at the start of a
    record of `window_bound(intervals)` samples (`_padded_window`): identification and
    validation cover the window only (kernels padded to `span_bound`, or to half the bound's
    duration for a shorter bound), and every chunk holds one (h, delays) setting (run on a
    thread per core), so every grid of one bound shares one compilation: the delay grids, the
    half-window pool's h, the refit and the refinement's single settings (the demo compiled 2
    chunk programs instead of 4: cold 31.0 -> 25.7 s, warm unchanged at 18.8-18.9 s)."""
    L, dt = intervals * config.samples, config.dt
    bound = config.window_bound(intervals)
    span = min(config.span_bound, bound * dt / 2)
    template = _window_signals(config, np.zeros(bound), np.zeros((bound, config.n_inputs)), 0.0)
    p = parameter_count(config)
    if config.eta is not None:
        eta = np.resize(np.asarray(config.eta), p)
    else:  # paper mode: the paper's eta = ones (Table 1), the offset's entry too
        eta = np.ones(p) if config.mode == "paper" else None
    window = (0.0, (L - 1) * dt)
    return plan_search(
        template, n=config.n, N=config.N, M=config.M, h=config.h if h is None else h, m=config.m,
        delays=[list(d) for d in delays], score="E", validate=window, identify=window,
        observer_window=min(config.T_obinit, (L - 1) * dt), eta=eta,
        chunk_size=1, simulate=True, span_bound=span, n_padded=bound,
        v_bound=bound,
    )


def _padded_window(config: OnlineConfig, y, u):
    """A window's samples at the start of a record of `window_bound` samples, its last sample
    repeated after it (the range of every signal, hence the excitation test, is unchanged;
    `_plan_grid`'s windows never reach the repeats)."""
    pad = config.window_bound(y.shape[0] // config.samples) - y.shape[0]
    return edge_padded(y, pad), edge_padded(u, pad)


@jit
def _score(sig, static, where, c):
    return validate_candidate(sig, static.v_length, c, where)


@jit
def _predict(sig, c, start: int, ob: int):
    """Final-state observer over samples [start, start+ob) then the simulation to the end."""
    forced, live = padded_forced(sig, c)
    length = sig.n_samples - start
    obs = observe_forced(forced, sig.y, sig.dt, start, length, ob, live)
    return obs.y_sim[ob:], obs.status


@jit
def _predict_many(sig, cs, start: int, ob: int):
    """`_predict` of a stack of candidates: (y_sim (C, S), status (C,))."""
    return jax.vmap(lambda c: _predict(sig, c, start, ob))(cs)


# -- the state machine ------------------------------------------------------------------------


def _candidate(config: OnlineConfig, model: dict) -> dict:
    K = config.n_inputs
    k = int(model["n"]) + sum(int(v) + 1 for v in model["m"]) + int(config.offset)
    host = {"a": model["a"], "b": model["b"], "offset": model["offset"], "n": model["n"],
            "delays": np.reshape(model["delays"], K), "k": float(k)}
    return jax.device_put({key: np.asarray(v) for key, v in host.items()})  # no eager program


def _take(state: OnlineState, start: int, length: int):
    """Samples start .. start+length-1 (absolute indices) from the ring buffer."""
    idx = np.arange(start, start + length) % state.buf_y.shape[0]
    return state.buf_y[idx], state.buf_u[idx]


def noise_variance(x) -> np.ndarray:
    """Per column of x (S, 1 + K: the output, then the inputs): the noise variance,
    (1.4826 MAD of the first differences)^2 / 2 (white noise: var(dx) = 2 sigma^2; the MAD
    keeps steps out); the output's at least a quantised signal's q^2 / 12, q its smallest
    nonzero difference: on an output recorded at a historian's resolution most differences
    are 0, the MAD too, and the improved mode's alarm (an interval's prediction MSE over 100
    noise variances) fired on every interval (19 of 19 at 0.5 degC, one with an MSE of
    0.017). Unquantised data: q is far below the noise, and the floor with it. Not the
    inputs': a set-point's or a PRBS's smallest step is a move, not a quantum (a floor there
    raised their steadiness thresholds above their own steps)."""
    dx = np.diff(x, axis=0)
    nv = (1.4826 * np.median(np.abs(dx - np.median(dx, axis=0)), axis=0)) ** 2 / 2
    q = np.min(np.where(dx[:, :1] != 0, np.abs(dx[:, :1]), np.inf), initial=np.inf)
    return np.concatenate([[max(nv[0], q**2 / 12 if np.isfinite(q) else 0.0)], nv[1:]])


def _interval_stats(state: OnlineState, j: int):
    c = state.config
    S, K = c.samples, c.n_inputs
    y, u = _take(state, j * S, S)
    x = np.column_stack([y, u])
    with np.errstate(over="ignore", invalid="ignore"):  # a sample beyond ~1e154: var inf
        var = x.var(axis=0) if np.all(np.isfinite(x)) else np.full(x.shape[1], np.nan)
    valid = bool(np.all(np.isfinite(var)))  # finite samples whose variance is finite too:
    if not valid:  # one 1e200 once made every later threshold NaN (no operating point, ever)
        return valid, False, 0.0, None, None, 0.0
    nv = noise_variance(x)
    n_iv = state.noise[0] + 1
    noise = np.stack([n_iv, state.noise[1] + (nv - state.noise[1]) / n_iv])
    count, mean, m2 = state.stream
    total = count + S  # the stream statistics include this interval (Chan's merge)
    delta = x.mean(axis=0) - mean
    new = np.stack([total, mean + delta * S / total, m2 + S * var + delta**2 * count * S / total])
    if c.steady_var is not None:
        thr = np.asarray(c.steady_var)
    else:
        thr = c.steady_rel * new[2] / new[0]
    if "steady" in c.improvements:  # never below the noise: a quiet interval's var ~ sigma^2
        thr = np.maximum(thr, NOISE_FACTOR * noise[1])
    level = float(np.max(var / np.where(thr > 0, thr, np.inf))) if np.all(
        thr > 0) else (0.0 if np.all(var <= thr) else math.inf)
    steady = bool(np.all(var <= thr))
    corr = 0.0
    L = state.buf_y.shape[0]
    delays = state.model["delays"]  # the delays in use (tracked in improved mode)
    for k in range(K):  # against the delayed input, when its history is still in the buffer
        shift = round(float(delays[k]) / c.dt)
        if j * S - shift < 0 or shift > L - S:
            continue
        _, ud = _take(state, j * S - shift, S)
        ud = ud[:, k]
        if np.all(np.isfinite(ud)) and np.ptp(ud) > 0 and np.ptp(y) > 0:  # constant: no corr
            corr = max(corr, abs(float(np.corrcoef(y, ud)[0, 1])))
    return valid, steady, corr, new, noise, level


def _model_record(config, model: dict, window, E_current, E_reident, reason, j, op_label,
                  sim_start=None):
    """The record of a model adopted at the end of interval j, fitted on `window` (t_start,
    t_end: the end exclusive, the time one sample after the window's last); it predicts from
    `sim_start` (default the window's end: the end of interval j where the window ends there;
    improved mode's winner fitted one interval early passes the end of interval j)."""
    n, m = int(model["n"]), [int(v) for v in model["m"]]
    return {
        "model": int(model["number"]), "operating_point": op_label,
        "operating_point_time": float(model["op_time"]),
        "ident_window": [float(window[0]), float(window[1])],
        "sim_start": float(window[1] if sim_start is None else sim_start), "sim_end": None,
        "interval": j,
        "N": plain_number(model["N"]), "M": plain_number(model["M"]), "h": float(model["h"]), "n": n, "m": m,
        "a": [float(v) for v in model["a"][: n + 1]],
        "b": [[float(v) for v in model["b"][k][: m[k] + 1]] for k in range(config.n_inputs)],
        "offset": float(model["offset"]) if config.offset else None,
        "delays": [float(v) for v in model["delays"]], "E_current": E_current,
        "E_reident": E_reident,
        "reason": reason,
    }


OUTLIER_Z = 8.0  # robust z above which a sample of the first identification window is a spike
OUTLIER_SIDE = 5  # samples on each side whose median a spike is compared with


def spike_scores(x: np.ndarray, scale_from: np.ndarray | None = None) -> np.ndarray:
    r"""Robust z-score of each sample as an isolated spike (0 for the first and last 5 samples).

    The rule: $d_i = \min(|x_i - \mathrm{med}_L|, |x_i - \mathrm{med}_R|)$, the distance to the
    nearer of the medians of the 5 samples before and the 5 after, divided by the largest of
    (a) the noise level, 1.4826 MAD of the first differences / sqrt(2), (b) the local trend
    $|\mathrm{med}_R - \mathrm{med}_L|$ and (c) 5 % of the signal's 1-99 % percentile spread.
    A step or a ramp lies near one side's median or within the trend, a smooth peak within the
    spread floor: only a sample far from both sides scores high. (a) and (c) are measured on
    the finite samples of `scale_from` (default `x`): a short `x` (an interval) may be quiet
    where its history is not. A sample whose 11-sample window holds a NaN scores 0. (On an
    output held at a recorder's resolution, a rare one-quantum blip scores high too: the
    1-99 % spread and the noise are 0 there.)
    """
    x = np.asarray(x, dtype=np.float64)
    ref = x if scale_from is None else np.asarray(scale_from, dtype=np.float64)
    ref = ref[np.isfinite(ref)]  # a history with gaps: its finite samples
    k, n = OUTLIER_SIDE, x.size
    z = np.zeros(n)
    if n < 2 * k + 1 or ref.size < 2:
        return z
    dx = np.diff(ref)
    noise = 1.4826 * np.median(np.abs(dx - np.median(dx))) / math.sqrt(2)
    lo, hi = np.percentile(ref, [1, 99])
    with np.errstate(invalid="ignore"):  # windows with a NaN: NaN medians, scored 0 below
        med = np.median(np.lib.stride_tricks.sliding_window_view(x, k), axis=1)  # of x[i:i+k]
        i = np.arange(k, n - k)
        left, right = med[i - k], med[i + 1]
        d = np.minimum(np.abs(x[i] - left), np.abs(x[i] - right))
        s = np.maximum(np.maximum(noise, 0.05 * (hi - lo)), np.abs(right - left))
        z[i] = np.where(s > 0, d / np.where(s > 0, s, 1.0), np.where(d > 0, np.inf, 0.0))
    return np.where(np.isnan(z), 0.0, z)


def _clean_spikes(state: OnlineState, j: int):
    """Improved "spikes": (state, notes). The output's samples jS - OUTLIER_SIDE ..
    (j+1)S - OUTLIER_SIDE - 1 (the last OUTLIER_SIDE of interval j-1, whose right-hand side is
    now known, and all but the last OUTLIER_SIDE of interval j, judged when interval j+1
    closes: a spike there is in interval j's statistics, where it can mark that interval as
    moving and the next as an operating point) are scored by `spike_scores` with
    OUTLIER_SIDE samples of context on each side and the scales of the last `n_start`
    intervals; one above OUTLIER_Z is replaced in the buffer by the median of the OUTLIER_SIDE
    samples on each side. A single glitch otherwise stays in the running variance that the
    steadiness threshold scales with: a 100 degC thermocouple spike at 1500 s of the
    forehearth's experiment 1 raised the threshold so far that the second operating point was
    never detected, and the re-identification windows holding it fitted the spike. The inputs
    are left alone: a PRBS held 2-3 samples, or a short pulse, is excitation, not a glitch (a
    review's run replaced 237 of 1000 PRBS samples by the other level). A sample whose window
    holds a NaN is not judged (`spike_scores`)."""
    c = state.config
    S, L, k = c.samples, state.buf_y.shape[0], OUTLIER_SIDE
    lo = max(j * S - 2 * k, 0)
    first = min(max(j + 1 - c.n_start, 0) * S, lo)  # the scales: the last n_start intervals
    history, _ = _take(state, first, (j + 1) * S - first)
    x = history[lo - first:]
    z = spike_scores(x, history)
    notes, fixed = [], x.copy()
    for i in np.flatnonzero(z > OUTLIER_Z):
        fixed[i] = np.median(np.concatenate([x[i - k : i], x[i + 1 : i + 1 + k]]))
        notes.append(f"{c.output_name} = {x[i]:.6g} at t = {float(state.t0) + (lo + i) * c.dt:g} "
                     f"(robust z = {z[i]:.3g} > {OUTLIER_Z:g}) replaced by {fixed[i]:.6g}")
    if not notes:
        return state, notes
    by = state.buf_y.copy()
    by[np.arange(lo, (j + 1) * S) % L] = fixed
    return eqx.tree_at(lambda s: s.buf_y, state, by), notes


def _outlier(state: OnlineState, j: int, w: int) -> str | None:
    """Why the first identification window (the last `w` intervals) is refused, or None.

    A window with a sample whose `spike_scores` exceed OUTLIER_Z (output or any input) is
    refused: the identifier waits for the next window instead of adopting a model fitted to a
    spike (the E rule guards re-identification only)."""
    c = state.config
    S = c.samples
    start = (j + 1 - w) * S
    y, u = _take(state, start, w * S)
    for name, x in [(c.output_name, y)] + [(c.input_names[k], u[:, k])
                                           for k in range(c.n_inputs)]:
        z = spike_scores(x)
        worst = int(np.argmax(z))
        if z[worst] > OUTLIER_Z:
            t = float(state.t0) + (start + worst) * c.dt
            return (f"refused: outlier in the identification window ({name} = {x[worst]:.6g} at "
                    f"t = {t:g}, robust z = {z[worst]:.3g} > {OUTLIER_Z:g}); waiting for the "
                    "next window")
    return None


def _identify_window(state: OnlineState, j: int, w: int, delays: tuple | None = None,
                     h: tuple | None = None):
    """The batched search on the `w` intervals up to j: (window signals, plan, result)."""
    c = state.config
    S = c.samples
    start = (j + 1 - w) * S
    y, u = _padded_window(c, *_take(state, start, w * S))
    t_start = float(state.t0) + start * c.dt
    sig = _window_signals(c, y, u, 0.0)
    plan = _plan_for(c, w) if delays is None else _plan_grid(c, w, delays, h)
    return sig, plan, run_plan(plan, sig), (t_start, t_start + w * S * c.dt)


def _delay_grid(config: OnlineConfig, current) -> tuple:
    """Improved mode's delays to try per input: the current value +- `delay_span` in steps of
    `delay_step` for each input with a nonzero configured delay (0 <= d, d + max h below the
    span bound that fixes the compiled kernel length); the current value alone otherwise."""
    out = []
    r = int(round(config.delay_span / config.delay_step))
    for k in range(config.n_inputs):
        d = round(float(current[k]), 9)
        if "delay" not in config.improvements or config.delays[k] == 0:
            out.append((d,))
            continue
        vals = [round(d + i * config.delay_step, 9) for i in range(-r, r + 1)]
        vals = [v for v in vals if v >= 0 and v + max(config.h) < config.span_bound]
        out.append(tuple(vals) or (d,))
    return tuple(out)


def _damping_ok(a, n: int, zeta: float) -> bool:
    """Every pole of a_n s^n + ... + a_0 in the open left half plane with damping ratio >=
    `zeta` (a thermal process does not ring; the data's bandwidth supports no oscillation)."""
    p = np.roots(np.asarray(a[: n + 1], dtype=np.float64)[::-1])
    if p.size == 0:
        return True
    if not np.all(np.isfinite(p)) or np.any(p.real >= 0):
        return False
    return bool(np.all(-p.real >= zeta * np.abs(p) - 1e-12 * np.abs(p)))


def _well_damped(a, n, zeta: float) -> np.ndarray:
    """`_damping_ok` of every row of `a` (orders `n`), the regular rows (finite, a_n and a_0
    nonzero) through one batched `eigvals` per order of the companion matrices `np.roots`
    builds (the same matrices, so the same poles); the others one at a time."""
    a, n = np.asarray(a, dtype=np.float64), np.asarray(n, dtype=int)
    ok = np.zeros(len(n), dtype=bool)
    for order in np.unique(n):
        rows = np.flatnonzero(n == order)
        p = a[rows, : order + 1][:, ::-1]  # highest power first, as np.roots takes it
        regular = np.all(np.isfinite(p), axis=1) & (p[:, 0] != 0) & (p[:, -1] != 0)
        for r in rows[~regular]:
            ok[r] = _damping_ok(a[r], int(order), zeta)
        rows, p = rows[regular], p[regular]
        if order == 0 or not rows.size:
            ok[rows] = True
            continue
        comp = np.zeros((rows.size, order, order))
        comp[:, 0, :] = -p[:, 1:] / p[:, :1]
        comp[:, np.arange(1, order), np.arange(order - 1)] = 1.0
        poles = np.linalg.eigvals(comp)
        mag = np.abs(poles)
        ok[rows] = (np.all(np.isfinite(poles), axis=1) & np.all(poles.real < 0, axis=1)
                    & np.all(-poles.real >= zeta * mag - 1e-12 * mag, axis=1))
    return ok


def _stack(config: OnlineConfig, picks, fill: dict) -> dict:
    """Candidates `picks` ((search result, column) pairs) as one padded stack (`_candidate`'s
    layout), `fill` (a `_candidate`) first and repeated up to 1 + 2 TOP_RANK rows (a fixed
    shape: one compilation)."""
    K, nm = config.n_inputs, config.n_max
    C = 1 + 2 * TOP_RANK
    a = np.repeat(np.asarray(fill["a"])[None], C, 0)
    b = np.repeat(np.asarray(fill["b"])[None], C, 0)
    off = np.repeat(np.asarray(fill["offset"])[None], C, 0)
    n = np.repeat(np.asarray(fill["n"])[None], C, 0)
    d = np.repeat(np.asarray(fill["delays"])[None], C, 0)
    k = np.repeat(np.asarray(fill["k"])[None], C, 0)
    for r, (res, i) in enumerate(picks, start=1):
        cols = res.columns
        a[r] = cols["a"][i][: nm + 1]
        b[r] = 0.0
        b[r][:, : cols["b"].shape[2]] = cols["b"][i]
        off[r] = cols["offset"][i] if config.offset else 0.0
        n[r] = cols["n"][i]
        d[r] = cols["delays"][i]
        k[r] = int(cols["n"][i]) + sum(int(v) + 1 for v in cols["m"][i]) + int(config.offset)
    return {"a": jnp.asarray(a), "b": jnp.asarray(b), "offset": jnp.asarray(off),
            "n": jnp.asarray(n), "delays": jnp.asarray(d).reshape(C, K), "k": jnp.asarray(k)}


def _ok_columns(config: OnlineConfig, res) -> list:
    """Column indices of the candidates with status ok (and, with "damping", well damped
    poles), best E on the fit window first."""
    cols = res.columns
    ok = [int(i) for i in res.rank if int(cols["status"][i]) == 0]
    if "damping" in config.improvements:
        damped = _well_damped(cols["a"][ok], cols["n"][ok], config.min_damping)
        ok = [i for i, keep in zip(ok, damped) if keep]
    return ok


def _no_candidate(config: OnlineConfig, results: list) -> str:
    """The rejection when no candidate of `results` passes `_ok_columns`, naming why the
    best by E failed: its status, or (status ok) its poles' damping."""
    text = "rejected: no candidate had status ok" + (
        f" and poles of damping ratio >= {config.min_damping:g}"
        if "damping" in config.improvements else "")
    tops = [(float(r.columns["E"][r.rank[0]]), int(r.columns["status"][r.rank[0]]),
             r.columns["a"][r.rank[0]], int(r.columns["n"][r.rank[0]]))
            for r in results if len(r)]
    if not tops:
        return text
    _, status, a, n = min(tops, key=lambda x: (not math.isfinite(x[0]), x[0]))
    if status:
        return text + f" (the best by E: {describe(status)})"
    poles = np.roots(np.asarray(a, dtype=np.float64)[: n + 1][::-1])
    zeta = float(np.min(-poles.real / np.maximum(np.abs(poles), 1e-300)))
    return text + f" (the best by E: status ok, a pole of damping ratio {zeta:.3g})"


def _improved_choice(state: OnlineState, j: int, w: int, model: dict | None):
    """Improved mode's identification at the end of interval j on the last `w` intervals.

    The search runs over `_delay_grid` around the delays in use; `_ok_columns` keeps the
    candidates with status ok (and well damped poles). Without "rank" (or for the first model)
    the best E on the fit window wins, and the current model's E is on the same window. With
    "rank", the candidates are fitted on the `w` intervals before interval j (and, with
    "window", also on the w/2 before it, with the h that fit there), and the best TOP_RANK of
    each pool by E and the current model each predict interval j exactly as Step 5 does
    (final-state observer, then simulation): data none of them was fitted on. The winner's
    settings (window length, structure, N, M, h, delays) are then fitted again on the newest
    window. Returns (best row or None, E of the current model or None, E of the best, the fit
    window, what the E values are on; for None: the rejection in words)."""
    c = state.config
    S, R = c.samples, c.history
    delays = _delay_grid(c, state.model["delays"])
    current = _candidate(c, model) if model is not None else None
    hold = ("rank" in c.improvements and j >= w
            and all(state.iv[(j - i) % R][0] for i in range(min(w + 1, R))) and w + 1 <= R)
    sig_p = None
    if hold:
        reach = max(max(d) for d in delays) if delays else 0.0
        if model is not None:
            reach = max(reach, float(np.max(model["delays"])))
        sig_p, _ = _prediction_signals(state, j, reach)
    if sig_p is None:  # rank on the fit window
        sig, plan, res, window = _identify_window(state, j, w, delays)
        ok = _ok_columns(c, res)
        if not ok:
            return None, None, None, window, _no_candidate(c, [res])
        i = ok[0]
        E_cur = (float(_score(sig, plan.static, plan.where, current)["E"])
                 if current is not None else None)
        return _row(res, i), E_cur, float(res.columns["E"][i]), window, "fit window"
    pools = [(w, None)]
    w_s = w // 2
    if "window" in c.improvements and w_s >= 1:
        reach = max(max(d) for d in delays)
        h_s = tuple(v for v in c.h if v + reach < w_s * c.interval / 2)
        if h_s:
            pools.append((w_s, h_s))
    picks, window, searched = [], None, []
    for wp, hp in pools:
        _, _, res, win = _identify_window(state, j - 1, wp, delays, hp)
        window = window or win
        searched.append(res)
        picks += [(res, i, wp, hp) for i in _ok_columns(c, res)[:TOP_RANK]]
    if not picks:
        return None, None, None, window, _no_candidate(c, searched)
    fill = current
    if fill is None:  # first model: no current one; the stack's row 0 repeats the first pick
        one = _stack(c, [picks[0][:2]], _candidate(c, _empty_model(c)))
        fill = {key: v[1] for key, v in one.items()}
    y_sim, status = _predict_many(sig_p, _stack(c, [p[:2] for p in picks], fill), c.margin,
                                  c.ob_final)
    y_j, _ = _take(state, j * S, S)
    E = np.sum((np.asarray(y_sim) - y_j) ** 2, axis=1) * c.dt
    E = np.where((np.asarray(status) == 0) & np.isfinite(E), E, np.inf)
    best = int(np.argmin(E[1 : 1 + len(picks)]))
    if not math.isfinite(E[1 + best]):
        failed = sorted({describe(int(v)) for v in np.asarray(status)[1:1 + len(picks)]})
        return None, None, None, window, (
            f"rejected: the forecast of interval {j} by each of the {len(picks)} candidates "
            f"with status ok failed (status {', '.join(failed)})")
    res, i, wp, hp = picks[best]
    winner = _row(res, i)
    # the winner's settings fitted again on the newest window (it includes interval j): its
    # h alone (one chunk of the same program; the other widths' candidates were never used)
    _, _, res2, window2 = _identify_window(state, j, wp, tuple((d,) for d in winner["delays"]),
                                           (winner["h"],))
    same = _same_settings(c, res2, winner)
    if same:
        winner, window = _row(res2, same[0]), window2
        if "refine" in c.improvements:
            winner = _refine_delays(state, j, wp, winner)
    else:
        window = (window[0] + (w - wp) * S * c.dt, window[1])
    E_cur = float(E[0]) if current is not None else None
    return winner, E_cur, float(E[1 + best]), window, f"forecast of interval {j}"


def _refine_delays(state: OnlineState, j: int, w: int, winner: dict) -> dict:
    """Improved "refine": each tracked input delay of `winner` (a row fitted on the `w` intervals
    up to j) refined by golden-section search within +-delay_step/2 of its grid value (the
    grid's resolution), minimising the observer-initialised E of the winner's structure, N, M
    and h on that window; each trial delay is one search of that h. Returns the row with the
    least E (the winner when no trial beats it)."""
    c = state.config
    best = winner
    E_best = winner["E"] if winner["E"] is not None else math.inf
    g = (math.sqrt(5.0) - 1.0) / 2.0

    def trial(k, d):
        ds = list(best["delays"])
        ds[k] = round(d, 3)
        if ds[k] < 0 or ds[k] + winner["h"] >= c.span_bound:
            return math.inf, None
        _, _, res, _ = _identify_window(state, j, w, tuple((float(v),) for v in ds),
                                        (winner["h"],))
        same = _same_settings(c, res, winner)
        if not same:
            return math.inf, None
        row = _row(res, same[0])
        return (row["E"] if row["E"] is not None else math.inf), row

    for k in range(c.n_inputs):
        if c.delays[k] == 0:
            continue
        d0 = float(best["delays"][k])
        lo, hi = d0 - c.delay_step / 2, d0 + c.delay_step / 2
        x1, x2 = hi - g * (hi - lo), lo + g * (hi - lo)
        f1, f2 = trial(k, x1), trial(k, x2)
        for _ in range(REFINE_STEPS):
            if f1[0] <= f2[0]:
                hi, x2, f2 = x2, x1, f1
                x1 = hi - g * (hi - lo)
                f1 = trial(k, x1)
            else:
                lo, x1, f1 = x1, x2, f2
                x2 = lo + g * (hi - lo)
                f2 = trial(k, x2)
        E_k, row = min((f1, f2), key=lambda v: v[0])
        if row is not None and E_k < E_best:
            best, E_best = row, E_k
    return best


def _same_settings(config: OnlineConfig, res, winner: dict) -> list:
    """Columns of `res` (ok, best E first) with the winner's structure, N, M and h."""
    return [i for i in _ok_columns(config, res) if int(res.columns["n"][i]) == winner["n"]
            and [int(v) for v in res.columns["m"][i]] == winner["m"]
            and float(res.columns["N"][i]) == float(winner["N"])
            and float(res.columns["M"][i]) == float(winner["M"])
            and float(res.columns["h"][i]) == winner["h"]]


def _row(res, i: int) -> dict:
    """The row of a search result by column index (not rank)."""
    return res.row(int(np.flatnonzero(res.rank == i)[0]))


def _best_ok(res):
    if len(res) == 0 or int(res.columns["status"][res.rank[0]]) != 0:
        return None
    return res.row(0)


def _as_model(config: OnlineConfig, row: dict, number: int, op: int, op_time: float) -> dict:
    K, nm = config.n_inputs, config.n_max
    b = np.zeros((K, nm + 1))
    for k in range(K):
        b[k, : len(row["b"][k])] = row["b"][k]
    a = np.zeros(nm + 1)
    a[: row["n"] + 1] = row["a"]
    return {
        "exists": np.asarray(True), "a": a, "b": b,
        "offset": np.asarray(row["offset"] or 0.0), "n": np.asarray(row["n"]),
        "m": np.asarray(row["m"], dtype=np.int64), "N": np.asarray(float(row["N"])),
        "M": np.asarray(float(row["M"])), "h": np.asarray(row["h"]),
        "number": np.asarray(number), "op": np.asarray(op), "op_time": np.asarray(op_time),
        "delays": np.asarray(row["delays"], dtype=np.float64),
    }


def _prediction_signals(state: OnlineState, j: int, delay: float):
    """The observer window and interval j's inputs as Signals (outputs after the observer window
    zeroed; inputs older than `delay` before it zeroed), or (None, why not)."""
    c = state.config
    S, ob, mg = c.samples, c.ob_final, c.margin
    start = j * S - ob - mg
    if start < 0 or start < int(state.n_seen) - c.buffer:
        return None, "no prediction: not enough history for the final-state observer"
    y, u = _take(state, start, mg + ob + S)
    y, u = y.copy(), u.copy()
    y[: mg], y[mg + ob :] = 0.0, 0.0  # outputs outside the observer window are not used
    need = math.ceil(delay / c.dt) + 1  # input history the delays reach
    u[: mg - need] = 0.0  # (the margin is sized for the largest allowed delay)
    if not (np.all(np.isfinite(y)) and np.all(np.isfinite(u))):
        return None, "no prediction: NaN or inf samples in the observer window or inputs"
    return _window_signals(c, y, u, 0.0), "predicted"


def _prediction(state: OnlineState, j: int):
    """Step 5 of interval j-1, evaluated when interval j closes: (y_pred (S,), reason)."""
    c = state.config
    ob, mg = c.ob_final, c.margin
    sig, why = _prediction_signals(state, j, float(np.max(state.model["delays"])))
    if sig is None:
        return None, why
    y_pred, status = _predict(sig, _candidate(c, state.model), mg, ob)
    if int(status) != 0:
        return None, "no prediction: observer failed (" + Status(int(status)).name + ")"
    return np.asarray(y_pred), "predicted"


def _close_interval(state: OnlineState, j: int):
    """Algorithm 1 at the end of interval j (0-based): returns (state, event, record, y_pred)."""
    c = state.config
    S, R = c.samples, c.history
    cleaned = []
    if "spikes" in c.improvements:
        state, cleaned = _clean_spikes(state, j)
    valid, steady, corr, stream, noise, level = _interval_stats(state, j)
    prev_steady = bool(state.iv[(j - 1) % R, 1]) if j > 0 else False
    if "steady" in c.improvements:  # onset: steady after an interval clearly not steady
        onset = steady and j > 0 and float(state.iv[(j - 1) % R, 4]) > HYSTERESIS
    else:
        onset = steady and not prev_steady
    iv = state.iv.copy()
    iv[j % R] = [valid, steady, onset, corr, level]
    t_iv = float(state.t0) + j * S * c.dt
    event = {"interval": j, "t_start": t_iv, "t_end": t_iv + S * c.dt, "valid": valid,
             "steady": steady, "operating_point": onset, "corr": corr, "action": "none",
             "E_current": None, "E_reident": None, "prediction": None}
    if cleaned:
        event["cleaned"] = cleaned
    model = state.model
    y_pred = None
    if bool(model["exists"]):
        y_pred, event["prediction"] = _prediction(state, j)
    state = eqx.tree_at(lambda s: (s.iv, s.n_closed), state, (iv, np.asarray(j + 1)))
    if stream is not None:
        state = eqx.tree_at(lambda s: (s.stream, s.noise), state, (stream, noise))

    def recent(w):  # rows of the last w intervals that exist
        return [iv[(j - i) % R] for i in range(min(w, j + 1))]

    record = None
    has = bool(model["exists"])
    w = c.n_start if not has else c.n_reident
    rows = recent(w)
    alarm = False  # improved "alarm": the prediction just made missed by far more than noise
    if "alarm" in c.improvements and has and y_pred is not None:
        yi, _ = _take(state, j * S, S)
        err = float(np.mean((yi - y_pred) ** 2)) if np.all(np.isfinite(yi)) else 0.0
        alarm = err > ALARM * float(state.noise[1][0])
        event["alarm"] = alarm
    # improved "window": 3000 s windows, but re-identification is triggered (as in the paper)
    # in the n_reident/2 = 6 intervals after an operating point
    w_trig = w // 2 if has and "window" in c.improvements else w
    # ... and once more when the window before interval j first lies wholly after it (a window
    # that spans an abrupt change fits neither regime)
    clean = (has and "window" in c.improvements and j - w >= 0 and w + 1 <= R
             and bool(iv[(j - w) % R][2]))
    if any(r[2] for r in recent(w_trig)) or alarm or clean:  # an operating point (Step 2)
        op_time = max((float(state.t0) + (j - i) * S * c.dt
                       for i, r in enumerate(rows) if r[2]), default=float(model["op_time"]))
        if j + 1 < w:
            event["action"] = f"waiting: {j + 1} of {w} intervals"
        elif not all(r[0] for r in rows):
            event["action"] = ("skipped: NaN, inf or overflowing (beyond 1e154) samples in "
                               "the identification window")
        elif max(r[3] for r in rows) < c.tr_corr:
            event["action"] = (f"skipped: input-output correlation below tr_corr={c.tr_corr:g}"
                               f" (largest over the window's intervals: "
                               f"{max(r[3] for r in rows):.3g})")
        elif not has and (spike := _outlier(state, j, w)) is not None:
            event["action"] = spike
        elif c.mode == "improved":
            best, E_cur, E_best, window, on = _improved_choice(state, j, w, model if has else None)
            # the model predicts from the end of interval j, also when it was fitted on the
            # window one interval earlier (its sim_start said that window's end, one early)
            t_next = float(state.t0) + (j + 1) * S * c.dt
            factor = 1.0 - (c.min_improvement if "hold" in c.improvements else 0.0)
            E_cur_ok = E_cur is not None and math.isfinite(E_cur)
            event.update(E_current=E_cur if E_cur_ok else None, E_reident=E_best,
                         E_on=on if best is not None else None)  # (else `on` is the rejection)
            if best is None:
                event["action"] = on  # the rejection, with the reason (`_improved_choice`)
            elif not has:
                new = _as_model(c, best, 1, 1, op_time)
                event.update(action="first model")
                record = _model_record(c, new, window, None, E_best, "first model", j, "p1",
                                       sim_start=t_next)
                state = eqx.tree_at(lambda s: (s.model, s.op_count), state, (new, np.asarray(1)))
            elif not E_cur_ok or E_best < factor * E_cur:
                same_op = float(model["op_time"]) == op_time
                op = int(state.op_count) + (0 if same_op else 1)
                new = _as_model(c, best, int(model["number"]) + 1, op, op_time)
                event["action"] = (f"model updated: E_reident < {factor:g} E_current ({on})")
                record = _model_record(c, new, window, event["E_current"], E_best,
                                       event["action"], j, f"p{op}", sim_start=t_next)
                state = eqx.tree_at(lambda s: (s.model, s.op_count), state,
                                    (new, np.asarray(op)))
            else:
                event["action"] = f"kept: E_reident >= {factor:g} E_current ({on})"
        else:
            sig, plan, res, window = _identify_window(state, j, w)
            best = _best_ok(res)
            if best is None:
                event["action"] = "rejected: every candidate was flagged" + (
                    f" (the best by E: {describe(res.columns['status'][res.rank[0]])})"
                    if len(res) else "")
            elif not has:  # Step 3: the first model
                new = _as_model(c, best, 1, 1, op_time)
                event.update(action="first model", E_reident=best["E"])
                record = _model_record(c, new, window, None, best["E"], "first model", j, "p1")
                state = eqx.tree_at(lambda s: (s.model, s.op_count), state, (new, np.asarray(1)))
            else:  # Step 4: E_current against E_reident
                E_cur = float(_score(sig, plan.static, plan.where, _candidate(c, model))["E"])
                E_cur_ok = math.isfinite(E_cur)
                event.update(E_current=E_cur if E_cur_ok else None, E_reident=best["E"])
                if not E_cur_ok or best["E"] < E_cur:
                    same_op = float(model["op_time"]) == op_time
                    op = int(state.op_count) + (0 if same_op else 1)
                    new = _as_model(c, best, int(model["number"]) + 1, op, op_time)
                    event["action"] = "model updated: E_reident < E_current"
                    record = _model_record(c, new, window, event["E_current"], best["E"],
                                           event["action"], j, f"p{op}")
                    state = eqx.tree_at(lambda s: (s.model, s.op_count), state,
                                        (new, np.asarray(op)))
                else:
                    event["action"] = "kept: E_reident >= E_current"
    event["model"] = int(state.model["number"])
    return state, event, record, y_pred


def _chunk_arrays(t, y, u, K: int):
    """t (P,), y (P,), u (P, K) of one chunk, checked (time-major; a (K, P) u is refused)."""
    _b.require_x64("update")
    t = _b.array("update", "t", t, ndim=(0, 1), fix="times must be finite")
    t = np.atleast_1d(t)
    P = t.shape[0]
    if np.ndim(y) == 2 and 1 in np.shape(y):  # a column of one output
        raise ValueError(f"update(): y must be 1-D, one output sample per time, got shape "
                         f"{np.shape(y)}; pass y.ravel()")
    y = np.atleast_1d(_b.array("update", "y", y, ndim=(0, 1), finite=False))
    if y.shape != (P,):
        raise ValueError(f"update(): y must have one sample per time (shape ({P},)), got shape "
                         f"{y.shape}")
    u = _b.array("update", "u", u, ndim=(0, 1, 2), finite=False)
    if u.ndim == 0 and P == 1 and K == 1:
        u = u.reshape(1, 1)
    elif u.ndim == 1 and u.shape[0] == P and K == 1:
        u = u[:, None]
    elif u.ndim == 1 and P == 1 and u.shape[0] == K:
        u = u[None, :]
    if u.shape != (P, K):
        hint = "; transpose it (u.T): u is time-major, one row per sample" if u.shape == (
            K, P) else ""
        raise ValueError(f"update(): need u (P, {K}) = ({P}, {K}), one row per time and one "
                         f"column per input; got shape {u.shape}{hint}")
    return t, y, u


def _skip_gap(state: OnlineState, new_seen: int):
    """Jump over a gap longer than the buffer: the buffered samples and interval statistics are
    reset (as if every skipped interval had been closed invalid) in O(buffer), whatever the
    gap's length; the model and the stream statistics are kept. Returns (state, one event)."""
    c = state.config
    S = c.samples
    j0, j1 = int(state.n_seen) // S, new_seen // S
    t0 = float(state.t0)
    state = eqx.tree_at(
        lambda s: (s.buf_y, s.buf_u, s.iv, s.n_seen, s.n_closed), state,
        (np.full_like(state.buf_y, np.nan), np.full_like(state.buf_u, np.nan),
         np.zeros_like(state.iv), np.asarray(new_seen), np.asarray(j1)))
    t_start, t_end = t0 + j0 * S * c.dt, t0 + j1 * S * c.dt
    event = {"interval": j0, "t_start": t_start, "t_end": t_end, "valid": False,
             "steady": False, "operating_point": False, "corr": 0.0,
             "action": f"gap: no samples for {j1 - j0} intervals ({t_end - t_start:g} time "
                       "units, longer than the buffer); buffered history reset",
             "E_current": None, "E_reident": None, "prediction": None,
             "model": int(state.model["number"]), "gap_intervals": j1 - j0}
    return state, event


def update(state: OnlineState, t, y, u):
    """Feed samples (times `t` (P,), output `y` (P,), inputs `u` (P, K)); any chunk size.

    Times must lie on the grid t0 + i dt (t0 = the first sample ever fed) and increase; a jump
    leaves a gap that is filled with NaN (its intervals are invalid); a gap longer than the
    buffer resets the buffered history instead (one event says so; time and memory stay bounded
    by the buffer whatever the jump). NaN or inf samples are accepted and mark their interval
    invalid. `u` is time-major (P, K); a (K, P) array is refused.

    **Returns:** (new state, `OnlineOutputs` of the intervals closed by this chunk).
    """
    if not isinstance(state, OnlineState):
        raise TypeError("update(): state must be an OnlineState (from init or load)")
    _b.eager_only("update", t, y, u)
    c = state.config
    K, S, L = c.n_inputs, c.samples, c.buffer
    narrow = getattr(t, "dtype", None)  # float32 times cannot be on a fine grid: said
    narrow = narrow if narrow in (np.float32, np.float16) else None
    t, y, u = _chunk_arrays(t, y, u, K)
    if t.size == 0 and not math.isfinite(float(state.t0)):  # nothing fed yet: t0 stays open
        return state, OnlineOutputs(t=np.zeros(0), y=np.zeros(0), y_pred=np.zeros(0),
                                    model_number=np.zeros(0, np.int64), events=(), models=())
    t0 = float(state.t0) if math.isfinite(float(state.t0)) else float(t[0])
    idx = np.round((t - t0) / c.dt).astype(np.int64)
    # 1e-6 dt, or the rounding of times this large (epoch seconds at dt = 0.1 read from a CSV
    # with 3 decimals miss the grid by 2.4e-7: refused before)
    off = np.abs(t - (t0 + idx * c.dt))
    tol = np.maximum(1e-6 * c.dt, 8 * np.spacing(np.maximum(np.abs(t), abs(t0))))
    if np.any(off > tol):
        j = int(np.argmax(off > tol))
        raise ValueError(
            f"update(): t is not on the sampling grid t0 + i*dt (t0={t0!r}, dt={c.dt:g}): "
            f"t[{j}] = {float(t[j])!r} is {float(t[j] - (t0 + idx[j] * c.dt)):+.3g} from its "
            f"grid point {float(t0 + idx[j] * c.dt)!r}; " + (
                f"t is {np.dtype(narrow).name}, whose spacing there is "
                f"{float(np.spacing(np.asarray(t[j], narrow))):.3g}: pass the times as float64 "
                "(rounding them in float32 cannot put them on the grid)"
                if narrow and off[j] <= 4 * float(np.spacing(np.asarray(t[j], narrow))) else
                "round the times to the grid, or check dt (a logger's real dt may differ from "
                "its nominal one)"))
    back = np.flatnonzero(np.diff(idx) <= 0)
    if back.size:
        i = int(back[0]) + 1
        raise ValueError(f"update(): t must increase: sample {i} of the chunk (t={t[i]:g}) "
                         f"follows t={t[i - 1]:g}")
    if idx.size and idx[0] < int(state.n_seen):
        raise ValueError(f"update(): t must increase and continue after the samples already "
                         f"fed: the chunk starts at t={t[0]:g}, the next expected sample is at "
                         f"t={t0 + int(state.n_seen) * c.dt:g}; drop the samples before it "
                         "(OnlineIdentifier.next_time)")
    if idx.size > 2 and int(np.min(np.diff(idx))) > 1:  # legal (gaps), but doubtful
        warnings.warn(f"update(): the chunk's samples are at least {int(np.min(np.diff(idx)))} "
                      f"dt apart (dt={c.dt:g}): the samples between them count as missing and "
                      "their intervals as invalid; check OnlineConfig.dt", stacklevel=2)
    state = eqx.tree_at(lambda s: s.t0, state, np.asarray(t0))
    ts, ys, ps, ms, events, models = [], [], [], [], [], []
    pos = 0
    while pos < idx.size:
        n_seen = int(state.n_seen)
        if n_seen % S == 0 and int(idx[pos]) - n_seen > L:  # gap longer than the buffer
            state, event = _skip_gap(state, int(idx[pos]) // S * S)
            events.append(event)
            continue
        end_iv = (n_seen // S + 1) * S  # first index after the current interval
        stop = int(np.searchsorted(idx, end_iv, side="left"))
        # samples pos..stop-1 belong to the current interval (with NaN in the gaps)
        last = min(end_iv, int(idx[stop - 1]) + 1) if stop > pos else n_seen
        span = np.arange(n_seen, last)
        by, bu = state.buf_y.copy(), state.buf_u.copy()
        by[span % L], bu[span % L] = np.nan, np.nan
        sel = idx[pos:stop]
        by[sel % L], bu[sel % L] = y[pos:stop], u[pos:stop]
        if stop == idx.size and last < end_iv:  # chunk ends inside the interval
            state = eqx.tree_at(lambda s: (s.buf_y, s.buf_u, s.n_seen), state,
                                (by, bu, np.asarray(last)))
            break
        # the interval is complete: either the chunk reached its end or jumped past it
        span = np.arange(last, end_iv)
        by[span % L], bu[span % L] = np.nan, np.nan
        state = eqx.tree_at(lambda s: (s.buf_y, s.buf_u, s.n_seen), state,
                            (by, bu, np.asarray(end_iv)))
        j = end_iv // S - 1
        predictor = int(state.model["number"])  # the model in force predicts interval j
        yi, ui = _take(state, j * S, S)  # as measured (improved "spikes" cleans the buffer)
        missing = int(np.sum(np.isnan(yi) & np.all(np.isnan(ui), axis=1)))  # rows never fed
        state, event, record, y_pred = _close_interval(state, j)
        if missing:  # (or NaN in every column): said in the event, warned below if most are
            event["missing"] = missing
        ts.append(t0 + np.arange(j * S, end_iv) * c.dt)
        ys.append(yi)
        ps.append(y_pred if y_pred is not None else np.full(S, np.nan))
        ms.append(np.full(S, predictor if y_pred is not None else 0))
        if y_pred is not None:
            ok = np.isfinite(yi) & np.isfinite(y_pred)  # as `OnlineIdentifier.mse`: NaN and
            event["mse"] = float(np.mean((yi[ok] - y_pred[ok]) ** 2)) if ok.any() else None
        events.append(event)
        if record is not None:
            models.append(record)
        pos = stop
    sparse = [e for e in events if e.get("missing", 0) * 2 >= S]
    if sparse:  # samples fed one at a time at 2 dt (a wrong OnlineConfig.dt) left every
        # interval invalid and nothing was said (the chunk check above needs 3 samples)
        e = sparse[0]
        warnings.warn(f"update(): {len(sparse)} interval(s) closed with at least half their "
                      f"samples missing (interval {e['interval']}: {e['missing']} of {S} never "
                      "fed, or NaN in every column): they are invalid and nothing is identified "
                      f"from them; if the data are sampled less often than dt={c.dt:g}, set "
                      "OnlineConfig.dt to their step", stacklevel=2)
    cat = lambda xs, dt=np.float64: np.concatenate(xs) if xs else np.zeros(0, dt)  # noqa: E731
    return state, OnlineOutputs(
        t=cat(ts), y=cat(ys), y_pred=cat(ps), model_number=cat(ms, np.int64),
        events=tuple(events), models=tuple(models),
    )


# -- checkpoints -------------------------------------------------------------------------------
# Format (version 2): an uncompressed .npz (zip) holding `header` (JSON: format, version, the
# configuration, `extra`, and per leaf its dtype and shape), one member per state leaf named by
# its pytree path (`jax.tree_util.keystr`, e.g. "state.model['a']"), and `sha256`: the SHA-256
# of the header text and of every leaf (path, dtype, shape, bytes) in sorted path order.
# Loading matches leaves by path, so a change of the state's layout is refused (missing or
# extra leaves named), never silently mis-assigned as with version 1's positional leaves.

CHECKPOINT_VERSION = 2


def _leaf_arrays(state: OnlineState) -> dict:
    flat, _ = jax.tree_util.tree_flatten_with_path(state)
    return {"state" + jax.tree_util.keystr(p): np.asarray(v, order="C") for p, v in flat}


def _digest(header_text: str, arrays: dict) -> str:
    import hashlib

    h = hashlib.sha256(header_text.encode())
    for key in sorted(arrays):
        a = arrays[key]
        h.update(f"\0{key}\0{a.dtype.str}\0{a.shape}\0".encode())
        h.update(a.tobytes(order="C"))
    return h.hexdigest()


def _pack(config: dict, extra: dict, arrays: dict) -> bytes:
    import io

    header = json.dumps({
        "format": FORMAT, "version": CHECKPOINT_VERSION, "config": config, "extra": extra,
        "leaves": {k: [a.dtype.str, list(a.shape)] for k, a in sorted(arrays.items())},
    }, sort_keys=True, allow_nan=False)
    buf = io.BytesIO()
    np.savez(buf, header=np.asarray(header), sha256=np.asarray(_digest(header, arrays)),
             **arrays)
    return buf.getvalue()


def save(path, state: OnlineState, extra: dict | None = None) -> None:
    """Write the whole state (configuration included) to one `.npz` file, atomically (a
    temporary file in the same folder, then `os.replace`: a crash mid-save leaves the previous
    checkpoint intact). `extra`: any JSON data to keep with it (e.g. the wrapper's records)."""
    from ._persist import atomic_write, json_safe

    if not isinstance(state, OnlineState):
        raise TypeError("save(): state must be an OnlineState (from init, update or load)")
    try:
        data = _pack(state.config.to_dict(), json_safe(extra or {}), _leaf_arrays(state))
    except (TypeError, ValueError) as err:
        raise ValueError(f"save(): extra must be JSON data ({err})") from None
    atomic_write(path, data)


def load_with_extra(path) -> tuple:
    """(state, extra) of a file written by `save` (`load` returns the state alone)."""
    import zipfile

    redo = "resume from an earlier checkpoint or start again from the data"
    fail = f"load(): {path} is truncated or corrupted and cannot be used; {redo}"
    try:
        with open(path, "rb") as fh:
            raw = fh.read()
    except OSError as err:
        raise ValueError(f"load(): cannot read {path}: {err.strerror}") from None
    if not raw:
        raise ValueError(f"load(): {path} is empty (0 bytes); {redo}")
    import io

    try:
        with np.load(io.BytesIO(raw), allow_pickle=False) as f:
            files = set(f.files)
            header_text = str(f["header"]) if "header" in files else "{}"
            header = json.loads(header_text)
            if not isinstance(header, dict) or header.get("format") != FORMAT:
                raise _Foreign()
            if header.get("version") != CHECKPOINT_VERSION:
                raise _Foreign(header.get("version"))
            digest = str(f["sha256"]) if "sha256" in files else None
            arrays = {k: f[k] for k in files - {"header", "sha256"}}
    except _Foreign as err:
        if err.args:
            raise ValueError(
                f"load(): {path} is an on-line checkpoint of format version {err.args[0]}; "
                f"this mfmjax reads version {CHECKPOINT_VERSION} (leaves stored by path, with a "
                "checksum): re-run the identifier on the data to write a new one"
            ) from None
        raise ValueError(f"load(): {path} is not an mfmjax on-line checkpoint "
                         f"(v{CHECKPOINT_VERSION})") from None
    except (zipfile.BadZipFile, EOFError, OSError, ValueError, KeyError, UnicodeDecodeError,
            RuntimeError, TypeError, AttributeError) as err:  # a damaged file, or a bare .npy
        raise ValueError(f"{fail} ({type(err).__name__}: {str(err)[:80]})") from None
    if digest is None or digest != _digest(header_text, arrays):
        raise ValueError(f"load(): {path} fails its SHA-256 checksum (corrupted); {redo}")
    try:
        like = init(OnlineConfig(**header["config"]))
    except (KeyError, TypeError, ValueError) as err:
        raise ValueError(f"load(): {path} holds an invalid configuration ({err})") from None
    expected = _leaf_arrays(like)
    missing, extra_leaves = sorted(set(expected) - set(arrays)), sorted(set(arrays) - set(expected))
    if missing or extra_leaves:
        raise ValueError(
            f"load(): {path} does not match this mfmjax's on-line state layout (missing leaves "
            f"{missing or 'none'}, unknown leaves {extra_leaves or 'none'}); re-run the "
            "identifier on the data to write a new checkpoint"
        )
    for key, want in expected.items():
        got = arrays[key]
        if got.dtype != want.dtype or got.shape != want.shape:
            raise ValueError(
                f"load(): {path}: leaf {key} has dtype {got.dtype} shape {got.shape}, the "
                f"state needs {want.dtype} {want.shape}; the checkpoint does not fit this config"
            )
    flat, treedef = jax.tree_util.tree_flatten_with_path(like)
    new = [arrays["state" + jax.tree_util.keystr(p)] for p, _ in flat]
    return jax.tree_util.tree_unflatten(treedef, new), header.get("extra", {})


class _Foreign(Exception):
    pass


def load(path) -> OnlineState:
    """Read a state written by `save`; resuming from it continues exactly where it stopped.

    Refuses, with a message saying so, a file of another format or version, an empty,
    truncated or corrupted file (zip CRC or SHA-256 mismatch) and a state of another layout.
    """
    return load_with_extra(path)[0]


# -- convenience wrapper ------------------------------------------------------------------------


def parameter_count(config) -> int:
    """The padded layout's length (a_0..a_nmax, each input's b up to its largest order that
    some structure uses, the offset), as the search builds it: an m above every n (m=[(0, 3)]
    with n=(1, 2)) counted 3 and the search's eta check refused the default eta."""
    structs = structures(config.n, config.m, config.n_inputs)
    return (max(s[0] for s in structs) + 1
            + sum(max(s[1][k] for s in structs) + 1 for k in range(config.n_inputs))
            + int(config.offset))


def _plus(count, more: int):
    """A running count, None (unknown: an older checkpoint) staying None."""
    return None if count is None else count + more


class OnlineIdentifier:
    """Thin stateful wrapper: keeps the state, the prediction series, events and model records.

    `keep_history=False` keeps only the state and the model records (endless streams).
    """

    def __init__(self, config: OnlineConfig | None = None, *, state: OnlineState | None = None,
                 keep_history: bool = True, **kwargs):
        unknown = sorted(set(kwargs) - set(OnlineConfig.__dataclass_fields__))
        if unknown:  # (keep_histroy=False read "give either config or its settings")
            raise TypeError(f"OnlineIdentifier(): unknown argument(s) {unknown}; it takes "
                            "config, state, keep_history, or OnlineConfig's settings as "
                            "keywords")
        if config is not None and kwargs:
            raise TypeError(f"OnlineIdentifier(): give either config or its settings as "
                            f"keywords, not both (got config and {sorted(kwargs)}); use "
                            "dataclasses.replace(config, ...) to change a setting")
        if state is not None and (config is not None or kwargs):
            raise TypeError("OnlineIdentifier(): state carries its own config; give state "
                            "alone")
        if state is None:
            state = init(config if config is not None else OnlineConfig(**kwargs))
        self.state, self.keep_history = state, keep_history
        self.models: list[dict] = []
        self.events: list[dict] = []
        self._series: list[OnlineOutputs] = []
        # squared prediction errors since the identifier started, across save/load and
        # without the history: sum, count, intervals (`mse`; the CLI's checkpoints too)
        # and "predicted": the intervals with a prediction (the CLI said "MSE over 16
        # intervals" of a run whose MSE was over 11); None when a checkpoint did not keep it
        self.prediction = {"sse": 0.0, "count": 0, "intervals": 0, "predicted": 0}
        self._resumed = False

    def update(self, t, y, u) -> OnlineOutputs:
        self.state, out = update(self.state, t, y, u)
        for rec in out.models:
            if self.models:
                self.models[-1]["sim_end"] = rec["sim_start"]
            self.models.append(dict(rec))
        ok = np.isfinite(out.y_pred) & np.isfinite(out.y)
        self.prediction = {"sse": self.prediction["sse"] + float(np.sum(
            (out.y[ok] - out.y_pred[ok]) ** 2)), "count": self.prediction["count"] + int(ok.sum()),
            "intervals": self.prediction["intervals"] + len(out.events),
            "predicted": _plus(self.prediction.get("predicted"), sum(
                e.get("prediction") == "predicted" for e in out.events))}
        if self.keep_history:
            self.events.extend(out.events)
            self._series.append(out)
        return out

    def series(self) -> dict:
        """Concatenated t, y, y_pred, model_number of every closed interval so far."""
        keys = ("t", "y", "y_pred", "model_number")
        if not self._series:
            return {k: np.zeros(0) for k in keys}
        return {k: np.concatenate([getattr(o, k) for o in self._series]) for k in keys}

    def mse(self) -> float:
        """Mean square prediction error over every predicted sample since the identifier
        started (the paper's figure), across `save`/`load` and with `keep_history=False` too;
        NaN before the first prediction."""
        if self.keep_history and not self._resumed:  # the series holds every sample
            s = self.series()
            ok = np.isfinite(s["y_pred"]) & np.isfinite(s["y"])
            return float(np.mean((s["y"][ok] - s["y_pred"][ok]) ** 2)) if ok.any() else math.nan
        p = self.prediction
        return p["sse"] / p["count"] if p["count"] else math.nan

    def why_no_prediction(self) -> str:
        """Why nothing was predicted yet (while `mse()` is NaN), in words: the last interval's
        action that held the first model back (`events`), or that no operating point was
        detected; unknown where the events are not kept (`keep_history=False`, or before a
        `load`). Once predictions were made it says so (it named the last held-back action
        of a run with an MSE of 0.063)."""
        if math.isfinite(self.mse()):
            return (f"predictions are being made ({len(self.models)} models accepted, MSE "
                    f"{self.mse():.4g} so far)")
        if self.models:  # (it said "no prediction yet: first model", as if that were why)
            after = [e for e in self.events if e.get("prediction") and e.get(
                "t_start", -math.inf) >= self.models[0]["sim_start"]]
            if not after and (self.keep_history and not self._resumed):
                return ("no prediction yet: the first model was accepted; it predicts from "
                        "the interval after it, which has not closed yet")
            if after:  # closed, nothing predicted: the last one's reason
                why = after[-1]["prediction"]
                return ("no prediction yet: the first model is accepted; " + (
                    "the intervals it predicted have no finite measured output"
                    if why == "predicted" else why))
        held = [e["action"] for e in self.events if e.get("action", "none") != "none"]
        if held:
            hint = ("; a lower tr_corr (OnlineConfig(tr_corr=...), in the CLI's --config "
                    "'tr_corr = 0.3') identifies on weaker correlation (0.5 is the paper's "
                    "choice, Table 1)" if held[-1].startswith("skipped: input-output "
                                                           "correlation") else "")
            return f"no prediction yet: {held[-1]}{hint}"
        closed = [e for e in self.events if "valid" in e]
        if closed and not any(e["valid"] for e in closed):  # (it blamed the operating point)
            gone = sum(e.get("missing", 0) for e in closed)
            S = self.state.config.samples
            return (f"no prediction yet: every interval so far ({len(closed)}) was invalid "
                    "(NaN, inf or missing samples" + (
                        f": {gone} of {len(closed) * S} samples never fed, or NaN in every "
                        f"column; if the data are sampled less often than "
                        f"dt={self.state.config.dt:g}, set OnlineConfig.dt to their step"
                        if gone else "") + ")")
        cfg, count = self.state.config, int(self.state.n_closed)  # the state's, whole run
        if count == 0:  # (it blamed the operating point: a 25-min record, interval=50 min)
            return (f"no prediction yet: no interval has closed (interval={cfg.interval:g} "
                    f"time units; the first identification needs n_start={cfg.n_start} of "
                    "them): feed more data, or check that interval is in the data's time unit")
        if count < cfg.n_start:  # (from the state: the events of a resumed run are its own)
            return (f"no prediction yet: {count} interval(s) closed, and the first "
                    f"identification needs n_start={cfg.n_start} (interval={cfg.interval:g} "
                    "time units)")
        if not self.keep_history or self._resumed:  # no events to read: do not guess
            return ("no prediction yet (why is not known: the events are not kept with "
                    "keep_history=False or across a load)")
        return ("no prediction yet: no operating point was detected (the first model is "
                "identified at the onset of a steady run: an interval where the output and "
                "every input vary less than steady_rel times their variance so far)")

    def model(self, number: int = -1) -> Model:
        """A model record as a `Model`: `number` indexes `models` (0-based, so the table's
        model nr k is `model(k - 1)`; default -1, the current one)."""
        count = len(self.models)
        if isinstance(number, bool) or not isinstance(number, int | np.integer) \
                or not -count <= number < count:
            raise (IndexError if count else ValueError)(
                f"OnlineIdentifier.model(): number={number!r} names no model; there are "
                f"{count} (0..{count - 1}, or -1 for the current one)" if count else
                "OnlineIdentifier.model(): no model has been accepted yet")
        rec = self.models[number]
        c = self.state.config
        return Model.from_coefficients(
            rec["a"], rec["b"], offset=rec["offset"], delays=rec["delays"],
            intersample=c.intersample, output_name=c.output_name, input_names=c.input_names,
        )

    def table(self, unit: str = "") -> str:
        """The model table (the paper's Tables 2-3 in one); `unit`: the time unit shown in
        the window columns' headers (e.g. "s"; none by default: the data's own unit)."""
        return model_table(self.models, end=self._end(), unit=unit)

    def _end(self):
        n = int(self.state.n_closed) * self.state.config.samples
        return float(self.state.t0) + n * self.state.config.dt if n else None

    def save(self, path) -> None:
        """The state, the model records and the running prediction error (`mse` goes on
        after `load`); the prediction series itself is not saved."""
        save(path, self.state, extra={"models": self.models, "prediction": self.prediction})

    @classmethod
    def load(cls, path, keep_history: bool = True) -> OnlineIdentifier:
        """An identifier from a checkpoint of `save` (or of `mfmjax online --checkpoint`):
        feed it the samples after the last one it saw (`next_time`)."""
        state, extra = load_with_extra(path)
        ident = cls(state=state, keep_history=keep_history)
        ident.models = list(extra.get("models", []))
        if "prediction" in extra:
            ident.prediction = {k: extra["prediction"].get(k) for k in ident.prediction}
        ident._resumed = True
        return ident

    @property
    def next_time(self) -> float | None:
        """The time of the next sample the identifier expects (None before the first)."""
        if int(self.state.n_seen) == 0:
            return None
        return float(self.state.t0) + int(self.state.n_seen) * self.state.config.dt


def model_table(models, end=None, unit: str = "") -> str:
    """The paper's Tables 2-3 (or 4-5) in one: windows, MF settings, orders, parameters, E.
    `unit`: the time unit in the window columns' headers ("" for none: a CSV's own unit)."""
    ident, sim = (f"ident [{unit}]", f"sim [{unit}]") if unit else ("ident", "sim")
    lines = [f"{'nr':>3} {'op':>4} {ident:>13} {sim:>13} {'N':>3} {'M':>3} "
             f"{'h':>6} {'n':>2} {'m':>5} {'E_current':>10} {'E_reident':>10}  parameters"]
    for r in models:
        sim_end = r["sim_end"] if r["sim_end"] is not None else end
        params = " ".join(f"a{i}={v:.4g}" for i, v in enumerate(r["a"]))
        for k, bk in enumerate(r["b"]):
            params += " " + " ".join(f"b{k + 1}{j}={v:.4g}" for j, v in enumerate(bk))
        if r["offset"] is not None:
            params += f" c={r['offset']:.4g}"
        e_cur = "-" if r["E_current"] is None else f"{r['E_current']:.4g}"
        lines.append(
            f"{r['model']:>3} {r['operating_point']:>4} "
            f"{r['ident_window'][0]:>6.0f}-{r['ident_window'][1]:<6.0f} "
            f"{r['sim_start']:>6.0f}-"  # "(next)": accepted, predicting nothing yet
            f"{'' if sim_end is None else '(next)' if sim_end <= r['sim_start'] else f'{sim_end:.0f}':<6} "
            f"{r['N']:>3} {r['M']:>3} {r['h']:>6.4g} {r['n']:>2} "
            f"{','.join(map(str, r['m'])):>5} {e_cur:>10} {r['E_reident']:>10.4g}  {params}"
        )
    return "\n".join(lines)
