"""The rough dielectric top interface (docs/model.md section 3a, docs/interface.md).

What is checked, and against what (every reference below is independent of
the package's code: float64 NumPy written from the textbook formulas, or
``iadpython``):

a. ``interface=None`` is today's estimator, bit for bit (numbers recorded
   from the estimator before the interface existed).
b. The closed-form reflection ``f_s``: against a NumPy float64 reference
   (Walter et al. 2007 with the classic Fresnel ``(R_s + R_p) / 2``),
   reciprocity, and its hemispherical albedo plus the transmittance is at
   most 1, the rest being the sampled shadowing loss.
c. The sampling weights of the walk (entry, exit bracket, internal
   reflection and transmission) against direct quadrature of Walter's
   ``f_t`` and ``f_r`` over the hemisphere, with test functions of the drawn
   direction (so the distribution is checked, not just the total).
d. Chi-square tests of the visible-normal sampler and of the refraction
   through it against their densities (Mitsuba's recipe: cells integrated
   numerically, small cells pooled, Sidak-corrected).
e. Energy: a white non-absorbing layer over a white Lambertian base
   reflects everything once the shadowing loss is counted, and tends to 1
   as ``alpha_s -> 0``.
f. Reciprocity of the whole BSDF.
g. A transparent layer (``t = 0``) over a Lambertian base against the exact
   answer built from the interface's own transmittances and internal
   reflectance (quadrature).
h. The smooth-boundary limit against adding-doubling (``iadpython``).
i. Derivatives with respect to ``eta``, ``alpha_s`` and every other
   parameter against central finite differences under common random
   numbers, and finiteness at the hard cases.
j. ``params.json``: the interface round trip, and unknown keys are errors.

Tolerances are multiples of standard errors measured by the tests
themselves, plus measured quadrature errors; keys are fixed.
"""

import json
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats

import jaxcos
from jaxcos import Layer, Material
from jaxcos.model import Interface
from jaxcos.model import _interface as I
from quadrature import half_hemisphere_grid

_PUB = jaxcos.model._material._PUBLISHED


def _bonferroni_z(n, alpha=1e-3):
    return float(stats.norm.isf(alpha / (2 * n)))


def _np(a):
    return np.asarray(a, dtype=np.float64)


def _dirs(theta_deg, phi_deg=0.0):
    th, ph = np.radians(theta_deg), np.radians(phi_deg)
    return np.stack(np.broadcast_arrays(np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)), axis=-1)


# --- float64 references, written from the formulas (docs/model.md section 3a) ---------------------------


def _fresnel_np(c, n):
    """Unpolarised Fresnel reflectance, ``(R_s + R_p) / 2`` with Snell's law; ``n = n_t / n_i``; 1 at TIR."""
    c = np.clip(c, 0.0, 1.0)
    s2t = (1.0 - c * c) / (n * n)
    ct = np.sqrt(np.clip(1.0 - s2t, 0.0, None))
    with np.errstate(invalid="ignore", divide="ignore"):
        rs = ((c - n * ct) / (c + n * ct)) ** 2
        rp = ((n * c - ct) / (n * c + ct)) ** 2
    return np.where(s2t >= 1.0, 1.0, 0.5 * (rs + rp))


def _ndf_np(h, a):
    """GGX ``D(h) = 1 / (pi a^2 cos^4 (1 + tan^2 / a^2)^2)`` for unit ``h``, 0 below."""
    c = h[..., 2]
    with np.errstate(invalid="ignore", divide="ignore"):
        tan2 = (1.0 - c * c) / (c * c)
        d = 1.0 / (np.pi * a * a * c ** 4 * (1.0 + tan2 / (a * a)) ** 2)
    return np.where(c > 0, d, 0.0)


def _lambda_np(w, a):
    c = np.abs(w[..., 2])
    with np.errstate(divide="ignore"):
        tan2 = (1.0 - c * c) / (c * c)
    return (np.sqrt(1.0 + a * a * tan2) - 1.0) / 2.0


def _g1_np(w, a):
    return 1.0 / (1.0 + _lambda_np(w, a))


def _g2_np(w1, w2, a):
    return 1.0 / (1.0 + _lambda_np(w1, a) + _lambda_np(w2, a))


def _unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _dot(a, b):
    return np.sum(a * b, axis=-1)


def _f_t_np(a, b, n_a, n_b, alpha):
    """Walter et al. (2007) eq. 21: ``a`` (index ``n_a``) and ``b`` (index ``n_b``) on opposite sides, both away."""
    ht = -(n_a * a + n_b * b)
    h = _unit(ht * np.sign(ht[..., 2:3]))
    ah, bh = _dot(a, h), _dot(b, h)
    ok = (ah * a[..., 2] > 0) & (bh * b[..., 2] > 0)
    f = _fresnel_np(np.abs(ah), n_b / n_a)
    val = (np.abs(ah) * np.abs(bh) / (np.abs(a[..., 2]) * np.abs(b[..., 2])) * n_b ** 2 * (1.0 - f)
           * _ndf_np(h, alpha) * _g2_np(a, b, alpha) / (n_a * ah + n_b * bh) ** 2)
    return np.where(ok, val, 0.0)


def _f_r_np(a, r, n_rel, alpha):
    """Microfacet reflection ``F(|a.h|; n_rel) D(h) G2 / (4 |a_z| |r_z|)``, ``a`` and ``r`` on one side."""
    hh = a + r
    h = _unit(hh * np.sign(hh[..., 2:3]))
    ah, rh = _dot(a, h), _dot(r, h)
    ok = (ah * a[..., 2] > 0) & (rh * r[..., 2] > 0)
    val = (_fresnel_np(np.abs(ah), n_rel) * _ndf_np(h, alpha) * _g2_np(a, r, alpha)
           / (4.0 * np.abs(a[..., 2]) * np.abs(r[..., 2])))
    return np.where(ok, val, 0.0)


def _hemisphere(n_mu, n_phi, down=False, split=None):
    """Directions and solid-angle weights of a hemisphere: Gauss-Legendre in ``|z|``, midpoints in ``phi``.

    ``split``: a value of ``|z|`` where the integrand jumps; Gauss-Legendre on each side of it. Walter's
    ``f_t`` jumps where the generalised half vector ``-(n_a a + n_b b)`` is horizontal (there it flips to
    ``h_z > 0`` and the no-back-facing rule switches; GGX's ``D`` does not vanish at the horizon), which for a
    fixed ``a`` is the circle ``n_b |b_z| = n_a |a_z|``: over a single Gauss-Legendre grid the quadrature then
    converges as ``1 / n`` and erratically (errors of 2e-4 at 1024^2 points for ``wi`` at 80 degrees).
    """
    x, w = np.polynomial.legendre.leggauss(n_mu)
    edges = [0.0, split, 1.0] if split is not None and 0 < split < 1 else [0.0, 1.0]
    mu = np.concatenate([(a + b) / 2 + (b - a) / 2 * x for a, b in zip(edges[:-1], edges[1:])])
    w_mu = np.concatenate([(b - a) / 2 * w for a, b in zip(edges[:-1], edges[1:])])
    phi = (np.arange(n_phi) + 0.5) * 2 * np.pi / n_phi
    MU, PHI = np.meshgrid(mu, phi, indexing="ij")
    s = np.sqrt(1 - MU * MU)
    d = np.stack([s * np.cos(PHI), s * np.sin(PHI), -MU if down else MU], axis=-1).reshape(-1, 3)
    return d, np.outer(w_mu, np.full(n_phi, 2 * np.pi / n_phi)).ravel()


def _normals(alpha, n_xi, n_phi):
    """Nodes ``h`` and weights of ``int g(h) D(h) h_z dh``.

    The substitution ``tan^2 = alpha^2 xi / (1 - xi)`` makes ``D h_z dh = dxi dphi / (2 pi)``; then
    ``xi = 1 - s^2`` (Gauss-Legendre in ``s``) absorbs the ``1 / sqrt(1 - xi)`` of integrands holding ``1 / h_z``.
    """
    x, w = np.polynomial.legendre.leggauss(n_xi)
    sq, w_sq = (x + 1) / 2, w / 2
    xi, w_xi = 1 - sq * sq, 2 * sq * w_sq
    phi = (np.arange(n_phi) + 0.5) * 2 * np.pi / n_phi
    XI, PHI = np.meshgrid(xi, phi, indexing="ij")
    t2 = alpha * alpha * XI / (1 - XI)
    c = 1 / np.sqrt(1 + t2)
    s = np.sqrt(t2) * c
    h = np.stack([s * np.cos(PHI), s * np.sin(PHI), c], axis=-1).reshape(-1, 3)
    return h, np.outer(w_xi, np.full(n_phi, 1.0 / n_phi)).ravel()


def _refract_np(w, h, n):
    c = _dot(w, h)
    s2 = (1 - c * c) / (n * n)
    ok = s2 < 1
    ct = np.sqrt(np.clip(1 - s2, 0, None))
    return -w / n + ((c / n - ct)[..., None]) * h, ok


def _albedos_np(w, eta, alpha, n_xi=256, n_phi=256):
    """``(R, T)``: reflected and transmitted fractions of light from ``w`` (``w_z > 0``, outside, index ratio ``eta``).

    By quadrature over microfacet normals: ``R = int (w.h) / w_z F D G2(w, r) dh``,
    ``T = int (w.h) / w_z (1 - F) D G2(w, t) dh`` (``r``, ``t`` through ``h``; zero
    where they end on the wrong side). ``eta < 1``: light from inside (mirrored frame).
    """
    h, wt = _normals(alpha, n_xi, n_phi)
    c = _dot(w, h)
    f = _fresnel_np(np.clip(c, 0, 1), eta)
    r = 2 * c[:, None] * h - w
    t, ok = _refract_np(w, h, eta)
    base = np.where(c > 0, c / (w[2] * h[:, 2]), 0.0)
    R = np.sum(wt * base * f * np.where(r[:, 2] > 0, _g2_np(w, r, alpha), 0.0))
    T = np.sum(wt * base * (1 - f) * np.where(ok & (t[:, 2] < 0), _g2_np(w, t, alpha), 0.0))
    return R, T


# --- a. interface=None is the index-matched estimator, bit for bit ----------------------------------

# Recorded with the estimator of commit d41128e (before the interface), JAX 0.10.2 on CPU: make_query([0, 30,
# 30, 75], [20, -45, 30, 80]), key 77, 8 walks, 8 bounces; f, stderr, reflected as float32 hex.
_GOLDEN = {
    "dewy1": {  # published("dewy1"), black base, next-event estimation
        "f": ["0x1.d45c24p-4", "0x1.e9ea94p-4", "0x1.f6a174p-4", "0x1.b7987ap-4", "0x1.af23b2p-4", "0x1.851f12p-4",
              "0x1.5920e4p-2", "0x1.77674ap-2", "0x1.9a852ap-2", "0x1.d1873p+0", "0x1.ece38ap+0", "0x1.06ee1p+1"],
        "stderr": ["0x1.4ddb0ap-6", "0x1.4c69fcp-6", "0x1.3ea964p-6", "0x1.9f4056p-6", "0x1.8dcaccp-6", "0x1.50d234p-6",
                   "0x1.2a70eap-5", "0x1.3ad06cp-5", "0x1.45e5dp-5", "0x1.29bdccp-3", "0x1.2e246p-3", "0x1.28fe66p-3"],
        "reflected": ["0x1.297776p-3", "0x1.1f84dap-3", "0x1.fdc59p-4", "0x1.36e9ep-2", "0x1.3e22c6p-2",
                      "0x1.39b7fap-2", "0x1.61925p-1", "0x1.5b4d82p-1", "0x1.463008p-1"],
    },
    "stack": {  # two layers over a Lambertian base, MIS connection
        "f": ["0x1.343ff8p-3", "0x1.0f9d2cp-3", "0x1.bb7996p-4", "0x1.c988e2p-4", "0x1.842952p-4", "0x1.231666p-4",
              "0x1.2267eap-3", "0x1.04c21ep-3", "0x1.bffa22p-4", "0x1.aca878p-1", "0x1.6b507cp-1", "0x1.15ffd6p-1"],
        "stderr": ["0x1.cd191ap-5", "0x1.75700ap-5", "0x1.0a96d6p-5", "0x1.20e5ap-4", "0x1.c240bcp-5", "0x1.1cc8bap-5",
                   "0x1.1ae7d2p-4", "0x1.acbfd8p-5", "0x1.0be966p-5", "0x1.18626cp-1", "0x1.e11026p-2", "0x1.746e6ep-2"],
        "reflected": ["0x1.47b0a8p-1", "0x1.0fea62p-1", "0x1.8bc312p-2", "0x1.42fbc8p-1", "0x1.005e86p-1",
                      "0x1.60499cp-2", "0x1.af9846p+0", "0x1.72d626p+0", "0x1.1ce36p+0"],
    },
}


def _golden_material(name):
    if name == "dewy1":
        return jaxcos.published("dewy1"), "nee"
    stack = Material(layers=(Layer(**{**_PUB["matte2"], "t": 1.0}), Layer(**{**_PUB["dewy1"], "t": 3.0, "phi_p": 30.0})),
                     base_albedo=(0.6, 0.5, 0.4))
    return stack, "mis"


def test_no_interface_is_the_index_matched_estimator():
    """``interface=None`` (the default) gives the numbers of the estimator before the interface existed.

    To float32 rounding of their sums (``rtol`` 2e-5): bit for bit on the machine that recorded them
    (CPU, JAX 0.10.2), up to 24 ulp on another CPU model with the same JAX, whose XLA code sums in
    another order. ``shadowed`` is zero. The full check (two structures, all tallies, a gradient)
    was run before and after the change (docs/interface.md).
    """
    query = jaxcos.make_query([0.0, 30.0, 30.0, 75.0], [20.0, -45.0, 30.0, 80.0])
    for name, fields in _GOLDEN.items():
        material, connection = _golden_material(name)
        assert material.interface is None
        est = jaxcos.simulate(material, query, jax.random.key(77), walks=8, bounces=8, connection=connection)
        for field, hexes in fields.items():
            want = np.array([float.fromhex(h) for h in hexes], np.float32).reshape(-1, 3)
            got = np.asarray(getattr(est, field))
            np.testing.assert_allclose(got, want, rtol=2e-5, err_msg=f"{name}.{field}")
        assert np.all(np.asarray(est.shadowed) == 0.0)


# --- b. the reflection outside --------------------------------------------------------------------


def _random_pairs(n, seed, grazing=True):
    rng = np.random.default_rng(seed)
    mu = rng.uniform(0.02, 1.0, (2, n))
    if grazing:
        mu[:, :8] = rng.uniform(1e-3, 2e-2, (2, 8))
    phi = rng.uniform(0, 2 * np.pi, (2, n))
    s = np.sqrt(1 - mu * mu)
    d = np.stack([s * np.cos(phi), s * np.sin(phi), mu], axis=-1)
    return d[0], d[1]


@pytest.mark.parametrize("eta, alpha", [(1.01, 0.005), (1.5, 0.1), (1.5, 0.5), (2.5, 1.0), (1.33, 0.02)])
def test_reflection_matches_reference_and_is_reciprocal(eta, alpha):
    """``f_s`` equals the float64 reference to float32 accuracy (relative ``2e-4 + 2e-6 / alpha`` where it is
    above 1e-6 of its peak), including grazing directions and near-mirror pairs, and ``f_s(wi, wo) = f_s(wo, wi)``
    (relative 1e-5)."""
    wi, wo = _random_pairs(400, 1)
    # near-mirror pairs: wo = mirror of wi, perturbed by a fraction of alpha
    rng = np.random.default_rng(2)
    wm = wi[:50] * np.array([-1, -1, 1]) + rng.normal(0, alpha, (50, 3)) * np.array([1, 1, 0])
    wm[:, 2] = np.abs(wm[:, 2])
    wi, wo = np.concatenate([wi, wi[:50]]), np.concatenate([wo, _unit(wm)])
    f = np.asarray(I.reflection(jnp.asarray(wi, jnp.float32), jnp.asarray(wo, jnp.float32), jnp.float32(eta),
                                jnp.float32(alpha)), np.float64)
    back = np.asarray(I.reflection(jnp.asarray(wo, jnp.float32), jnp.asarray(wi, jnp.float32), jnp.float32(eta),
                                   jnp.float32(alpha)), np.float64)
    wi32, wo32 = wi.astype(np.float32).astype(np.float64), wo.astype(np.float32).astype(np.float64)
    h = _unit(wi32 + wo32)
    ref = (_fresnel_np(_dot(wi32, h), eta) * _ndf_np(h, alpha) * _g2_np(wi32, wo32, alpha)
           / (4 * wi32[:, 2] * wo32[:, 2]))
    assert np.all(np.isfinite(f)) and np.all(f >= 0)
    big = ref > 1e-6 * ref.max()
    # float32 rounding of wi + wo moves the half vector by ~6e-8, which D amplifies by ~8 / alpha near its peak
    np.testing.assert_allclose(f[big], ref[big], rtol=2e-4 + 2e-6 / alpha)
    np.testing.assert_allclose(f[~big], ref[~big], atol=2e-6 * ref.max())
    np.testing.assert_allclose(f, back, rtol=1e-5, atol=1e-30)


@pytest.mark.parametrize("eta, alpha", [(1.5, 0.3), (2.5, 0.6)])
def test_reflection_albedo_plus_transmittance_is_at_most_one(eta, alpha):
    """The albedo of ``f_s`` (quadrature of the package's ``f_s`` over ``wo``) agrees with the independent
    quadrature over microfacet normals; adding the transmittance (quadrature of Walter's ``f_t``, float64)
    gives at most 1, and the remainder is the shadowing loss the entry sampler reports (its mean over 2^20
    draws, within 5 standard errors plus the quadrature error)."""
    out, w_out = _hemisphere(512, 512)
    u = jax.random.uniform(jax.random.key(3), (1 << 20, 2))
    for theta in (0.0, 45.0, 80.0):
        wi = _dirs(theta) * np.array([-1, 1, 1])
        inward, w_in = _hemisphere(256, 512, down=True, split=wi[2] / eta)
        fs = np.asarray(I.reflection(jnp.asarray(wi, jnp.float32)[None], jnp.asarray(out, jnp.float32),
                                     jnp.float32(eta), jnp.float32(alpha)), np.float64)
        r_quad = np.sum(w_out * fs * out[:, 2])
        r_h, t_h = _albedos_np(wi, eta, alpha)
        t_quad = np.sum(w_in * _f_t_np(wi, inward, 1.0, eta, alpha) * np.abs(inward[:, 2]))
        assert abs(r_quad - r_h) < 2e-4 * max(r_h, 0.05), (theta, r_quad, r_h)
        assert abs(t_quad - t_h) < 1e-5, (theta, t_quad, t_h)
        assert r_h + t_h <= 1.0 + 1e-6
        _, w_t, w_r, lost = I.enter(jnp.asarray(wi, jnp.float32), jnp.float32(eta), jnp.float32(alpha), u[:, 0], u[:, 1])
        lost = _np(lost)
        assert np.all(lost >= -1e-6)
        se = lost.std() / math.sqrt(lost.size)
        assert abs(lost.mean() - (1 - r_h - t_h)) < 5 * se + 3e-4, (theta, lost.mean(), 1 - r_h - t_h, se)


# --- c. the walk's sampling weights against quadrature -----------------------------------------------

_TEST_FUNCTIONS = (lambda d: np.ones(d.shape[:-1]), lambda d: d[..., 0], lambda d: d[..., 2] ** 2,
                   lambda d: np.exp(2 * d[..., 0] + d[..., 1]))


def _check_weights(label, samples, weights, reference, quad_err, lines, failures, z_max):
    for k, g in enumerate(_TEST_FUNCTIONS):
        x = weights * g(samples)
        mean, se = x.mean(), x.std() / math.sqrt(x.size)
        ref = reference(g)
        z = max(abs(mean - ref) - quad_err[k], 0.0) / se
        line = f"{label} g{k}: {mean:.6f} vs {ref:.6f} (se {se:.1e}, quadrature {quad_err[k]:.1e}) z {z:.2f}"
        lines.append(line)
        if z > z_max:
            failures.append(line)


@pytest.mark.parametrize("eta, alpha", [(1.5, 0.3), (2.5, 0.6), (1.33, 0.15)])
def test_sampling_weights_match_quadrature(eta, alpha):
    """``E[weight g(direction)]`` of each sampler against ``int f |cos| g`` by direct quadrature of the
    float64 BSDF over the hemisphere of the drawn direction (2^20 draws; four test functions ``g``):

    * entry: ``u`` and ``(1 - F) G2 / G1`` against ``f_t(wi -> u) |u_z|``,
    * exit: ``v`` and the bracket against ``f_t(wo <- v) |v_z|`` (which keeps ``1 / eta^2``),
    * from below: ``r`` and ``F G2 / G1`` against the internal reflection ``f_r(a, r) |r_z|`` (total internal
      reflection included), and the transmitted tally against ``int f_t(a -> b) |b_z| db``.

    The quadrature error is measured (two grids, split where ``f_t`` jumps: see :func:`_hemisphere`). Dropping ``1 / eta^2`` from the
    bracket, or taking ``G2`` for ``G2 / G1``, fails by hundreds of standard errors.
    """
    n = 1 << 20
    u = jax.random.uniform(jax.random.key(5), (n, 2))
    eta32, alpha32 = jnp.float32(eta), jnp.float32(alpha)
    z_max = _bonferroni_z(3 * 3 * 5 * len(_TEST_FUNCTIONS))
    lines, failures = [], []

    def quad(fn, split=None):
        """``fn(grid_down, grid_up) -> (directions, weighted integrand)``; ``[(value, error)]`` per test function,
        the error being the change from a ``192 x 384`` to a ``256 x 512`` grid (split where ``f_t`` jumps)."""
        vals = []
        for m in (192, 256):
            d, wv = fn(_hemisphere(m, 2 * m, down=True, split=split), _hemisphere(m, 2 * m, split=split))
            vals.append([np.sum(wv * g(d)) for g in _TEST_FUNCTIONS])
        return [(b, abs(b - a) + 1e-7) for a, b in zip(*vals)]

    for theta in (0.0, 40.0, 80.0):
        w = _dirs(theta) * np.array([-1, 1, 1])  # light from -x, like wi
        # entry
        d, w_t, _, _ = I.enter(jnp.asarray(w, jnp.float32), eta32, alpha32, u[:, 0], u[:, 1])
        q = quad(lambda gd, gu: (gd[0], gd[1] * _f_t_np(w, gd[0], 1.0, eta, alpha) * np.abs(gd[0][:, 2])), w[2] / eta)
        _check_weights(f"entry theta {theta:g}", _np(d), _np(w_t), lambda g, q=q: q[_TEST_FUNCTIONS.index(g)][0],
                       [e for _, e in q], lines, failures, z_max)
        # exit towards wo = w mirrored (a viewer direction)
        wo = w * np.array([-1, 1, 1])
        v, bracket = I.leave(jnp.asarray(wo, jnp.float32), eta32, alpha32, u[:, 0], u[:, 1])
        q = quad(lambda gd, gu: (gu[0], gu[1] * _f_t_np(-gu[0], wo, eta, 1.0, alpha) * gu[0][:, 2]), wo[2] / eta)
        _check_weights(f"exit theta {theta:g}", _np(v), _np(bracket), lambda g, q=q: q[_TEST_FUNCTIONS.index(g)][0],
                       [e for _, e in q], lines, failures, z_max)
        # from below: light propagating up along p (theta from the normal), a = -p points into the stack
        for theta_in in (theta, 60.0 if theta == 0.0 else theta / 2 + 5):
            p = _dirs(theta_in) * np.array([-1, 1, 1])
            r, w_r, w_tr, _ = I.reflect_inside(jnp.asarray(p, jnp.float32), eta32, alpha32, u[:, 0], u[:, 1])
            a = -p
            q = quad(lambda gd, gu: (gd[0], gd[1] * _f_r_np(a, gd[0], 1.0 / eta, alpha) * np.abs(gd[0][:, 2])))
            _check_weights(f"inside reflection theta {theta_in:g}", _np(r), _np(w_r),
                           lambda g, q=q: q[_TEST_FUNCTIONS.index(g)][0], [e for _, e in q], lines, failures, z_max)
            q = quad(lambda gd, gu: (gu[0], gu[1] * _f_t_np(a, gu[0], eta, 1.0, alpha) * gu[0][:, 2]), eta * p[2])
            x = _np(w_tr)
            mean, se = x.mean(), x.std() / math.sqrt(n)
            z = max(abs(mean - q[0][0]) - q[0][1], 0.0) / se
            line = f"inside transmission theta {theta_in:g}: {mean:.6f} vs {q[0][0]:.6f} (se {se:.1e}) z {z:.2f}"
            lines.append(line)
            if z > z_max:
                failures.append(line)
    print(f"\n[weights eta {eta} alpha {alpha}] bound {z_max:.2f}\n" + "\n".join(lines))
    assert not failures, "\n".join(failures)


# --- d. chi-square of the samplers --------------------------------------------------------------------


def _chi2(counts, expected):
    """Pool cells with fewer than 5 expected draws (those of zero density included); the p-value."""
    counts, expected = counts.ravel(), expected.ravel()
    small = expected < 5
    c = np.append(counts[~small], counts[small].sum())
    e = np.append(expected[~small], expected[small].sum())
    if e[-1] < 5:  # pool the pooled cell into the smallest remaining one
        c, e = c[:-1], e[:-1]
        c[np.argmin(e)] += counts[small].sum()
        e[np.argmin(e)] += expected[small].sum()
    e = e * c.sum() / e.sum()
    return stats.chisquare(c, e).pvalue


def _cells(n_a, n_b, sub):
    """Midpoints of ``sub x sub`` sub-cells of an ``n_a x n_b`` grid over the unit square, ``(n_a, n_b, sub^2, 2)``."""
    a = (np.arange(n_a * sub) + 0.5) / (n_a * sub)
    b = (np.arange(n_b * sub) + 0.5) / (n_b * sub)
    A, B = np.meshgrid(a, b, indexing="ij")
    pts = np.stack([A, B], axis=-1).reshape(n_a, sub, n_b, sub, 2).transpose(0, 2, 1, 3, 4)
    return pts.reshape(n_a, n_b, sub * sub, 2)


_CHI2_NORMALS = [(0.0, 0.3), (60.0, 0.6), (85.0, 1.0), (30.0, 0.05)]
_CHI2_REFRACTION = [(30.0, 0.5, 1.5), (75.0, 1.0, 2.5), (0.0, 0.7, 1.33)]


def test_samplers_chi_square():
    """Histograms of 2^20 draws against cell probabilities integrated numerically (Sidak, 1e-3 family-wise),
    and no draw where the density is 0.

    * Visible normals ``h`` from ``w``: cells uniform in ``s = alpha / sqrt(alpha^2 + tan^2)`` and ``phi``, where
      the density per unit ``s phi`` is the smooth ``G1(w) max(0, w.h) sqrt(s^2 + alpha^2 (1 - s^2)) / (pi w_z)``
      (``D h_z dh = dxi dphi / (2 pi)`` with ``xi = 1 - s^2``).
    * Refraction ``u`` of ``wi`` through them, over the whole sphere: density
      ``D_wi(h) eta^2 |u.h| / (wi.h + eta u.h)^2`` with ``h`` the generalised half vector (Walter et al. 2007).
    """
    tests = len(_CHI2_NORMALS) + len(_CHI2_REFRACTION)
    level = 1 - (1 - 1e-3) ** (1 / tests)
    n = 1 << 20
    u = jax.random.uniform(jax.random.key(7), (n, 2))
    lines = []
    for theta, alpha in _CHI2_NORMALS:
        w = _dirs(theta)
        h = _np(I.sample_visible_normal(jnp.asarray(w, jnp.float32), jnp.float32(alpha), u[:, 0], u[:, 1]))
        assert np.all(h[:, 2] >= 0) and np.all(_dot(h, w) > -1e-6), "a draw where the density is 0"
        t2 = (h[:, 0] ** 2 + h[:, 1] ** 2) / h[:, 2] ** 2
        s_h = alpha / np.sqrt(alpha ** 2 + t2)  # sqrt(1 - xi)
        phi = np.mod(np.arctan2(h[:, 1], h[:, 0]), 2 * np.pi) / (2 * np.pi)
        na, nb = 24, 24
        counts = np.histogram2d(s_h, phi, bins=[na, nb], range=[[0, 1], [0, 1]])[0]
        pts = _cells(na, nb, 16)
        ss, ps = pts[..., 0], pts[..., 1] * 2 * np.pi
        tt = alpha * np.sqrt(1 - ss * ss) / ss
        c = 1 / np.sqrt(1 + tt * tt)
        hh = np.stack([tt * c * np.cos(ps), tt * c * np.sin(ps), c], axis=-1)
        # per unit xi: G1 max(0, w.h) / (2 pi w_z h_z); d xi = 2 s ds and 2 s / h_z = 2 sqrt(s^2 + alpha^2 (1 - s^2))
        jac = 2 * np.sqrt(ss * ss + alpha ** 2 * (1 - ss * ss))
        dens = _g1_np(w, alpha) * np.clip(_dot(hh, w), 0, None) * jac / (2 * np.pi * w[2])
        expected = dens.mean(axis=-1) / (na * nb) * 2 * np.pi * n
        p = _chi2(counts, expected)
        lines.append(f"visible normals theta {theta:g} alpha {alpha:g}: p = {p:.3g}")
        assert p > level, lines[-1]
    for theta, alpha, eta in _CHI2_REFRACTION:
        wi = _dirs(theta) * np.array([-1, 1, 1])
        h = I.sample_visible_normal(jnp.asarray(wi, jnp.float32), jnp.float32(alpha), u[:, 0], u[:, 1])
        t, _ = I.refract(jnp.asarray(wi, jnp.float32), h, jnp.float32(eta))
        t = _np(t)
        hs = -(wi + eta * t)
        hs = _unit(hs * np.sign(hs[:, 2:3]))
        assert np.all(_dot(wi, hs) > -1e-5) and np.all(_dot(t, hs) < 1e-5), "a draw where the density is 0"
        z = np.clip(t[:, 2], -1, 1)
        phi = np.mod(np.arctan2(t[:, 1], t[:, 0]), 2 * np.pi) / (2 * np.pi)
        # cells uniform in z on each side of z = -wi_z / eta, where the density jumps (see _hemisphere)
        z_jump = -wi[2] / eta
        edges = np.concatenate([np.linspace(-1, z_jump, 31), np.linspace(z_jump, 1, 11)[1:]])
        na, nb, sub = len(edges) - 1, 32, 8
        counts = np.histogram2d(z, phi, bins=[edges, np.linspace(0, 1, nb + 1)])[0]
        pts = _cells(na, nb, sub)
        width = np.diff(edges)
        zz = edges[:-1, None, None] + (pts[..., 0] * na - np.arange(na)[:, None, None]) * width[:, None, None]
        ps = pts[..., 1] * 2 * np.pi
        s = np.sqrt(1 - zz * zz)
        uu = np.stack([s * np.cos(ps), s * np.sin(ps), zz], axis=-1)
        ht = -(wi + eta * uu)
        hh = _unit(ht * np.sign(ht[..., 2:3]))
        ih, uh = _dot(wi, hh), _dot(uu, hh)
        ok = (ih > 0) & (uh < 0)
        pdf_h = _g1_np(wi, alpha) * np.clip(ih, 0, None) * _ndf_np(hh, alpha) / wi[2]
        dens = np.where(ok, pdf_h * eta ** 2 * np.abs(uh) / (ih + eta * uh) ** 2, 0.0)
        expected = dens.mean(axis=-1) * width[:, None] * (2 * np.pi / nb) * n  # d(omega) = dz dphi
        assert abs(expected.sum() / n - 1) < 2e-3, expected.sum() / n  # the density integrates to 1
        p = _chi2(counts, expected)
        lines.append(f"refraction theta {theta:g} alpha {alpha:g} eta {eta:g}: p = {p:.3g}")
        assert p > level, lines[-1]
    print("\n[chi-square] level %.2g\n" % level + "\n".join(lines))


# --- shared: walks through a query -----------------------------------------------------------------------


def _with_interface(material, eta, alpha):
    return Material(layers=material.layers, base_albedo=material.base_albedo, variant=material.variant,
                    interface=Interface(eta=eta, alpha_s=alpha))


# --- e. energy -------------------------------------------------------------------------------------------

_E_TI = (0.0, 60.0)
_E_NMU, _E_NPHI = 16, 9
_E_WALKS, _E_BOUNCES, _E_REPLICATES = 256, 96, 8


def _energy(material, alpha, lines, failures, t_star, loose=False, reflectance_at_least=None, walks=_E_WALKS):
    """Replicates of ``int f mu_o + shadowed + absorbed_base`` (and its parts) for ``material`` under ``eta = 1.5``."""
    to, po, weights = half_hemisphere_grid(_E_NMU, _E_NPHI)
    n_i, n_o = len(_E_TI), len(to)
    query = jaxcos.make_query(np.repeat(_E_TI, n_o), np.tile(to, n_i), np.tile(po, n_i))
    material = _with_interface(material, 1.5, alpha)
    wi = _dirs(np.array(_E_TI)) * np.array([-1, 1, 1])
    fs = np.asarray(I.reflection(jnp.asarray(wi, jnp.float32)[:, None], query.wo, jnp.float32(1.5),
                                 jnp.float32(alpha)), np.float64)
    r_s = np.array([_albedos_np(w, 1.5, alpha)[0] for w in wi])
    total, book, unfinished, reflectance = [], [], [], []
    for r in range(_E_REPLICATES):
        est = jaxcos.simulate(material, query, jax.random.key(30_000 + r), walks=walks, bounces=_E_BOUNCES)
        f = _np(est.f)[:, 0].reshape(n_i, n_o) - fs  # the walks' part; albedos 1: channels equal
        reflectance.append(f @ weights + r_s)
        total.append(reflectance[-1] + _np(est.shadowed + est.absorbed_base)[:, 0])
        book.append(_np(est.reflected + est.shadowed + est.absorbed_base + est.unfinished)[:, 0])
        unfinished.append(_np(est.unfinished)[:, 0])
    (total, se), (book, se_b), (refl, se_r) = [(np.mean(x, 0), np.std(x, 0, ddof=1) / math.sqrt(len(x)))
                                               for x in (total, book, reflectance)]
    unf = np.mean(unfinished, 0)
    label = f"t {float(material.layers[0].t):g}, base {material.base}, alpha_s {alpha:g}"
    for i, a in enumerate(_E_TI):
        # 1 - unfinished <= total <= 1 in expectation: flight B + 1's escape is in f, not yet in the tallies
        z = max((1 - unf[i]) - total[i], total[i] - 1, 0.0) / se[i]
        zb = abs(book[i] - 1) / max(se_b[i], 1e-7)
        line = (f"{label} ti {a:g}: int f mu = {refl[i]:.5f}, + shadowed + absorbed = {total[i]:.5f} +- {se[i]:.5f}"
                f" (z {z:.2f}), unfinished {unf[i]:.1e}; tallies {book[i]:.5f} (z {zb:.2f})")
        lines.append(line + (" [loose]" if loose else ""))
        if z > t_star or zb > t_star:
            failures.append(line)
        if reflectance_at_least is not None and not refl[i] > reflectance_at_least - t_star * se_r[i]:
            failures.append(line + f": reflectance {refl[i]:.4f} below {reflectance_at_least}")


@pytest.mark.slow
def test_energy_is_conserved_but_for_the_shadowing_loss():
    """Non-absorbing stacks under ``eta = 1.5``: the reflectance ``int f mu_o`` (quadrature of the walks' part
    over a 16 x 9 half-hemisphere grid, plus the albedo of the exact ``f_s`` by float64 quadrature over
    normals), plus the ``shadowed`` tally (and ``absorbed_base`` over a black base) is 1, given the energy
    still unfinished (``1 - unfinished <= sum <= 1`` in expectation); the walks' own tallies
    (``reflected + shadowed + absorbed_base + unfinished``) are 1 as well. Standard errors from 8 replicate
    keys (t quantile, Bonferroni).

    * A white diffusing layer (albedo 1, ``c_d`` 1, ``t = 1``) over a black base, ``alpha_s`` 0.3 (about 10%
      of the light is lost to shadowing) and 0.01.
    * A white Lambertian base under the bare interface (``t = 0``): reflectance above 0.99 at ``alpha_s``
      0.01, where the shadowing loss is below 1%.
    * A white layer (``t = 0.5``) over a white Lambertian base, ``alpha_s`` 0.3: light trapped between a
      lossless layer and base is the estimator's worst case (the throughput's variance grows at every choice
      between a boundary and the medium, docs/interface.md): its standard error is about 5%, so this case
      is a loose check.
    """
    t_star = float(stats.t.isf(1e-3 / (2 * 2 * len(_E_TI) * 5), _E_REPLICATES - 1))
    layer = lambda t: Layer(t=t, c_d=1.0, albedo_d=1.0, g1=0.5, g2=0.5, w_g=1.0, albedo_p=1.0, alpha_p=0.5,
                            theta_p=0.0)  # one HG lobe (g2 = g1): every scattering weight is exactly 1
    lines, failures = [], []
    for alpha in (0.3, 0.01):
        _energy(Material(layers=(layer(1.0),), variant="diffusers_only"), alpha, lines, failures, t_star)
    _energy(Material(layers=(layer(0.0),), base_albedo=1.0, variant="diffusers_only"), 0.01, lines, failures, t_star,
            reflectance_at_least=0.99, walks=2048)
    _energy(Material(layers=(layer(0.5),), base_albedo=1.0, variant="diffusers_only"), 0.3, lines, failures, t_star,
            loose=True)
    print(f"\n[energy] bound {t_star:.2f}\n" + "\n".join(lines))
    assert not failures, "\n".join(failures)


# --- f. reciprocity ------------------------------------------------------------------------------------

_RECIP = [(10.0, 50.0), (30.0, -60.0), (0.0, 75.0), (45.0, 20.0), (70.0, -20.0), (15.0, -80.0)]


def _reciprocal_query():
    ti, to = [], []
    for a, b in _RECIP:
        ti += [a, abs(b)]
        to += [b, a if b >= 0 else -a]
    return np.array(ti), np.array(to)


_SHARED = dict(walks=4096, bounces=24)  # one compiled program for tests f and g


@pytest.mark.slow
def test_reciprocity():
    """``f(wi, wo) = f(wo, wi)`` within standard errors (Bonferroni over pairs and channels): one layer of
    diffusers and untilted platelets (mirror-symmetric, so the swapped in-plane pair is a query of the same
    form) over a Lambertian base, under ``eta = 1.5``, ``alpha_s = 0.2``. The exit bracket's ``1 / eta^2``
    and the entry weight's lack of it only balance in the round trip: dropping either fails."""
    layer = Layer(**{**_PUB["matte1"], "t": 2.0, "theta_p": 0.0, "alpha_p": 0.3})
    material = Material(layers=(layer,), base_albedo=(0.7, 0.5, 0.3), interface=Interface(eta=1.5, alpha_s=0.2))
    ti, to = _reciprocal_query()
    est = jaxcos.simulate(material, jaxcos.make_query(ti, to), jax.random.key(11), **_SHARED)
    f, se = _np(est.f).reshape(-1, 2, 3), _np(est.stderr).reshape(-1, 2, 3)
    z = (f[:, 0] - f[:, 1]) / np.hypot(se[:, 0], se[:, 1])
    bound = _bonferroni_z(z.size)
    print(f"\n[reciprocity] |z| max {np.abs(z).max():.2f} (bound {bound:.2f}); relative SE max "
          f"{(se / f).max():.3f}")
    assert np.abs(z).max() < bound, z


# --- g. a transparent layer over a Lambertian base --------------------------------------------------------


@pytest.mark.slow
@pytest.mark.parametrize("eta, alpha", [(1.5, 0.3), (1.33, 0.12)])
def test_zero_thickness_over_lambertian_is_exact(eta, alpha):
    """``t = 0`` over a Lambertian base ``rho``: with bounces ``B`` the walks hold the base's first ``B / 2``
    reflections, so exactly

        f = f_s + rho T(wi) E(wo) / pi * sum_{n < B/2} (rho Rbar)^n,

    ``T(wi) = int f_t(wi -> u) |u_z| du`` and ``E(wo) = int f_t(wo <- v) |v_z| dv`` by quadrature of Walter's
    ``f_t`` (float64), ``Rbar`` the cosine-weighted internal reflectance (total internal reflection included)
    by quadrature over normals. Within 5 standard errors plus the quadrature error, at the pairs of the
    reciprocity test."""
    rho = np.array([0.2, 0.45, 0.6])
    layer = Layer(**{**_PUB["matte1"], "t": 0.0})
    material = Material(layers=(layer,), base_albedo=rho, interface=Interface(eta=eta, alpha_s=alpha))
    ti, to = _reciprocal_query()
    est = jaxcos.simulate(material, jaxcos.make_query(ti, to), jax.random.key(12), **_SHARED)
    wi = _dirs(ti) * np.array([-1, 1, 1])
    wo = _dirs(to)
    fs = np.asarray(I.reflection(jnp.asarray(wi, jnp.float32), jnp.asarray(wo, jnp.float32), jnp.float32(eta),
                                 jnp.float32(alpha)), np.float64)

    def transmittances(m):
        t_in, e_out = [], []
        for w in wi:
            down, w_down = _hemisphere(m, 2 * m, down=True, split=w[2] / eta)
            t_in.append(np.sum(w_down * _f_t_np(w, down, 1.0, eta, alpha) * np.abs(down[:, 2])))
        for w in wo:
            up, w_up = _hemisphere(m, 2 * m, split=w[2] / eta)
            e_out.append(np.sum(w_up * _f_t_np(-up, w, eta, 1.0, alpha) * up[:, 2]))
        return np.array(t_in), np.array(e_out)

    def rbar(m):
        x, wx = np.polynomial.legendre.leggauss(m)
        mu, w_mu = (x + 1) / 2, wx / 2
        return sum(2 * wm * m_ * _albedos_np(np.array([np.sqrt(1 - m_ * m_), 0.0, m_]), 1.0 / eta, alpha, 160, 160)[0]
                   for m_, wm in zip(mu, w_mu))

    (t1, e1), (t2, e2) = transmittances(160), transmittances(224)
    r1, r2 = rbar(48), rbar(64)
    n_terms = math.ceil(_SHARED["bounces"] / 2)
    series = lambda rb: (1 - (rho * rb) ** n_terms) / (1 - rho * rb)
    expected = fs[:, None] + (t2 * e2)[:, None] * rho * series(r2) / np.pi
    quad_err = np.abs((t2 * e2)[:, None] * series(r2) - (t1 * e1)[:, None] * series(r1)) * rho / np.pi + 1e-6
    f, se = _np(est.f), _np(est.stderr)
    z = np.clip(np.abs(f - expected) - quad_err, 0, None) / se
    print(f"\n[t = 0, eta {eta} alpha {alpha}] Rbar {r2:.5f}; max |z| {z.max():.2f}; max relative deviation "
          f"{np.max(np.abs(f / expected - 1)):.4f}; relative SE max {(se / f).max():.4f}")
    assert z.max() < 5.0, (f, expected, se)


# --- h. the smooth-boundary limit against adding-doubling -----------------------------------------------


def _iad_top_boundary_ur1(a, g, tau, n, quad_pts):
    """iadpython's total reflectance ``UR1`` of an HG slab with an air/slab boundary on top and nothing below.

    ``Sample(n=..., n_above=1, n_below=1).rt()`` would also put a slab/air boundary below (which reflects
    light back, unlike a black base): the top boundary is added to the bare slab with ``add_slide_above``
    (``n_above = 1``: no glass, the boundary is air/slab), and the bottom left index-matched.
    """
    import iadpython

    sample = iadpython.Sample(a=a, b=tau, g=g, n=n, n_above=1.0, n_below=1.0, quad_pts=quad_pts)
    sample.update_quadrature()
    r12, t12 = iadpython.simple_layer_matrices(sample)
    r01, r10, t01, t10 = iadpython.start.boundary_layer(sample, top=True)
    r02, _, t02, _ = iadpython.add_slide_above(sample, r01, r10, t01, t10, r12, r12, t12, t12)
    return float(sample.UX1_and_UXU(r02, t02)[0])


@pytest.mark.slow
def test_smooth_limit_matches_adding_doubling():
    """An HG slab (albedo 0.9, ``g`` 0.5, ``tau`` 2, index 1.5) under an almost smooth boundary (``alpha_s``
    0.01) over a black base: the total reflectance at normal incidence (``int f mu_o``: Gauss-Legendre over
    ``mu_o`` of the walks' part, plus the albedo of ``f_s`` by quadrature over normals) against adding-doubling
    (iadpython 0.5.3, :func:`_iad_top_boundary_ur1`), whose ``UR1`` includes the specular reflection. Within
    1% and 4.5 standard errors (the shadowing loss at ``alpha_s`` 0.01 is below 0.1%; iadpython's error,
    ``|R(16) - R(24)|`` (6e-5), is added)."""
    a, g, tau, n = 0.9, 0.5, 2.0, 1.5
    iad = [_iad_top_boundary_ur1(a, g, tau, n, k) for k in (16, 24)]
    layer = Layer(t=tau, c_d=1.0, albedo_d=a, g1=g, g2=g, w_g=1.0, albedo_p=0.5, alpha_p=0.5, theta_p=0.0)
    material = Material(layers=(layer,), variant="diffusers_only", interface=Interface(eta=n, alpha_s=0.01))
    x, w = np.polynomial.legendre.leggauss(16)
    mu, w_mu = (x + 1) / 2, w / 2
    to = np.degrees(np.arccos(mu))
    weights = 2 * np.pi * w_mu * mu
    r_s = _albedos_np(np.array([0.0, 0.0, 1.0]), n, 0.01)[0]
    fs = np.asarray(I.reflection(jnp.array([[0.0, 0.0, 1.0]]), jnp.asarray(_dirs(to), jnp.float32), jnp.float32(n),
                                 jnp.float32(0.01)), np.float64)
    query = jaxcos.make_query(np.zeros_like(to), to)
    runs = []
    for r in range(8):
        est = jaxcos.simulate(material, query, jax.random.key(40_000 + r), walks=4096, bounces=96)
        runs.append(weights @ (_np(est.f)[:, 0] - fs) + r_s)
    total, se = np.mean(runs), np.std(runs, ddof=1) / math.sqrt(len(runs))
    iad_err = abs(iad[1] - iad[0])
    print(f"\n[smooth limit] walks {total:.5f} +- {se:.5f}, adding-doubling {iad[1]:.5f} (+- {iad_err:.1e}), "
          f"specular {r_s:.5f}")
    assert abs(total - iad[1]) < 0.01 * iad[1] + iad_err
    assert abs(total - iad[1]) < 4.5 * se + iad_err


# --- i. derivatives -------------------------------------------------------------------------------------

_G_TI = [20.0, 20.0, 60.0, 60.0]
_G_TO = [-30.0, 25.0, 58.0, 80.0]
_G_KEYS = 64


def _flat_material(v, lambertian):
    layer = Layer(t=v[0], c_d=v[1], albedo_d=v[2:5], g1=v[5], g2=v[6], w_g=v[7], albedo_p=v[8:11],
                  alpha_p=v[11], theta_p=v[12], phi_p=v[13])
    return Material(layers=(layer,), base_albedo=v[14:17] if lambertian else None,
                    interface=Interface(eta=v[17], alpha_s=v[18]))


_G_NAMES = ("t", "c_d", "albedo_d0", "albedo_d1", "albedo_d2", "g1", "g2", "w_g", "albedo_p0", "albedo_p1", "albedo_p2",
            "alpha_p", "theta_p", "phi_p", "base0", "base1", "base2", "eta", "alpha_s")


@pytest.mark.slow
def test_gradients_match_finite_differences():
    """Forward-mode derivatives along ``eta``, ``alpha_s`` and a random direction in all 19 parameters
    (Lambertian base) against central finite differences under common random numbers (the same keys, lobe
    and boundary probabilities held fixed), over 64 keys of 16 walks.

    Unbiasedness: the mean of AD - FD is within 4.5 standard errors of its spread over keys. A jump of the
    estimate (a decision whose probability moved with the parameter, a weight that did not vanish where its
    draw becomes invalid) puts into FD a boundary term that AD lacks, whatever the step.

    Per key the estimate is continuous but not everywhere smooth: Fresnel's reflectance has an infinite
    derivative at the critical angle (``1 - F ~ sqrt(c - c_crit)``), so a walk reflected from below near it
    gives a key whose AD derivative is large and whose finite difference is not (measured: such kinks, not
    jumps, explain the keys where the two differ). So per key only the typical agreement is asserted: the
    median of ``|AD - FD|`` is below 5% of the derivative's spread over keys."""
    query = jaxcos.make_query(_G_TI, _G_TO)
    v0 = np.array([2.0, 0.7, 0.9, 0.8, 0.7, 0.5, -0.2, 0.7, 0.9, 0.85, 0.8, 0.3, 10.0, 20.0, 0.5, 0.4, 0.3, 1.5, 0.2],
                  np.float32)
    lp = jaxcos.lobe_probabilities(_flat_material(jnp.asarray(v0), True))
    weights = jnp.asarray(np.random.default_rng(0).uniform(0.5, 1.5, (len(_G_TI), 3)), jnp.float32)

    def scalar(v, key):
        est = jaxcos.simulate(_flat_material(v, True), query, key, walks=16, bounces=32, lobe_probs=lp,
                              boundary_prob=0.3)
        return jnp.sum(est.f * weights)

    run = jax.jit(jax.vmap(lambda v, dv, key: jax.jvp(lambda x: scalar(x, key), (v,), (dv,)), in_axes=(None, None, 0)))
    keys = jax.random.split(jax.random.key(21), _G_KEYS)
    rng = np.random.default_rng(1)
    scale = np.abs(v0) * 0.02 + 0.01
    random_dir = (rng.normal(size=v0.size) * scale).astype(np.float32)
    directions = {"eta": np.eye(v0.size, dtype=np.float32)[17] * 0.003,
                  "alpha_s": np.eye(v0.size, dtype=np.float32)[18] * 0.003,
                  "all": random_dir * 0.3}
    lines, failures = [], []
    for name, dv in directions.items():
        _, ad = run(jnp.asarray(v0), jnp.asarray(dv), keys)
        plus, _ = run(jnp.asarray(v0 + dv), jnp.asarray(dv), keys)
        minus, _ = run(jnp.asarray(v0 - dv), jnp.asarray(dv), keys)
        ad, fd = _np(ad), (_np(plus) - _np(minus)) / 2
        diff = ad - fd
        z = diff.mean() / (diff.std(ddof=1) / math.sqrt(_G_KEYS))
        typical = np.median(np.abs(diff)) / ad.std()
        line = (f"{name}: AD {ad.mean():+.6f}, FD {fd.mean():+.6f} (spread over keys {ad.std():.5f}); "
                f"z {z:+.2f}; per-key |AD - FD| / spread: median {typical:.3f}, max {np.abs(diff).max() / ad.std():.2f}")
        lines.append(line)
        assert np.all(np.isfinite(ad)) and np.all(np.isfinite(fd))
        if abs(z) > 4.5 or typical > 0.05:
            failures.append(line)
        assert abs(ad.mean()) > 3 * ad.std() / math.sqrt(_G_KEYS), f"{name}: no measurable derivative; {line}"
    print("\n[derivatives]\n" + "\n".join(lines))
    assert not failures, "\n".join(failures)


def _hard_interface_materials(lambertian):
    """Hard values inside one structure: alpha_s 0.005 and 1, eta 1.01 and 2.5, t 0 and 16, narrow and
    broad platelets, strong forward scattering."""
    out = []
    for i, (a_s, eta, t, a_p) in enumerate(__import__("itertools").product((0.005, 1.0), (1.01, 2.5), (0.0, 16.0),
                                                                           (0.002, 1.0))):
        layer = Layer(t=t, c_d=0.5, albedo_d=(1.0, 0.5, 0.0), g1=0.99 if i % 2 else 0.0, g2=-0.5, w_g=0.5,
                      albedo_p=(0.0, 0.5, 1.0), alpha_p=a_p, theta_p=(0.0, 45.0, 89.0)[i % 3], phi_p=0.0)
        out.append(Material(layers=(layer,), base_albedo=(1.0, 0.5, 0.0) if lambertian else None,
                            interface=Interface(eta=eta, alpha_s=a_s)))
    return out


@pytest.mark.slow
@pytest.mark.parametrize("lambertian, mode", [(False, "exact"), (True, "mc")])
def test_hard_cases_are_finite(lambertian, mode):
    """Values, standard errors, tallies and the forward derivative along every parameter at once (tangent 1
    on every leaf: a non-finite partial derivative makes it non-finite) are finite at alpha_s 0.005 and 1,
    eta 1.01 and 2.5, t 0 and 16, alpha_p 0.002 and 1, g 0.99, normal, grazing (85-89.9 degrees) and mirror
    directions, over black and Lambertian bases (total internal reflection occurs inside at every eta);
    and f and the tallies are non-negative."""
    ti = [0.0, 0.0, 45.0, 45.0, 85.0, 85.0, 89.0, 89.0]
    to = [0.0, 89.9, 45.0, -85.0, 85.0, 60.0, 89.0, -89.0]
    query = jaxcos.make_query(ti, to)
    materials = _hard_interface_materials(lambertian)
    stacked = jax.tree.map(lambda *x: jnp.stack(x), *materials)

    def one(m):
        def est(m):
            e = jaxcos.simulate(m, query, jax.random.key(50), walks=8, bounces=16, single_scattering=mode)
            return e.f, (e.stderr, e.reflected, e.unfinished, e.shadowed, e.absorbed_base)
        tangent = jax.tree.map(jnp.ones_like, m)
        (f, rest), (df, _) = jax.jvp(est, (m,), (tangent,))
        return f, rest, df

    f, rest, df = jax.jit(lambda ms: jax.lax.map(one, ms))(stacked)
    for name, a in [("f", f), ("df", df)] + list(zip(("stderr", "reflected", "unfinished", "shadowed", "absorbed"), rest)):
        a = np.asarray(a)
        bad = np.flatnonzero(~np.isfinite(a).reshape(len(materials), -1).all(axis=1))
        assert bad.size == 0, f"{name} not finite for materials {bad.tolist()}"
        if name not in ("df", "stderr"):
            assert np.all(a >= -1e-6), name


# --- j. params.json ----------------------------------------------------------------------------------------


def test_params_json_round_trip_and_unknown_keys(tmp_path):
    """The interface is written only when present and read back; a misspelt top-level key, a key inside the
    interface or a value out of range is an error that names the file and the key."""
    m = _with_interface(jaxcos.published("dewy1"), 1.45, 0.08)
    path = tmp_path / "params.json"
    jaxcos.save_params(m, path, extra={"fit": {"loss": 1.0}})
    data = json.loads(path.read_text())
    assert data["interface"] == pytest.approx({"eta": 1.45, "alpha_s": 0.08})
    back = jaxcos.load_params(path)
    assert float(back.interface.eta) == pytest.approx(1.45) and float(back.interface.alpha_s) == pytest.approx(0.08)
    plain = tmp_path / "plain.json"
    jaxcos.save_params(jaxcos.published("dewy1"), plain)
    assert "interface" not in json.loads(plain.read_text())
    assert jaxcos.load_params(plain).interface is None
    from jaxcos._errors import InputError

    plain_data = {k: v for k, v in data.items() if k != "interface"}
    bad_cases = {
        "interfac": ({**plain_data, "interfac": data["interface"]}, "interfac"),
        "eta": ({**data, "interface": {"eta": 1.0, "alpha_s": 0.1}}, "eta"),
        "alpha_s": ({**data, "interface": {"eta": 1.5, "alpha_s": 0.0}}, "alpha_s"),
        "extra key": ({**data, "interface": {"eta": 1.5, "alpha_s": 0.1, "ior": 1.5}}, "ior"),
        "missing": ({**data, "interface": {"eta": 1.5}}, "alpha_s"),
        "type": ({**data, "interface": 1.5}, "interface"),
    }
    for label, (content, key) in bad_cases.items():
        p = tmp_path / f"{label.replace(' ', '_')}.json"
        p.write_text(json.dumps(content))
        with pytest.raises(InputError, match=key) as err:
            jaxcos.load_params(p)
        assert str(p) in str(err.value), label


def test_interface_values_are_checked_and_variants_keep_it():
    with pytest.raises(ValueError, match="eta"):
        Interface(eta=1.0, alpha_s=0.1)
    with pytest.raises(ValueError, match="alpha_s"):
        Interface(eta=1.5, alpha_s=0.0)
    m = _with_interface(jaxcos.published("matte2"), 1.5, 0.2)
    assert jaxcos.with_variant(m, "single_lobe").interface is m.interface
    assert [jax.tree_util.keystr(p) for p, _ in jax.tree_util.tree_flatten_with_path(m)[0]][-2:] == [
        ".interface.eta", ".interface.alpha_s"]


def test_mis_connection_falls_back_to_next_event_estimation():
    """Under an interface ``connection="mis"`` is next-event estimation (the backward platelet strategy does
    not go through the boundary): the same numbers."""
    m = _with_interface(jaxcos.published("dewy2", t=2.0), 1.5, 0.1)
    query = jaxcos.make_query([20.0], [25.0])
    run = lambda c: np.asarray(jaxcos.simulate(m, query, jax.random.key(2), walks=4, bounces=4, connection=c).f)
    np.testing.assert_array_equal(run("mis"), run("nee"))
