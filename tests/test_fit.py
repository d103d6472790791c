"""The fit: recovery of known parameters, stability at the truth, clear errors."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxcos
from jaxcos._cli import main
from jaxcos._fit import fit, make_problem, parameterization, with_mc_error
from jaxcos._measurements import Measurements

# The fit's Monte Carlo error is correlated across the outgoing angles of an
# incidence (the same walks serve them all), so weighting it into the
# likelihood as independent noise understates its effect on the parameters.
# These tests keep it well below the measurement noise (about 3% of a value
# at 256 walks against 10% noise) so the tolerances derived from the noise hold.
WALKS, BOUNCES = 256, 48


def _synthetic(material, seed=7, rel=0.10, add=0.005):
    """A small reflectance-factor data set from ``material``: a noise-free reference plus Gaussian noise."""
    ti = np.repeat([10.0, 35.0, 60.0], 9)
    to = np.tile([-60.0, -30.0, -5.0, 10.0, 25.0, 35.0, 45.0, 60.0, 75.0], 3)
    f = np.pi * np.asarray(jaxcos.inplane_bsdf(material, ti, to, jax.random.key(1000), walks=4096, bounces=BOUNCES))
    std = np.sqrt((rel * f) ** 2 + add ** 2)
    values = f + std * np.random.default_rng(seed).standard_normal(f.shape)
    return Measurements(theta_i=ti, theta_o=to, phi_o=np.zeros_like(ti), values=values, std=std,
                        quantity="reflectance_factor", metadata={}, path="synthetic.csv")


TRUTH = jaxcos.Material(layers=(jaxcos.Layer(t=16.0, c_d=0.6, albedo_d=(0.9, 0.8, 0.7), g1=0.4, g2=0.0, w_g=1.0,
                                             albedo_p=(0.85, 0.85, 0.8), alpha_p=0.3, theta_p=4.0),),
                        variant="single_lobe")


@pytest.fixture(scope="module")
def data():
    return _synthetic(TRUTH)


def _laplace_sigma(meas, result):
    """Standard deviations of the fitted coordinates from the Gauss-Newton covariance ``(J^T J)^-1``."""
    problem = result.problem
    jac = jax.jacfwd(problem.residuals)(result.x)
    cov = np.linalg.inv(np.asarray(jac.T @ jac, dtype=float))
    return np.sqrt(np.diag(cov))


@pytest.mark.slow
def test_fit_recovers_known_parameters(data):
    """From the default start, LM lands within 4 posterior standard deviations of the truth, per coordinate.

    The tolerance is the Gauss-Newton (Laplace) standard deviation of each
    unbounded coordinate at the optimum, under the fit's own weights (noise
    and Monte Carlo error): the fit may not know the truth better than the
    data allow, and must not miss it by more.
    """
    result = fit(data, variant="single_lobe", walks=WALKS, bounces=BOUNCES, start=jaxcos.Material(
        layers=(jaxcos.Layer(t=16.0, c_d=0.5, albedo_d=0.8, g1=0.2, g2=0.0, w_g=1.0, albedo_p=0.8, alpha_p=0.2,
                             theta_p=2.0),), variant="single_lobe"))
    x_true = result.param.from_material(TRUTH)
    sigma = _laplace_sigma(data, result)
    z = (np.asarray(result.x) - np.asarray(x_true)) / sigma
    assert np.all(np.abs(z) < 4.0), dict(zip(result.param.labels(), np.round(z, 2)))
    assert 0.3 < result.record["reduced_chi2"] < 3.0


@pytest.mark.slow
def test_fit_started_at_truth_stays(data):
    """Started at the truth, the optimum moves by less than 4 Laplace standard deviations and the loss drops."""
    result = fit(data, variant="single_lobe", walks=WALKS, bounces=BOUNCES, start=TRUTH)
    x_true = result.param.from_material(TRUTH)
    sigma = _laplace_sigma(data, result)
    assert np.all(np.abs((np.asarray(result.x) - np.asarray(x_true)) / sigma) < 4.0)
    problem = with_mc_error(result.problem, data, x_true)
    assert result.record["loss"] <= float(problem.loss(x_true)) * (1 + 1e-6)


def test_parameterization_round_trip():
    param = parameterization("two_lobe", fit_t=True, fit_phi=True)
    m = jaxcos.Material(layers=(jaxcos.Layer(t=3.0, c_d=0.4, albedo_d=(0.2, 0.5, 0.9), g1=0.7, g2=-0.4, w_g=0.3,
                                             albedo_p=(0.6, 0.7, 0.8), alpha_p=0.05, theta_p=12.0, phi_p=30.0),))
    back = param.to_material(param.from_material(m))
    for name in ("t", "c_d", "albedo_d", "g1", "g2", "w_g", "albedo_p", "alpha_p", "theta_p", "phi_p"):
        np.testing.assert_allclose(getattr(back.layers[0], name), getattr(m.layers[0], name), rtol=2e-4, atol=1e-4)
    assert param.size == 14 and len(param.labels()) == 14


@pytest.mark.parametrize("variant, size", [("two_lobe", 12), ("single_lobe", 10), ("diffusers_only", 6),
                                           ("platelets_only", 5)])
def test_variant_parameter_counts(variant, size):
    assert parameterization(variant).size == size


def test_every_iterate_is_physical():
    """Extreme unbounded coordinates still map to a valid material with a finite model."""
    param = parameterization("two_lobe")
    meas = _tiny()
    problem = make_problem(meas, param, key=jax.random.key(0), walks=8, bounces=8)
    for x in (jnp.full(param.size, 40.0), jnp.full(param.size, -40.0)):
        layer = param.to_material(x).layers[0]
        assert 0 <= float(layer.c_d) <= 1 and abs(float(layer.g1)) <= 1 and 0 < float(layer.alpha_p) <= 1
        assert 0 <= float(layer.theta_p) <= 90
        assert np.all(np.isfinite(np.asarray(problem.residuals(x))))


def _tiny():
    ti = np.array([20.0, 20.0, 50.0])
    to = np.array([-10.0, 20.0, 50.0])
    values = np.full((3, 3), 0.2)
    return Measurements(theta_i=ti, theta_o=to, phi_o=np.zeros(3), values=values, std=np.full((3, 3), 0.01),
                        quantity="reflectance_factor", metadata={}, path="tiny.csv")


def test_unknown_variant_is_a_clear_error(tmp_path, capsys):
    csv = tmp_path / "m.csv"
    csv.write_text("theta_i,theta_o,r,g,b\n20,10,0.1,0.1,0.1\n20,30,0.2,0.2,0.2\n")
    out = tmp_path / "fit"
    assert main(["fit", str(csv), "--out", str(out), "--variant", "three_lobe"]) == 2
    err = capsys.readouterr().err.strip()
    assert "unknown variant 'three_lobe'" in err and "two_lobe" in err and len(err.splitlines()) == 1
    assert not out.exists()


def test_bad_file_is_a_clear_error(tmp_path, capsys):
    csv = tmp_path / "m.csv"
    csv.write_text("theta_i,theta_o,r,g,b\n20,10,0.1,abc,0.1\n")
    out = tmp_path / "fit"
    assert main(["fit", str(csv), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert str(csv) in err and "line 2" in err and "'abc'" in err and len(err.splitlines()) == 1
    assert not out.exists()


def test_existing_result_is_not_overwritten(tmp_path, capsys):
    out = tmp_path / "fit"
    out.mkdir()
    (out / "params.json").write_text("{}")
    csv = tmp_path / "m.csv"
    csv.write_text("theta_i,theta_o,r,g,b\n20,10,0.1,0.1,0.1\n")
    assert main(["fit", str(csv), "--out", str(out)]) == 2
    assert "already exists" in capsys.readouterr().err
    assert (out / "params.json").read_text() == "{}"
