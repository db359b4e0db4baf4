"""Noise-free (or noisy) experiments on known continuous-time models, simulated exactly."""

from __future__ import annotations

import numpy as np

from .. import _boundary as _b
from .._model import Model
from .._signals import Signals
from .._simulate import simulate


def _inputs(T: int, dt: float, modes, rng) -> np.ndarray:
    """Plant-like inputs: smooth multisines for foh inputs, held random levels for zoh inputs."""
    t = np.arange(T) * dt
    cols = []
    for mode in modes:
        if mode == "foh":
            freqs = rng.uniform(2.0, 30.0, 5) / (T * dt)
            cols.append(sum(np.sin(2 * np.pi * f * t + rng.uniform(0, 2 * np.pi)) for f in freqs))
        else:
            hold = max(T // 40, 1)
            levels = rng.normal(size=T // hold + 1)
            cols.append(np.repeat(levels, hold)[:T])
    return np.stack(cols, axis=1)


def simulated_experiment(
    model: Model,
    *,
    dt: float,
    n_samples: int,
    x0=None,
    noise_std: float = 0.0,
    seed: int = 0,
) -> Signals:
    """Exact response of `model` to generated inputs (intersample modes and delays of the model).

    `noise_std` adds white Gaussian noise to the output. Deterministic per `seed`.
    """
    fn = "simulated_experiment"
    if not isinstance(model, Model):
        raise TypeError(f"{fn}(): model must be a Model, got {type(model).__name__}")
    dt = _b.number(fn, "dt", dt, lo=0, lo_open=True)
    n_samples = _b.integer(fn, "n_samples", n_samples, lo=16)
    noise_std = _b.number(fn, "noise_std", noise_std, lo=0)
    seed = _b.integer(fn, "seed", seed, lo=0)
    rng = np.random.default_rng(seed)
    u = _inputs(n_samples, dt, model.intersample, rng)
    y = np.asarray(simulate(model, u, x0, dt=dt))
    if noise_std:
        y = y + noise_std * rng.standard_normal(n_samples)
    return Signals(
        y,
        u,
        dt=dt,
        intersample=model.intersample,
        delays=np.asarray(model.delays),
        input_names=model.input_names,
        output_name=model.output_name,
        # a model with an offset term: its data have one (the default rule saw an output
        # from rest at zero and left it off: every fit then lacked the term; an audit)
        offset=True if model.has_offset else None,
    )


def paper_table3_model1() -> Model:
    """The paper's Table 3 model 1 (glass forehearth, experiment 1): n = 2, m = (0, 0).

    Input 1 (previous zone temperature) as foh, input 2 (gas-air pressure) as zoh.
    """
    return Model.from_coefficients(
        [62.86e-6, 10.82e-3, 1.0], [[141.61e-6], [247.02e-6]], intersample=("foh", "zoh")
    )


def third_order_two_input() -> Model:
    """A 3rd-order 2-input test system, poles -0.5, -1, -2; m = (1, 0); one foh, one zoh input."""
    return Model.from_coefficients(
        [1.0, 3.5, 3.5, 1.0], [[1.0, 0.5], [0.8]], intersample=("foh", "zoh")
    )


def switching_plant() -> tuple[Model, Model]:
    """Two 2nd-order, 2-input plants (foh, zoh inputs) for the on-line identifier's tests:
    poles -0.04, -0.05, then -0.06 +- 0.02j (time constants 15-25 s at 1 s sampling)."""
    first = Model.from_coefficients([0.002, 0.09, 1.0], [[0.004], [0.001, 0.02]],
                                    intersample=("foh", "zoh"))
    second = Model.from_coefficients([0.004, 0.12, 1.0], [[0.010], [0.003, 0.01]],
                                     intersample=("foh", "zoh"))
    return first, second


def switching_experiment(
    models=None, *, interval: int = 250, n_intervals: int = 40, quiet=(0, 1, 16, 17, 18),
    switches=(16,), noise_std: float = 0.0, seed: int = 0,
):
    """A plant that moves between known LTI models at known operating points (1 s sampling).

    Intervals listed in `quiet` have constant (zero) inputs, so the plant settles there (an
    operating point); the others carry slow multisines on input 1 (foh) and held random levels
    on input 2 (zoh). At the start of each interval in `switches` the plant becomes the next
    model of `models`, its state carried over (the output stays continuous).

    **Returns:** (t (T,), y (T,), u (T, 2), switch times).
    """
    fn = "switching_experiment"
    interval = _b.integer(fn, "interval", interval, lo=8)
    n_intervals = _b.integer(fn, "n_intervals", n_intervals, lo=1)
    noise_std = _b.number(fn, "noise_std", noise_std, lo=0)
    seed = _b.integer(fn, "seed", seed, lo=0)
    if models is not None and (isinstance(models, (str, bytes)) or not all(
            isinstance(mdl, Model) for mdl in models)):
        raise TypeError(f"{fn}(): models must be a sequence of Model (got {models!r})")
    models = list(models or switching_plant())
    if len(switches) != len(models) - 1:
        raise ValueError("switching_experiment(): need len(models) - 1 switches")
    if any(not 0 < s < n_intervals for s in switches):
        raise ValueError("switching_experiment(): switches must lie inside the n_intervals")
    rng = np.random.default_rng(seed)
    S, T = interval, interval * n_intervals
    t = np.arange(T, dtype=np.float64)
    u = np.zeros((T, 2))
    for j in range(n_intervals):
        if j in quiet:
            continue
        sl = slice(j * S, (j + 1) * S)
        f = rng.uniform(1 / 400, 1 / 150, 2)
        u[sl, 0] = sum(np.sin(2 * np.pi * fi * (t[sl] - t[sl][0])) for fi in f)
        u[sl, 1] = 0.3 * np.repeat(rng.normal(size=S // 50 + 1), 50)[:S]
    edges = [0] + [s * S for s in switches] + [T]
    x = np.zeros(models[0].n)
    ys = []
    for i, model in enumerate(models):
        a, b = edges[i], edges[i + 1]
        # one sample more to carry the state to the switch (same A, B realisation form);
        # `simulate`'s compiled program (called eagerly, every operation compiled on its own:
        # 180 small programs in one fuzz test)
        y, xs = simulate(model, u[a : min(b + 1, T)], x, dt=1.0, return_state=True)
        ys.append(np.asarray(y)[: b - a])  # sliced on the host: no eager program per length
        x = np.asarray(xs)[-1] if b < T else x
    y = np.concatenate(ys)
    if noise_std:
        y = y + noise_std * rng.standard_normal(T)
    return t, y, u, [float(s * S) for s in switches]
