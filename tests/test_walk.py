"""Statistical and structural tests of the estimator (``jaxcos.model._walk``), through the public API.

Every statistical tolerance below is a multiple of a standard error that the
test measures (``Estimate.stderr``, or the spread of independent replicate
runs under different keys), with the multiple chosen for a stated false-alarm
probability; keys are fixed, so a passing test stays passing until the random
streams or the physics change. The budgets (walks, bounces, directions) are
chosen so the whole file runs in a few minutes on a 2-core CPU; shapes are
shared between calls so each program is compiled once.

References used:

* an independent float64 NumPy implementation of docs/model.md section 4's closed
  form for single scattering (``_first_order_reference``);
* the exact energy bookkeeping of a conservative medium (albedos 1, black base);
* reciprocity ``f(wi, wo) = f(wo, wi)`` and the mirror symmetry x -> -x;
* adding-doubling (``iadpython``) for Henyey-Greenstein slabs;
* a zero-thickness stack over a Lambertian base, ``f = rho / pi`` exactly.
"""

import dataclasses
import math
import time
from pathlib import Path

import jax
import jax.extend
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats

import jaxcos
from jaxcos import Layer, Material
from quadrature import half_hemisphere_grid

# the published fits as Layer keyword arguments (docs/model.md section 5, paper Table 2)
_PUB = jaxcos.model._material._PUBLISHED

_LAYER_FIELDS = ("t", "c_d", "albedo_d", "g1", "g2", "w_g", "albedo_p", "alpha_p", "theta_p", "phi_p")


def _layer(name, **changes):
    return Layer(**{**_PUB[name], "t": 16.0, **changes})


def _bonferroni_z(n, alpha=1e-3):
    """Two-sided normal quantile with family-wise false-alarm probability ``alpha`` over ``n`` tests."""
    return float(stats.norm.isf(alpha / (2 * n)))


def _bonferroni_t(n, dof, alpha=1e-3):
    """Same, for a t statistic with ``dof`` degrees of freedom (standard error estimated from replicates)."""
    return float(stats.t.isf(alpha / (2 * n), dof))


def _np(a):
    return np.asarray(a, dtype=np.float64)


def _assert_same_estimates(title, zs, lines):
    """Two estimators agree: every z of the list of arrays ``zs`` within a Sidak bound at 1 % family-wise,
    and their mean within a two-sided 0.1 % bound. ``lines``: the per-case report."""
    z = np.concatenate(zs)
    bound = stats.norm.isf((1 - 0.99 ** (1 / z.size)) / 2)
    print(f"\n[{title}] {z.size} comparisons, bound {bound:.2f}\n" + "\n".join(lines))
    assert np.all(np.isfinite(z))
    assert np.abs(z).max() < bound, "\n".join(lines)
    assert abs(z.mean()) < _bonferroni_z(1), "\n".join(lines)


# --- an independent reference for single scattering ----------------------------------------


def _hg_np(c, g):
    return (1 - g * g) / (4 * np.pi * (1 + g * g - 2 * g * c) ** 1.5)


def _cross2_np(a, m):
    c = np.cross(a, m)
    return np.sum(c * c, axis=-1)


def _first_order_reference(material, ti, to, po):
    """docs/model.md section 4, float64, written from the spec (not from the package's code).

    ``f_1 = sum_layers exp(-tau above) sigma_s f(-wi -> wo) (1 - exp(-t rate)) / (sigma_t(-wi) mu_o + sigma_t(wo) mu_i)``
    with ``rate = sigma_t(-wi) / mu_i + sigma_t(wo) / mu_o``, plus ``exp(-tau of the stack) rho / pi``
    over a Lambertian base. ``sigma_s f = albedo_d c_d f_d + albedo_p (1 - c_d) D(h) / 4``.
    """
    ti, to, po = (np.radians(np.asarray(a, dtype=np.float64)) for a in (ti, to, po))
    wi = np.stack([-np.sin(ti), np.zeros_like(ti), np.cos(ti)], axis=-1)
    wo = np.stack([np.sin(to) * np.cos(po), np.sin(to) * np.sin(po), np.cos(to)], axis=-1)
    w = -wi
    mu_i, mu_o = wi[:, 2], wo[:, 2]
    total = np.zeros((len(ti), 3))
    above = np.zeros(len(ti))
    for layer in material.layers:
        p = {k: _np(getattr(layer, k)) for k in _LAYER_FIELDS}
        c_d = {"diffusers_only": 1.0, "platelets_only": 0.0}.get(material.variant, p["c_d"])
        w_g = 1.0 if material.variant == "single_lobe" else p["w_g"]
        th, ph, a = np.radians(p["theta_p"]), np.radians(p["phi_p"]), p["alpha_p"]
        m = np.array([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)])
        sigma_S = lambda v: np.sqrt(a * a * _cross2_np(v, m) + (v @ m) ** 2)
        sig_i = c_d + (1 - c_d) * sigma_S(w)
        sig_o = c_d + (1 - c_d) * sigma_S(wo)
        cos = np.sum(w * wo, axis=-1)
        f_d = w_g * _hg_np(cos, p["g1"]) + (1 - w_g) * _hg_np(cos, p["g2"])
        h = wo - w
        h /= np.linalg.norm(h, axis=-1, keepdims=True)
        ndf = 1.0 / (np.pi * a * a * (_cross2_np(h, m) / (a * a) + (h @ m) ** 2) ** 2)
        sigma_s_f = (c_d * f_d)[:, None] * p["albedo_d"] + ((1 - c_d) * ndf / 4)[:, None] * p["albedo_p"]
        rate = sig_i / mu_i + sig_o / mu_o
        total += sigma_s_f * (np.exp(-above) * -np.expm1(-rate * p["t"]) / (sig_i * mu_o + sig_o * mu_i))[:, None]
        above = above + rate * p["t"]
    if material.base_albedo is not None:
        total += np.exp(-above)[:, None] * _np(material.base_albedo) / np.pi
    return total


# --- 1. the walk's first order is the closed form --------------------------------------------

_T1_TI = (0.0, 30.0, 60.0, 85.0, 89.0)
_T1_OUT = ((-89.0, 0.0), (-60.0, 0.0), (-30.0, 0.0), (0.0, 0.0), (20.0, 0.0), (45.0, 0.0), (70.0, 0.0),
           (85.0, 0.0), (45.0, 90.0), (70.0, 135.0), (30.0, -60.0))
_T1_WALKS = 1 << 15


def _t1_pairs():
    ti, to, po = [], [], []
    for a in _T1_TI:
        outs = list(_T1_OUT) + [(a, 0.0), (-a if a else 5.0, 0.0)]  # + the mirror and the retro direction
        for o, p in outs:
            ti.append(a), to.append(o), po.append(p)
    return np.array(ti), np.array(to), np.array(po)


def _t1_materials():
    tilted90 = dict(theta_p=20.0, phi_p=90.0)
    return {
        "two_lobe": [jaxcos.published(n) for n in jaxcos.PRODUCTS]
        + [Material(layers=(_layer("matte2", t=0.5),)),
           Material(layers=(_layer("dewy1", **tilted90),)),
           Material(layers=(_layer("dewy2", t=2.0, **tilted90),))],
        "single_lobe": [jaxcos.with_variant(jaxcos.published(n), "single_lobe") for n in ("dewy2", "matte1")],
        "diffusers_only": [jaxcos.with_variant(jaxcos.published("matte2"), "diffusers_only"),
                           jaxcos.with_variant(Material(layers=(_layer("dewy2", t=0.5),)), "diffusers_only")],
        "platelets_only": [jaxcos.with_variant(jaxcos.published("dewy1"), "platelets_only"),
                           jaxcos.with_variant(Material(layers=(_layer("matte2", **tilted90),)), "platelets_only"),
                           jaxcos.with_variant(Material(layers=(_layer("dewy2", t=1.0, **tilted90),)), "platelets_only")],
        # a matte layer over a dewy layer with tilted platelets, over a Lambertian base
        "stack": [Material(layers=(_layer("matte2", t=1.0), _layer("dewy1", t=3.0, **tilted90)),
                           base_albedo=(0.6, 0.5, 0.4)),
                  Material(layers=(_layer("matte1", t=0.5), _layer("dewy2", t=0.3)), base_albedo=(0.2, 0.5, 0.9))],
    }


@pytest.mark.slow
def test_first_order_walk_matches_closed_form():
    """``mc`` with one bounce (the walks' first-order NEE) vs ``exact`` with one bounce (the closed form).

    The closed form is itself checked against an independent float64 NumPy
    implementation of docs/model.md section 4 (to float32 rounding). The walks'
    estimate is tested twice, both tests valid under any correlation between
    points (the pairs of one incidence share walks):

    * every point: ``|z| < z*`` with a Bonferroni threshold over all points;
    * every (material, incidence): ``|mean z| < z*`` over its pairs and
      channels (a mean of standard normals has variance <= 1 whatever their
      correlation), which catches a bias of a fraction of a standard error
      that is common to the pairs.
    """
    ti, to, po = _t1_pairs()
    query = jaxcos.make_query(ti, to, po)
    incidence = np.searchsorted(np.unique(ti), ti)
    results = []
    for group, materials in _t1_materials().items():
        for i, material in enumerate(materials):
            key = jax.random.key(1000 + 17 * len(results))
            mc = jaxcos.simulate(material, query, key, walks=_T1_WALKS, bounces=1, single_scattering="mc")
            ex = jaxcos.simulate(material, query, key, walks=_T1_WALKS, bounces=1, single_scattering="exact")
            ref = _first_order_reference(material, ti, to, po)
            f_ex = _np(ex.f)
            assert np.all(_np(ex.stderr) == 0.0), "bounces=1 with exact single scattering has no Monte Carlo part"
            # float32 rounding: D(h) near its peak has relative condition ~ 1/alpha (|h x m| / alpha)
            alpha_min = min(float(l.alpha_p) for l in material.layers)
            rtol = max(1e-5, 8 * np.finfo(np.float32).eps / alpha_min)
            np.testing.assert_allclose(f_ex, ref, rtol=rtol, atol=0, err_msg=f"{group}[{i}]: exact vs NumPy")
            se = _np(mc.stderr)
            assert np.all(se > 0) and np.all(np.isfinite(se))
            z = (_np(mc.f) - f_ex) / se
            results.append((group, i, z, se / f_ex))
    n_points = sum(z.size for _, _, z, _ in results)
    n_groups = len(results) * len(_T1_TI)
    z_point, z_group = _bonferroni_z(n_points), _bonferroni_z(n_groups)
    worst_point = max(float(np.abs(z).max()) for _, _, z, _ in results)
    worst_group = max(float(abs(z[incidence == k].mean())) for _, _, z, _ in results for k in range(len(_T1_TI)))
    report = "\n".join(f"{g}[{i}]: max|z| {np.abs(z).max():.2f}, mean z {z.mean():+.2f}, "
                       f"mean z^2 {np.mean(z * z):.2f}, max rel. stderr {r.max():.4f}" for g, i, z, r in results)
    print(f"\nfirst order: {n_points} points, worst |z| {worst_point:.2f} (limit {z_point:.2f}), "
          f"worst |mean z| per incidence {worst_group:.2f} (limit {z_group:.2f})\n{report}")
    assert worst_point < z_point, report
    assert worst_group < z_group, report


# --- 2. energy conservation of a conservative slab over a black base --------------------------

_E_TI = (0.0, 40.0, 70.0)
_E_NMU, _E_NPHI = 16, 13
_E_BOUNCES = 64
_E_WALKS = 256
_E_REPLICATES = 32


def _conservative(t, platelets):
    """Albedos 1, black base; moderately rough platelets tilted in the plane of incidence, or diffusers only.

    ``phi_p = 0`` keeps the BSDF symmetric under ``y -> -y`` (and the walks'
    expectation with it), which the half-hemisphere quadrature uses.
    """
    layer = Layer(t=t, c_d=0.5, albedo_d=1.0, g1=0.6, g2=-0.3, w_g=0.7, albedo_p=1.0, alpha_p=0.4,
                  theta_p=25.0, phi_p=0.0)
    return Material(layers=(layer,), variant="two_lobe" if platelets else "diffusers_only")


def _replicate_stats(samples):
    """Mean and standard error over the leading (replicate) axis."""
    samples = np.asarray(samples, dtype=np.float64)
    return samples.mean(axis=0), samples.std(axis=0, ddof=1) / math.sqrt(samples.shape[0])


@pytest.mark.slow
def test_energy_conservation():
    """With albedos 1 over a black base, every bit of energy is reflected, absorbed by the base, or unfinished.

    The reflected energy is the BSDF integrated with its cosine over the
    outgoing hemisphere, by quadrature over ``16 x 13`` directions (a half
    hemisphere, by symmetry) that one batch of walks serves at once.

    Bookkeeping: NEE at the scattering vertices ``1..B`` of a walk with ``B``
    bounces is the energy leaving in flights ``2..B+1``, while ``reflected``,
    ``absorbed_base`` and ``unfinished`` of the same walk account for flights
    ``1..B`` only. The exact identities, for any ``B``, are therefore (in
    expectation)

    * ``reflected(B) + absorbed_base(B) + unfinished(B) = 1``,
    * ``int f(B) cos = reflected(B + 1)`` (``reflected`` agrees with the quadrature),
    * ``int f(B) cos + absorbed_base(B + 1) + unfinished(B + 1) = 1``,

    tested here with ``B = 64`` (so that a thick layer, whose walks are far
    from finished, is tested as sharply as a thin one), thin (``t = 0.5``) and
    thick (``t = 16``) layers, with and without platelets, ``exact`` for all and
    ``mc`` for the thick diffusers (``mc`` is checked against the closed form in
    the first-order test). Standard errors come from 32 independent replicates (t
    test, Bonferroni over all checks). The quadrature error is measured on the
    first-order term (the BSDF's sharpest part) against a ``200 x 181`` grid
    with the NumPy reference, and added to the allowance.
    """
    to, po, weights = half_hemisphere_grid(_E_NMU, _E_NPHI)
    n_i, n_o = len(_E_TI), len(to)
    grid = jaxcos.make_query(np.repeat(_E_TI, n_o), np.tile(to, n_i), np.tile(po, n_i))
    single = jaxcos.make_query(list(_E_TI), [0.0] * n_i)
    fine = half_hemisphere_grid(200, 181)
    cases = [(t, platelets, "exact") for platelets in (False, True) for t in (0.5, 16.0)]
    cases += [(16.0, False, "mc")]
    n_checks = len(cases) * n_i * 3
    t_star = _bonferroni_t(n_checks, _E_REPLICATES - 1)
    rounding = (_E_BOUNCES + 1) * np.finfo(np.float32).eps  # float32 sums of the tallies over the bounces
    keys = [jax.random.key(10_000 + r) for r in range(_E_REPLICATES)]
    next_bounce = {}  # (t, platelets) -> replicates of [reflected, absorbed + unfinished] after B + 1 bounces
    quadrature_error = {}

    def first_order_integral(material, grid_):
        to_, po_, w_ = grid_
        return np.array([_first_order_reference(material, np.full(len(to_), a), to_, po_)[:, 0] @ w_ for a in _E_TI])

    lines, failures = [], []
    for t, platelets, mode in cases:
        material = _conservative(t, platelets)
        if (t, platelets) not in next_bounce:
            runs = [jaxcos.simulate(material, single, jax.random.fold_in(k, 1), walks=_E_WALKS, bounces=_E_BOUNCES + 1)
                    for k in keys]
            next_bounce[t, platelets] = [np.stack([_np(e.reflected), _np(e.absorbed_base + e.unfinished)]) for e in runs]
        integral, book, escaped_or_left = [], [], []
        for k in keys:
            est = jaxcos.simulate(material, grid, k, walks=_E_WALKS, bounces=_E_BOUNCES, single_scattering=mode)
            integral.append(np.einsum("ijc,j->ic", _np(est.f).reshape(n_i, n_o, 3), weights))
            book.append(_np(est.reflected + est.absorbed_base + est.unfinished))
            escaped_or_left.append(_np(est.reflected) + _np(est.unfinished))
        integral, se_integral = _replicate_stats(integral)
        book, se_book = _replicate_stats(book)
        (refl1, rest1), (se_refl1, se_rest1) = _replicate_stats(next_bounce[t, platelets])
        refl_plus_unf0 = np.mean(escaped_or_left, axis=0)
        if (t, platelets) not in quadrature_error:
            quadrature_error[t, platelets] = np.abs(first_order_integral(material, (to, po, weights))
                                                    - first_order_integral(material, fine))[:, None]
        qerr = quadrature_error[t, platelets]
        assert np.all(qerr < 1e-3), f"quadrature grid too coarse: {qerr.ravel()}"
        # albedos 1: the three channels are the same numbers
        np.testing.assert_allclose(integral, integral[:, :1].repeat(3, axis=1), rtol=1e-5)
        checks = {
            "reflected+absorbed+unfinished-1": (book - 1, np.hypot(se_book, rounding), 0 * qerr),
            "int f cos - reflected(B+1)": (integral - refl1, np.hypot(se_integral, se_refl1), qerr),
            "int f cos + absorbed(B+1) + unfinished(B+1) - 1": (integral + rest1 - 1, np.hypot(se_integral, se_rest1), qerr),
        }
        for name, (dev, se, sys_err) in checks.items():
            z = (np.abs(dev) - sys_err).clip(min=0) / se
            for i, a in enumerate(_E_TI):
                line = (f"{mode} t={t:g} platelets={platelets} ti={a:g} {name}: {dev[i, 0]:+.5f} +- {se[i, 0]:.5f} "
                        f"(quadrature {sys_err[i, 0]:.1e}) |z| {z[i, 0]:.2f}")
                lines.append(line)
                if z[i, 0] > t_star:
                    failures.append(line)
        # int f(B) cos - reflected(B) is the energy of flight B + 1, at most unfinished(B): up to noise,
        # int f(B) cos <= reflected(B) + unfinished(B)
        limit = refl_plus_unf0 + t_star * np.hypot(se_integral, se_refl1) + qerr
        assert np.all(integral[:, 0] <= limit[:, 0]), (integral[:, 0], limit[:, 0])
    print(f"\nenergy, limit |z| < {t_star:.2f}:\n" + "\n".join(lines))
    assert not failures, "\n".join(failures)


# --- 4. Henyey-Greenstein slabs against adding-doubling ----------------------------------------

_IAD_G = (-0.3, 0.0, 0.5, 0.8)
_IAD_ALBEDO = (0.5, 0.9, 0.99)
_IAD_TAU = (0.5, 2.0, 16.0)
_IAD_WALKS = 2048  # walks per call; calls are repeated until the relative standard error is small
_IAD_MIN_CALLS = 16
_IAD_MAX_CALLS = 1000
_IAD_TARGET = 0.0025  # relative standard error aimed at: 1% is four of them
_IAD_NMU, _IAD_NPHI = 8, 2


def _iad_reflectance(a, tau, g, quad_pts):
    import iadpython

    return float(iadpython.Sample(a=a, b=tau, g=g, n=1.0, n_above=1.0, n_below=1.0, quad_pts=quad_pts).rt()[0])


def _iad_groups():
    """Cases grouped into calls: the three albedos ride on the three colour channels of one walk when they
    need the same number of bounces (the walk's directions and flights do not depend on the albedo).

    Bounces: enough that the energy still in the walks (an upper bound of the
    missing reflectance, checked) is below 1e-3 of R. Calls that need many
    bounces tally ``reflected`` only (one outgoing direction), the others also
    the hemispherical integral of ``f`` (``exact``, 8 x 2 directions).
    """
    groups = []
    for g in _IAD_G:
        groups.append((g, 0.5, _IAD_ALBEDO, 24, True))
        groups.append((g, 2.0, _IAD_ALBEDO, 48, True))
        groups.append((g, 16.0, (0.5,) * 3, 24, True))
        groups.append((g, 16.0, (0.9,) * 3, 96, False))
        groups.append((g, 16.0, (0.99,) * 3, 384, False))
    return groups


@pytest.mark.slow
def test_hg_slab_reflectance_matches_adding_doubling():
    """Total reflectance of index-matched HG slabs over a black base, normal incidence, vs ``iadpython``.

    ``variant="diffusers_only"``, ``c_d = 1``, ``w_g = 1`` (and ``g2 = g1``, so
    both diffuser lobes are the same HG lobe whatever the lobe-selection
    probabilities): a plain HG slab of optical thickness ``tau`` and albedo
    ``a``, whose UR1 is estimated twice by the same walks at ``theta_i = 0``:
    ``Estimate.reflected`` (R), and the cosine-weighted integral of ``f`` over
    the outgoing hemisphere (Q: Gauss-Legendre in ``mu`` times two azimuths;
    the BSDF at normal incidence does not depend on ``phi_o``), whose
    first-order part is exact. Their minimum-variance combination (weights from
    the replicates' covariance) is the estimate that must be within 1%.

    * iadpython (0.5.3) converges in ``quad_pts`` up to 28 and breaks down from
      32 on (numerically unstable): the reference is ``quad_pts = 24`` and its
      error is taken as ``|R(16) - R(24)|`` (<= 0.15%, for g = 0.8).
    * The quadrature error of Q is measured on the first-order term with the
      NumPy reference (< 1e-4 relative) and added to the allowance.
    * Calls of 2048 walks are repeated until the relative standard error (from
      the spread of at least 16 calls) is at most 0.25%, so that 1% is four
      standard errors of a correct estimate (0.2% costs 1.5 times as much).
    * The walks stop after a number of bounces where the energy they still carry
      (an upper bound of the reflectance they miss) is below 0.1% of R; the
      estimate is taken as the interval [mean, mean + that energy].

    Asserted for all 36 cases: the combined estimate's interval is within 1% of iad;
    R alone, Q alone and the combination each agree with iad within
    ``t* sqrt(SE^2 + iad error^2 + quadrature error^2)`` (t quantile,
    Bonferroni over all tests).
    """
    x, w = np.polynomial.legendre.leggauss(_IAD_NMU)
    mu, w_mu = (x + 1) / 2, w / 2
    to = np.repeat(np.degrees(np.arccos(mu)), _IAD_NPHI)
    po = np.tile((np.arange(_IAD_NPHI) + 0.5) * 180.0 / _IAD_NPHI, _IAD_NMU)
    weights = np.repeat(2 * np.pi * w_mu * mu, _IAD_NPHI) / _IAD_NPHI
    hemisphere = jaxcos.make_query(np.zeros(len(to)), to, po)
    normal = jaxcos.make_query([0.0], [0.0])
    fine_x, fine_w = np.polynomial.legendre.leggauss(400)
    fine_mu = (fine_x + 1) / 2
    fine_to, fine_weights = np.degrees(np.arccos(fine_mu)), np.pi * fine_w * fine_mu

    rows, failures = [], []
    n_tests = 36 * 3
    for c, (g, tau, albedos, bounces, with_f) in enumerate(_iad_groups()):
        material = Material(layers=(Layer(t=tau, c_d=1.0, albedo_d=albedos, g1=g, g2=g, w_g=1.0, albedo_p=0.5,
                                          alpha_p=0.5, theta_p=0.0),), variant="diffusers_only")
        key = jax.random.key(20_000 + c)
        refl, quad, unfinished = [], [], []
        started = time.perf_counter()
        while True:
            est = jaxcos.simulate(material, hemisphere if with_f else normal, jax.random.fold_in(key, len(refl)),
                                  walks=_IAD_WALKS, bounces=bounces, single_scattering="exact")
            refl.append(_np(est.reflected[0]))
            unfinished.append(_np(est.unfinished[0]))
            if with_f:
                quad.append(weights @ _np(est.f))
            if len(refl) >= _IAD_MIN_CALLS:
                r = np.asarray(refl)
                if with_f:
                    q = np.asarray(quad)
                    cov = np.array([np.cov(q[:, ch], r[:, ch]) for ch in range(3)])  # (3, 2, 2)
                    den = cov[:, 0, 0] + cov[:, 1, 1] - 2 * cov[:, 0, 1]
                    weight_q = np.clip((cov[:, 1, 1] - cov[:, 0, 1]) / np.where(den > 0, den, 1.0), 0.0, 1.0)
                    comb = weight_q * q + (1 - weight_q) * r
                else:
                    comb = r
                mean, se = _replicate_stats(comb)
                if np.all(se <= _IAD_TARGET * mean) or len(refl) >= _IAD_MAX_CALLS:
                    break
        n_calls = len(refl)
        elapsed = time.perf_counter() - started
        t_star = _bonferroni_t(n_tests, n_calls - 1)
        r_mean, r_se = _replicate_stats(refl)
        q_mean, q_se = _replicate_stats(quad) if with_f else (None, None)
        for ch, a in enumerate(albedos if albedos[0] != albedos[1] else albedos[:1]):
            ref, ref16 = _iad_reflectance(a, tau, g, 24), _iad_reflectance(a, tau, g, 16)
            iad_err = abs(ref16 - ref)
            assert iad_err < 0.0025 * ref, (g, a, tau, ref16, ref)
            qerr = 0.0
            if with_f:
                one = Material(layers=(Layer(t=tau, c_d=1.0, albedo_d=a, g1=g, g2=g, w_g=1.0, albedo_p=0.5,
                                             alpha_p=0.5, theta_p=0.0),), variant="diffusers_only")
                coarse = weights @ _first_order_reference(one, np.zeros(len(to)), to, po)[:, 0]
                fine = fine_weights @ _first_order_reference(one, np.zeros(len(fine_to)), fine_to, 0 * fine_to)[:, 0]
                qerr = abs(coarse - fine)
                assert qerr < 1e-4 * ref
            # the walks stop after `bounces`: their expectation is R - delta with 0 <= delta <= unfinished
            left = float(np.mean(unfinished, axis=0)[ch])
            z = {}
            for name, m_, se_, sys_ in (("R", r_mean, r_se, 0.0), ("Q", q_mean, q_se, qerr),
                                        ("comb", mean, se, qerr)):
                if m_ is None:
                    continue
                d = m_[ch] - ref
                excess = d if d > 0 else min(d + left, 0.0)
                z[name] = excess / math.sqrt(se_[ch] ** 2 + iad_err ** 2 + sys_ ** 2)
            dev = (mean[ch] - ref) / ref
            row = (f"g={g:+.1f} a={a:.2f} tau={tau:4.1f}: {mean[ch]:.5f} +- {se[ch] / mean[ch]:.2%} vs iad {ref:.5f} "
                   f"(+- {iad_err / ref:.3%}): dev {dev:+.3%}; z " + " ".join(f"{k} {v:+.2f}" for k, v in z.items())
                   + f"; {n_calls} calls x {_IAD_WALKS} walks x {bounces} bounces ({elapsed:.1f} s), "
                   f"unfinished {left / ref:.1e} R")
            rows.append(row)
            dev_high = (mean[ch] + left - ref) / ref
            if (max(abs(dev), abs(dev_high)) >= 0.01 or se[ch] > _IAD_TARGET * mean[ch]
                    or any(abs(v) > t_star for v in z.values()) or left > 1e-3 * ref):
                failures.append(row)
    print("\nHG slabs vs adding-doubling:\n" + "\n".join(rows))
    assert len(rows) == 36
    assert not failures, "\n".join(failures)


# --- 3. reciprocity ----------------------------------------------------------------------------
#
# In-plane convention: wi = (-sin ti, 0, cos ti), wo = (sin to, 0, cos to), ti >= 0.
#
# * Same side (to < 0): wo = (-sin|to|, 0, cos to) is itself a valid incidence
#   ti' = -to, and wi = (sin(-ti), 0, cos ti) a valid outgoing to' = -ti. So
#   f(wi, wo) = f(wo, wi) reads  f(ti, to) = f(-to, -ti)  for any material (no symmetry used).
# * Opposite sides (to > 0): wo lies on the +x side, where no incidence of the
#   convention lies. The mirror X: x -> -x maps wi to (sin ti, 0, cos ti) and wo
#   to (-sin to, 0, cos to); it maps the mean flake normal's azimuth phi_p to
#   180 - phi_p (and leaves Henyey-Greenstein lobes alone). The BSDF is
#   invariant under any orthogonal map applied to the directions and the
#   material together, so f_M(wi, wo) = f_XM(X wi, X wo) = [reciprocity]
#   f_XM(X wo, X wi), i.e.  f_M(ti, to) = f_XM(to, ti)  with XM = M with
#   phi_p -> 180 - phi_p. phi_p = 90 is its own mirror image (a rotation about
#   x tilts the normal out of the plane symmetrically): f(ti, to) = f(to, ti)
#   within one material; phi_p = 0 pairs with phi_p = 180.
#   (Rotating by 180 degrees about z instead, phi_p -> phi_p + 180, and then
#   mirroring y -> -y, phi_p -> -phi_p, gives the same map.)
#
# With single_scattering="exact" the first order is the closed form, reciprocal
# term by term (sigma_s f(-wi -> wo) = D(h)/4 or an HG lobe of wi.wo, and the
# denominator sigma_t(-wi) mu_o + sigma_t(wo) mu_i is symmetric since
# sigma_t(-w) = sigma_t(w)); every further order is reciprocal on its own, so a
# truncated walk is reciprocal in expectation too. The test is a z test on the
# Monte Carlo part, the two sides coming from different incidences (independent walks).

_R_ANGLES = (10.0, 20.0, 30.0, 40.0, 50.0, 60.0, 70.0, 80.0)
_R_WALKS = 4096
_R_BOUNCES = 32


def _reciprocity_query():
    ti, to = [], []
    for a in _R_ANGLES:
        for b in _R_ANGLES:
            if a != b:
                ti += [a, a]
                to += [-b, b]
    return np.array(ti), np.array(to)


def _tilted(phi_p):
    return Material(layers=(Layer(t=2.0, c_d=0.5, albedo_d=(0.9, 0.8, 0.7), g1=0.5, g2=-0.2, w_g=0.6,
                                  albedo_p=(0.8, 0.85, 0.9), alpha_p=0.3, theta_p=20.0, phi_p=phi_p),))


def _tilted_stack():
    """Two layers over a Lambertian base; both tilts at phi_p = 90, so the stack is its own mirror image."""
    return Material(layers=(Layer(**{**_PUB["matte2"], "t": 1.0, "theta_p": 20.0, "phi_p": 90.0}),
                            Layer(**{**_PUB["dewy1"], "t": 2.0, "alpha_p": 0.3, "theta_p": 35.0, "phi_p": 90.0})),
                    base_albedo=(0.7, 0.5, 0.3))


def _run_reciprocity(material, key, connection):
    ti, to = _reciprocity_query()
    est = jaxcos.simulate(material, jaxcos.make_query(ti, to), key, walks=_R_WALKS, bounces=_R_BOUNCES,
                          connection=connection)
    table = {(a, b): (f, s) for a, b, f, s in zip(ti, to, _np(est.f), _np(est.stderr))}
    return table


@pytest.mark.slow
@pytest.mark.parametrize("connection", ["nee", "mis"])
def test_reciprocity_with_tilted_platelets(connection):
    """``f(wi, wo) = f(wo, wi)`` for tilted platelets (theta_p = 20, phi_p = 0, 90, 180) and a tilted stack,
    with either connection of the walks to the viewer."""
    run = lambda material, key: _run_reciprocity(material, key, connection)
    tables = {phi: run(_tilted(phi), jax.random.key(30_000 + int(phi))) for phi in (0.0, 90.0, 180.0)}
    tables["stack"] = run(_tilted_stack(), jax.random.key(30_500))
    comparisons = []  # (label, (f, se), (f, se))
    for name, table in tables.items():
        for a in _R_ANGLES:
            for b in _R_ANGLES:
                if a < b:  # same side: (a, -b) <-> (b, -a)
                    comparisons.append((f"{name}: f({a:g},{-b:g}) vs f({b:g},{-a:g})", table[a, -b], table[b, -a]))
    for name in (90.0, "stack"):  # opposite sides, mirror-symmetric materials
        for a in _R_ANGLES:
            for b in _R_ANGLES:
                if a < b:
                    comparisons.append((f"{name}: f({a:g},{b:g}) vs f({b:g},{a:g})", tables[name][a, b], tables[name][b, a]))
    for a in _R_ANGLES:  # opposite sides: phi_p = 0 and its mirror image phi_p = 180
        for b in _R_ANGLES:
            if a != b:
                comparisons.append((f"phi_p 0/180: f0({a:g},{b:g}) vs f180({b:g},{a:g})", tables[0.0][a, b], tables[180.0][b, a]))
    z = np.array([(f1 - f2) / np.hypot(s1, s2) for _, (f1, s1), (f2, s2) in comparisons])  # (n, 3)
    rel_se = np.array([np.hypot(s1, s2) / np.abs(f1 + f2) * 2 for _, (f1, s1), (f2, s2) in comparisons])
    limit = _bonferroni_z(z.size)
    worst = int(np.argmax(np.abs(z).max(axis=1)))
    print(f"\nreciprocity ({connection}): {len(comparisons)} pairs x 3 channels, max |z| {np.abs(z).max():.2f} "
          f"(limit {limit:.2f}), "
          f"mean z {z.mean():+.3f}, mean z^2 {np.mean(z * z):.2f}, median relative SE of the difference "
          f"{np.median(rel_se):.3%}; worst: {comparisons[worst][0]}")
    assert np.all(np.isfinite(z))
    assert np.abs(z).max() < limit, comparisons[worst][0]
    # a common bias: the mean of the z's has variance <= 1 whatever their correlation
    assert abs(z.mean()) < _bonferroni_z(1)


# --- 5. a zero-thickness stack over a Lambertian base -----------------------------------------
# --- 6. hard cases stay finite in float32 -------------------------------------------------------

_H_TI = (0.0, 45.0, 89.9)
_H_WALKS = 8
_H_BOUNCES = 16
_MAPPED = {}


def _hard_query():
    ti, to, po = [], [], []
    for a in _H_TI:
        for b, p in ((a, 0.0), (-a, 0.0), (0.0, 0.0), (89.9, 0.0), (-89.9, 0.0), (60.0, 90.0)):
            ti.append(a), to.append(b), po.append(p)
    return np.array(ti), np.array(to), np.array(po)


def _simulate_many(materials, key, mode, connection="nee"):
    """``simulate`` for a list of materials of one structure: one compiled program, ``lax.map`` over the values."""
    stacked = jax.tree.map(lambda *x: jnp.stack(x), *materials)
    structure = (jax.tree.structure(materials[0]), materials[0].variant, len(materials[0].layers), mode, connection)
    if structure not in _MAPPED:
        query = jaxcos.make_query(*_hard_query())
        _MAPPED[structure] = jax.jit(lambda ms, k: jax.lax.map(
            lambda m: jaxcos.simulate(m, query, k, walks=_H_WALKS, bounces=_H_BOUNCES, single_scattering=mode,
                                      connection=connection), ms))
    return _MAPPED[structure](stacked, key)


def _values(**axes):
    """The full product of the given parameter values, as a list of dicts."""
    import itertools

    names = list(axes)
    return [dict(zip(names, combo)) for combo in itertools.product(*(axes[n] for n in names))]


def test_zero_thickness_over_lambertian_is_exact():
    """A stack of zero optical thickness over a Lambertian base is the base: ``f = rho / pi`` exactly.

    With ``exact`` single scattering the closed form is ``rho / pi`` (the base
    seen through nothing) and the walks must add exactly nothing: a flight
    through a zero-thickness layer ends in it with probability 0, and the walk
    leaves through the top after the base with weight 0. Checked to float32
    rounding (a few ulp) at all angles of the hard-case query (grazing 89.9
    included), with zero standard error.
    """
    materials = []
    for v in _values(alpha_p=(1e-4, 0.13, 1.0), g=(-0.999, 0.0, 0.999), c_d=(0.0, 0.5, 1.0)):
        for rho in ((0.0, 0.5, 1.0), (0.8, 0.3, 0.1)):
            materials.append(Material(layers=(Layer(t=0.0, c_d=v["c_d"], albedo_d=(0.9, 0.5, 1.0), g1=v["g"],
                                                    g2=-v["g"], w_g=0.5, albedo_p=(1.0, 0.7, 0.2), alpha_p=v["alpha_p"],
                                                    theta_p=30.0, phi_p=45.0),), base_albedo=rho))
    est = _simulate_many(materials, jax.random.key(40_000), "exact")
    f = np.asarray(est.f)
    expected = np.stack([np.asarray(m.base_albedo, np.float32) / np.float32(np.pi) for m in materials])[:, None, :]
    assert f.dtype == np.float32
    np.testing.assert_allclose(f, np.broadcast_to(expected, f.shape), rtol=4 * np.finfo(np.float32).eps, atol=0)
    assert np.all(np.asarray(est.stderr) == 0.0)


def _hard_materials(structure):
    """Hard parameter values, varied inside one structure (variant, layers, base)."""
    alphas, gs, ts = (1e-4, 0.002, 0.13, 1.0), (-0.999, 0.0, 0.999), (0.0, 1e-3, 100.0)
    materials = []
    if structure in ("two_lobe_black", "two_lobe_lambertian"):
        if structure == "two_lobe_black":  # every combination
            grid = _values(alpha_p=alphas, g=gs, c_d=(0.0, 1.0), w_g=(0.0, 1.0), albedo_d=(0.0, 1.0),
                           albedo_p=(0.0, 1.0), t=ts)
        else:  # the extremes of (c_d, w_g, albedo_d, albedo_p) in four combinations
            grid = [{**v, **dict(zip(("c_d", "w_g", "albedo_d", "albedo_p"), combo))}
                    for v in _values(alpha_p=alphas, g=gs, t=ts)
                    for combo in ((0.0, 0.0, 0.0, 1.0), (1.0, 1.0, 1.0, 0.0), (0.0, 1.0, 1.0, 1.0), (1.0, 0.0, 0.0, 0.0))]
        for i, v in enumerate(grid):
            layer = Layer(t=v["t"], c_d=v["c_d"], albedo_d=v["albedo_d"], g1=v["g"], g2=-v["g"], w_g=v["w_g"],
                          albedo_p=v["albedo_p"], alpha_p=v["alpha_p"], theta_p=(0.0, 90.0, 45.0)[(i // 3) % 3], phi_p=0.0)
            base = None if structure == "two_lobe_black" else (float(i % 2),) * 3
            materials.append(Material(layers=(layer,), base_albedo=base))
    elif structure == "platelets_only":
        for v in _values(alpha_p=alphas, albedo_p=(0.0, 1.0), t=ts, theta_p=(0.0, 45.0, 90.0)):
            layer = Layer(t=v["t"], c_d=0.0, albedo_d=0.5, g1=0.0, g2=0.0, w_g=1.0, albedo_p=v["albedo_p"],
                          alpha_p=v["alpha_p"], theta_p=v["theta_p"], phi_p=90.0)
            materials.append(Material(layers=(layer,), variant="platelets_only"))
    elif structure == "stack":
        for i, v in enumerate(_values(alpha_p=alphas, g=gs, t1=ts, t2=ts, c_d=(0.0, 1.0))):
            top = Layer(t=v["t1"], c_d=v["c_d"], albedo_d=1.0, g1=v["g"], g2=0.0, w_g=1.0, albedo_p=1.0,
                        alpha_p=v["alpha_p"], theta_p=90.0 * (i % 2))
            bottom = Layer(t=v["t2"], c_d=1.0 - v["c_d"], albedo_d=0.0 if i % 3 == 0 else 1.0, g1=-v["g"], g2=v["g"],
                           w_g=0.0, albedo_p=1.0, alpha_p=v["alpha_p"], theta_p=45.0, phi_p=30.0)
            materials.append(Material(layers=(top, bottom), base_albedo=(float(i % 2),) * 3))
    return materials


@pytest.mark.parametrize("structure, mode, connection", [
    ("two_lobe_black", "exact", "nee"), ("two_lobe_lambertian", "exact", "nee"), ("platelets_only", "mc", "nee"),
    ("stack", "exact", "nee"), ("two_lobe_black", "exact", "mis"), ("two_lobe_lambertian", "exact", "mis"),
    ("platelets_only", "mc", "mis"), ("stack", "exact", "mis")])
def test_hard_cases_are_finite(structure, mode, connection):
    """Extreme but legal values (alpha_p 1e-4..1, g = +-0.999, c_d and w_g exactly 0 and 1, albedos 0 and 1,
    t = 0, 1e-3, 100, tilts 0..90, angles to 89.9 degrees incl. mirror and retro-reflection) give finite
    f, stderr and energy tallies in float32 (and non-negative f and tallies).

    One compiled program per structure (variant, layers, base, mode) with a
    small budget (8 walks, 16 bounces), ``lax.map`` over the parameter values:
    the values vary, the structure does not.
    """
    materials = _hard_materials(structure)
    est = _simulate_many(materials, jax.random.key(50_000), mode, connection)
    assert np.asarray(est.f).dtype == np.float32
    bad = []
    for name in ("f", "stderr", "reflected", "absorbed_base", "unfinished"):
        a = np.asarray(getattr(est, name))
        ok = np.isfinite(a).all(axis=tuple(range(1, a.ndim)))
        bad += [f"{name}: {_describe(materials[i])}" for i in np.flatnonzero(~ok)[:5]]
        if name != "stderr":
            assert np.all(a[np.isfinite(a)] >= 0), name
    print(f"\n{structure}/{mode}/{connection}: {len(materials)} materials x {np.asarray(est.f).shape[1]} pairs, "
          f"all finite: {not bad}")
    assert not bad, "\n".join(bad)


def _describe(material):
    return "; ".join(", ".join(f"{k}={np.asarray(getattr(l, k)).tolist()}" for k in _LAYER_FIELDS) for l in material.layers)


# --- 7. variants are structure: switched-off parameters are not in the program -------------------


def _is_literal(v):
    return isinstance(v, jax.extend.core.Literal)


def _sub_jaxpr(p):
    """The open jaxpr of a (closed) jaxpr parameter."""
    return p.jaxpr if hasattr(p, "jaxpr") and hasattr(p, "consts") else p


def _live_inputs(jaxpr, live_out):
    """Which inputs of an open jaxpr the live outputs depend on (backward liveness, through sub-jaxprs).

    Conservative where unsure (an unknown higher-order primitive uses all its
    inputs), so "not live" is a proof that the input is unused.
    """
    live = {v for v, keep in zip(jaxpr.outvars, live_out) if keep and not _is_literal(v)}
    for eqn in reversed(jaxpr.eqns):
        outs = [o in live for o in eqn.outvars]
        if not any(outs) and not eqn.effects:
            continue
        for v, used in zip(eqn.invars, _eqn_live_inputs(eqn, outs)):
            if used and not _is_literal(v):
                live.add(v)
    return [v in live for v in jaxpr.invars]


def _eqn_live_inputs(eqn, outs):
    params = eqn.params
    name = eqn.primitive.name
    if name == "scan":
        body = _sub_jaxpr(params["jaxpr"])
        n_consts, n_carry = params["num_consts"], params["num_carry"]
        carry = list(outs[:n_carry])
        while True:  # a carry is live if its final value is, or if the next iteration needs it
            inner = _live_inputs(body, carry + list(outs[n_carry:]))
            new = [a or b for a, b in zip(carry, inner[n_consts:n_consts + n_carry])]
            if new == carry:
                return inner
            carry = new
    if name == "while":
        cond, body = _sub_jaxpr(params["cond_jaxpr"]), _sub_jaxpr(params["body_jaxpr"])
        nc, nb = params["cond_nconsts"], params["body_nconsts"]
        cond_live = _live_inputs(cond, [True] * len(cond.outvars))
        carry = [a or b for a, b in zip(outs, cond_live[nc:])]
        while True:
            inner = _live_inputs(body, carry)
            new = [a or b for a, b in zip(carry, inner[nb:])]
            if new == carry:
                return cond_live[:nc] + inner[:nb] + carry
            carry = new
    if name == "cond":
        branches = [_live_inputs(_sub_jaxpr(b), outs) for b in params["branches"]]
        return [True] + [any(col) for col in zip(*branches)]
    for key in ("jaxpr", "call_jaxpr", "fun_jaxpr"):  # jit/pjit, closed_call, remat, custom_jvp/vjp
        if key in params:
            inner = _sub_jaxpr(params[key])
            if len(inner.invars) == len(eqn.invars) and len(inner.outvars) == len(outs):
                return _live_inputs(inner, outs)
    return [True] * len(eqn.invars)


def _count_eqns(jaxpr):
    n = 0
    for eqn in jaxpr.eqns:
        n += 1
        for p in eqn.params.values():
            for q in p if isinstance(p, (list, tuple)) else (p,):
                if hasattr(q, "eqns") or (hasattr(q, "jaxpr") and hasattr(q, "consts")):
                    n += _count_eqns(_sub_jaxpr(q))
    return n


def _program(material, mode="exact"):
    """The jaxpr of ``simulate`` with every array leaf of ``material`` an input; ``(jaxpr, {field: [input index]})``."""
    query = jaxcos.make_query([0.0, 30.0, 60.0], [10.0, -30.0, 60.0])
    paths, treedef = jax.tree_util.tree_flatten_with_path(material)
    leaves = [leaf for _, leaf in paths]

    def run(*args):
        est = jaxcos.simulate(jax.tree.unflatten(treedef, args), query, jax.random.key(0), walks=4, bounces=2,
                              single_scattering=mode)
        return est.f, est.stderr, est.reflected, est.absorbed_base, est.unfinished

    closed = jax.make_jaxpr(run)(*leaves)
    fields = {}
    for i, (path, _) in enumerate(paths):
        name = getattr(path[-1], "name", None) or str(path[-1])
        fields.setdefault(name, []).append(i)
    return closed.jaxpr, fields


def _used(material, mode="exact"):
    """``{field: whether any layer's leaf of that name reaches an output}`` and the program size."""
    jaxpr, fields = _program(material, mode)
    live = _live_inputs(jaxpr, [True] * len(jaxpr.outvars))
    return {name: any(live[i] for i in idx) for name, idx in fields.items()}, _count_eqns(jaxpr)


_PLATELET_FIELDS = {"albedo_p", "alpha_p", "theta_p", "phi_p"}
_DIFFUSER_FIELDS = {"albedo_d", "g1", "g2", "w_g"}


@pytest.mark.parametrize("mode", ["exact", "mc"])
def test_variants_are_structure(mode):
    """A variant's program contains no work for the parts it switches off.

    The switched-off parameters are inputs of the traced program that no output
    depends on (backward liveness through the scan/jit/cond sub-programs), and
    the program is strictly smaller than the full model's. A black base has no
    base work: its program is strictly smaller than the Lambertian one, whose
    base albedo is used. Positive control: in the full model every parameter is used.
    """
    two = Material(layers=(_layer("matte2", t=2.0), _layer("dewy1", t=3.0, phi_p=30.0)))
    used, size = {}, {}
    for variant in jaxcos.VARIANTS:
        used[variant], size[variant] = _used(jaxcos.with_variant(two, variant), mode)
    lambertian = Material(layers=two.layers, base_albedo=(0.5, 0.4, 0.3))
    used["lambertian"], size["lambertian"] = _used(lambertian, mode)
    print(f"\nprogram sizes ({mode}): {size}")
    everything = set(_LAYER_FIELDS)
    assert {k for k, v in used["two_lobe"].items() if v} == everything, used["two_lobe"]
    assert {k for k, v in used["lambertian"].items() if v} == everything | {"base_albedo"}, used["lambertian"]
    off = {
        "diffusers_only": _PLATELET_FIELDS | {"c_d"},
        "platelets_only": _DIFFUSER_FIELDS | {"c_d"},
        "single_lobe": {"g2", "w_g"},
    }
    for variant, fields in off.items():
        unused = {k for k, v in used[variant].items() if not v}
        assert unused == fields, (variant, unused)
        assert size[variant] < size["two_lobe"], (variant, size)
    assert size["platelets_only"] < size["two_lobe"] and size["diffusers_only"] < size["single_lobe"]
    assert size["two_lobe"] < size["lambertian"]


# --- 8. determinism ------------------------------------------------------------------------------


def test_same_key_same_numbers():
    """The same key gives bit-identical estimates; another key other numbers; ``inplane_bsdf`` is ``simulate``'s f."""
    ti, to, po = _t1_pairs()
    query = jaxcos.make_query(ti, to, po)
    material = jaxcos.published("matte2")
    run = lambda key: jaxcos.simulate(material, query, key, walks=_T1_WALKS, bounces=1, single_scattering="mc")
    a, b, c = run(jax.random.key(7)), run(jax.random.key(7)), run(jax.random.key(8))
    for name in ("f", "stderr", "reflected", "absorbed_base", "unfinished"):
        np.testing.assert_array_equal(np.asarray(getattr(a, name)), np.asarray(getattr(b, name)), err_msg=name)
    assert np.all(np.asarray(a.f) != np.asarray(c.f))
    assert np.all(np.asarray(a.stderr) != np.asarray(c.stderr))
    f = jaxcos.inplane_bsdf(material, ti, to, jax.random.key(7), walks=_T1_WALKS, bounces=1, phi_o_deg=po,
                            single_scattering="mc")
    np.testing.assert_array_equal(np.asarray(f), np.asarray(a.f))


def test_incidences_walked_in_sequence_give_the_same_numbers():
    """``incidence_batch`` (1, or 2 of 5 incidences with a remainder) changes the schedule, not the estimate."""
    ti, to, po = _t1_pairs()
    query = jaxcos.make_query(ti, to, po)
    assert np.unique(ti).size == 5
    material = jaxcos.published("dewy2")
    run = lambda batch: jaxcos.simulate(material, query, jax.random.key(4), walks=8, bounces=8, incidence_batch=batch)
    together = run(None)
    for batch in (1, 2):
        apart = run(batch)
        for name in ("f", "stderr", "reflected", "absorbed_base", "unfinished"):
            np.testing.assert_allclose(np.asarray(getattr(apart, name)), np.asarray(getattr(together, name)),
                                       rtol=1e-5, atol=1e-9, err_msg=f"{name}, batch {batch}")
    other = jaxcos.simulate(material, query, jax.random.key(5), walks=8, bounces=8, incidence_batch=2)
    assert not np.allclose(np.asarray(other.f), np.asarray(together.f))


@pytest.mark.parametrize("connection, interface, thin_after", [("nee", False, None), ("mis", False, None),
                                                                ("nee", True, None), ("nee", False, 4)])
def test_chunks_of_walks_are_the_walks_of_one_evaluation(connection, interface, thin_after):
    """``first`` picks walks ``first ..`` of the key: two chunks of 8 are the 16 walks of one evaluation (without
    thinning; thinned chunks thin within themselves), and the chunks differ."""
    ti, to, po = _t1_pairs()
    query = jaxcos.make_query(ti, to, po)
    material = jaxcos.published("dewy2")
    if interface:
        material = dataclasses.replace(material, interface=jaxcos.Interface(eta=1.4, alpha_s=0.2))
    run = lambda walks, first: jaxcos.simulate(material, query, jax.random.key(4), walks=walks, bounces=16,
                                               connection=connection, thin_after=thin_after, first=first).f
    a, b = run(8, jnp.int32(0)), run(8, jnp.int32(8))
    np.testing.assert_array_equal(np.asarray(a), np.asarray(run(8, 0)))
    assert not np.allclose(np.asarray(a), np.asarray(b))
    if thin_after is None:
        np.testing.assert_allclose((np.asarray(a) + np.asarray(b)) / 2, np.asarray(run(16, 0)), rtol=1e-5, atol=1e-9)


def test_directions_drawn_from_the_material_itself_give_the_same_numbers():
    """``sampling=material`` (detached) draws the same directions with the same weights as the default."""
    query = jaxcos.make_query([15.0, 45.0, 70.0], [-40.0, 47.0, 10.0])
    material = jaxcos.published("dewy1")
    run = lambda **kw: jaxcos.simulate(material, query, jax.random.key(3), walks=16, bounces=32, **kw).f
    np.testing.assert_allclose(np.asarray(run(sampling=material)), np.asarray(run()), rtol=1e-5, atol=1e-9)
    with pytest.raises(ValueError, match="variant"):
        run(sampling=jaxcos.with_variant(material, "diffusers_only"))


@pytest.mark.slow
def test_directions_drawn_from_another_material_are_unbiased():
    """Detached sampling from lobes unlike the material's (``g`` 0.3 for 0.55, ``alpha_p`` 0.3 for 0.13,
    ``theta_p`` off by 8 degrees) estimates the same BSDF as the default, within the standard errors.

    Two independent keys, 4096 walks each; z per point and channel against a Sidak bound at 1 %
    family-wise (measured: RMS z 1.16, max 2.40 of 3.72). Drawing the directions from the other HG
    lobes but dividing by the material's own HG densities (a wrong ``W / pdf``) fails it: max |z| 12.1.
    """
    ti, to, po = _t1_pairs()
    keep = np.isin(ti, (0.0, 30.0, 60.0)) & np.isin(to, (-60.0, -30.0, 0.0, 30.0, 60.0, 75.0))
    query = jaxcos.make_query(ti[keep], to[keep], po[keep])
    material = jaxcos.published("dewy1")
    layer = material.layers[0]
    other = Material(layers=(dataclasses.replace(layer, g1=0.3, g2=0.0, alpha_p=0.3, theta_p=layer.theta_p + 8.0),))
    budget = dict(walks=4096, bounces=64, lobe_probs=jaxcos.lobe_probabilities(material))
    plain = jaxcos.simulate(material, query, jax.random.key(11), **budget)
    detached = jaxcos.simulate(material, query, jax.random.key(12), sampling=other, **budget)
    z = np.asarray((detached.f - plain.f) / jnp.hypot(detached.stderr, plain.stderr)).ravel()
    bound = stats.norm.isf((1 - 0.99 ** (1 / z.size)) / 2)
    print(f"\n[detached] {z.size} comparisons: RMS z {np.sqrt(np.mean(z ** 2)):.2f}, max |z| {np.abs(z).max():.2f} "
          f"(bound {bound:.2f})")
    assert np.abs(z).max() < bound


@pytest.mark.parametrize("mis", [False, True])
def test_first_walks_of_a_batch_are_the_smaller_batch(mis):
    """A walk's random numbers do not depend on the batch size (the fit's Jacobian uses the first walks)."""
    from jaxcos.model._walk import stack_medium, _walk_one

    material = jaxcos.published("dewy1")
    query = jaxcos.make_query([30.0, 30.0], [-20.0, 40.0])
    seed = jax.random.bits(jax.random.key(3), (2,), jnp.uint32)
    run = lambda walks: _walk_one(stack_medium(material), None, jaxcos.lobe_probabilities(material), query.wi[0],
                                  query.wo[0], seed, walks, 16, True, None, mis)
    small, large = run(8), run(32)
    for a, b in zip(small, large):  # same numbers; float32 rounding of differently vectorised code differs
        np.testing.assert_allclose(np.asarray(a), np.asarray(b)[:8], rtol=1e-5, atol=1e-9)
    assert not np.allclose(np.asarray(large[0])[8:16], np.asarray(small[0]))


# --- 10. the MIS connection: unbiased, and tame where next-event estimation spikes ----------------


def _mis_cases():
    """(label, material, sampling): every path of the backward connection. One layer of narrow tilted
    platelets (attached and detached directions), platelets only, and a stack over a Lambertian base."""
    narrow = Material(layers=(_layer("dewy1", alpha_p=0.05, theta_p=8.0),))
    other = Material(layers=(_layer("dewy1", g1=0.3, alpha_p=0.1, theta_p=11.0),))
    alone = jaxcos.with_variant(Material(layers=(_layer("dewy1", t=2.0, alpha_p=0.1, theta_p=10.0),)),
                                "platelets_only")
    stack = Material(layers=(_layer("matte2", t=1.0, alpha_p=0.1), _layer("dewy1", t=3.0, alpha_p=0.05,
                                                                           theta_p=20.0, phi_p=90.0)),
                     base_albedo=(0.6, 0.5, 0.4))
    return [("narrow", narrow, None), ("narrow, detached", narrow, other), ("platelets only", alone, None),
            ("stack", stack, None)]


@pytest.mark.slow
def test_mis_connection_is_unbiased():
    """``connection="mis"`` and ``"nee"`` estimate the same BSDF, within their standard errors.

    Independent keys, 4096 walks each, 64 bounces (both strategies cover the same scattering
    orders); z per point and channel against a Sidak bound at 1 % family-wise (measured: max |z|
    2.9 of 4.1). Dropping the balance heuristic's weight from next-event estimation (counting the
    platelet paths twice) fails it: max |z| 6.2. The narrow case's RMS z (1.6) is next-event
    estimation's heavy tail, whose standard error a single run underestimates; over 12 replicate
    keys per side the RMS z was 1.02.
    """
    ti, to, po = _t1_pairs()
    keep = np.isin(ti, (0.0, 30.0, 60.0)) & np.isin(to, (-60.0, -30.0, 0.0, 30.0, 45.0, 60.0, 75.0))
    query = jaxcos.make_query(ti[keep], to[keep], po[keep])
    zs, lines = [], []
    for i, (label, material, sampling) in enumerate(_mis_cases()):
        budget = dict(walks=4096, bounces=64, lobe_probs=jaxcos.lobe_probabilities(material), sampling=sampling)
        nee = jaxcos.simulate(material, query, jax.random.key(60_000 + i), connection="nee", **budget)
        mis = jaxcos.simulate(material, query, jax.random.key(61_000 + i), connection="mis", **budget)
        z = np.asarray((mis.f - nee.f) / jnp.hypot(mis.stderr, nee.stderr)).ravel()
        zs.append(z)
        lines.append(f"  {label:18s} RMS z {np.sqrt(np.mean(z ** 2)):.2f}, max |z| {np.abs(z).max():.2f}")
    _assert_same_estimates("mis vs nee", zs, lines)


def test_mis_connection_tames_a_near_mirror_lobe():
    """On dewy2's bundled angles (``alpha_p = 0.002``) the MIS connection at least halves the largest
    relative standard error over the points: next-event estimation's rare spikes through the mirror
    lobe are what set it (measured: 0.28 against 0.07 at 1024 walks), while the median hardly moves.
    """
    meas = jaxcos.load_measurements(str(Path(__file__).parent.parent / "measurements" / "dewy2.csv"))
    query = jaxcos.make_query(meas.theta_i, meas.theta_o, meas.phi_o)
    material = jaxcos.published("dewy2")
    rel = {}
    for connection in ("nee", "mis"):
        est = jaxcos.simulate(material, query, jax.random.key(1), walks=1024, bounces=128, connection=connection)
        rel[connection] = np.mean(np.asarray(est.stderr) / np.asarray(est.f), axis=1)
    print(f"\n[near mirror] largest relative SE: nee {rel['nee'].max():.3f}, mis {rel['mis'].max():.3f}; "
          f"median: nee {np.median(rel['nee']):.4f}, mis {np.median(rel['mis']):.4f}")
    assert rel["mis"].max() < 0.5 * rel["nee"].max()


# --- 11. fewer walks for the later steps: unbiased, with honest standard errors -------------------


def test_stages_halve_the_walks_as_the_steps_double():
    """The plan of :func:`~jaxcos.model._walk.stages`: contiguous steps, every walk first, counts that
    halve evenly, at most four times and never below the chunk; a budget within ``thin_after``, a count
    that does not halve or ``None`` is one stage."""
    from jaxcos.model._walk import THIN_CHUNK, stages

    assert stages(1024, 128, 16) == ((0, 16, 1024), (16, 32, 512), (32, 64, 256), (64, 128, 128))
    assert stages(128, 512, 16)[-1] == (128, 512, 8)  # four halvings
    assert stages(64, 16, 16) == ((0, 16, 64),)
    assert stages(64, 64, None) == ((0, 64, 64),)
    assert stages(3, 64, 16) == ((0, 64, 3),)
    for walks, bounces in [(1024, 128), (128, 512), (96, 100), (16, 33)]:
        plan = stages(walks, bounces, 4)
        assert plan[0][0] == 0 and plan[-1][1] == bounces and plan[0][2] == walks and len(plan) > 1
        assert all(a[1] == b[0] and a[2] == 2 * b[2] >= 2 * THIN_CHUNK for a, b in zip(plan, plan[1:]))


def _thinning_cases():
    """(label, material, connection): one thick layer; a stack over a Lambertian base with the MIS
    connection; a layer under a rough top interface."""
    stack = Material(layers=(_layer("matte2", t=1.0, alpha_p=0.1), _layer("dewy1", t=3.0, alpha_p=0.05,
                                                                           theta_p=20.0, phi_p=90.0)),
                     base_albedo=(0.6, 0.5, 0.4))
    rough = Material(layers=(_layer("dewy1", t=4.0),), interface=jaxcos.Interface(eta=1.5, alpha_s=0.2))
    return [("dewy1", jaxcos.published("dewy1"), "nee"), ("stack, mis", stack, "mis"), ("interface", rough, "nee")]


def _walk_tallies(material, query, incidence, key, thin_after, connection):
    """Mean and standard error ``(3,)`` of the energy tallies of one incidence's 2048 walks x 64 bounces."""
    from jaxcos.model._walk import _walk_one, stack_medium, stage_stderr, stages

    seed = jax.random.bits(jax.random.key(key), (2,), jnp.uint32)
    _, *tallies = _walk_one(stack_medium(material), material.base_albedo, jaxcos.lobe_probabilities(material),
                            query.wi[incidence], query.wo[incidence], seed, 2048, 64, True, None, connection == "mis",
                            material.interface, None, thin_after)
    total = sum(tallies)
    return _np(total.mean(axis=0)), _np(stage_stderr(total[None], stages(2048, 64, thin_after))[0])


@pytest.mark.slow
def test_thinned_walks_are_unbiased():
    """Thinned walks (here from step 4 on, five stages down to a sixteenth of the walks) and walks that
    all make every step estimate the same BSDF and energy tallies, within their standard errors.

    Independent keys, 2048 walks, 64 bounces; z per point and channel (and for the sum of the energy
    tallies of one incidence) against a Sidak bound at 1 % family-wise. Leaving out the rescaling of
    the kept walks' throughput at the boundaries (a thinned estimate of the later steps that no longer
    stands for the walks left out) fails it.
    """
    query = jaxcos.make_query([0.0, 30.0, 30.0, 60.0, 60.0], [0.0, -30.0, 30.0, 60.0, -70.0])
    zs, lines = [], []
    for i, (label, material, connection) in enumerate(_thinning_cases()):
        budget = dict(walks=2048, bounces=64, lobe_probs=jaxcos.lobe_probabilities(material), connection=connection)
        full = jaxcos.simulate(material, query, jax.random.key(70_000 + i), thin_after=None, **budget)
        thin = jaxcos.simulate(material, query, jax.random.key(71_000 + i), thin_after=4, **budget)
        z = np.asarray((thin.f - full.f) / jnp.hypot(thin.stderr, full.stderr)).ravel()
        zs.append(z)
        # the energy tallies (reflected + absorbed + unfinished + shadowed) of one incidence, from the walks
        tallies = [_walk_tallies(material, query, 1, 70_000 + i, None, connection),
                   _walk_tallies(material, query, 1, 71_000 + i, 4, connection)]
        z_e = (tallies[1][0] - tallies[0][0]) / np.hypot(tallies[1][1], tallies[0][1])
        zs.append(z_e)
        lines.append(f"  {label:12s} RMS z {np.sqrt(np.mean(z ** 2)):.2f}, max |z| {np.abs(z).max():.2f}; "
                     f"energy {tallies[1][0].mean():.4f} vs {tallies[0][0].mean():.4f} (z {np.abs(z_e).max():.2f})")
    _assert_same_estimates("thinned vs full", zs, lines)


@pytest.mark.slow
@pytest.mark.parametrize("thin_after", [4, None])
def test_thinned_standard_errors_match_the_spread_over_keys(thin_after):
    """The standard error of an estimate (walks grouped by the steps they made, :func:`stage_stderr`) is
    the spread of the estimate over independent keys: 200 keys of 256 walks x 64 bounces on dewy1,
    thinned from step 4 (five groups of walks) and not thinned (one).

    The ratio of the spread to the RMS reported standard error, pooled over 15 points and 3 channels,
    must lie in the chi-square band at 0.1 % for 199 x 5 degrees of freedom: one per key and incidence,
    as the points and channels of an incidence share its walks (fewer than the 199 x 45 values, so the
    band is wide enough). The plain standard deviation over the thinned walks, which treats them as
    identically distributed, overstates the error by about 13 % (ratio 0.88) and fails it.
    """
    material = jaxcos.published("dewy1")
    query = jaxcos.make_query([0.0, 0.0, 0.0, 30.0, 30.0, 30.0, 30.0, 30.0, 60.0, 60.0, 60.0, 60.0, 75.0, 75.0, 75.0],
                              [0.0, 30.0, -60.0, -30.0, 0.0, 30.0, 60.0, -75.0, -60.0, 0.0, 60.0, 80.0, 75.0, 0.0, -40.0])
    lp = jaxcos.lobe_probabilities(material)
    one = lambda key: jaxcos.simulate(material, query, key, walks=256, bounces=64, lobe_probs=lp, thin_after=thin_after)
    run = jax.jit(jax.vmap(one))
    keys = jax.random.split(jax.random.key(72_000), 200)
    ests = [run(keys[a:a + 50]) for a in range(0, 200, 50)]
    f = np.concatenate([_np(e.f) for e in ests])
    se = np.concatenate([_np(e.stderr) for e in ests])
    ratio = np.sqrt(np.mean(np.var(f, axis=0, ddof=1) / np.mean(se ** 2, axis=0)))
    dof = 199 * 5
    lo, hi = np.sqrt(stats.chi2.ppf([5e-4, 1 - 5e-4], dof) / dof)
    print(f"\n[stderr, thin_after={thin_after}] spread / stderr = {ratio:.3f} (band {lo:.3f} .. {hi:.3f})")
    assert lo < ratio < hi
