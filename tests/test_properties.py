"""Property tests: no NaN escapes without a flag; invalid input always gets the clear error."""

import warnings

import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import mfmjax
from mfmjax import ModulatingFunction, Signals, Structure

T, DT, H_MAX = 200, 0.1, 5.0
SETTINGS = settings(max_examples=20, deadline=None,
                    suppress_health_check=[HealthCheck.too_slow])


@st.composite
def valid_problem(draw):
    n = draw(st.integers(1, 3))
    K = draw(st.integers(0, 2))
    m = tuple(draw(st.integers(0, n)) for _ in range(K))
    seed = draw(st.integers(0, 2**31 - 1))
    rng = np.random.default_rng(seed)
    kind = draw(st.sampled_from(["noise", "constant", "zero", "smooth", "huge"]))
    y = rng.normal(size=T)
    u = rng.normal(size=(T, K))
    if kind == "constant" and K:
        u[:, 0] = 3.0
    elif kind == "zero":
        u[:] = 0.0
        y[:] = 0.0
    elif kind == "smooth":
        y = np.sin(np.arange(T) * DT)
    elif kind == "huge":
        y *= 1e12
    N = draw(st.integers(n, n + 4))
    M = draw(st.integers(n, n + 4))
    h = draw(st.floats(1.0, H_MAX))
    modes = tuple(draw(st.sampled_from(["zoh", "foh"])) for _ in range(K))
    delays = [draw(st.floats(0.0, 3.0)) for _ in range(K)]
    return n, m, y, u, N, M, h, modes, delays


@SETTINGS
@given(valid_problem())
def test_valid_input_never_silent_nan(problem):
    n, m, y, u, N, M, h, modes, delays = problem
    sig = Signals(y, u, dt=DT, intersample=modes or None, delays=delays or None)
    mf = ModulatingFunction(jnp.asarray(float(N)), jnp.asarray(float(M)), h, h_max=H_MAX)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = mfmjax.identify(sig, Structure(n, m), mf, delay_max=3.0)
    params = np.concatenate([np.asarray(model.a)] + [np.asarray(b) for b in model.b])
    assert int(model.status) != 0 or np.all(np.isfinite(params))
    assert np.all(np.isfinite(np.asarray(model.theta))) or int(model.status) != 0


INVALID = [
    ("N < n", lambda: mfmjax.identify(_sig(), Structure(3, (0,)), ModulatingFunction(2, 4, 2.0)),
     "N must be >= n"),
    ("M < n", lambda: mfmjax.identify(_sig(), Structure(3, (0,)), ModulatingFunction(4, 1, 2.0)),
     "M must be >= n"),
    ("m > n", lambda: Structure(2, (3,)), "exceeds n"),
    ("h <= 0", lambda: ModulatingFunction(3, 3, -0.5), "h must be > 0"),
    ("short", lambda: mfmjax.identify(_sig(), Structure(1, (0,)), ModulatingFunction(2, 2, 19.5)),
     "too short"),
    ("nan", lambda: Signals(np.r_[np.nan, np.zeros(T - 1)], dt=DT), "NaN or inf"),
    ("mode", lambda: Signals(np.zeros(T), np.zeros(T), dt=DT, intersample="cubic"),
     "unknown intersample"),
    ("delay", lambda: Signals(np.zeros(T), np.zeros(T), dt=DT, delays=[-0.1]), "delays must"),
    ("m len", lambda: mfmjax.identify(_sig(K=2), Structure(1, (0, 0, 0)),
                                      ModulatingFunction(2, 2, 2.0)), "m has 3 entries"),
]


def _sig(K=1):
    rng = np.random.default_rng(0)
    return Signals(rng.normal(size=T), rng.normal(size=(T, K)), dt=DT)


@settings(max_examples=20, deadline=None)
@given(st.sampled_from(INVALID))
def test_invalid_input_always_clear_error(case):
    _, make, match = case
    with pytest.raises(ValueError, match=match):
        make()
