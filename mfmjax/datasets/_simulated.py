"""Noise-free (or noisy) experiments on known continuous-time models, simulated exactly."""

from __future__ import annotations

import numpy as np

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
