"""The ablation: variant structure, padding, statistics, the BIC verdict on synthetic data, the command."""

import csv
import dataclasses
import json
import os

import jax
import jax.extend
import jax.numpy as jnp
import numpy as np
import pytest

import jaxcos
from jaxcos.inference._ablate import (
    CSV_COLUMNS,
    check_variants,
    embed,
    information_criteria,
    mean_delta_e2000,
    n_params,
    pad_measurements,
    start_from_two_lobe,
    with_interface_variants,
    _common_shape,
)
from jaxcos.cli import main
from jaxcos.inference._fit import make_problem, parameterization
from jaxcos.inference._kubelka_munk import make_km_problem
from jaxcos.io._measurements import Measurements
from jaxcos.report._ablate import ABLATION_FILES, ablation_report

# --- structure ---------------------------------------------------------------------------

COUNTS = {"diffusers_only": 6, "platelets_only": 5, "single_lobe": 10, "two_lobe": 12, "kubelka_munk": 8}
# Parameters each Monte Carlo variant switches off (docs/formats.md: c_d = 1, c_d = 0, w_g = 1).
SWITCHED_OFF = {
    "diffusers_only": ("c_d", "albedo_p", "alpha_p", "theta_p"),
    "platelets_only": ("c_d", "albedo_d", "g1", "g2", "w_g"),
    "single_lobe": ("g2", "w_g"),
    "two_lobe": (),
}
FULL = jaxcos.Layer(t=16.0, c_d=0.6, albedo_d=(0.8, 0.7, 0.6), g1=0.5, g2=-0.3, w_g=0.7, albedo_p=(0.85, 0.8, 0.75),
                    alpha_p=0.25, theta_p=3.0)


def test_parameter_counts():
    for variant, k in COUNTS.items():
        assert n_params(variant) == k
        if variant != "kubelka_munk":  # the counterpart with a top interface: eta and alpha_s besides
            assert n_params(variant + "+interface") == k + 2
    for variant in SWITCHED_OFF:
        names = parameterization(variant).names
        assert not set(names) & set(SWITCHED_OFF[variant])


def _count_eqns(jaxpr):
    total = 0
    for eqn in jaxpr.eqns:
        total += 1
        for sub in jax.extend.core.jaxprs_in_params(eqn.params):
            total += _count_eqns(sub)
    return total


def test_switched_off_parts_are_not_simulated():
    """Changing a switched-off parameter changes nothing, and each reduced program is smaller than the full one."""
    query = jaxcos.make_query([30.0, 30.0], [-20.0, 40.0])
    key = jax.random.key(3)
    sim = jax.jit(lambda m: jaxcos.simulate(m, query, key, walks=4, bounces=3).f)
    other = dict(c_d=0.3, albedo_d=(0.2, 0.3, 0.4), g1=-0.4, g2=0.8, w_g=0.2, albedo_p=(0.1, 0.2, 0.3), alpha_p=0.7,
                 theta_p=20.0)
    sizes = {}
    for variant, off in SWITCHED_OFF.items():
        m = jaxcos.with_variant(jaxcos.Material(layers=(FULL,)), variant)
        f = np.asarray(sim(m))
        for name in off:
            changed = jaxcos.Material(layers=(FULL.__class__(**{**_fields(m.layers[0]), name: other[name]}),),
                                      variant=variant)
            np.testing.assert_array_equal(np.asarray(sim(changed)), f, err_msg=f"{variant}: {name} still acts")
        kept = [n for n in ("c_d", "g1", "w_g", "alpha_p") if n not in off]
        for name in kept:  # and the parameters it keeps do act
            changed = jaxcos.Material(layers=(FULL.__class__(**{**_fields(m.layers[0]), name: other[name]}),),
                                      variant=variant)
            assert not np.array_equal(np.asarray(sim(changed)), f), f"{variant}: {name} has no effect"
        jaxpr = jax.make_jaxpr(lambda mm: jaxcos.simulate(mm, query, key, walks=4, bounces=3).f)(m)
        sizes[variant] = _count_eqns(jaxpr.jaxpr)
    for variant in ("diffusers_only", "platelets_only", "single_lobe"):
        assert sizes[variant] < sizes["two_lobe"], sizes


def _fields(layer):
    return {k: getattr(layer, k) for k in ("t", "c_d", "albedo_d", "g1", "g2", "w_g", "albedo_p", "alpha_p",
                                           "theta_p", "phi_p")}


def test_starts_for_reduced_and_nesting_variants():
    two = jaxcos.Material(layers=(FULL,))
    single = start_from_two_lobe(two, "single_lobe")
    assert single.variant == "single_lobe" and float(single.layers[0].w_g) == 1.0
    assert float(single.layers[0].g1) == pytest.approx(0.7 * 0.5 + 0.3 * -0.3)  # the mean cosine
    assert float(start_from_two_lobe(two, "diffusers_only").layers[0].c_d) == 1.0
    assert float(start_from_two_lobe(two, "platelets_only").layers[0].c_d) == 0.0
    # a nested fit embedded in the larger variant reproduces it (same phase function, exactly)
    query = jaxcos.make_query([30.0, 50.0], [-20.0, 50.0])
    up = embed(single, "two_lobe", two)
    assert up.variant == "two_lobe" and float(up.layers[0].w_g) == 0.5
    assert float(up.layers[0].g2) == float(up.layers[0].g1) == float(single.layers[0].g1)
    from jaxcos.model._walk import single_scattering, stack_medium

    np.testing.assert_allclose(single_scattering(stack_medium(up), None, query.wi, query.wo),
                               single_scattering(stack_medium(single), None, query.wi, query.wo), rtol=1e-6)
    plate = start_from_two_lobe(two, "platelets_only")
    assert float(embed(plate, "single_lobe", single).layers[0].c_d) == pytest.approx(0.03)


def test_variant_lists():
    assert check_variants("two_lobe, kubelka_munk") == ("two_lobe", "kubelka_munk")
    assert check_variants(["kubelka_munk", "diffusers_only"]) == ("diffusers_only", "kubelka_munk")
    # each Monte Carlo variant followed by its counterpart with a top interface; Kubelka-Munk has none
    assert with_interface_variants(("single_lobe", "two_lobe", "kubelka_munk")) == (
        "single_lobe", "single_lobe+interface", "two_lobe", "two_lobe+interface", "kubelka_munk")
    for bad, message in (("three_lobe", "unknown variant 'three_lobe'"), ("two_lobe,two_lobe", "given twice"),
                         ("", "no variant"), ("two_lobe+interface", "--interface")):
        with pytest.raises(jaxcos.InputError, match=message):
            check_variants(bad)


# --- padding -------------------------------------------------------------------------------


def _meas(ti, to, values=None, std=True, path="m.csv"):
    ti, to = np.asarray(ti, float), np.asarray(to, float)
    values = np.full((ti.size, 3), 0.3) if values is None else values
    return Measurements(theta_i=ti, theta_o=to, phi_o=np.zeros_like(ti), values=values,
                        std=np.full_like(values, 0.01) if std else None, quantity="reflectance_factor", path=path)


def test_padding_gives_one_shape_and_changes_no_residual():
    a = _meas([20, 20, 20, 40, 40, 60], [-10, 10, 30, 0, 40, 60], path="a.csv")
    b = _meas([30, 30, 50, 50, 50, 50, 50, 70], [0, 30, 10, 30, 50, 60, 70, 70],
              values=np.linspace(0.1, 0.9, 24).reshape(8, 3), path="b.csv")
    shape = _common_shape([a, b])
    pa, pb = pad_measurements(a, shape), pad_measurements(b, shape)
    leaves = lambda m: [(x.shape, x.dtype) for x in jax.tree.leaves(
        make_problem(m, parameterization("single_lobe"), key=jax.random.key(0), walks=4, bounces=2))]
    assert leaves(pa) == leaves(pb)  # the same compiled fit serves both
    structure = lambda m: jax.tree.structure(make_problem(m, parameterization("single_lobe"), key=jax.random.key(0)))
    assert structure(pa) == structure(pb)
    assert pa.n_points == pb.n_points == shape[2]
    np.testing.assert_array_equal(pb.values[:b.n_points], b.values)  # real points first, unchanged
    assert np.all(np.isinf(pb.std[b.n_points:]))
    # deterministic model: padded and unpadded objectives agree, dummy residuals and Jacobian rows are 0
    x = jnp.linspace(-1.0, 1.0, 8)
    np.testing.assert_allclose(make_km_problem(pb).loss(x), make_km_problem(b).loss(x), rtol=1e-6)
    r = np.asarray(make_km_problem(pb).residuals(x)).reshape(-1, 3)
    jac = np.asarray(jax.jacfwd(make_km_problem(pb).residuals)(x)).reshape(-1, 3, 8)
    assert np.all(r[b.n_points:] == 0) and np.all(jac[b.n_points:] == 0)
    with pytest.raises(ValueError):
        pad_measurements(_meas([20], [10], std=False), shape)


# --- statistics -----------------------------------------------------------------------------


def test_information_criteria_follow_the_gaussian_likelihood():
    rng = np.random.default_rng(0)
    meas = _meas(np.repeat([20.0, 40.0], 5), np.tile([-40.0, -10.0, 10.0, 30.0, 60.0], 2))
    model = meas.values + 0.01 * rng.standard_normal(meas.values.shape)
    chi2, aic, bic = information_criteria(meas, model, 4)
    n = meas.values.size
    m2ll = np.sum(((model - meas.values) / 0.01) ** 2) + n * np.log(2 * np.pi * 0.01 ** 2)
    np.testing.assert_allclose([aic, bic], [m2ll + 8, m2ll + 4 * np.log(n)], rtol=1e-10)
    # without std: profile likelihood, the variance counted as a parameter
    free = _meas(meas.theta_i, meas.theta_o, values=meas.values, std=False)
    chi2, aic, _ = information_criteria(free, model, 4)
    rss = np.sum((model - meas.values) ** 2)
    assert np.isnan(chi2) and aic == pytest.approx(n * (np.log(2 * np.pi * rss / n) + 1) + 10)


def test_mean_delta_e2000():
    v = np.array([[0.2, 0.3, 0.4], [0.8, 0.8, 0.8]])
    assert mean_delta_e2000(v, v) == 0.0
    d = mean_delta_e2000(v, v * [1.1, 1.0, 0.9])
    assert 1.0 < d < 20.0
    # the same colours stated as a BRDF give the same difference; the exposure matters
    assert mean_delta_e2000(v / np.pi, v * [1.1, 1.0, 0.9] / np.pi, "brdf") == pytest.approx(d, rel=1e-6)
    assert mean_delta_e2000(v, v * [1.1, 1.0, 0.9], exposure=0.2) != pytest.approx(d, rel=1e-3)


# --- the verdict on synthetic data -----------------------------------------------------------

WALKS, BOUNCES = 256, 24
# Diffusers dominate (c_d = 0.85) so that their phase function shows in the exact single-scattering term;
# albedos near 0.5 keep the Monte Carlo part (orders two and up) small against the noise.
SINGLE = jaxcos.Material(layers=(jaxcos.Layer(t=16.0, c_d=0.85, albedo_d=(0.55, 0.5, 0.45), g1=0.45, g2=0.0, w_g=1.0,
                                              albedo_p=(0.6, 0.6, 0.55), alpha_p=0.25, theta_p=3.0),),
                         variant="single_lobe")
TWO = jaxcos.Material(layers=(jaxcos.Layer(t=16.0, c_d=0.85, albedo_d=(0.55, 0.5, 0.45), g1=0.8, g2=-0.5, w_g=0.6,
                                           albedo_p=(0.6, 0.6, 0.55), alpha_p=0.25, theta_p=3.0),))
N_POINTS = 51


def _synthetic(material, path, seed, walks=4096):
    """Reflectance factors of ``material`` (4096 walks: Monte Carlo error far below the noise) with 3% + 0.005 noise.

    Three incidences by seventeen viewing angles.
    """
    ti = np.repeat([10.0, 35.0, 60.0], 17)
    to = np.tile(np.arange(-80.0, 81.0, 10.0), 3)
    est = jaxcos.simulate(material, jaxcos.make_query(ti, to), jax.random.key(99), walks=walks, bounces=BOUNCES)
    f = np.pi * np.asarray(est.f, dtype=float)
    std = np.sqrt((0.03 * f) ** 2 + 0.005 ** 2)
    values = f + std * np.random.default_rng(seed).standard_normal(f.shape)
    return Measurements(theta_i=ti, theta_o=to, phi_o=np.zeros_like(ti), values=values, std=std,
                        quantity="reflectance_factor", metadata={}, path=path)


@pytest.fixture(scope="module")
def ablation():
    """One ablation of two synthetic files: one made by a single-lobe model, one by a strongly two-lobed one."""
    files = [_synthetic(SINGLE, "single.csv", 3), _synthetic(TWO, "two.csv", 4)]
    return jaxcos.ablate(files, variants=("single_lobe", "two_lobe"), walks=WALKS, bounces=BOUNCES, starts=3, seed=0,
                         finer=False)


def _row(result, name, variant):
    return next(r for r in result.rows if r["file"] == name and r["variant"] == variant)


@pytest.mark.slow
def test_single_lobe_data_do_not_prefer_two_lobes(ablation):
    single, two = _row(ablation, "single.csv", "single_lobe"), _row(ablation, "single.csv", "two_lobe")
    assert single["bic"] < two["bic"], (single, two)
    # the two-lobe model, which contains the single lobe, fits at least about as well
    assert two["chi2"] < single["chi2"] + 5.0
    # the single-lobe fit is consistent with the noise (153 residuals, 10 parameters)
    assert single["reduced_chi2"] < 1.5


@pytest.mark.slow
def test_two_lobe_data_do_prefer_two_lobes(ablation):
    """The same verdict can go the other way: the test above is not passed by construction."""
    single, two = _row(ablation, "two.csv", "single_lobe"), _row(ablation, "two.csv", "two_lobe")
    assert two["bic"] < single["bic"] - 10.0, (single, two)


GLOSSY = jaxcos.Material(layers=(jaxcos.Layer(t=16.0, c_d=1.0, albedo_d=(0.6, 0.55, 0.5), g1=0.5, g2=-0.2, w_g=0.7,
                                              albedo_p=(0.8, 0.8, 0.8), alpha_p=0.3, theta_p=0.0),),
                         variant="diffusers_only", interface=jaxcos.Interface(eta=1.5, alpha_s=0.12))
"""Diffusers under a rough dielectric interface: a gloss that grows towards grazing, which no diffuser makes."""


@pytest.fixture(scope="module")
def interface_ablation():
    """An ablation with ``interface=True`` of one file simulated with an interface, at a small budget.

    Diffusers alone miss the gloss by far (reduced chi-square above 100), so 1024 walks for the data and
    32 for the fits decide it; the fit with the interface is within about 1.5 of the noise.
    """
    data = _synthetic(GLOSSY, "glossy.csv", 5, walks=1024)
    return jaxcos.ablate([data], variants=("diffusers_only",), walks=32, bounces=16, starts=0, seed=0, interface=True,
                         finer=False)


@pytest.mark.slow
def test_interface_data_prefer_the_interface(interface_ablation, tmp_path):
    """Each variant is compared with its counterpart under an interface, by BIC; the written table only grows."""
    result = interface_ablation
    assert result.variants == ("diffusers_only", "diffusers_only+interface")
    plain, top = (_row(result, "glossy.csv", v) for v in result.variants)
    assert top["n_params"] == plain["n_params"] + 2 == COUNTS["diffusers_only"] + 2
    assert top["bic"] < plain["bic"] - 100.0, (plain, top)
    assert top["start"] in ("multi-start", "index-matched fit") and top["walks"] == 32
    fitted = result.fits[(0, "diffusers_only+interface")].material
    assert fitted.variant == "diffusers_only" and result.fits[(0, "diffusers_only")].material.interface is None
    # the interface of the data is found (eta 1.5, alpha_s 0.12), and fits them to about their noise
    assert abs(float(fitted.interface.eta) - 1.5) < 0.2 and 0.06 < float(fitted.interface.alpha_s) < 0.25
    assert top["reduced_chi2"] < 3.0 < 100.0 < plain["reduced_chi2"]
    out = tmp_path / "abl"
    jaxcos.write_ablation(result, out)
    with open(out / "ablation.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert tuple(rows[0]) == CSV_COLUMNS and [r["variant"] for r in rows] == list(result.variants)
    report = (out / "report.md").read_text()
    assert "## With and without the interface" in report and "`diffusers_only+interface`" in report
    assert "like a reflection at the surface" not in report
    # without the interface, the report says that this file's gloss is a surface's
    plain_only = dataclasses.replace(result, variants=result.variants[:1], rows=[plain],
                                     fits={(0, "diffusers_only"): result.fits[(0, "diffusers_only")]})
    assert "like a reflection at the surface" in ablation_report(plain_only)
    assert "again with `--interface`" in ablation_report(plain_only)
    fits = json.loads((out / "fits.json").read_text())["glossy.csv"]
    assert "interface" in fits["diffusers_only+interface"] and "interface" not in fits["diffusers_only"]


@pytest.mark.slow
def test_rows_and_written_results(ablation, tmp_path):
    assert [(r["file"], r["variant"]) for r in ablation.rows] == [
        (f, v) for f in ("single.csv", "two.csv") for v in ("single_lobe", "two_lobe")]
    for r in ablation.rows:
        assert r["n_params"] == COUNTS[r["variant"]] and r["n_points"] == N_POINTS
        assert np.isfinite([r["l2"], r["rmse"], r["delta_e2000"], r["aic"], r["bic"]]).all()
        assert r["bic"] - r["aic"] == pytest.approx(r["n_params"] * (np.log(3 * N_POINTS) - 2))
    fit = ablation.fits[(0, "single_lobe")]
    assert fit.material.variant == "single_lobe" and float(fit.material.layers[0].w_g) == 1.0
    assert fit.model.shape == (N_POINTS, 3)
    out = tmp_path / "abl"
    paths = jaxcos.write_ablation(ablation, out)
    assert sorted(os.listdir(out)) == sorted(ABLATION_FILES)
    with open(out / "ablation.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert tuple(rows[0]) == CSV_COLUMNS and len(rows) == 4
    assert float(rows[1]["bic"]) == pytest.approx(ablation.rows[1]["bic"], rel=1e-5)
    report = (out / "report.md").read_text()
    assert "CIEDE2000" in report and "exposure 1" in report and "D65" in report and "## single.csv" in report
    assert ablation.settings["finer"] is False and "no fit's last refinement at four times the walks" in report
    assert not any(s.label.endswith("x walks") for s in fit.starts)
    assert (out / "ablation.png").stat().st_size > 10000
    with pytest.raises(jaxcos.InputError, match="already exists"):
        jaxcos.write_ablation(ablation, out)
    assert paths == [str(out / n) for n in ABLATION_FILES]


# --- the command -------------------------------------------------------------------------------


def _csv(tmp_path, name="m.csv", body=None):
    path = tmp_path / name
    rows = body or "".join(f"{ti},{to},{0.3 + 0.001 * to:.4f},0.3,0.25,0.01,0.01,0.01\n"
                           for ti in (20, 50) for to in (-40, -10, 10, 30, 50, 70))
    path.write_text("# quantity: reflectance_factor\ntheta_i,theta_o,r,g,b,r_std,g_std,b_std\n" + rows)
    return path


def test_command_writes_the_table_and_refuses_to_overwrite(tmp_path, capsys):
    a, b = _csv(tmp_path, "a.csv"), _csv(tmp_path, "b.csv")
    out = tmp_path / "out"
    assert main(["ablate", str(a), str(b), "--out", str(out), "--variants", "kubelka_munk", "--starts", "2"]) == 0
    captured = capsys.readouterr()
    assert "jaxcos ablate [" in captured.err and "best by BIC kubelka_munk" in captured.out
    assert sorted(os.listdir(out)) == sorted(ABLATION_FILES)
    before = (out / "ablation.csv").read_text()
    assert before.count("\n") == 3 and before.startswith(",".join(CSV_COLUMNS))
    assert main(["ablate", str(a), "--out", str(out), "--variants", "kubelka_munk"]) == 2
    err = capsys.readouterr().err.strip()
    assert "already exists" in err and "--force" in err and len(err.splitlines()) == 1
    assert (out / "ablation.csv").read_text() == before
    assert main(["ablate", str(a), "--out", str(out), "--variants", "kubelka_munk", "--force"]) == 0
    assert (out / "ablation.csv").read_text().count("\n") == 2


def test_interface_flag_leaves_the_baseline_alone(tmp_path, capsys):
    """Kubelka-Munk has no counterpart under an interface: with --interface its table is the same."""
    out = tmp_path / "out"
    assert main(["ablate", str(_csv(tmp_path, "a.csv")), "--out", str(out), "--variants", "kubelka_munk",
                 "--starts", "1", "--interface"]) == 0
    assert "x 1 variant(s)" in capsys.readouterr().out
    table = (out / "ablation.csv").read_text().splitlines()
    assert table[0] == ",".join(CSV_COLUMNS) and len(table) == 2 and table[1].split(",")[1] == "kubelka_munk"
    report = (out / "report.md").read_text()
    assert "+interface" not in report and "## With and without the interface" not in report


@pytest.mark.parametrize("args, message", [
    (["--variants", "three_lobe"], "unknown variant 'three_lobe'"),
    (["--walks", "0"], "walks must be a positive integer"),
    (["--exposure", "-1"], "exposure must be a positive number"),
    (["--variants", "two_lobe+interface"], "--interface"),
])
def test_command_rejects_bad_options(tmp_path, capsys, args, message):
    out = tmp_path / "out"
    assert main(["ablate", str(_csv(tmp_path)), "--out", str(out)] + args) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and len(err.splitlines()) == 1 and err.startswith("jaxcos ablate: ")
    assert not out.exists()


def test_command_names_the_bad_file_and_line(tmp_path, capsys):
    good = _csv(tmp_path, "good.csv")
    bad = _csv(tmp_path, "bad.csv", body="20,10,0.1,0.1,0.1,0.01,0.01,0.01\n20,30,0.2,abc,0.2,0.01,0.01,0.01\n")
    out = tmp_path / "out"
    assert main(["ablate", str(good), str(bad), "--out", str(out), "--variants", "kubelka_munk"]) == 2
    err = capsys.readouterr().err.strip()
    assert str(bad) in err and "line 4" in err and "'abc'" in err and len(err.splitlines()) == 1
    assert not out.exists()
    assert main(["ablate", str(good), str(good), "--out", str(out)]) == 2
    assert "given twice" in capsys.readouterr().err
    assert main(["ablate", str(tmp_path / "missing.csv"), "--out", str(out)]) == 2
    assert "missing.csv" in capsys.readouterr().err and not out.exists()
