"""The Kubelka-Munk baseline: closed forms, limits, the two-flux equations, inversion, specular lobe, fit."""

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import solve_bvp

import jaxcos
from jaxcos.inference._kubelka_munk import KM_N_PARAMS, KM_PARAMETERS, km_from_x, km_labels, km_to_x, make_km_problem
from jaxcos.model._kubelka_munk import beckmann, directions, kelemen_specular
from jaxcos.io._measurements import Measurements

S = np.array([5.0, 20.0, 50.0])
K = np.array([0.5, 1.0, 0.1])


def _textbook(s, k, x):
    """R0 and T in the sinh/cosh form of Huang et al. eqs. (1)-(2), float64."""
    a = 1 + k / s
    b = np.sqrt(a * a - 1)
    y = b * s * x
    d = a * np.sinh(y) + b * np.cosh(y)
    return np.sinh(y) / d, b / d


def test_layer_matches_the_textbook_form():
    for x in (0.01, 0.1, 0.3, 1.0):
        r0, t = jaxcos.km_layer(S, K, x)
        r0_ref, t_ref = _textbook(S, K, x)
        np.testing.assert_allclose(r0, r0_ref, rtol=2e-5)
        np.testing.assert_allclose(t, t_ref, rtol=2e-5, atol=1e-7)


def test_limits():
    a = 1 + K / S
    b = np.sqrt(a * a - 1)
    r0, t = jaxcos.km_layer(S, K, 1e4)  # thick: R_inf = a - b, nothing through
    np.testing.assert_allclose(r0, a - b, rtol=1e-5)
    np.testing.assert_allclose(jaxcos.km_r_inf(S, K), a - b, rtol=1e-5)
    assert np.all(np.asarray(t) == 0)
    r0, t = jaxcos.km_layer(S, K, 0.0)  # no layer: nothing reflected, everything through
    assert np.all(np.asarray(r0) == 0) and np.all(np.asarray(t) == 1)
    r0, t = jaxcos.km_layer(S, 0.0, 0.7)  # no absorption: R0 = SX / (1 + SX), R0 + T = 1
    np.testing.assert_allclose(r0, 0.7 * S / (1 + 0.7 * S), rtol=1e-6)
    np.testing.assert_allclose(np.asarray(r0) + np.asarray(t), 1.0, rtol=1e-6)
    r0, t = jaxcos.km_layer(0.0, K, 0.7)  # no scattering: Beer-Lambert
    np.testing.assert_allclose(t, np.exp(-0.7 * K), rtol=1e-6)
    assert np.all(np.asarray(r0) == 0)


def _two_flux(s, k, x, rg):
    """Solve the Kubelka-Munk equations as a boundary-value problem in float64.

    ``i`` flows down, ``j`` up, depth from 0 (top) to ``x``:
    ``di/dz = -(S + K) i + S j``, ``dj/dz = (S + K) j - S i``, ``i(0) = 1``, ``j(x) = Rg i(x)``.
    Returns the reflectance ``j(0)``, the transmittance into the background
    ``i(x)`` and the absorbed fraction ``K integral (i + j) dz``.
    """
    def rhs(z, y):
        i, j = y
        return np.vstack([-(s + k) * i + s * j, (s + k) * j - s * i])

    def bc(ya, yb):
        return np.array([ya[0] - 1.0, yb[1] - rg * yb[0]])

    z = np.linspace(0.0, x, 401)
    sol = solve_bvp(rhs, bc, z, np.vstack([np.exp(-z), 0.1 * np.ones_like(z)]), tol=1e-10, max_nodes=100000)
    assert sol.success
    zz = np.linspace(0.0, x, 20001)
    i, j = sol.sol(zz)
    absorbed = k * np.trapezoid(i + j, zz)
    return j[0], i[-1], absorbed


@pytest.mark.parametrize("s, k, x", [(5.0, 0.5, 0.3), (20.0, 1.0, 0.2), (2.0, 2.0, 1.0)])
def test_reflectance_transmittance_and_absorption_follow_the_two_flux_equations(s, k, x):
    """R0 and T solve the differential equations; R0 + T + absorbed = 1 (energy)."""
    r_ref, t_ref, absorbed = _two_flux(s, k, x, 0.0)
    r0, t = jaxcos.km_layer(s, k, x)
    np.testing.assert_allclose([float(r0), float(t)], [r_ref, t_ref], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(float(r0) + float(t) + absorbed, 1.0, atol=1e-5)
    # over a background: what the background returns is absorbed or reflected, nothing is lost
    r_ref, _, _ = _two_flux(s, k, x, 0.6)
    np.testing.assert_allclose(float(jaxcos.km_over_background(s, k, x, 0.6)), r_ref, rtol=1e-5)


def test_two_layers_combine_like_one_thicker_layer():
    r1, t1 = jaxcos.km_layer(S, K, 0.1)
    r2, t2 = jaxcos.km_layer(S, K, 0.25)
    r12, t12 = jaxcos.km_combine(r1, t1, r2, t2)
    r, t = jaxcos.km_layer(S, K, 0.35)
    np.testing.assert_allclose(r12, r, rtol=1e-5)
    np.testing.assert_allclose(t12, t, rtol=1e-5)
    # an opaque background is a layer with T = 0
    rg = np.array([0.05, 0.5, 0.95])
    np.testing.assert_allclose(jaxcos.km_over_background(S, K, 0.1, rg), jaxcos.km_combine(r1, t1, rg, 0.0)[0],
                               rtol=1e-6)
    # and a different layer below changes the result (the combination is not trivially symmetric)
    r3, t3 = jaxcos.km_layer(2 * S, 3 * K, 0.2)
    assert not np.allclose(jaxcos.km_combine(r1, t1, r3, t3)[0], jaxcos.km_combine(r3, t3, r1, t1)[0])


@pytest.mark.parametrize("rg", [0.0, 0.05, 0.3, 0.97])
def test_inversion_round_trip(rg):
    """S, K -> (R_inf, R over Rg) -> km_invert -> S, K; also for a background lighter than R_inf."""
    x = 0.15
    r_inf = jaxcos.km_r_inf(S, K)
    r = jaxcos.km_over_background(S, K, x, rg)
    s_back, k_back = jaxcos.km_invert(r_inf, r, rg, x)
    np.testing.assert_allclose(s_back, S, rtol=2e-3)
    np.testing.assert_allclose(k_back, K, rtol=2e-3)


def test_inversion_matches_the_papers_arccoth_form_and_rejects_impossible_data():
    r_inf, r, rg, d = 0.8, 0.5, 0.05, 0.15
    a = 0.5 * (1 / r_inf + r_inf)
    b = np.sqrt(a * a - 1)
    acoth = lambda v: 0.5 * np.log((v + 1) / (v - 1))
    s_ref = (acoth((a - r) / b) - acoth((a - rg) / b)) / (b * d)
    s, k = jaxcos.km_invert(r_inf, r, rg, d)
    np.testing.assert_allclose([float(s), float(k)], [s_ref, s_ref * (a - 1)], rtol=1e-5)
    # R outside (Rg, R_inf): no Kubelka-Munk layer explains it
    assert np.isnan(float(jaxcos.km_invert(0.8, 0.85, 0.05, d)[0]))
    assert np.isnan(float(jaxcos.km_invert(0.8, 0.03, 0.05, d)[0]))


def test_gradients_are_finite_at_the_limits():
    for fn in (lambda k: jaxcos.km_layer(3.0, k, 1.0)[0], lambda s: jaxcos.km_layer(s, 0.3, 1.0)[1],
               lambda x: jaxcos.km_layer(3.0, 0.3, x)[0], lambda x: jaxcos.km_layer(3.0, 0.3, x)[1]):
        for v in (0.0, 1e-6, 1.0, 1e4):
            assert np.isfinite(float(jax.grad(fn)(v)))
    # at K = 0: dR0/dK by central differences
    fd = (jaxcos.km_layer(3.0, 1e-3, 1.0)[0] - jaxcos.km_layer(3.0, 0.0, 1.0)[0]) / 1e-3
    np.testing.assert_allclose(float(jax.grad(lambda k: jaxcos.km_layer(3.0, k, 1.0)[0])(0.0)), float(fd), rtol=2e-2)


def test_beckmann_is_normalised_and_the_lobe_peaks_at_the_mirror():
    th = np.linspace(0, np.pi / 2, 20001)
    for m in (0.05, 0.2, 0.6):
        d = np.asarray(beckmann(jnp.asarray(np.cos(th)), m), dtype=float)
        integral = np.trapezoid(d * np.cos(th) * np.sin(th) * 2 * np.pi, th)
        np.testing.assert_allclose(integral, 1.0, rtol=1e-3)
    to = np.arange(-80.0, 81.0, 1.0)
    wi, wo = directions(np.full_like(to, 35.0), to)
    f = np.asarray(kelemen_specular(wi, wo, 0.15, 0.05))
    # the peak lies just past the mirror (1 / (h . wi)^2 grows there: Kelemen's off-specular shift),
    # nowhere near retro-reflection
    assert 35.0 <= to[np.argmax(f)] <= 40.0 and f[to == -35.0] < 1e-3 * f.max()
    # value at the mirror: D(0) F(cos ti) / (4 cos^2 ti)
    c = np.cos(np.deg2rad(35.0))
    expected = 1 / (np.pi * 0.15 ** 2) * (0.05 + 0.95 * (1 - c) ** 5) / (4 * c * c)
    np.testing.assert_allclose(f[to == 35.0], expected, rtol=1e-5)
    # reciprocity f(wi, wo) = f(wo, wi), also out of the plane
    a, b = directions([20.0, 50.0], [60.0, -10.0], [30.0, 100.0])
    np.testing.assert_allclose(kelemen_specular(a, b, 0.3, 0.1), kelemen_specular(b, a, 0.3, 0.1), rtol=1e-5)


def test_bsdf_is_diffuse_plus_specular_in_the_stated_convention():
    km = jaxcos.KubelkaMunk(scattering=S, absorption=K, thickness=0.3, roughness=0.02, f0=0.0, substrate=0.2)
    r = jaxcos.km_over_background(S, K, 0.3, 0.2)
    f = np.asarray(km.bsdf([0.0, 30.0, 60.0], [-70.0, 5.0, 85.0]))  # far from every mirror direction
    np.testing.assert_allclose(f, np.broadcast_to(np.asarray(r) / np.pi, (3, 3)), rtol=1e-5, atol=1e-9)
    km = jaxcos.KubelkaMunk(scattering=S, absorption=K, thickness=0.3, roughness=0.2, f0=0.05)
    f = np.asarray(km.bsdf([40.0, 40.0], [40.0, -40.0]))
    assert np.all(f[0] > f[1] + 0.1)  # the highlight is at theta_o = theta_i, not on the light's side


def test_parameterization_round_trip_and_count():
    x = km_to_x([0.3, 0.6, 0.9], [2.0, 5.0, 40.0], 0.12, 0.07)
    assert x.shape == (KM_N_PARAMS,) == (len(km_labels()),)
    km = km_from_x(x)
    np.testing.assert_allclose(km.r_inf, [0.3, 0.6, 0.9], rtol=1e-5)
    np.testing.assert_allclose(km.scattering, [2.0, 5.0, 40.0], rtol=1e-5)
    np.testing.assert_allclose([float(km.roughness), float(km.f0)], [0.12, 0.07], rtol=1e-5)
    for extreme in (jnp.full(8, 40.0), jnp.full(8, -40.0)):
        km = km_from_x(extreme)
        assert np.all(np.isfinite(np.asarray(km.bsdf([30.0], [30.0]))))


def test_fit_recovers_the_model_that_made_the_data():
    truth = km_from_x(km_to_x([0.5, 0.6, 0.7], [3.0, 4.0, 6.0], 0.25, 0.06))
    ti = np.repeat([10.0, 40.0, 65.0], 9)
    to = np.tile([-60.0, -30.0, 0.0, 10.0, 25.0, 40.0, 55.0, 65.0, 80.0], 3)
    values = np.pi * np.asarray(truth.bsdf(ti, to), dtype=float)
    meas = Measurements(theta_i=ti, theta_o=to, phi_o=np.zeros_like(ti), values=values, std=0.01 + 0.02 * values,
                        quantity="reflectance_factor", path="km.csv")
    result = jaxcos.fit_kubelka_munk(meas, seed=1, starts=5)
    assert result.record.n_params == 8 and result.record.loss < 1e-3
    np.testing.assert_allclose(result.model, values, rtol=1e-3, atol=1e-4)
    assert float(make_km_problem(meas).loss(result.x)) == pytest.approx(result.record.loss, abs=1e-5)
    fit = result.record.to_json()
    assert fit["variant"] == "kubelka_munk" and fit["fitted"] == list(KM_PARAMETERS) and "reduced_chi2" in fit
    assert fit["parameters"]["thickness"] == 1.0 and fit["substrate"] == [0.0, 0.0, 0.0]
    json.dumps(fit)


def test_km_problem_is_a_weighted_least_squares_problem():
    from jaxcos.inference import WeightedLeastSquares

    ti, to = np.array([10.0, 40.0]), np.array([20.0, -30.0])
    meas = Measurements(theta_i=ti, theta_o=to, phi_o=np.zeros(2), values=np.full((2, 3), 0.3),
                        std=np.full((2, 3), 0.02), quantity="reflectance_factor", path="m.csv")
    problem = make_km_problem(meas)
    assert isinstance(problem, WeightedLeastSquares)
    x = km_to_x([0.4, 0.5, 0.6], [3.0, 4.0, 5.0], 0.2, 0.05)
    expected = (np.asarray(problem.model(x)) - 0.3) / 0.02
    np.testing.assert_allclose(problem.residuals(x), expected.reshape(-1), rtol=1e-5)
    assert float(problem.loss(x)) == pytest.approx(float(np.sum(expected ** 2)), rel=1e-5)


def test_bad_substrate_is_a_clear_error():
    meas = Measurements(theta_i=np.array([10.0]), theta_o=np.array([20.0]), phi_o=np.zeros(1),
                        values=np.full((1, 3), 0.3), std=None, path="m.csv")
    with pytest.raises(jaxcos.InputError, match=r"substrate reflectance .* \[0, 1\)"):
        make_km_problem(meas, substrate=1.5)
