"""Simulated forehearth (physics sanity, determinism, the paper's delay ranges) and DaISy loaders."""

import os

import numpy as np
import pytest
from conftest import SHARED

from mfmjax.datasets import DAISY, daisy, forehearth, transport_delay
from mfmjax.datasets import _forehearth as F


@pytest.fixture(scope="module")
def exp1():
    return forehearth(1, seed=3)


def test_forehearth_shapes_and_determinism(exp1):
    assert exp1["t"].shape == (8001,) and exp1["u"].shape == (8001, 2)
    np.testing.assert_array_equal(forehearth(1, seed=3)["y"], exp1["y"])
    assert not np.array_equal(forehearth(1, seed=4)["y"], exp1["y"])
    assert forehearth(2)["t"][-1] == 9500.0
    assert np.all(np.isfinite(exp1["y"])) and np.all(np.isfinite(exp1["u"]))


def test_forehearth_pull_and_delay_match_the_paper(exp1):
    assert exp1["pull"][0] == 82 and exp1["pull"][-1] == 60
    # the paper: 260-319 s for 82 -> 60 t/24h and 313-337 s for 62 -> 55 t/24h
    assert 260 <= exp1["delay"].min() and exp1["delay"].max() <= 320
    d2 = forehearth(2)["delay"]
    assert 312 <= d2.min() and d2.max() <= 338
    # delay = thermocouple distance / transport velocity (mean flow + convective drift)
    v = 82 * 1000 / 86400 / (F.RHO * F.WIDTH * F.DEPTH) + F.V_CONV
    assert transport_delay(82) == pytest.approx(F.X_TC / v, rel=1e-12)


def test_forehearth_starts_at_rest_on_the_setpoint(exp1):
    # the initial state is the plant's steady state with the controller in balance
    y0 = exp1["y"][:200]
    assert abs(y0.mean() - 1164.0) < 0.1 and y0.std() < 0.2
    p0 = exp1["u"][:200, 1]
    assert F.P_MIN < p0.mean() < F.P_MAX and p0.std() < 0.2


def test_forehearth_physics_directions():
    # energy balance at rest: the outlet is cooler than the inlet by the losses minus the heat
    v = F._velocity(70.0)
    tau = F.X_TC / v
    k_loss = F.U_LOSS / (F.RHO * F.CP * F.DEPTH)
    loss = k_loss * (1165 - F.T_AMB) * tau  # degC lost on the way to the thermocouple
    heat = F.Q_NOM / (F.RHO * F.CP * F.DEPTH) * tau
    assert 5 < loss < 40 and 5 < heat < 40  # same order: the burner compensates the losses
    # lower pull -> longer residence -> the controller needs more gas (experiment 1, 82 -> 60)
    d = forehearth(1)
    assert d["u"][-500:, 1].mean() > d["u"][200:700, 1].mean() - 1.0


def test_forehearth_errors():
    with pytest.raises(ValueError, match="experiment must be 1 or 2"):
        forehearth(3)


@pytest.mark.skipif(not os.path.isdir(SHARED), reason="shared data not present")
@pytest.mark.parametrize("name, T, K, dt", [
    ("heat_exchanger", 4000, 1, 1.0), ("dryer", 867, 3, 10.0), ("glass_furnace", 1247, 3, 1.0),
    ("heating_system", 801, 1, 2.0),
])
def test_daisy_loaders(name, T, K, dt):
    sig = daisy(name)
    assert (sig.n_samples, sig.n_inputs, sig.dt) == (T, K, dt) and sig.offset
    assert sig.output_name == DAISY[name][3]


def test_daisy_errors(tmp_path):
    with pytest.raises(ValueError, match="unknown dataset"):
        daisy("nope")
    with pytest.raises(FileNotFoundError, match="MFMJAX_DATA"):
        daisy("dryer", path=str(tmp_path / "missing.dat"))
    if os.path.isdir(SHARED):  # the sample-index column was accepted as the output
        with pytest.raises(ValueError, match=r"daisy\(\): dryer has no output column 'k'; its "
                                             r"outputs are \['dry_bulb', 'wet_bulb', "
                                             r"'moisture'\]"):
            daisy("dryer", output="k")


def test_daisy_says_when_path_is_another_file(tmp_path):
    """A file of other columns gave read_csv's message, which names the CLI's --names."""
    other = tmp_path / "seven.dat"
    np.savetxt(other, np.arange(21.0).reshape(3, 7))
    with pytest.raises(ValueError, match=r"daisy\(\): .*seven.dat does not have the 3 columns "
                                         r"of heat_exchanger \(t, q, theta\): line 1 has 7 "
                                         r"fields; check path="):
        daisy("heat_exchanger", path=str(other))


@pytest.mark.skipif(not os.path.isdir(SHARED), reason="shared data not present")
def test_daisy_refuses_another_record_of_as_many_columns():
    """The heating system's file (t, u, y) loaded as the heat exchanger (t, q, theta): 801
    samples labelled dt = 1 and q -> theta (an audit of 2026-11-28); the row count tells."""
    other = os.path.join(SHARED, "daisy-heating-system", "heating_system.dat")
    with pytest.raises(ValueError, match=r"daisy\(\): .*heating_system.dat has 801 rows, "
                                         r"heat_exchanger has 4000; check path="):
        daisy("heat_exchanger", path=other)


def test_simulated_data_of_a_model_with_an_offset_have_the_term():
    """`simulated_experiment` of a model with an offset term returned Signals without it (the
    default rule saw an output from rest at zero), so every fit left it out; and an offset
    given as text ("no", "false") read as True."""
    import mfmjax
    from mfmjax.datasets import simulated_experiment

    model = mfmjax.Model.from_coefficients([1.0, 3.5, 3.5, 1.0], [[1.0, 0.5], [0.8]],
                                           intersample=("foh", "zoh"), offset=2.5)
    sig = simulated_experiment(model, dt=0.05, n_samples=400)
    assert sig.offset and model.has_offset
    plain = simulated_experiment(mfmjax.Model.from_coefficients([1.0, 3.5, 3.5, 1.0],
                                                                [[1.0, 0.5], [0.8]]),
                                 dt=0.05, n_samples=400)
    assert not plain.offset  # the default rule, as before
    for bad in ("no", "false", 2):
        with pytest.raises(TypeError, match=r"Signals\(\): offset must be True, False or None"):
            mfmjax.Signals(np.asarray(sig.y), np.asarray(sig.u), dt=0.05, offset=bad)
