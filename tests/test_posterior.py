"""Posterior spreads: the sampler on a known posterior, implicit sensitivities, coverage of a truth, errors."""

import dataclasses
import functools
import json
import os
from types import SimpleNamespace

import jax
import numpy as np
import pytest
from scipy.stats import chi2

import jaxcos
from jaxcos.cli import main
from jaxcos.io._measurements import Measurements
from jaxcos.inference._fit import parameterization
from jaxcos.inference._posterior import (Chain, Linearisation, NoiseModel, PosteriorRecord, derived, estimate_noise,
                                        laplace, run_ensemble, sample, sensitivity, summarise, uncertainty,
                                        widen_steps)
from jaxcos.model._phase import hg
from jaxcos.report import write_uncertainty
from jaxcos.report._posterior import _corner, _sensitivity_maps

# --- a linear-Gaussian problem whose posterior is known exactly -------------------


def _linear_problem(seed=0, m=40, p=3):
    rng = np.random.default_rng(seed)
    a = rng.normal(size=(m, p))
    sigma = 0.1 + rng.uniform(size=m)
    y = a @ np.array([0.5, -1.0, 2.0])[:p] + sigma * rng.normal(size=m)
    return a, y, sigma


def test_sampler_recovers_a_linear_gaussian_posterior():
    """Mean and spreads of the chain match the closed form within their Monte Carlo error."""
    a, y, sigma = _linear_problem()
    aw, yw = a / sigma[:, None], y / sigma
    cov = np.linalg.inv(aw.T @ aw)
    mean = cov @ aw.T @ yw
    log_prob = lambda v: -0.5 * np.sum((np.asarray(v) @ aw.T - yw) ** 2, axis=1)
    chain = run_ensemble(log_prob, mean + 0.3 * np.sqrt(np.diag(cov)), np.sqrt(np.diag(cov)), seed=3, walkers=16,
                         max_steps=4000)
    assert chain.converged
    sd = np.sqrt(np.diag(cov))
    ess = chain.ess
    # Standard errors of a mean and of a standard deviation from ESS effective draws; 4 of them.
    assert np.all(np.abs(chain.samples.mean(axis=0) - mean) < 4 * sd / np.sqrt(ess))
    assert np.all(np.abs(chain.samples.std(axis=0) / sd - 1) < 4 / np.sqrt(2 * ess))
    assert 0.1 < np.mean(chain.acceptance) < 0.9


def test_short_chain_is_reported():
    a, y, sigma = _linear_problem()
    log_prob = lambda v: -0.5 * np.sum(((np.asarray(v) @ a.T - y) / sigma) ** 2, axis=1)
    chain = run_ensemble(log_prob, np.zeros(3), np.ones(3), seed=0, walkers=8, max_steps=50, check_every=25)
    assert not chain.converged and chain.steps == 50


def test_a_chain_that_stops_early_is_converged():
    """The chain stops on the autocorrelation times it is judged by (those after its burn-in), so a chain
    that stopped before ``max_steps`` is converged; frequent checks stop it close to the threshold."""
    log_prob = lambda v: -0.5 * np.sum(np.asarray(v) ** 2, axis=1)
    for seed in range(12):
        chain = run_ensemble(log_prob, np.zeros(3), np.ones(3), seed=seed, walkers=8, max_steps=4000,
                             check_every=10)
        assert chain.steps < 4000 and chain.converged, seed


def test_draws_whose_lobes_cross_are_reported_forward_first():
    """Where two alike lobes cross in the chain (``g1 < g2``), the summary's percentiles are those of the draws
    relabelled forward-first: every ``g1`` above every ``g2`` quantile, and ``w_g`` both ways round."""
    labels = ["g1", "g2", "w_g"]
    rng = np.random.default_rng(0)
    n = 4000
    samples = np.column_stack([0.1 + 0.05 * rng.standard_normal(n), 0.1 + 0.05 * rng.standard_normal(n),
                               np.full(n, 0.8)])
    chain = Chain(samples=samples, tau=np.ones(3), steps=n, burn=0, walkers=1, acceptance=np.ones(1),
                  ess=np.full(3, float(n)), converged=True, seconds=0.0)
    lin = SimpleNamespace(anchor=np.array([0.1, 0.1, 0.8]))
    summary, derived_summary, _ = summarise(chain, np.zeros((3, 3)), labels, np.array([0.12, 0.08, 0.8]), lin,
                                            np.ones(3), np.array([-1.0, -1.0, 0.0]), np.ones(3),
                                            rng=np.random.default_rng(1))
    assert summary["g1"]["p2.5"] > summary["g2"]["p16"] and summary["g1"]["p16"] > summary["g2"]["median"]
    # the larger of two normals is above 0.1 with probability 3/4; the relabelled weight is 0.2 as often as 0.8
    assert summary["g1"]["p16"] < 0.1 < summary["g1"]["median"] and summary["g2"]["median"] < 0.1 < summary["g2"]["p84"]
    assert summary["w_g"]["p16"] == pytest.approx(0.2) and summary["w_g"]["p84"] == pytest.approx(0.8)
    # the mean cosine does not depend on the labels
    g_mean = 0.8 * samples[:, 0] + 0.2 * samples[:, 1]
    assert derived_summary["g_mean"]["median"] == pytest.approx(np.median(g_mean))


def test_laplace_and_sensitivity_of_a_linear_least_squares_problem():
    """Laplace is the exact covariance; the sensitivity is the exact derivative of the solution."""
    a, y, sigma = _linear_problem(m=12)
    jac = a / sigma[:, None]
    solve = lambda yy: np.linalg.lstsq(jac, yy / sigma, rcond=None)[0]
    np.testing.assert_allclose(laplace(jac), np.linalg.inv(jac.T @ jac), rtol=1e-8)
    sens = sensitivity(jac, sigma)
    eps = 1e-3
    for m in (0, 5, 11):
        dy = np.zeros_like(y)
        dy[m] = eps
        np.testing.assert_allclose((solve(y + dy) - solve(y)) / eps, sens[:, m], rtol=1e-6, atol=1e-9)


def _noisy_linearisation(noise_scale, seed=0, n=30, p=3):
    """A :class:`Linearisation` whose slopes of parameter 0 differ between halves by ``noise_scale`` per value."""
    rng = np.random.default_rng(seed)
    slopes = rng.normal(size=(n, 3, p))
    difference = np.zeros_like(slopes)
    difference[..., 0] = noise_scale * rng.normal(size=(n, 3))
    return Linearisation(anchor=np.zeros(p), value=np.zeros((n, 3)), slopes=slopes, relative_error=0.0,
                         measured=np.zeros((n, 3)), noise=np.ones((n, 3)), slope_difference=difference)


def test_slope_noise_is_never_more_than_the_slopes():
    """``J^T J - N`` is positive semi-definite; where the raw noise is smaller than the slopes it is kept whole."""
    quiet, loud = _noisy_linearisation(0.2), _noisy_linearisation(6.0)
    np.testing.assert_allclose(quiet.slope_noise, quiet.raw_slope_noise, atol=1e-10)
    jtj = loud.jac.T @ loud.jac
    assert loud.raw_slope_noise[0, 0] > jtj[0, 0]
    w = np.linalg.eigvalsh(jtj - loud.slope_noise)
    assert np.min(w) > -1e-9 * np.max(w) and np.sum(w < 1e-9 * np.max(w)) == 1


def test_noisy_slopes_get_longer_steps():
    """Only the parameter whose slopes are mostly noise gets a longer step, by ``4 sqrt(rho)``, within the cap."""
    lin = _noisy_linearisation(2.0)
    rho = lin.noise_dominated()
    assert rho[0] > 0.25 and np.all(rho[1:] == 0)
    step = np.array([1e-3, 1e-3, 1e-3])
    np.testing.assert_allclose(widen_steps(lin, step, np.ones(3)), [min(4e-3 * np.sqrt(rho[0]), 8e-3), 1e-3, 1e-3])
    np.testing.assert_allclose(widen_steps(lin, step, np.full(3, 2e-3)), [2e-3, 1e-3, 1e-3])


def test_chain_is_centred_at_the_anchor_and_flat_where_the_slopes_are_noise():
    """The chain's mean is the anchor, though the linear model's optimum lies elsewhere; along a parameter whose
    slopes are all noise it is uniform over the region (mean at the centre, sd its width over sqrt(12)).

    Tolerances: four standard errors of a mean and of a standard deviation from the effective sample size.
    """
    lin = dataclasses.replace(_noisy_linearisation(6.0), value=np.full((30, 3), 3.0))
    info = lin.jac.T @ lin.jac - lin.slope_noise
    sd = np.sqrt(np.diag(laplace(lin.jac, lin.slope_noise)))
    optimum = -laplace(lin.jac, lin.slope_noise) @ lin.jac.T @ lin.residuals
    assert np.max(np.abs(optimum[1:]) / sd[1:]) > 1.5  # the linear model's optimum is off the anchor
    region = (np.full(3, -1.0), np.full(3, 1.0))
    chain, _ = sample(lin, region, np.full(3, 0.1), seed=2, walkers=8, max_steps=20000,
                      progress=lambda message: None)
    assert chain.converged
    ess = chain.ess
    w, u = np.linalg.eigh(info)
    assert w[0] < 1e-9 * w[-1] and abs(u[0, 0]) > 0.99  # parameter 0 alone is unresolved
    mean, spread = chain.samples.mean(axis=0), chain.samples.std(axis=0)
    assert np.all(np.abs(mean[1:]) < 4 * sd[1:] / np.sqrt(ess[1:]))
    assert np.all(np.abs(spread[1:] / sd[1:] - 1) < 4 / np.sqrt(2 * ess[1:]))
    uniform = 2 / np.sqrt(12)
    assert abs(mean[0]) < 4 * uniform / np.sqrt(ess[0])
    assert abs(spread[0] / uniform - 1) < 4 * np.sqrt(0.8 / 4 / ess[0])


# --- a small jaxcos problem with a known truth ---------------------------------------

TRUTH = jaxcos.Material(layers=(jaxcos.Layer(t=16.0, c_d=0.6, albedo_d=(0.9, 0.8, 0.7), g1=0.4, g2=0.0, w_g=1.0,
                                             albedo_p=(0.85, 0.85, 0.8), alpha_p=0.3, theta_p=4.0),),
                        variant="single_lobe")


ANGLES_I = np.repeat([0.0, 20.0, 40.0, 60.0], 13)
ANGLES_O = np.tile([-70.0, -50.0, -30.0, -10.0, 5.0, 15.0, 25.0, 35.0, 45.0, 55.0, 65.0, 75.0, 85.0], 4)


@functools.lru_cache(maxsize=None)
def _truth_curve(walks):
    """Reflectance factors of TRUTH, ``(52, 3)``, from an estimate with ``walks`` walks under its own key.

    48 bounces, as in the fit: the test is about the spreads, not the truncation.
    """
    est = jaxcos.simulate(TRUTH, jaxcos.make_query(ANGLES_I, ANGLES_O), jax.random.key(1234), walks=walks, bounces=48)
    return np.pi * np.asarray(est.f, dtype=float)


def _synthetic(seed=11, walks=8192):
    """The truth curve plus 5% + 0.005 Gaussian noise.

    The curve's own Monte Carlo error is a bias shared by every draw: at 8192
    walks it is 0.09 noise-sd per point (RMS), and it shifts the best fit by
    0.2-0.5 posterior sd. The coverage benchmark uses 2^18 walks.
    """
    f = _truth_curve(walks)
    std = np.sqrt((0.05 * f) ** 2 + 0.005 ** 2)
    values = f + std * np.random.default_rng(seed).standard_normal(f.shape)
    return Measurements(theta_i=ANGLES_I, theta_o=ANGLES_O, phi_o=np.zeros_like(ANGLES_I), values=values, std=std,
                        quantity="reflectance_factor", metadata={}, path="synthetic.csv")


@pytest.fixture(scope="module")
def small_posterior():
    """The posterior at a small budget after the fit that ``jaxcos uncertainty`` runs, started at the truth.

    The fit includes its finer stage. Without it, a fit at 128 walks follows
    its key's Monte Carlo error (its Jacobian moves ``g1``, ``alpha_p`` and
    ``theta_p``, docs/method.md), and the anchor search, compared under
    1024-walk keys here, stops at different points of a flat ``c_d``-``g1``
    valley: the truth's d2 ranged 15-40 over the search's settings
    (benchmarks/RESULTS.md, "Posterior").
    """
    data = _synthetic()
    start = jaxcos.fit(data, variant="single_lobe", bounces=48, start=TRUTH)
    post = uncertainty(data, start, walkers=24, max_steps=600, hi_walks=1024,
                       checks=4, replicas=12)
    return data, post


# The truth lies inside the posterior's joint region: its Mahalanobis distance
# from the posterior mean, under the posterior covariance, is a chi-square
# variable with as many degrees of freedom as parameters. (One marginal at a
# time would not do: a truth at the edge of the joint region can sit several
# marginal widths from the median of a correlated parameter.)
CHI2_BOUND = float(chi2.ppf(1 - 1e-4, 10))


@pytest.mark.slow
def test_posterior_covers_the_truth(small_posterior):
    _, post = small_posterior
    truth = np.asarray(post.fit.param.to_physical(post.fit.param.from_material(TRUTH)), float)
    mean = np.array([post.summary[n]["median"] for n in post.labels])
    half = np.array([0.5 * (post.summary[n]["p84"] - post.summary[n]["p16"]) for n in post.labels])
    cov = post.correlation * np.outer(half, half)
    d2 = float((truth - mean) @ np.linalg.solve(cov, truth - mean))
    assert d2 < CHI2_BOUND, d2
    for name in post.labels:
        s = post.summary[name]
        assert s["p2.5"] <= s["p16"] <= s["median"] <= s["p84"] <= s["p97.5"]
    assert np.all(np.isfinite(post.chain.tau)) and np.all(post.chain.ess > 0)


RECORD_KEYS = ("labels", "variant", "n_points", "n_params", "walkers", "steps", "burn", "acceptance_fraction",
               "acceptance_fraction_min", "chain_in_tau", "converged", "sampling_time_s", "time_s", "seed", "prior",
               "linear_region", "budget", "noise", "noise_scale", "slope_steps", "chi2_high_budget_at_fit",
               "chi2_high_budget_at_anchor", "mc_anchor_relative_error", "mc_anchor_error_over_noise",
               "mc_model_error_over_noise", "noise_relative", "noise_absolute", "noise_log10_sd", "unresolved")
"""The keys of posterior.json's "record", in order: as they were before the record was typed, then the
estimated noise's (``None`` for a file with std columns), then the parameters the slopes do not resolve."""


@pytest.mark.slow
def test_write_uncertainty(small_posterior, tmp_path):
    data, post = small_posterior
    out = tmp_path / "post"
    paths = write_uncertainty(post, data, str(out))
    assert sorted(os.listdir(out)) == sorted(os.path.basename(p) for p in paths)
    doc = json.loads((out / "posterior.json").read_text())
    assert set(doc["parameters"]) == set(post.labels)
    assert {"median", "p16", "p84", "p2.5", "p97.5"} <= set(doc["parameters"]["alpha_p"])
    assert doc["diagnostics"]["converged"] == post.converged
    # the typed record writes the "record" object as the dict it replaced did: the same keys, in order
    assert isinstance(post.record, PosteriorRecord) and tuple(doc["record"]) == RECORD_KEYS
    assert doc["record"]["budget"] == {"hi_walks": 1024, "bounces": 48}
    assert doc["record"]["prior"]["alpha_p"] == list(post.record.prior["alpha_p"])
    assert doc["record"]["chain_in_tau"] == post.record.chain_in_tau and not post.record.interface
    assert doc["record"]["noise"] == "file std columns" and doc["record"]["noise_relative"] is None
    assert doc["derived"] == {} == post.derived  # one diffuser lobe: g1 is its mean cosine
    report = (out / "report.md").read_text()
    assert "autocorrelation" in report and "Laplace" in report
    with pytest.raises(jaxcos.InputError, match="exists"):
        write_uncertainty(post, data, str(out))


# --- a file without std columns ----------------------------------------------------------


@pytest.mark.parametrize("absolute", [0.002, 0.0])
def test_noise_levels_are_recovered_by_maximum_likelihood(absolute):
    """Residuals drawn with std = 0.03 |y| + absolute: the estimate is within 4 of its own Laplace sd.

    Without an absolute term its level is not identified: whatever is estimated
    adds at most a tenth to the std of the smallest value.
    """
    rng = np.random.default_rng(4)
    y = np.exp(rng.uniform(np.log(1e-3), np.log(1.0), (300, 3)))
    resid = (0.03 * y + absolute) * rng.standard_normal(y.shape)
    model = estimate_noise(resid, y, np.zeros_like(y))
    assert abs(np.log10(model.relative / 0.03)) < 4 * model.sd[0]
    if absolute:
        assert abs(np.log10(model.absolute / absolute)) < 4 * model.sd[1]
    else:
        assert model.absolute < 0.1 * 0.03 * y.min() or model.sd[1] > 1.0
    # the degrees of freedom of a fit scale both levels alike
    scaled = estimate_noise(resid, y, np.zeros_like(y), n_fitted=100)
    assert scaled.relative / model.relative == pytest.approx(np.sqrt(900 / 800), rel=1e-6)
    assert scaled.absolute / model.absolute == pytest.approx(np.sqrt(900 / 800), rel=1e-6)


@pytest.fixture(scope="module")
def no_std_posterior():
    """The small problem's data with the std columns removed: the posterior estimates the noise."""
    data = dataclasses.replace(_synthetic(), std=None)
    start = jaxcos.fit(data, variant="single_lobe", walks=128, bounces=48, start=TRUTH, finer=False)
    return data, uncertainty(data, start, walkers=24, max_steps=600, hi_walks=1024, checks=4, replicas=12)


@pytest.mark.slow
def test_posterior_without_std_estimates_the_noise_and_covers_the_truth(no_std_posterior, tmp_path):
    data, post = no_std_posterior
    model = post.noise_model
    assert isinstance(model, NoiseModel) and post.record.noise.startswith("estimated by maximum likelihood")
    assert (post.record.noise_relative, post.record.noise_absolute) == (model.relative, model.absolute)
    np.testing.assert_allclose(post.noise, model.std(data.values))
    # the data's noise, sqrt((0.05 f)^2 + 0.005^2), read by the model 0.05 |y| + a: between the two forms
    assert 0.5 * 0.05 < model.relative + model.absolute / np.median(np.abs(data.values)) < 2 * 0.05
    truth = np.asarray(post.fit.param.to_physical(post.fit.param.from_material(TRUTH)), float)
    mean = np.array([post.summary[n]["median"] for n in post.labels])
    half = np.array([0.5 * (post.summary[n]["p84"] - post.summary[n]["p16"]) for n in post.labels])
    d2 = float((truth - mean) @ np.linalg.solve(post.correlation * np.outer(half, half), truth - mean))
    assert d2 < CHI2_BOUND, d2
    write_uncertainty(post, data, str(tmp_path / "post"))
    report = (tmp_path / "post" / "report.md").read_text()
    assert "no std columns" in report and f"--noise {model.relative:.3g},{model.absolute:.3g}" in report
    record = json.loads((tmp_path / "post" / "posterior.json").read_text())["record"]
    assert record["noise_relative"] == model.relative and len(record["noise_log10_sd"]) == 2


# --- a fit with a top interface ---------------------------------------------------------

GLOSSY = jaxcos.Material(layers=(jaxcos.Layer(t=16.0, c_d=1.0, albedo_d=(0.85, 0.75, 0.6), g1=0.5, g2=-0.2, w_g=0.7,
                                              albedo_p=(0.8, 0.8, 0.8), alpha_p=0.3, theta_p=0.0),),
                         variant="diffusers_only", interface=jaxcos.Interface(eta=1.5, alpha_s=0.15))
GLOSSY_I = np.repeat([15.0, 45.0, 65.0], 9)
GLOSSY_O = np.tile([-60.0, -30.0, 0.0, 15.0, 30.0, 45.0, 55.0, 65.0, 75.0], 3)


@pytest.fixture(scope="module")
def interface_posterior():
    """A short chain on a small diffusers-under-an-interface set (8 parameters).

    The chain starts from the truth standing in for a fit (what :func:`uncertainty` reads of one:
    ``param``, ``x``, the bounces of its budget, and the record written beside the posterior):
    compiling a fit of the interface walk would cost more than the rest of the test.
    """
    est = jaxcos.simulate(GLOSSY, jaxcos.make_query(GLOSSY_I, GLOSSY_O), jax.random.key(7), walks=256, bounces=16)
    f = np.pi * np.asarray(est.f, dtype=float)
    std = np.sqrt((0.03 * f) ** 2 + 0.005 ** 2)
    data = Measurements(theta_i=GLOSSY_I, theta_o=GLOSSY_O, phi_o=np.zeros_like(GLOSSY_I),
                        values=f + std * np.random.default_rng(5).standard_normal(f.shape), std=std,
                        quantity="reflectance_factor", metadata={}, path="glossy.csv")
    param = parameterization("diffusers_only", interface=True, template=GLOSSY)
    start = SimpleNamespace(param=param, x=param.from_material(GLOSSY),
                            record=SimpleNamespace(budget=SimpleNamespace(bounces=16), to_json=lambda: {}))
    return data, uncertainty(data, start, max_steps=200, hi_walks=256, checks=2, replicas=4)


@pytest.mark.slow
def test_posterior_samples_the_interface(interface_posterior, tmp_path, monkeypatch):
    """eta and alpha_s are sampled within their ranges and named in the summary, the report and the figures."""
    import jaxcos.report._posterior as written

    data, post = interface_posterior
    figures = {}  # the figures write_uncertainty draws, kept to read their labels
    monkeypatch.setattr(written, "_corner", lambda *a: figures.setdefault("corner", _corner(*a)))
    monkeypatch.setattr(written, "_sensitivity_maps",
                        lambda *a: figures.setdefault("sensitivity", _sensitivity_maps(*a)))
    assert post.labels[-2:] == ["eta", "alpha_s"] and post.record.interface
    assert post.chain.samples.shape[1] == len(post.labels) == post.record.n_params == 8
    for name, (low, high) in (("eta", (1.01, 2.5)), ("alpha_s", (0.005, 1.0))):
        column = post.chain.samples[:, post.labels.index(name)]
        assert np.all((column >= low) & (column <= high)) and np.std(column) > 0, name
        s = post.summary[name]
        assert low <= s["p2.5"] <= s["p16"] <= s["median"] <= s["p84"] <= s["p97.5"] <= high
        assert post.record.prior[name] == pytest.approx((low, high))
    out = tmp_path / "post"
    write_uncertainty(post, data, str(out))
    doc = json.loads((out / "posterior.json").read_text())
    assert {"eta", "alpha_s"} <= set(doc["parameters"]) and doc["record"]["labels"][-2:] == ["eta", "alpha_s"]
    report = (out / "report.md").read_text()
    assert "top interface" in report and "| `eta` |" in report and "| `alpha_s` |" in report
    corner = figures["corner"]
    assert {"eta", "alpha_s"} <= {ax.get_xlabel() for ax in corner.axes} | {ax.get_ylabel() for ax in corner.axes}
    assert {"eta", "alpha_s"} <= {ax.get_title() for ax in figures["sensitivity"].axes}
    # too few walkers for the parameters is refused before any work, in one sentence
    with pytest.raises(jaxcos.InputError, match="at least 2 \\* parameters \\+ 2 = 18"):
        uncertainty(data, post.fit, walkers=16)


def test_cli_bad_inputs(tmp_path, capsys):
    assert main(["uncertainty", "measurements/matte2.csv", "--out", str(tmp_path / "o"),
                 "--params", str(tmp_path / "missing.json")]) == 2
    assert "missing.json" in capsys.readouterr().err
    bad = tmp_path / "bad.csv"
    bad.write_text("theta_i,theta_o,r,g,b\n0,10,0.1,0.1\n")
    assert main(["uncertainty", str(bad), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip()
    assert "bad.csv" in err and len(err.splitlines()) == 1
    assert main(["uncertainty", "measurements/matte2.csv", "--out", str(tmp_path / "o"), "--walkers", "2"]) == 2
    assert not (tmp_path / "o").exists()


def test_report_says_when_the_chain_reaches_the_edge_of_the_linearisation():
    """A posterior cut by the linearisation's region is told apart from one cut by the prior."""
    from jaxcos.report._posterior import _laplace_notes

    row = dict(p16_noise_only=0.2, p84_noise_only=0.3, laplace_sd=0.05)
    summary = {"inside": dict(row, **{"p2.5": 0.15, "p97.5": 0.35}),
               "at_region": dict(row, **{"p2.5": 0.15, "p97.5": 0.4}),
               "at_prior": dict(row, **{"p2.5": 0.0, "p97.5": 0.35}),
               "unresolved": dict(row, **{"p2.5": 0.0, "p97.5": 0.4})}
    record = SimpleNamespace(prior={n: (0.0, 1.0) for n in summary},
                             linear_region={"inside": (0.0, 0.6), "at_region": (0.0, 0.4), "at_prior": (0.0, 0.6),
                                            "unresolved": (0.0, 0.4)},
                             unresolved=["unresolved"])
    notes = _laplace_notes(SimpleNamespace(summary=summary, record=record))
    assert len(notes) == 3
    assert notes[0].startswith("`at_region`") and "linearised" in notes[0]
    assert notes[1].startswith("`at_prior`") and "prior" in notes[1]
    assert notes[2].startswith("`unresolved`") and "Monte Carlo noise" in notes[2]


def test_report_names_unresolved_parameters_behind_a_laplace_disagreement():
    """Where the chain is narrower than the Laplace sd only through a parameter the linearisation does not resolve
    (the Laplace sd with it held agrees), the note names that parameter; otherwise it says "not Gaussian"."""
    from jaxcos.report._posterior import _laplace_notes

    # Laplace: a and u correlated 0.9, sd 0.1 each: a's sd with u held is 0.1 sqrt(1 - 0.81) = 0.0436
    cov = 0.01 * np.array([[1.0, 0.9, 0.0], [0.9, 1.0, 0.0], [0.0, 0.0, 1.0]])
    row = dict(laplace_sd=0.1, **{"p2.5": 0.3, "p97.5": 0.7})
    summary = {"a": dict(row, p16_noise_only=0.455, p84_noise_only=0.545),      # half-width 0.045
               "u": dict(row, p16_noise_only=0.4, p84_noise_only=0.6),
               "b": dict(row, p16_noise_only=0.48, p84_noise_only=0.52)}         # 0.02: too narrow either way
    box = {n: (0.0, 1.0) for n in summary}

    def post(unresolved):
        record = SimpleNamespace(prior=box, linear_region=box, unresolved=unresolved)
        return SimpleNamespace(summary=summary, record=record, labels=["a", "u", "b"], laplace_cov=cov)

    notes = {n.split("`")[1]: n for n in _laplace_notes(post(["u"]))}
    assert "0.0436 with `u` held" in notes["a"] and "not Gaussian" not in notes["a"]
    assert "not Gaussian" in notes["b"]
    notes = {n.split("`")[1]: n for n in _laplace_notes(post([]))}
    assert "not Gaussian" in notes["a"]
    # a fixed by u (correlation 1: a singular covariance, as from fewer values than parameters): nothing is left
    # of a's sd with u held, and the note is the plain one, not a division by that zero
    cov[:] = 0.01 * np.array([[1.0, 1.0, 0.0], [1.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    notes = {n.split("`")[1]: n for n in _laplace_notes(post(["u"]))}
    assert "not Gaussian" in notes["a"]


def test_mean_cosine_is_the_first_moment_of_the_diffuser_mixture():
    """``g_mean`` against the mean of ``w . w'`` under the walk's own two-lobe phase function, integrated
    numerically over the sphere (midpoint rule in ``cos``; the function is azimuthally symmetric)."""
    labels = ["c_d", "g1", "g2", "w_g", "alpha_p"]
    v = np.array([[0.5, 0.62, -0.35, 0.7, 0.1], [0.5, 0.05, 0.3, 0.2, 0.1], [0.5, 0.8, 0.8, 0.4, 0.1]])
    n = 200000
    mu = (np.arange(n) + 0.5) / n * 2.0 - 1.0
    out = np.stack([mu * 0, np.sqrt(1 - mu ** 2), mu], axis=-1)
    w = np.array([0.0, 0.0, 1.0])
    for row, g_mean in zip(v, derived(labels, v)["g_mean"]):
        _, g1, g2, wg, _ = row
        f = wg * np.asarray(hg(w, out, g1)) + (1 - wg) * np.asarray(hg(w, out, g2))
        moment = 2 * np.pi * np.sum(mu * f) * (2.0 / n)
        assert abs(g_mean - moment) < 1e-4, (row, g_mean, moment)
    assert derived(["c_d", "g1", "alpha_p"], v[:, :3]) == {}


def test_report_says_when_the_two_lobes_overlap():
    """Overlapping 95% intervals of ``g1`` and ``g2`` get a note on ``w_g``; separate ones do not."""
    from jaxcos.report._posterior import _laplace_notes

    def post(g1, g2):
        row = dict(p16_noise_only=0.4, p84_noise_only=0.6, laplace_sd=0.1)
        summary = {name: dict(row, **{"p2.5": a, "p97.5": b}) for name, (a, b) in
                   (("g1", g1), ("g2", g2), ("w_g", (0.3, 0.7)))}
        box = {n: (-1.0, 1.0) for n in summary}
        record = SimpleNamespace(prior=box, linear_region=box, unresolved=[])
        return SimpleNamespace(summary=summary, record=record)

    assert [n for n in _laplace_notes(post((-0.01, 0.11), (-0.09, 0.03))) if n.startswith("`w_g`")]
    assert not [n for n in _laplace_notes(post((0.19, 0.21), (0.33, 0.41))) if n.startswith("`w_g`")]


def test_a_chain_that_never_moved_gets_its_length_as_autocorrelation_time():
    """emcee's estimate is 0/0 for a parameter with no variance; the chain's length stands in, never NaN."""
    from jaxcos.inference._posterior import _tau

    class Frozen:
        def get_chain(self, discard=0):
            chain = np.random.default_rng(0).standard_normal((40, 8, 2))
            chain[:, :, 1] = 0.5  # a parameter that never moved
            return chain[discard:]

    tau = _tau(Frozen(), discard=10)
    assert np.all(np.isfinite(tau)) and tau[1] == 30.0 and tau[0] < 30.0
