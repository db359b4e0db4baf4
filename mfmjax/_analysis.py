r"""What a practitioner checks after identification: compare, residual analysis, step and Bode
responses with uncertainty bands (the delta method on the parameter covariance).

Residual analysis follows MATLAB's `resid` and Ljung (System Identification, 2nd ed., 16.6).
On a window of $N$ samples, $e = y - y_{sim}$ with the state from the initial-state observer
(eq. 14). With $\bar e$, $\bar u_k$ the mean-removed residual and inputs,
$R_e(\tau) = \frac1N \sum_t \bar e(t)\bar e(t-\tau)$,
$R_{eu}(\tau) = \frac1N \sum_t \bar e(t)\bar u(t-\tau)$ (sums over the samples where both
indices exist), $r_{ee} = R_e / R_e(0)$, $r_{ue} = R_{eu} / \sqrt{R_e(0) R_u(0)}$. A positive
lag $\tau$ correlates the residual with past inputs (unmodelled dynamics); a negative one with
future inputs (feedback).

Bounds (99 %, $z = 2.5758$, the standard normal's 0.995 quantile): $\pm z/\sqrt N$ for
$r_{ee}(\tau)$; $\pm z\sqrt{P_1/N}$ for $r_{ue}(\tau)$ with $P_1 = \sum_{k=-L}^{L}
r_{ee}(k) r_{uu}(k)$ (MATLAB's bound: Bartlett's variance of the cross-correlation of two
independent series). The verdicts are portmanteau tests at the 1 % level, not "every lag
inside its bound" (25 lags of white noise would fail that 22 % of the time):
whiteness $Q = N\sum_{\tau=1}^{L} r_{ee}(\tau)^2 \le \chi^2_{0.99}(L)$ (Box-Pierce);
independence of input $k$: $Q = c^T S^{+} c \le \chi^2_{0.99}(\mathrm{rank}\,S)$ with $c$ the
$2L+1$ cross-correlations and $S_{ij} = \frac1N\sum_{k=-L}^{L} r_{ee}(k)\,r_{uu}(k + \tau_j -
\tau_i)$ their Bartlett covariance (diagonal $P_1/N$; eigenvalues below $10^{-10}$ of the
largest dropped).

These verbs run eagerly on concrete data (the correlations in host NumPy; the responses and
their Jacobians in jitted programs, one per structure and grid length).
"""

from __future__ import annotations

import math
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from . import _boundary as _b
from ._jit import jit
from ._model import Model, finite_or_none, growing_poles
from ._observers import fit_percent, observe, validation_window
from ._output_error import free_parameters, order_parameters, with_parameters
from ._signals import Signals
from ._simulate import simulate_status

LEVEL = 0.99
Z99 = 2.5758293035489004  # standard normal 0.995 quantile: a two-sided 99 % band is +-Z99 sigma


def _chi2_99(dof: int) -> float:
    from scipy.stats import chi2

    return float(chi2.ppf(LEVEL, dof))


# -- compare -----------------------------------------------------------------------------------


class Comparison(eqx.Module):
    """Measured and simulated output on a window (state from the observer) and the fit %."""

    t: np.ndarray
    y: np.ndarray
    y_sim: np.ndarray
    fit: float  # `fit_percent(y, y_sim)` (NaN for a constant y)
    output_name: str = eqx.field(static=True)

    def summary(self) -> str:
        return (f"compare {self.output_name} on {self.t[0]:g} .. {self.t[-1]:g} "
                f"({self.t.size} samples): {_fit_text(self.fit)}")

    def plot(self, path) -> None:
        """Write measured vs simulated output with the fit % as a PNG to `path`."""
        from ._plotting import plot_compare

        plot_compare(self, path)


def _check(model, signals, fn):
    _b.require_x64(fn)
    if not isinstance(model, Model):
        raise TypeError(f"{fn}(): model must be a Model, got {type(model).__name__}"
                        f"{_b.swap_hint(fn, model)}")
    if not isinstance(signals, Signals):
        raise TypeError(f"{fn}(): signals must be a Signals, got {type(signals).__name__}"
                        f"{_b.swap_hint(fn, signals)}")
    _b.eager_only(fn, signals, model)  # compare, residuals: host-side comparisons
    _b.same_inputs(fn, model, signals)


def _simulated(model, signals, window, observer_window, fn):
    """(t, y, y_sim, first sample) on the window, the state from the initial-state observer."""
    _check(model, signals, fn)
    k0, length, _ = validation_window(signals, window, observer_window, model.n, fn, "window")
    obs = observe(model, signals, window, observer_window=observer_window)
    y = np.asarray(signals.y)[k0 : k0 + length]
    t = signals.t0 + signals.dt * np.arange(k0, k0 + length)
    return t, y, np.asarray(obs.y_sim), k0


def compare(model: Model, signals: Signals, window=None, *, observer_window=None) -> Comparison:
    """Measured vs simulated output on `window` (default: the record) and the fit % of MATLAB's
    `compare` (`fit_percent`); the state at the window start from the observer (eq. 14) on the
    first `observer_window` time units (default: the whole window). **Returns:** `Comparison`."""
    t, y, y_sim, _ = _simulated(model, signals, window, observer_window, "compare")
    return Comparison(t, y, y_sim, _window_fit("compare", y, y_sim), signals.output_name)


def _window_fit(fn: str, y, y_sim) -> float:
    """fit % on the window; NaN where the output does not move there (undefined), said."""
    if np.ptp(y) > 0:
        return float(fit_percent(y, y_sim))
    warnings.warn(f"{fn}(): the output is constant on the window, so the fit % is undefined "
                  "(NaN); compare on a window where it moves", stacklevel=_b.user_stacklevel())
    return math.nan


def _fit_text(fit: float) -> str:
    return f"fit {fit:.2f} %" if math.isfinite(fit) else "fit undefined (constant output)"


# -- residual analysis -------------------------------------------------------------------------


class Residuals(eqx.Module):
    """Residual analysis (MATLAB `resid`): see the module docstring for every definition."""

    t: np.ndarray  # (N,) times of the residual samples
    e: np.ndarray  # (N,) y - y_sim
    lags: np.ndarray  # (L+1,) 0..L
    auto: np.ndarray  # (L+1,) r_ee(tau), auto[0] = 1
    auto_bound: float  # z / sqrt(N)
    whiteness_stat: float  # Box-Pierce Q
    whiteness_critical: float  # chi2_0.99(L)
    white: bool | None  # None: undefined (constant or rounding-level residuals: `EXACT_FIT`)
    cross_lags: np.ndarray  # (2L+1,) -L..L
    cross: np.ndarray  # (K, 2L+1) r_ue(tau) per input
    cross_bound: np.ndarray  # (K,) z sqrt(P1 / N)
    independence_stat: np.ndarray  # (K,)
    independence_critical: np.ndarray  # (K,)
    independent: tuple  # per input: True / False (None when the input or e is constant)
    fit: float
    output_name: str = eqx.field(static=True)
    input_names: tuple = eqx.field(static=True)

    @property
    def ok(self) -> bool:
        """No test fails: whiteness and independence from every input pass, or are undefined
        (a constant input; residuals constant or at rounding level, `EXACT_FIT`)."""
        return self.white is not False and all(v is not False for v in self.independent)

    def summary(self) -> str:
        N, L = self.e.size, self.lags.size - 1
        flat = self.white is None  # constant residuals: no correlation is defined
        white = ("undefined (the residuals are constant or at rounding level: the model "
                 "reproduces the data)" if flat
                 else "PASS" if self.white else "FAIL")
        out = [f"residual analysis of {self.output_name}: N = {N}, lags 0..{L}, 99 % level, "
               f"{_fit_text(self.fit)}, mean(e) = {np.mean(self.e):.4g}, "
               f"std(e) = {np.std(self.e):.4g}",
               f"whiteness: Q = {self.whiteness_stat:.2f} vs chi2_0.99({L}) = "
               f"{self.whiteness_critical:.2f}: {white} "
               f"({int(np.sum(np.abs(self.auto[1:]) > self.auto_bound))} of {L} lags outside "
               f"+-{self.auto_bound:.3g})"]
        for k, name in enumerate(self.input_names):
            ok = self.independent[k]
            verdict = ("undefined (residuals at rounding level)" if ok is None and flat else
                       "undefined (constant input)" if ok is None else
                       "PASS" if ok else "FAIL")
            outside = int(np.sum(np.abs(self.cross[k]) > self.cross_bound[k]))
            out.append(f"independence from {name}: Q = {self.independence_stat[k]:.2f} vs "
                       f"{self.independence_critical[k]:.2f}: {verdict} ({outside} of "
                       f"{self.cross_lags.size} lags outside +-{self.cross_bound[k]:.3g})")
        return "\n".join(out)

    def to_dict(self) -> dict:
        """JSON-ready verdicts and statistics (no sample arrays; None where a statistic is
        undefined, e.g. the tests of a constant input: JSON has no NaN)."""
        num = finite_or_none
        return {
            "N": int(self.e.size), "lags": int(self.lags.size - 1), "level": LEVEL,
            "fit": num(self.fit), "mean_e": num(np.mean(self.e)), "std_e": num(np.std(self.e)),
            "whiteness": {"pass": None if self.white is None else bool(self.white),
                          "Q": num(self.whiteness_stat),
                          "critical": num(self.whiteness_critical),
                          "bound": num(self.auto_bound)},
            "independence": {name: {"pass": self.independent[k],
                                    "Q": num(self.independence_stat[k]),
                                    "critical": num(self.independence_critical[k]),
                                    "bound": num(self.cross_bound[k])}
                             for k, name in enumerate(self.input_names)},
        }

    def plot(self, path) -> None:
        """Write the auto- and cross-correlation with their 99 % bounds as a PNG to `path`."""
        from ._plotting import plot_residuals

        plot_residuals(self, path)


def _xcorr(a, b, lags):
    """(1/N) sum_t a(t) b(t - tau) for tau in `lags` (sums over the valid samples), by FFT."""
    N = a.size
    size = 1 << (2 * N - 1).bit_length()
    full = np.fft.irfft(np.fft.rfft(a, size) * np.conj(np.fft.rfft(b, size)), size)
    return np.array([full[tau % size] for tau in lags]) / N  # circular index: no wrap (size >= 2N)


# residual RMS at most this fraction of the output's standard deviation: the model reproduces
# the data to rounding (noise-free data; float64 simulations agree to about 1e-13 there), so
# the correlation tests would judge rounding errors, and errors below it are ties (`estimate`)
EXACT_FIT = 1e-9


def exact_floor(y, dt: float = 1.0) -> float:
    """E (eq. 17, dt sum e^2) of residuals at `EXACT_FIT` of the spread of `y`."""
    y = np.asarray(y)
    return float(EXACT_FIT**2 * dt * np.sum((y - np.mean(y)) ** 2))


def whiteness(e, lags: int, y=None):
    """(centred e, its variance, autocorrelation r_ee(0..lags), Box-Pierce Q, white: Q below
    its 99 % chi-square critical value, None when undefined) of residuals e (N,): the
    variance is 0 (no test) for constant residuals, or residuals within `exact_floor` of the
    output `y` (given): a fit to rounding."""
    N = e.size
    eb = e - e.mean()
    Re0 = float(eb @ eb) / N
    if y is not None and float(e @ e) <= exact_floor(y):
        Re0 = 0.0  # rounding errors: no test
    auto = _xcorr(eb, eb, np.arange(lags + 1)) / Re0 if Re0 > 0 else np.full(lags + 1, np.nan)
    Q = float(N * np.sum(auto[1:] ** 2))
    return eb, Re0, auto, Q, (bool(Q <= _chi2_99(lags)) if Re0 > 0 else None)


def residual_tests(e, u, lags: int, y=None):
    """The statistics of `Residuals` from residuals e (N,) and inputs u (N, K) (NumPy); both
    tests are undefined (None) for constant residuals, or residuals within `exact_floor` of
    the output `y` (given): a fit to rounding."""
    N, K = e.size, u.shape[1]
    eb, Re0, auto, Q, white = whiteness(e, lags, y)
    xl = np.arange(-lags, lags + 1)
    r_ee_sym = np.concatenate([auto[:0:-1], auto])  # r_ee(k), k = -L..L
    cross = np.full((K, xl.size), np.nan)
    bound = np.full(K, np.nan)
    stat = np.full(K, np.nan)
    crit = np.full(K, np.nan)
    indep = []
    for k in range(K):
        ub = u[:, k] - u[:, k].mean()
        Ru0 = float(ub @ ub) / N
        if not (Ru0 > 0 and Re0 > 0):
            indep.append(None)
            continue
        cross[k] = _xcorr(eb, ub, xl) / math.sqrt(Re0 * Ru0)
        far = min(3 * lags, N - 1)
        r_uu = np.zeros(3 * lags + 1)
        r_uu[: far + 1] = _xcorr(ub, ub, np.arange(far + 1)) / Ru0
        P1 = float(np.sum(r_ee_sym * r_uu[np.abs(xl)]))
        bound[k] = Z99 * math.sqrt(max(P1, 0.0) / N)
        d = xl[None, :] - xl[:, None]  # tau_j - tau_i
        S = np.einsum("k,ijk->ij", r_ee_sym, r_uu[np.abs(xl[None, None, :] + d[:, :, None])]) / N
        lam, V = np.linalg.eigh(0.5 * (S + S.T))
        keep = lam > 1e-10 * lam.max()
        proj = V[:, keep].T @ cross[k]
        stat[k] = float(np.sum(proj**2 / lam[keep]))
        crit[k] = _chi2_99(int(keep.sum()))
        indep.append(bool(stat[k] <= crit[k]))
    return dict(auto=auto, auto_bound=Z99 / math.sqrt(N), whiteness_stat=Q,
                whiteness_critical=_chi2_99(lags),
                white=white,
                cross_lags=xl, cross=cross, cross_bound=bound, independence_stat=stat,
                independence_critical=crit, independent=tuple(indep), lags=np.arange(lags + 1))


RESIDUAL_LAGS = 25  # lags of the residual tests by default (`residuals`, `estimate`, `srivc`)


def residuals(model: Model, signals: Signals, window=None, *, observer_window=None,
              lags: int = RESIDUAL_LAGS) -> Residuals:
    r"""Residual analysis of `model` on `window` of `signals`, as MATLAB's `resid`.

    $e = y - y_{sim}$ with the state at the window start from the initial-state observer
    (eq. 14, on the first `observer_window` time units; default the whole window). Its
    auto-correlation $r_{ee}(\tau)$, $\tau = 0..L$, and cross-correlation $r_{ue}(\tau)$ with
    each input, $\tau = -L..L$, with 99 % bounds and a whiteness and an independence test
    (definitions, bounds and tests in the module docstring of `mfmjax._analysis`).

    **Arguments:** `lags` = L, an integer in 1..N/4.

    **Returns:** `Residuals` (`white`, `independent`, `ok`, `summary()`, `plot(path)`).
    """
    _check(model, signals, "residuals")
    if isinstance(lags, bool) or not isinstance(lags, (int, np.integer)) or lags < 1:
        raise ValueError(f"residuals(): lags must be an integer >= 1 (got lags={lags!r})")
    N = validation_window(signals, window, observer_window, model.n, "residuals", "window")[1]
    if lags > N // 4:  # before the observer (whose warnings would precede this error)
        raise ValueError(f"residuals(): lags={lags} is more than a quarter of the {N} residual "
                         f"samples; use lags <= {N // 4} or a longer window")
    t, y, y_sim, k0 = _simulated(model, signals, window, observer_window, "residuals")
    u = np.asarray(signals.u)[k0 : k0 + N]
    e = y - y_sim
    stats = residual_tests(e, u, int(lags), y=y)
    fit = _window_fit("residuals", y, y_sim)
    return Residuals(t=t, e=e, fit=fit, output_name=signals.output_name,
                     input_names=tuple(signals.input_names), **stats)


# -- responses with bands ----------------------------------------------------------------------


def model_and_covariance(obj, covariance, fn: str):
    """(model, covariance or None, joint or None) from a Model (+ `covariance`) or a fit with
    `.covariance` (`Estimate`, `OutputErrorFit`, `SrivcFit`), checked against
    `free_parameters(model)`; `joint`: the fit's `joint_covariance` (the parameters' and the
    delays'), where it has a finite one and `covariance` was not given."""
    _b.require_x64(fn)
    names = joint = None
    if isinstance(obj, Model):
        model = obj
    elif isinstance(getattr(obj, "model", None), Model) and hasattr(obj, "covariance"):
        model = obj.model
        names = tuple(getattr(obj, "names", ()) or ()) or None
        held = getattr(obj, "joint_covariance", None)
        if covariance is None and held is not None:
            joint = usable_joint(model, held)
        if covariance is None:
            covariance = usable_covariance(model, obj.covariance)
            if covariance is None:
                import warnings

                warnings.warn(f"{fn}(): the fit carries no usable covariance (empty or not "
                              "finite): no bands", stacklevel=3)
                return model, None, None
    else:
        raise TypeError(f"{fn}(): model must be a Model or a fit with a covariance (Estimate, "
                        f"OutputErrorFit, SrivcFit), got {type(obj).__name__}")
    free, _ = free_parameters(model)
    if names is not None and tuple(names) != free:
        raise ValueError(f"{fn}(): the fit's parameters {list(names)} are not the model's free "
                         f"parameters {list(free)}")
    if covariance is None:
        return model, None, None
    cov = _b.array(fn, "covariance", covariance, ndim=2,
                   fix="an undetermined parameter (infinite variance) has no band: give a finite "
                       "covariance, or leave it out")
    p, K = len(free), model.n_inputs
    if K and cov.shape == (p + K, p + K) and joint is None:  # a joint covariance given
        joint, cov = cov, cov[:p, :p]
    elif cov.shape != (p, p):
        raise ValueError(f"{fn}(): covariance must be ({p}, {p}), ordered as the free parameters "
                         f"{list(free)}" + (f", or ({p + K}, {p + K}) with each input's delay "
                                            "after them (a fit's joint_covariance)" if K else "")
                         + f" (got shape {cov.shape})")
    if np.any(np.diag(cov) < 0) or not np.allclose(cov, cov.T, rtol=1e-8, atol=0.0):
        raise ValueError(f"{fn}(): covariance must be symmetric with a non-negative diagonal")
    cov = np.asarray(cov, dtype=np.float64)
    worst = _least_correlation_eigenvalue(cov if joint is None else joint)
    if worst < -PSD_TOL:  # clamped variances gave bands of zero width
        raise ValueError(f"{fn}(): covariance is not positive semidefinite (its correlation "
                         f"matrix has the eigenvalue {worst:.3g}): no distribution has it; "
                         "check how it was computed (a correlation above 1 in magnitude?)")
    return model, cov, joint


PSD_TOL = 1e-10  # a correlation matrix's eigenvalue below -this: not a covariance (rounding
# leaves about p eps)


def _least_correlation_eigenvalue(cov) -> float:
    """Least eigenvalue of `cov`'s correlation matrix (scale-free), over the parameters of
    positive variance; -inf when a parameter of zero variance covaries with another."""
    d = np.diag(cov)
    pos = d > 0
    if np.any(cov[~pos] != 0):
        return -np.inf
    if not pos.any():
        return 0.0
    s = np.sqrt(d[pos])
    return float(np.linalg.eigvalsh(cov[np.ix_(pos, pos)] / s[:, None] / s[None, :]).min())


def usable_joint(model: Model, joint):
    """A fit's `joint_covariance` (of the free parameters and each input's delay) as a float64
    matrix for the bands, a delay fitted down to its bound 0 (inf std error, warned by the
    fit) counted as known (zero rows; the others keep their share); None when it is absent,
    misshapen or not finite elsewhere (an undetermined parameter: no joint bands)."""
    if joint is None:
        return None
    joint = np.array(joint, dtype=np.float64)
    p = len(free_parameters(model)[0])
    if joint.shape != (p + model.n_inputs,) * 2:
        return None
    lost = p + np.flatnonzero(~np.all(np.isfinite(joint[p:]), axis=1))
    joint[lost, :] = joint[:, lost] = 0.0
    return joint if np.all(np.isfinite(joint)) else None


def usable_covariance(model: Model, covariance):
    """`covariance` as a float64 matrix when it is a finite (p, p) matrix over the model's p
    free parameters, else None (e.g. the NaN covariance of a plain-MFM estimate)."""
    if covariance is None:
        return None
    p = len(free_parameters(model)[0])
    try:
        cov = np.asarray(covariance, dtype=np.float64)
    except (TypeError, ValueError):
        return None
    return cov if cov.shape == (p, p) and np.all(np.isfinite(cov)) else None


def _poles(model):
    return np.roots(np.asarray(model.a, dtype=np.float64)[::-1])


def _growing(fn: str, model, what: str):
    """Warn that the model has poles with Re > 0 (`what`: what that means for `fn`'s result);
    returns the largest growth rate (0 when there is none)."""
    growing = growing_poles(model.a)
    if growing.size == 0:
        return 0.0
    rate = float(np.max(growing.real))
    warnings.warn(f"{fn}(): the model is unstable (poles with Re > 0: "
                  f"{', '.join(f'{p:.3g}' for p in growing)}): {what}", stacklevel=3)
    return rate


def _placed(cov, joint, live, size: int, K: int):
    """The covariance of (`order_parameters`' vector (size), the K delays): `joint` (the free
    parameters' and the delays') or `cov` (the free parameters' alone: delays known, zero
    rows) at the positions `live`, zero elsewhere (the extra coefficients are known zeros);
    None stays None."""
    if cov is None:
        return None
    at = np.concatenate([live, size + np.arange(K)])
    out = np.zeros((size + K, size + K))
    if joint is None:
        out[np.ix_(live, live)] = cov
    else:
        out[np.ix_(at, at)] = joint
    return out


def _value_and_std(f, theta, cov):
    """f(theta) and, with a covariance, the delta method's sqrt(diag(J cov J^T)) (J = jacfwd;
    columns of zero variance left out: a delay held where its derivative is not defined)."""
    value = f(theta)
    if cov is None:
        return value, None
    J = jax.jacfwd(f)(theta).reshape(-1, theta.shape[0])
    J = jnp.where(jnp.diag(cov)[None, :] > 0, J, 0.0)
    var = jnp.einsum("ij,jk,ik->i", J, cov, J)
    return value, jnp.sqrt(jnp.maximum(var, 0.0)).reshape(value.shape)


class StepResponse(eqx.Module):
    """Unit-step response of each input from rest (offset excluded), with a 99 % band
    (value +- 2.576 std, delta method) when a covariance was given (else `std` is None)."""

    t: np.ndarray  # (T,)
    y: np.ndarray  # (K, T)
    std: np.ndarray | None  # (K, T)
    output_name: str = eqx.field(static=True)
    input_names: tuple = eqx.field(static=True)

    @property
    def lower(self):
        return None if self.std is None else self.y - Z99 * self.std

    @property
    def upper(self):
        return None if self.std is None else self.y + Z99 * self.std

    def plot(self, path) -> None:
        """Write the step responses (with bands when available) as a PNG to `path`."""
        from ._plotting import plot_step

        plot_step(self, path)


def _step_base(form):
    """The model's `simulation_form` (one program per order n) as the step programs see it:
    zoh inputs, offset 0."""
    from ._pytree import replace_fields

    return replace_fields(form, offset=np.float64(0.0), intersample=("zoh",) * form.n_inputs)


@jit
def _step_program(base, theta, u, cov, dt):
    """Step response y (T,) for inputs u (T+1, K) that step at sample 1 (inputs before sample
    0 are held at u[0] = 0, so delays see rest), and its delta-method std; `theta` ends with
    the K delays' shifts from the model's (zeros: their derivatives for the band)."""
    P = theta.shape[0] - base.n_inputs

    def f(th):
        m = with_parameters(base, th[:P])
        m = eqx.tree_at(lambda q: (q.offset, q.delays), m,
                        (jnp.zeros_like(m.offset), base.delays + th[P:]))
        y, _, status = simulate_status(m, u, jnp.zeros(base.n), dt)
        # an overflowing response is frozen at its last finite state: NaN, so that
        # `step_response` raises (a flat 5e149 came back for a pole at +1 over 400 s)
        y = jnp.where(status == 0, y, jnp.nan)
        return y[1:]  # y at t_j - dt = the step response at j dt, j = 0..T-1
    return _value_and_std(f, theta, cov)


def step_response(model, t_final=None, *, covariance=None, n_points: int = 500) -> StepResponse:
    r"""Unit-step response of each input (from rest, offset excluded, delays included) by the
    exact simulation, on `n_points` times 0..`t_final` (default: 7 time constants of the
    slowest stable pole, at least 3 periods of the slowest undamped oscillation, or 3
    e-folding times of the fastest growing mode; 7 with integrators alone; plus the largest
    delay), with a 99 % band $\pm 2.576\sigma$ from the
    delta method ($\sigma^2 = \mathrm{diag}(J \Sigma J^T)$, $J$ the Jacobian of the response in
    the free parameters by `jax.jacfwd`, $\Sigma$ their covariance; delays count as known,
    unless the fit carries `joint_covariance` (delays fitted or counted: `output_error(...,
    fit_delays=True)`, an `estimate` that fitted its grid's delays): then the Jacobian holds
    the delays' columns and $\Sigma$ is the joint one).

    **Arguments:** `model`: a `Model`, or a fit carrying its covariance (`Estimate`,
    `OutputErrorFit`, `SrivcFit`); `covariance`: of `free_parameters(model)` (a_0..a_{n-1},
    b_kj, offset), or a joint one with each input's delay after them (a fit's
    `joint_covariance`, `load_covariance(path, joint=True)`), overrides the fit's.
    **Returns:** `StepResponse`.
    """
    _b.eager_only("step_response", model, t_final, covariance)
    model, cov, joint = model_and_covariance(model, covariance, "step_response")
    n_points = _b.integer("step_response", "n_points", n_points, lo=2, hi=100_000)
    p = _poles(model)
    rate = _growing("step_response", model, "its step response grows without bound" + (
        "; the default horizon shows 3 e-folding times of the fastest growing mode"
        if t_final is None else ""))
    # poles within the roots' rounding of the imaginary axis (as `growing_poles`): an
    # undamped pair came back from np.roots at Re = -7e-17 and, counted as stable, set a
    # default horizon of 1e17 (the oscillation's phase lost to float64, the values off by 3.7)
    tol = 1e-9 * np.max(np.abs(p), initial=0.0)
    axis = p[np.abs(p.real) <= tol]
    if t_final is None:  # 7 time constants of the slowest stable pole, or 3 e-folding times
        # of the fastest unstable one (the slowest stable pole hid a slow divergence: the
        # DaISy dryer's +0.00055 looked settled at 988 s); at least 3 periods of the slowest
        # undamped oscillation
        stable, omega = p[p.real < -tol], np.abs(axis.imag[np.abs(axis.imag) > tol])
        scale = 7.0 / np.min(-stable.real) if stable.size else 0.0
        if omega.size:
            scale = max(scale, 3.0 * 2.0 * np.pi / np.min(omega))
        if scale == 0:  # integrators only: 7 x the smallest nonzero |p|'s time, or 7
            rest = np.abs(p[np.abs(p) > tol])
            scale = 7.0 / np.min(rest) if rest.size else 7.0
        t_final = (3.0 / rate if rate > 0 else scale) + float(
            np.max(np.asarray(model.delays), initial=0.0))
    t_final = _b.number("step_response", "t_final", t_final, lo=0, lo_open=True,
                        fix="give the duration in the model's time unit")
    dt = np.float64(t_final / (n_points - 1))  # a value: no program per t_final
    form, theta, live = order_parameters(model, free_parameters(model)[1])
    base, ys, stds = _step_base(form), [], []
    cov = _placed(cov, joint, live, theta.size, model.n_inputs)
    theta = np.concatenate([theta, np.zeros(model.n_inputs)])  # the delays' shifts
    for k in range(model.n_inputs):
        u = np.zeros((n_points + 1, model.n_inputs))
        u[1:, k] = 1.0
        y, sd = _step_program(base, theta, u, cov, dt)
        ys.append(np.asarray(y))
        if sd is not None:
            stds.append(np.asarray(sd))
    y = np.stack(ys) if ys else np.zeros((0, n_points))
    if not np.all(np.isfinite(y)):
        raise ValueError("step_response(): the response overflows float64 (unstable model); "
                         "give a shorter t_final")
    if stds and not all(np.all(np.isfinite(sd)) for sd in stds):
        raise ValueError("step_response(): the band overflows float64 (the response's "
                         f"sensitivity to the parameters over t_final={t_final:g}); give a "
                         "shorter t_final")
    return StepResponse(np.arange(n_points) * dt, y, np.stack(stds) if cov is not None and stds
                        else None, model.output_name, tuple(model.input_names))


class FrequencyResponse(eqx.Module):
    r"""$H_k(j\omega) = B_k(j\omega) / A(j\omega)\, e^{-j\omega\tau_k}$ per input, magnitude in
    dB and unwrapped phase in degrees, with 99 % bands ($\pm 2.576\sigma$, delta method) on both
    when a covariance was given (else the std fields are None)."""

    w: np.ndarray  # (W,) rad per time unit
    H: np.ndarray  # (K, W) complex
    mag_db: np.ndarray  # (K, W)
    phase_deg: np.ndarray  # (K, W)
    mag_db_std: np.ndarray | None
    phase_deg_std: np.ndarray | None
    output_name: str = eqx.field(static=True)
    input_names: tuple = eqx.field(static=True)

    def plot(self, path, *, nyquist: float | None = None) -> None:
        """Write the Bode diagram (with bands when available) as a PNG to `path`. `nyquist`
        (rad per time unit, e.g. pi / dt of the data the model came from): marked, and the
        frequencies above it shaded, where the sampled data said nothing about the model."""
        from ._plotting import plot_bode

        if nyquist is not None:
            nyquist = _b.number("FrequencyResponse.plot", "nyquist", nyquist, lo=0.0,
                                lo_open=True)
        plot_bode(self, path, nyquist)


@jit
def _freq_program(base, theta, w, cov, k):
    """(|H_k| in dB, angle of B_k/A in rad) (2, W) at w and its delta-method std (the delay
    term -w tau_k is added outside; `theta` ends with the K delays' shifts, zeros, whose
    derivative -w enters the phase's band)."""
    s = 1j * w
    P = theta.shape[0] - base.n_inputs

    def f(th):
        m = with_parameters(base, th[:P])
        A = jnp.polyval(m.a[::-1].astype(jnp.complex128), s)
        B = jnp.polyval(jnp.stack(m.b)[k][::-1].astype(jnp.complex128), s)  # k: a value
        H = B / A
        return jnp.stack([20.0 * jnp.log10(jnp.abs(H)), jnp.angle(H) - w * th[P + k]])
    return _value_and_std(f, theta, cov)


def frequency_response(model, w=None, *, covariance=None, n_points: int = 400):
    r"""Frequency response of each input's transfer function $B_k(s)/A(s)\,e^{-s\tau_k}$ at
    `w` (rad per time unit; default `n_points` log-spaced from 0.01x the smallest to 100x the
    largest nonzero pole or zero magnitude), with 99 % bands on magnitude (dB) and phase (deg)
    from the delta method (`jax.jacfwd` in the free parameters; delays count as known unless
    the fit carries `joint_covariance`, as `step_response`: the phase band then holds
    -w tau_k's share).

    **Arguments:** as `step_response`. **Returns:** `FrequencyResponse`.
    """
    _b.eager_only("frequency_response", model, w, covariance)
    model, cov, joint = model_and_covariance(model, covariance, "frequency_response")
    _growing("frequency_response", model, "B_k(jw)/A(jw) is defined, but it is no "
             "steady-state response (the model has none)")
    if w is None:
        n_points = _b.integer("frequency_response", "n_points", n_points, lo=2, hi=100_000)
        w = _default_grid(np.concatenate([_poles(model)] + [np.roots(np.asarray(bk)[::-1])
                                                            for bk in model.b]), n_points)
    w = _b.array("frequency_response", "w", w, ndim=1)
    if w.size < 1 or np.any(w <= 0):
        raise ValueError("frequency_response(): w must hold frequencies > 0 (rad per time unit)")
    w = np.asarray(w, dtype=np.float64)
    base, theta, live = order_parameters(model, free_parameters(model)[1])
    cov = _placed(cov, joint, live, theta.size, model.n_inputs)
    theta = np.concatenate([theta, np.zeros(model.n_inputs)])  # the delays' shifts
    delays = np.asarray(model.delays, dtype=np.float64)
    Hs, mags, phases, mstd, pstd = [], [], [], [], []
    for k in range(model.n_inputs):
        val, sd = _freq_program(base, theta, w, cov, np.int32(k))
        mag, ang = np.asarray(val)
        if not (np.all(np.isfinite(mag)) and np.all(np.isfinite(ang))):
            raise ValueError(f"frequency_response(): the response of input "
                             f"{model.input_names[k]!r} is zero or infinite at some w (its "
                             "magnitude in dB is not finite); check b_k and the poles on the "
                             "imaginary axis, or give other frequencies w")
        phase = _continuous_phase(ang, w, model.a, model.b[k]) - w * delays[k]
        mags.append(mag)
        phases.append(np.degrees(phase))
        Hs.append(10 ** (mag / 20) * np.exp(1j * phase))
        if sd is not None:
            sd = np.asarray(sd)
            if not np.all(np.isfinite(sd)):
                raise ValueError("frequency_response(): the band is not finite (the response's "
                                 "sensitivity to the parameters overflows); check the model")
            mstd.append(sd[0])
            pstd.append(np.degrees(sd[1]))
    K = model.n_inputs
    empty = np.zeros((K, w.size))
    return FrequencyResponse(
        w, np.stack(Hs) if K else empty.astype(complex), np.stack(mags) if K else empty,
        np.stack(phases) if K else empty,
        (np.stack(mstd) if K else empty) if cov is not None else None,
        (np.stack(pstd) if K else empty) if cov is not None else None,
        model.output_name, tuple(model.input_names))


def _default_grid(roots, n_points: int) -> np.ndarray:
    """`n_points` log-spaced from 0.01x the smallest to 100x the largest nonzero root
    magnitude, each damped root's natural frequency wn and half-power points wn (1 +- zeta)
    put in place of the nearest grid points (a lightly damped peak fell between grid points:
    32.8 dB shown of 54.0 dB at zeta = 0.001), and a point within 1e-9 of an undamped root's
    wn (where the response is 0 or inf) moved 1e-6 above it. The length stays `n_points`: one
    compiled program for every model of a layout."""
    roots = roots[np.isfinite(roots) & (np.abs(roots) > 0)]
    mags = np.abs(roots)
    lo, hi = (mags.min(), mags.max()) if mags.size else (1.0, 1.0)
    w = np.logspace(np.log10(0.01 * lo), np.log10(100 * hi), n_points)
    zeta = np.abs(roots.real) / mags
    damped = zeta > 1e-12
    # half-power points first, the peaks last: a peak wins a grid point it shares
    extra = np.concatenate([mags[damped] * (1 - zeta[damped]), mags[damped] * (1 + zeta[damped]),
                            mags[damped]])
    free = np.ones(n_points, bool)  # grid points not yet taken by an extra frequency
    for f in extra[(extra > w[0]) & (extra < w[-1])]:
        cand = np.flatnonzero(free) if free.any() else np.arange(n_points)
        i = cand[np.argmin(np.abs(np.log(w[cand] / f)))]
        w[i], free[i] = f, False
    w = np.sort(w)
    for wn in mags[~damped]:
        w = np.where(np.abs(w - wn) <= 1e-9 * wn, wn * (1 + 1e-6), w)
    return w


def _continuous_phase(ang, w, a, b) -> np.ndarray:
    """The phase of B(jw)/A(jw) at `w`, continuous in w: `ang` (its principal value) moved by
    2 pi to the branch nearest the sum of its factors' angles, angle(jw - z) - angle(jw - p),
    each continuous for w > 0. `np.unwrap` of samples chose the wrong branch wherever the
    phase moved by more than 180 degrees between grid points (1/(s + 1)^4 at w = 0.1, 10:
    +22.8 degrees for -337.2). The branch is the one continuous from w -> 0, where the phase is
    0 for a positive DC gain and +180 degrees for a negative one (as a grid starting low shows
    it, in python-control and MATLAB too), less 90 per net integrator: a grid starting at high
    frequency kept its first point's principal value (1/(s + 1)^4 at w = 10 alone: +22.8
    degrees for -337.2)."""
    b = np.trim_zeros(np.asarray(b, dtype=np.float64), "b")
    a = np.trim_zeros(np.asarray(a, dtype=np.float64), "b")
    zeros, poles = np.roots(b[::-1]), np.roots(a[::-1])

    def factors(x):  # the sum of the factors' angles at the frequencies x > 0
        jx = 1j * np.asarray(x)[:, None]
        return (np.angle(b[-1]) + np.sum(np.angle(jx - zeros[None, :]), axis=1)
                - np.sum(np.angle(jx - poles[None, :]), axis=1))

    ka, kb = int(np.argmax(a != 0)), int(np.argmax(b != 0))  # integrators, differentiators
    dc = (0.0 if b[kb] / a[ka] > 0 else np.pi) - (ka - kb) * np.pi / 2
    roots = np.abs(np.r_[zeros, poles])
    tiny = 1e-9 * min([float(np.min(w))] + [float(r) for r in roots if r > 0])
    guide = factors(w)
    guide = guide + 2 * np.pi * np.round((dc - factors([tiny])[0]) / (2 * np.pi))
    return ang + 2 * np.pi * np.round((guide - ang) / (2 * np.pi))


def saved_covariance(path, model: Model):
    """(covariance or None, a sentence saying which) from a model file written by `save_model`
    (`load_covariance`): the joint one of the parameters and the delays where the file holds
    it, else the parameters' (the delays then count as known, said where one is nonzero)."""
    from ._persist import load_covariance

    cov = load_covariance(path, model)
    if cov is None:
        return None, ("no bands: the model file has no covariance (none is saved for a "
                      "model without finite standard errors, e.g. an estimate whose method is "
                      "'mfm'; from Python: save_model(model, path, "
                      "covariance=estimate.covariance) where they are finite)")
    joint = load_covariance(path, model, joint=True)
    text = "bands: 99 % (+-2.576 sigma, delta method on the saved covariance"
    if joint is not None:
        return joint, text + ", the fitted delays' uncertainty included)"
    if np.any(np.asarray(model.delays) != 0):
        return cov, (text + "; the delays count as known: the file holds no covariance of "
                     "them, which a fit of the delays saves (identify --refine --delays, "
                     "search --estimate; from Python: save_model(..., "
                     "joint_covariance=fit.joint_covariance)))")
    return cov, text + ")"
