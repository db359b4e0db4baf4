"""`estimate`: search -> SRIVC (-> output error) in one call, on a noisy record (issue 14)."""

import numpy as np
import pytest

import mfmjax
from mfmjax import Model
from mfmjax.datasets import simulated_experiment

TRUE = Model.from_coefficients([2.0, 3.0, 1.0], [[1.0]], intersample=["zoh"])
DT, T = 0.05, 1500
GRID = dict(h=(2.0, 3.0), n=(1, 2, 3), N=(3, 4), M=(3, 4))


@pytest.fixture(scope="module")
def noisy():
    clean = simulated_experiment(TRUE, dt=DT, n_samples=T, seed=7)
    sd = float(np.std(np.asarray(clean.y))) / np.sqrt(10.0)  # 10 dB SNR
    return simulated_experiment(TRUE, dt=DT, n_samples=T, seed=7, noise_std=sd), sd


def _params(model):
    return np.concatenate([np.asarray(model.a)[:-1], np.asarray(model.b[0])])


def test_estimate_is_consistent_at_10_db(noisy):
    """One realisation at 10 dB: the order is found (BIC), SRIVC converges, and every parameter
    is within 5 Cramer-Rao standard deviations of the truth (SRIVC's spread is 1.0-1.15 CRB in
    benchmarks/noise_montecarlo.py, so 5 CRB is a > 4-sigma bound); its IV standard errors
    agree with the CRB within a factor 2."""
    sig, sd = noisy
    est = mfmjax.estimate(sig, **GRID)
    assert est.model.n == 2 and est.converged and est.method == "srivc"
    _, crb = mfmjax.cramer_rao(TRUE, sig.u, np.zeros(2), dt=DT, sigma=sd)
    err = (_params(est.model) - np.array([2.0, 3.0, 1.0])) / crb
    assert np.all(np.abs(err) < 5.0), err
    assert np.all((est.std_errors > crb / 2) & (est.std_errors < 2 * crb))
    assert "converged" in est.summary() and "NOT" not in est.summary()
    assert est.start.n == 2 and len(est.search) > 1  # the path is kept


def test_estimate_with_output_error_polish(noisy):
    sig, _ = noisy
    est = mfmjax.estimate(sig, polish=True, **GRID)
    assert est.method == "srivc + output error" and est.output_error is not None
    assert est.output_error.E <= est.output_error.E_start
    assert est.names == est.output_error.names


def test_estimate_refuses_a_non_bool_polish(noisy):
    with pytest.raises(TypeError, match=r"estimate\(\): polish must be True or False"):
        mfmjax.estimate(noisy[0], polish="yes", **GRID)


def test_cli_search_estimate(noisy, tmp_path, capsys):
    """`mfmjax search ... --estimate`: the same path from the command line, same model."""
    import json

    from mfmjax._cli import main

    sig, _ = noisy
    path = tmp_path / "noisy.csv"
    np.savetxt(path, np.column_stack([np.asarray(sig.y), np.asarray(sig.u)[:, 0]]),
               delimiter=",", header="y,u", comments="")
    args = ["search", str(path), "--output", "y", "--inputs", "u", "--dt", str(DT),
            "--intersample", "zoh", "--n", "1:3", "--N", "3:4", "--M", "3:4", "--h", "2,3",
            "--score", "bic", "--estimate"]
    assert main(args) == 0
    text = capsys.readouterr().out
    assert "method: MFM search -> srivc" in text and "std error" in text
    assert main(args + ["--json"]) == 0
    est = json.loads(capsys.readouterr().out)["estimated"]
    ref = mfmjax.estimate(sig, **GRID)
    got = [est["parameters"][k]["value"] for k in ref.names]
    np.testing.assert_allclose(got, _params(ref.model), rtol=1e-12)  # the same computation
    assert main(args + ["--refine"]) == 2  # one way to improve the winner at a time
