"""Peers of the real-data benchmark (issue 15, item 6): ARX and N4SID from `sippy-unipi`, and a
SciPy continuous-time SRIVC followed by output error, on the four DaISy records.

    pip install sippy-unipi            # benchmark-only dependency
    python benchmarks/real_data_peers.py

Protocol (the same for every peer, and for mfmjax in benchmarks/real_data.py):

- Split: first 2/3 of the samples = estimation data, last 1/3 = validation.
- Tasks: heat exchanger (1 input -> 1 output), industrial dryer (3 inputs -> dry-bulb temperature,
  the first output, as `daisy('dryer')`), glass furnace (3 inputs -> all six outputs; fit per output
  and their mean), heating system (1 input -> 1 output).
- Means: the means of the estimation data are removed from inputs and outputs; the same means are
  removed from the validation data. (Inside structure selection the fit part plays the role of the
  estimation data: its means are the ones removed.)
- Structure selection on estimation data only: the estimation data are split into a fit part (their
  first 2/3) and a hold-out part (their last 1/3); every candidate structure is estimated on the fit
  part and scored by its simulation fit % on the hold-out part (scored as below); the best one is
  re-estimated on all estimation data. One rule for all peers: best hold-out simulation fit %
  (per output for the MISO peers ARX and SRIVC, the mean over the outputs for the MIMO N4SID).
- Score: fit % = 100 (1 - ||y - y_sim|| / ||y - mean y||) on the whole scored window, simulation
  (not prediction), initial state by least squares on the first 20 % of the window (x0 = argmin
  ||y - (O x0 + forced response from rest)|| over those samples, `validation_fit`), then simulated
  over all of it. Input delays are whole samples, applied to the whole record, so the delayed input
  at the start of a window is the measured one. This matches mfmjax's initial-state observer over
  the first 20 % of the window.
- Peers and grids:
  ARX (sippy, least squares): na, nb in 1..5, nk in 0..3 (true delay in samples, nk = 0 is direct
  feed-through; sippy counts its delay from 1, so its `theta` is nk - 1, with the input advanced one
  sample for nk = 0); nb and nk common to all inputs.
  N4SID (sippy, MIMO for the glass furnace): order 1..8, horizon f in {10, 20}, D free or zero.
  SRIVC (tests/reference_srivc.py, time in samples): n in 1..3, numerator degrees m_k in 0..n
  (m_k = n is feed-through), chosen per input for n <= 2 and common to all inputs for n = 3; delay
  0..3 samples (common) on the heating system, none elsewhere; started from a
  state-variable-filter least squares with the filter pole at lambda in {0.3, 0.1, 0.03, 0.01} per
  sample, keeping the start whose SRIVC has the lowest fit-part error.
  If no start gives a stable SRIVC on all estimation data, the fit-part estimate is kept
  (`srivc_refit_stable: false` in the results).
  SRIVC+OE: each SRIVC estimate refined by output error: scipy.optimize.least_squares over the
  denominator, with the numerators and the initial state (linear in the simulated output) solved
  by least squares over the whole window at each step (variable projection); the structure chosen
  again by the hold-out rule.
- Times: wall seconds per record and peer, structure selection + final fit. SRIVC+OE includes the
  SRIVC runs it starts from. BLAS threads are set to 1 (OPENBLAS/OMP/MKL_NUM_THREADS) when this
  module is imported before NumPy; threaded BLAS on these tiny matrices made SciPy's expm ~70x
  slower on the shared 2-core machine.
"""

from __future__ import annotations

import contextlib
import io
import itertools
import json
import os
import sys
import time
import warnings

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")  # small matrices: threaded BLAS is ~70x slower (expm)

import numpy as np  # noqa: E402
from scipy import optimize, signal  # noqa: E402

from mfmjax.datasets import DAISY, daisy  # noqa: E402

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "tests"))
import reference_srivc  # noqa: E402

TASKS = {  # record: outputs (daisy output names), SRIVC delay grid in samples
    "heat_exchanger": dict(outputs=["theta"], delays=(0,)),
    "dryer": dict(outputs=["dry_bulb"], delays=(0,)),
    "glass_furnace": dict(outputs=["y1", "y2", "y3", "y4", "y5", "y6"], delays=(0,)),
    "heating_system": dict(outputs=["y"], delays=(0, 1, 2, 3)),
}
OBSERVER_FRACTION = 0.2
ARX_NA, ARX_NB, ARX_NK = range(1, 6), range(1, 6), range(0, 4)
N4SID_ORDERS, N4SID_HORIZONS = range(1, 9), (10, 20)
SRIVC_ORDERS, SRIVC_LAMBDAS = (1, 2, 3), (0.3, 0.1, 0.03, 0.01)
PEERS = ("ARX", "N4SID", "SRIVC", "SRIVC+OE")


# --------------------------------------------------------------------------- shared protocol
def fit_percent(y, y_sim):
    """100 (1 - ||y - y_sim|| / ||y - mean y||) per column of (T, p) arrays."""
    y, y_sim = np.atleast_2d(y.T).T, np.atleast_2d(y_sim.T).T
    err = np.linalg.norm(y - y_sim, axis=0)
    return 100.0 * (1.0 - err / np.linalg.norm(y - y.mean(axis=0), axis=0))


def validation_fit(simulate_from_x0, n_states, y, fraction=OBSERVER_FRACTION):
    """The shared score. `simulate_from_x0(x0) -> (T, p)` simulates the window from the initial
    state x0 (affine in x0); x0 is the least-squares fit of the first `fraction` of the window,
    then the whole window is scored. **Returns:** (fit % per output, y_sim, x0)."""
    y = np.asarray(y, dtype=float).reshape(len(y), -1)
    forced = np.asarray(simulate_from_x0(np.zeros(n_states))).reshape(y.shape)
    free = np.stack([np.asarray(simulate_from_x0(e)).reshape(y.shape) - forced
                     for e in np.eye(n_states)], axis=-1)  # (T, p, n)
    k = max(int(round(fraction * len(y))), 1)
    if not (np.all(np.isfinite(forced)) and np.all(np.isfinite(free))):
        return np.full(y.shape[1], -np.inf), forced, np.full(n_states, np.nan)
    x0 = np.linalg.lstsq(free[:k].reshape(-1, n_states), (y - forced)[:k].ravel(), rcond=None)[0]
    y_sim = forced + free @ x0
    if not np.all(np.isfinite(y_sim)):
        return np.full(y.shape[1], -np.inf), y_sim, x0
    return fit_percent(y, y_sim), y_sim, x0


def ss_simulator(A, B, C, D, u):
    """x0 -> y (T, p) of x_{t+1} = A x_t + B u_t, y_t = C x_t + D u_t over the inputs u (T, K)."""
    A, B, C, D = (np.atleast_2d(np.asarray(M, dtype=float)) for M in (A, B, C, D))
    Bu = u @ B.T

    def simulate(x0):
        x, out = np.asarray(x0, dtype=float).copy(), np.empty((len(u), C.shape[0]))
        with np.errstate(all="ignore"):
            for t in range(len(u)):
                out[t] = C @ x
                x = A @ x + Bu[t]
        return out + u @ D.T

    return simulate


def tf_simulator(nums, den, u):
    """x0 -> y (T, 1) of the MISO transfer function sum_k nums[k](z)/den(z) u_k (descending powers
    of z, common denominator); x0 weights the n = deg den free responses (impulses of 1/den at
    t = 0..n-1, a basis of the free responses)."""
    den = np.asarray(den, dtype=float)
    n = den.size - 1
    forced = sum(signal.lfilter(np.concatenate([np.zeros(den.size - len(b)), b]), den, u[:, k])
                 for k, b in enumerate(nums))
    imp = np.zeros((len(u), n))
    imp[np.arange(n), np.arange(n)] = 1.0
    basis = signal.lfilter([1.0], den, imp, axis=0)

    def simulate(x0):
        return (forced + basis @ np.asarray(x0, dtype=float))[:, None]

    return simulate, n


def delayed(u, lags):
    """u_k(t - lag_k) over the whole record, holding the first value before it."""
    return np.stack([u[np.clip(np.arange(len(u)) - lag, 0, len(u) - 1), k]
                     for k, lag in enumerate(lags)], axis=1)


# --------------------------------------------------------------------------- data
def record(name):
    """(Y (T, p), U (T, K), dt, intersample) of the task `name`."""
    sigs = [daisy(name, output=o) for o in TASKS[name]["outputs"]]
    Y = np.column_stack([np.asarray(s.y, dtype=float) for s in sigs])
    return Y, np.asarray(sigs[0].u, dtype=float), float(sigs[0].dt), tuple(sigs[0].intersample)


def centred(Y, U, a, b, remove_means=True):
    """Y, U minus the means of the rows a:b (the estimation window); unchanged if not
    remove_means (a variant for comparison only, not the protocol)."""
    if not remove_means:
        return Y, U
    return Y - Y[a:b].mean(axis=0), U - U[a:b].mean(axis=0)


@contextlib.contextmanager
def quiet():
    with contextlib.redirect_stdout(io.StringIO()), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        yield


# --------------------------------------------------------------------------- ARX (sippy)
def _sippy():
    try:
        from sippy_unipi import system_identification
    except ImportError as err:
        raise ImportError("real_data_peers needs sippy-unipi (a benchmark-only dependency): "
                          "pip install sippy-unipi") from err
    return system_identification


def arx_fit(Y, U, a, b, na, nb, nk):
    """sippy ARX on rows a:b, delay nk in samples (0 = feed-through). Returns per output
    (den, [b_k]) with b_k the coefficients of lags nk..nk+nb-1."""
    system_identification = _sippy()
    if nk == 0:  # sippy's first lag is 1: advance the input one sample
        y, u, theta = Y[a:b - 1], U[a + 1:b], 0
    else:
        y, u, theta = Y[a:b], U[a:b], nk - 1
    with quiet():
        model = system_identification(y, u, "ARX", ARX_orders=[na, nb, theta])
    out = []
    for i in range(Y.shape[1]):
        den = np.asarray(model.DENOMINATOR[i][0], dtype=float)[: na + 1]
        nums = [np.asarray(model.NUMERATOR[i][k], dtype=float)[theta:theta + nb]
                for k in range(U.shape[1])]
        out.append((den, nums))
    return out


def arx_score(model, Y, U, a, b, nk):
    """Fit % per output on rows a:b; the ARX as a transfer function of the delayed input."""
    Ud = delayed(U, [nk] * U.shape[1])[a:b]
    fits = []
    for i, (den, nums) in enumerate(model):
        p = max(den.size - 1, max(len(n_) for n_ in nums) - 1)
        den_z = np.concatenate([den, np.zeros(p - (den.size - 1))])
        nums_z = [np.concatenate([n_, np.zeros(p + 1 - len(n_))]) for n_ in nums]
        if p == 0:
            fits.append(float(fit_percent(Y[a:b, i], sum(n_[0] * Ud[:, k] for k, n_ in
                                                         enumerate(nums_z)))[0]))
            continue
        sim, ns = tf_simulator(nums_z, den_z, Ud)
        fits.append(float(validation_fit(sim, ns, Y[a:b, i])[0][0]))
    return np.array(fits)


def peer_arx(Y, U, e, v, remove_means=True):
    """ARX: structure per output by hold-out fit, then re-estimated on the estimation data."""
    h = (2 * e) // 3
    Yc, Uc = centred(Y, U, 0, h, remove_means)
    best = [(-np.inf, None)] * Y.shape[1]
    for na in ARX_NA:
        for nb in ARX_NB:
            for nk in ARX_NK:
                fits = arx_score(arx_fit(Yc, Uc, 0, h, na, nb, nk), Yc, Uc, h, e, nk)
                best = [max(bst, (f, (na, nb, nk)), key=lambda t: t[0])
                        for bst, f in zip(best, fits)]
    Yc, Uc = centred(Y, U, 0, e, remove_means)
    fits = []
    for i, (hold, (na, nb, nk)) in enumerate(best):
        model = arx_fit(Yc[:, [i]], Uc, 0, e, na, nb, nk)
        fits.append(float(arx_score(model, Yc[:, [i]], Uc, e, v, nk)[0]))
    return dict(structure=[dict(na=s[1][0], nb=s[1][1], nk=s[1][2], holdout_fit=s[0])
                           for s in best], fit=fits)


# --------------------------------------------------------------------------- N4SID (sippy)
def n4sid_fit(Y, U, a, b, order, f, D):
    system_identification = _sippy()
    with quiet():
        m = system_identification(Y[a:b], U[a:b], "N4SID", SS_fixed_order=order, SS_f=f,
                                  SS_D_required=D)
    return m.A, m.B, m.C, m.D


def n4sid_score(model, Y, U, a, b):
    A, B, C, D = model
    with np.errstate(all="ignore"):
        return validation_fit(ss_simulator(A, B, C, D, U[a:b]), A.shape[0], Y[a:b])[0]


def peer_n4sid(Y, U, e, v, remove_means=True):
    """N4SID (MIMO): order, horizon and D by the mean hold-out fit over the outputs."""
    h = (2 * e) // 3
    Yc, Uc = centred(Y, U, 0, h, remove_means)
    best = (-np.inf, None)
    for f in N4SID_HORIZONS:
        for D in (False, True):
            for order in N4SID_ORDERS:
                try:
                    fits = n4sid_score(n4sid_fit(Yc, Uc, 0, h, order, f, D), Yc, Uc, h, e)
                except (np.linalg.LinAlgError, ValueError):
                    continue
                score = float(np.mean(fits))
                if np.isfinite(score) and score > best[0]:
                    best = (score, (order, f, D))
    order, f, D = best[1]
    Yc, Uc = centred(Y, U, 0, e, remove_means)
    fits = n4sid_score(n4sid_fit(Yc, Uc, 0, e, order, f, D), Yc, Uc, e, v)
    return dict(structure=dict(order=order, f=f, D=D, holdout_fit=best[0]),
                fit=[float(x) for x in fits])


# --------------------------------------------------------------------------- SRIVC (+ OE)
def ct_simulator(theta, n, m, modes, u):
    """Time in samples: the CT model of theta ([a_0..a_{n-1}, b_k ascending powers], a_n = 1)
    discretised per input by its intersample rule (zoh / foh), as a tf_simulator."""
    a, bs, _ = reference_srivc.split(np.asarray(theta, dtype=float), n, m, False)
    den_c = a[::-1]
    dens, nums = [], []
    for k, b in enumerate(bs):
        num_d, den_d, _ = signal.cont2discrete((b[::-1], den_c), 1.0, method=modes[k])
        nums.append(np.atleast_1d(np.squeeze(num_d)))
        dens.append(np.asarray(den_d, dtype=float))
    den = dens[0]  # the same poles exp(p dt) for every input
    return tf_simulator(nums, den, u)


def svf_start(y, u, n, m, modes, lam):
    """Least squares with the state-variable filter 1/(s + lam)^n: the SRIVC start."""
    a0 = np.poly(-lam * np.ones(n))[::-1]
    K = len(m)
    cols = []
    for k in range(K):
        cols.append(reference_srivc.filtered(a0, u[:, [k]], modes[k], 1.0)[:, : m[k] + 1, 0])
    yf = reference_srivc.filtered(a0, y[:, None], "foh", 1.0)[:, :, 0]
    Phi = np.concatenate([-yf[:, :n]] + cols, axis=1)
    return np.linalg.lstsq(Phi, yf[:, n], rcond=None)[0]


def srivc_fit(y, u, n, m, modes):
    """SRIVC from the best of the SVF starts (lowest simulation error on the data it fits)."""
    best = None
    for lam in SRIVC_LAMBDAS:
        with np.errstate(all="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore")
            try:
                r = reference_srivc.srivc(svf_start(y, u, n, m, modes, lam), y, u, n, m, modes,
                                          1.0, max_iter=20)
            except (np.linalg.LinAlgError, ValueError):
                continue
        if (np.all(np.isfinite(r["theta"])) and reference_srivc.hurwitz(np.append(r["theta"][:n], 1))
                and (best is None or r["E"] < best["E"])):
            best = r
    return None if best is None else best["theta"]


def oe_regressors(a, m, modes, u):
    """Columns s^i/A(s) u_k (i <= m_k, time in samples, from rest, exact zoh/foh) and the n
    sampled free responses of 1/A(s): the output is linear in [b, x0] for a fixed A."""
    n = a.size - 1
    cols = [None] * len(m)
    for mode in set(modes):
        ks = [k for k in range(len(m)) if modes[k] == mode]
        F = reference_srivc.filtered(a, u[:, ks], mode, 1.0)
        for s_, k in enumerate(ks):
            cols[k] = F[:, : m[k] + 1, s_]
    den = np.real(np.poly(np.exp(np.roots(a[::-1]))))
    imp = np.zeros((len(u), n))
    imp[np.arange(n), np.arange(n)] = 1.0
    return np.concatenate(cols + [signal.lfilter([1.0], den, imp, axis=0)], axis=1)


def oe_fit(theta, y, u, n, m, modes):
    """Output error from the SRIVC estimate theta, by variable projection: least_squares over
    the denominator a_0..a_{n-1} (a_n = 1); the numerators and the initial state, linear in the
    simulated output, by least squares over the whole window at each step."""
    penalty = 10.0 * np.abs(y) + 1.0

    def solve(an):
        a = np.append(an, 1.0)
        if not reference_srivc.hurwitz(a):
            return None, penalty
        with np.errstate(all="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore")
            Phi = oe_regressors(a, m, modes, u)
            if not np.all(np.isfinite(Phi)):
                return None, penalty
            c = np.linalg.norm(Phi, axis=0)
            c[c == 0] = 1.0
            beta = np.linalg.lstsq(Phi / c, y, rcond=None)[0] / c
        return beta, y - Phi @ beta

    a0 = np.asarray(theta[:n], dtype=float)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        sol = optimize.least_squares(lambda an: solve(an)[1], a0, x_scale="jac",
                                     max_nfev=100 * n)
    best = min((sol.x, a0), key=lambda an: float(np.sum(solve(an)[1] ** 2)))
    beta, _ = solve(best)
    if beta is None:
        return np.asarray(theta, dtype=float)
    return np.concatenate([best, beta[: sum(mk + 1 for mk in m)]])


def ct_score(theta, n, m, modes, y, u):
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        sim, ns = ct_simulator(theta, n, m, modes, u)
        return float(validation_fit(sim, ns, y)[0][0])


def ct_structures(K, delays):
    """(n, m, delay): m_k in 0..n per input for n <= 2, one m common to all inputs for n = 3
    (99 structures per output for 3 inputs would not fit the time budget; 39 do)."""
    out = []
    for n in SRIVC_ORDERS:
        ms = (itertools.product(range(n + 1), repeat=K) if n <= 2
              else [(mm,) * K for mm in range(n + 1)])
        out += [(n, tuple(m), d) for m in ms for d in delays]
    return out


def peer_srivc(Y, U, e, v, modes, delays, remove_means=True):
    """SRIVC and SRIVC+OE, MISO per output, each choosing its structure by hold-out fit."""
    h = (2 * e) // 3
    K = U.shape[1]
    res = {"SRIVC": dict(structure=[], fit=[], seconds=0.0),
           "SRIVC+OE": dict(structure=[], fit=[], seconds=0.0)}
    for i in range(Y.shape[1]):
        t0 = time.perf_counter()
        Yc, Uc = centred(Y[:, [i]], U, 0, h, remove_means)
        cands = []
        for n, m, d in ct_structures(K, delays):
            Ud = delayed(Uc, [d] * K)
            th = srivc_fit(Yc[:h, 0], Ud[:h], n, m, modes)
            if th is not None:
                cands.append(((n, m, d), th, ct_score(th, n, m, modes, Yc[h:e, 0], Ud[h:e])))
        t_srivc = time.perf_counter() - t0
        oe = []
        for (n, m, d), th, _ in cands:
            Ud = delayed(Uc, [d] * K)
            th2 = oe_fit(th, Yc[:h, 0], Ud[:h], n, m, modes)
            oe.append(((n, m, d), th2, ct_score(th2, n, m, modes, Yc[h:e, 0], Ud[h:e])))
        t_oe = time.perf_counter() - t0 - t_srivc
        Yc, Uc = centred(Y[:, [i]], U, 0, e, remove_means)
        for peer, pool, extra in (("SRIVC", cands, 0.0), ("SRIVC+OE", oe, t_srivc + t_oe)):
            t1 = time.perf_counter()
            (n, m, d), th_fit, hold = max(pool, key=lambda c: c[2])
            Ud = delayed(Uc, [d] * K)
            th = srivc_fit(Yc[:e, 0], Ud[:e], n, m, modes)
            refit_ok = th is not None
            if not refit_ok:  # no stable SRIVC on all estimation data: keep the fit-part one
                th = th_fit
            if peer == "SRIVC+OE":
                th = oe_fit(th, Yc[:e, 0], Ud[:e], n, m, modes)
            fit = ct_score(th, n, m, modes, Yc[e:v, 0], Ud[e:v])
            final = time.perf_counter() - t1
            res[peer]["structure"].append(dict(n=n, m=list(m), delay=d, holdout_fit=hold,
                                               srivc_refit_stable=refit_ok))
            res[peer]["fit"].append(fit)
            res[peer]["seconds"] += (t_srivc if peer == "SRIVC" else extra) + final
    return res


# --------------------------------------------------------------------------- API
def peers(name, remove_means=True):
    """All peers on the DaISy record `name` (a key of `TASKS`): dict with the record's facts and
    `peers`: {peer: {structure, fit (per output, %), fit_mean, seconds}}. `remove_means=False`
    skips the mean removal (a comparison variant, not the protocol)."""
    Y, U, dt, modes = record(name)
    T = len(Y)
    e = (2 * T) // 3
    out = {}
    for peer, fn in (("ARX", peer_arx), ("N4SID", peer_n4sid)):
        t0 = time.perf_counter()
        r = fn(Y, U, e, T, remove_means=remove_means)
        r["seconds"] = time.perf_counter() - t0
        out[peer] = r
    out.update(peer_srivc(Y, U, e, T, modes, TASKS[name]["delays"], remove_means))
    for r in out.values():
        r["fit_mean"] = float(np.mean(r["fit"]))
    return dict(record=name, outputs=TASKS[name]["outputs"], samples=T, estimation_samples=e,
                dt=dt, means_removed=remove_means, peers=out)


def main():
    rows = []
    for name in DAISY:
        t0 = time.perf_counter()
        rows.append(peers(name))
        print(f"{name}: {time.perf_counter() - t0:.1f} s", flush=True)
    print(f"\n{'record':<16}" + "".join(f"{p + ' fit %':>16}{'s':>7}" for p in PEERS))
    for r in rows:
        print(f"{r['record']:<16}" + "".join(
            f"{r['peers'][p]['fit_mean']:>16.1f}{r['peers'][p]['seconds']:>7.1f}" for p in PEERS))
    print("\nchosen structures (hold-out fit %):")
    for r in rows:
        for p in PEERS:
            st = r["peers"][p]["structure"]
            st = st if isinstance(st, list) else [st]
            print(f"  {r['record']:<15}{p:<9}" + "; ".join(
                ",".join(f"{k}={v}" for k, v in d.items() if k not in ("holdout_fit",
                                                                      "srivc_refit_stable"))
                + f" ({d['holdout_fit']:.1f})" for d in st))
    gf = next(r for r in rows if r["record"] == "glass_furnace")
    print("\nglass furnace per output (y1..y6):")
    for p in PEERS:
        print(f"  {p:<9}" + " ".join(f"{x:6.1f}" for x in gf["peers"][p]["fit"]))
    os.makedirs(os.path.join(os.path.dirname(__file__), "results"), exist_ok=True)
    with open(os.path.join(os.path.dirname(__file__), "results", "real_data_peers.json"),
              "w") as fh:
        json.dump(_plain(rows), fh, indent=1)


def _plain(x):
    """JSON-safe copy: NumPy scalars as Python numbers, non-finite floats as None."""
    if isinstance(x, dict):
        return {k: _plain(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_plain(v) for v in x]
    if isinstance(x, np.generic):
        x = x.item()
    if isinstance(x, float) and not np.isfinite(x):
        return None
    return x


if __name__ == "__main__":
    main()
