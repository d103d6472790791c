"""The optional rough dielectric top interface (docs/model.md section 3a; derivation in docs/interface.md).

A boundary between air (index 1) and the stack (index ``eta > 1``): isotropic
Trowbridge-Reitz (GGX) microfacets of roughness ``alpha_s`` about the
macro-normal ``+z``, height-correlated Smith shadowing, exact unpolarised
Fresnel reflectance. Its reflection outside, :func:`reflection`, is a closed
form; light crossing it or reflected from below is sampled by visible
normals (:func:`sample_visible_normal`), and the samplers return the
weights ``f |cos| / pdf`` that the walk multiplies in:

* :func:`enter`: refraction of ``wi`` into the stack, weight
  ``(1 - F(wi.h; eta)) G2(wi, u) / G1(wi)``; the reflection through the same
  normal and the energy lost to shadowing come with it (tallies);
* :func:`leave`: a direction ``v`` inside that leaves towards ``wo``, drawn from
  the interface as seen from ``wo``, weight
  ``(1 - F(wo.h; eta)) G2(wo, v) / (G1(wo) eta^2)``;
* :func:`reflect_inside`: reflection of light that meets the boundary from
  below, weight ``F(a.h; 1 / eta) G2(a, r) / G1(a)`` (total internal reflection
  included), with the transmitted and lost fractions as tallies.

Conventions: directions are unit 3-vectors on the last axis. A direction
"pointing away" from the boundary on the air side has ``z > 0``; the
microfacet normal ``h`` always has ``h_z >= 0``. Every sampler is
reparameterized: given uniform numbers it returns a direction and a weight
that are continuous functions of ``eta`` and ``alpha_s``, and a weight goes
to zero continuously wherever a draw becomes invalid (a refracted or
reflected direction reaching the horizon: ``G2 -> 0`` there), so masking
invalid draws is no parameter-dependent decision (derivatives stay
unbiased). Gradients are finite at ``alpha_s`` down to 1e-3, grazing
directions, normal incidence and the critical angle (double ``where``).
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from . import _phase as P

_TINY = 1e-30


def _scalar(x):
    return jnp.asarray(x, dtype=jnp.result_type(float))


class Interface(eqx.Module):
    """A rough dielectric top boundary (docs/model.md section 3a).

    Attributes:
        eta: index of refraction of the stack relative to air, ``> 1``. An
            index-matched top (``eta = 1``) is ``Material(interface=None)``, a
            structural choice, never a value of ``eta``.
        alpha_s: GGX roughness of the boundary, in ``(0, 1]``.

    Example::

        import jaxcos
        m = jaxcos.Material(layers=jaxcos.published("dewy1").layers,
                            interface=jaxcos.Interface(eta=1.5, alpha_s=0.1))
    """

    eta: jnp.ndarray = eqx.field(converter=_scalar)
    alpha_s: jnp.ndarray = eqx.field(converter=_scalar)

    def __check_init__(self):
        # concrete values only: inside jit/vmap the leaves are tracers (checked by whoever built them)
        if isinstance(self.eta, jax.core.Tracer) or isinstance(self.alpha_s, jax.core.Tracer):
            return
        try:
            eta, alpha = np.asarray(self.eta), np.asarray(self.alpha_s)
        except Exception:  # not a plain array (e.g. a placeholder of a tree transformation)
            return
        if eta.dtype.kind == "f" and not np.all(eta > 1.0):
            raise ValueError(f"Interface: eta = {eta} must be greater than 1 (an index-matched top is interface=None).")
        if alpha.dtype.kind == "f" and not np.all((alpha > 0.0) & (alpha <= 1.0)):
            raise ValueError(f"Interface: alpha_s = {alpha} must be in (0, 1].")


# --- GGX and Smith ----------------------------------------------------------------
#
# The samplers run once per walk, outgoing direction and step, so they are written on separate
# x, y, z components: XLA fuses the chain into one loop, where stacked (..., 3) intermediates
# (normalisations of stacked vectors) made it recompute the chain per component (4x the cost).


def _xyz(w):
    return w[..., 0], w[..., 1], w[..., 2]


def _stack(x, y, z):
    x, y, z = jnp.broadcast_arrays(x, y, z)
    return jnp.stack([x, y, z], axis=-1)


def _ndf(x, y, z, alpha):
    a2 = alpha * alpha
    xy = x * x + y * y
    zz = z * z
    q = xy + a2 * zz
    ok = jnp.logical_and(z > 0, q > _TINY)
    q = jnp.where(ok, q, 1.0)
    n2 = xy + zz
    return jnp.where(ok, a2 * (n2 / q) * (n2 / q) / jnp.pi, 0.0)


def ggx_ndf(h, alpha):
    """GGX normal distribution ``D(h)`` in 1/sr for a unit or unnormalised ``h`` (0 where ``h_z <= 0``).

    ``alpha^2 |h|^4 / (pi (h_x^2 + h_y^2 + alpha^2 h_z^2)^2)``: the stable form of
    docs/model.md section 7 (no cancellation at ``h_z = 1``), homogeneous of
    degree 0 in ``h``.
    """
    return _ndf(*_xyz(h), alpha)


def _smith_xyz(x, y, z, alpha):
    """``(num, den)`` with Smith's ``Lambda = num / den`` (``den = 0`` at the horizon, where ``Lambda`` is infinite).

    ``Lambda = (sqrt(1 + alpha^2 tan^2) - 1) / 2 = alpha^2 s^2 / (2 |w_z| (|w_z| + sqrt(w_z^2 + alpha^2 s^2)))``
    with ``s^2 = w_x^2 + w_y^2``: no cancellation near the normal, no division by ``w_z``.
    """
    num = alpha * alpha * (x * x + y * y)
    az = jnp.abs(z)
    r = jnp.sqrt(az * az + num)  # > 0 for a unit vector and alpha > 0
    return num, 2.0 * az * (az + r)


def _ratio(num, den):
    """``num / den``, 0 where ``den`` is 0 (finite gradient there)."""
    ok = den > 0
    return jnp.where(ok, num / jnp.where(ok, den, 1.0), 0.0)


def smith_lambda(w, alpha):
    """Smith's ``Lambda(w)`` for GGX (infinite at the horizon)."""
    num, den = _smith_xyz(*_xyz(w), alpha)
    return jnp.where(den > 0, num / jnp.where(den > 0, den, 1.0), jnp.inf)


def smith_g1(w, alpha):
    """Masking ``G1(w) = 1 / (1 + Lambda(w))``, in ``[0, 1]``; 0 at the horizon."""
    num, den = _smith_xyz(*_xyz(w), alpha)
    return _ratio(den, den + num)


def _g2(sa, sb, over_g1=False):
    """``G2`` (or ``G2 / G1(a)``) from the ``(num, den)`` of ``Lambda(a)`` and ``Lambda(b)``."""
    (na, da), (nb, db) = sa, sb
    total = da * db + na * db + nb * da
    return _ratio(db * (da + na) if over_g1 else da * db, total)


def smith_g2(a, b, alpha):
    """Height-correlated masking-shadowing ``G2(a, b) = 1 / (1 + Lambda(a) + Lambda(b))``.

    Depends on ``|a_z|``, ``|b_z|`` only, so directions on either side of the boundary may be given.
    """
    return _g2(_smith_xyz(*_xyz(a), alpha), _smith_xyz(*_xyz(b), alpha))


def smith_g2_over_g1(a, b, alpha):
    """``G2(a, b) / G1(a) = (1 + Lambda(a)) / (1 + Lambda(a) + Lambda(b))``, in ``[0, 1]``, finite at the horizon."""
    return _g2(_smith_xyz(*_xyz(a), alpha), _smith_xyz(*_xyz(b), alpha), over_g1=True)


# --- Fresnel, reflection and refraction ---------------------------------------------


def fresnel(c, n):
    """Exact unpolarised Fresnel reflectance for the cosine ``c >= 0`` on the incident side, relative index ``n``.

    ``n = n_2 / n_1`` (towards the other side over this side); 1 at total
    internal reflection. Walter et al. (2007) eq. 22:
    ``F = (g - c)^2 / (2 (g + c)^2) (1 + ((c (g + c) - 1) / (c (g - c) + 1))^2)``,
    ``g^2 = n^2 - 1 + c^2``, with ``g - c = (n^2 - 1) / (g + c)`` (no cancellation as
    ``n -> 1``). Continuous at the critical angle (``F -> 1``); its derivative
    there is infinite in theory, large but finite here (``g^2 > 1e-12``).
    """
    c = jnp.clip(c, 0.0, 1.0)
    n2m1 = n * n - 1.0
    g2 = n2m1 + c * c
    ok = g2 > 1e-12
    g = jnp.sqrt(jnp.where(ok, g2, 1.0))
    gpc = g + c
    a = n2m1 / (gpc * gpc)  # (g - c) / (g + c)
    b = (c * gpc - 1.0) / (c * n2m1 / gpc + 1.0)
    return jnp.where(ok, 0.5 * a * a * (1.0 + b * b), 1.0)


def _reflect_xyz(w, h):
    (x, y, z), (hx, hy, hz) = w, h
    c2 = 2.0 * (x * hx + y * hy + z * hz)
    return c2 * hx - x, c2 * hy - y, c2 * hz - z


def reflect(w, h):
    """Mirror ``w`` about the normal ``h``: ``2 (w.h) h - w`` (both pointing away from the surface)."""
    return _stack(*_reflect_xyz(_xyz(w), _xyz(h)))


def _refract_xyz(w, h, n):
    (x, y, z), (hx, hy, hz) = w, h
    c = x * hx + y * hy + z * hz
    cx, cy, cz = y * hz - z * hy, z * hx - x * hz, x * hy - y * hx
    inv = 1.0 / n
    ct2 = 1.0 - (cx * cx + cy * cy + cz * cz) * inv * inv  # cos^2 of the transmitted angle, without 1 - c^2
    ok = ct2 > 0
    k = c * inv - jnp.sqrt(jnp.where(ok, ct2, 1.0))
    return (k * hx - inv * x, k * hy - inv * y, k * hz - inv * z), ok


def refract(w, h, n):
    """Refraction of ``w`` (pointing away from the surface on its side, ``w.h > 0``) through the normal ``h``.

    ``n``: index of the far side over that of ``w``'s side. Returns the
    transmitted direction (pointing away on the far side, ``t.h < 0``) and
    whether it exists (``False`` at total internal reflection, where the
    direction returned is finite but meaningless).
    """
    t, ok = _refract_xyz(_xyz(w), _xyz(h), n)
    return _stack(*t), ok


# --- visible normals ----------------------------------------------------------------


def _sincos_2pi(u):
    """``(cos 2 pi u, sin 2 pi u)`` for ``u`` in ``[0, 1)``, by polynomials (absolute error < 1e-7).

    XLA's ``cos`` and ``sin`` on CPU cost about 20 ns each, as much as a whole
    next-event connection; these run once per walk, outgoing direction and
    step. Half angle ``y = pi (u - 1/2)`` in ``[-pi/2, pi/2)``: Taylor polynomials of
    ``sin y`` (to ``y^11``) and ``cos y`` (to ``y^12``), then double angle.
    """
    y = jnp.pi * (u - 0.5)
    y2 = y * y
    s = y * (1.0 + y2 * (-1.0 / 6 + y2 * (1.0 / 120 + y2 * (-1.0 / 5040 + y2 * (1.0 / 362880 - y2 / 39916800)))))
    c = 1.0 + y2 * (-0.5 + y2 * (1.0 / 24 + y2 * (-1.0 / 720 + y2 * (1.0 / 40320 + y2 * (-1.0 / 3628800
                                                                                     + y2 / 479001600)))))
    return s * s - c * c, -2.0 * s * c  # cos(2y + pi), sin(2y + pi)


def _vndf_xyz(w, alpha, u1, u2):
    x, y, z = w
    sx, sy = alpha * x, alpha * y
    inv = jax.lax.rsqrt(sx * sx + sy * sy + z * z)
    sx, sy, sz = sx * inv, sy * inv, z * inv
    # the cap's height c = (1 - u1)(1 + sz) - sz, in (-sz, 1]; 1 - c and c + sz without cancellation
    one_minus_c = u1 * (1.0 + sz)
    c_plus_sz = (1.0 - u1) * (1.0 + sz)
    sin_t = jnp.sqrt(jnp.maximum(one_minus_c * (c_plus_sz + (1.0 - sz)), 1e-30))
    cos_p, sin_p = _sincos_2pi(u2)
    hx = alpha * (sx + sin_t * cos_p)
    hy = alpha * (sy + sin_t * sin_p)
    hz = c_plus_sz  # sz + c, exactly non-negative
    n2 = hx * hx + hy * hy + hz * hz
    ok = n2 > 1e-30
    inv = jax.lax.rsqrt(jnp.where(ok, n2, 1.0))
    return jnp.where(ok, hx * inv, 0.0), jnp.where(ok, hy * inv, 0.0), jnp.where(ok, hz * inv, 1.0)


def sample_visible_normal(w, alpha, u1, u2):
    """A microfacet normal drawn from the distribution of normals visible from ``w`` (``w_z > 0``).

    Density ``D_w(h) = G1(w) max(0, w.h) D(h) / w_z``. Heitz (2018) in the form
    of Dupuy and Benyoub (2023): in the configuration stretched to
    ``alpha = 1``, the visible normal is ``w_std + c`` with ``c`` uniform on the
    spherical cap ``c_z >= -w_std.z`` (no tangent frame: nothing is
    discontinuous in ``w``), then un-stretched. ``u1``, ``u2``: uniforms in
    ``[0, 1)``. Reparameterized (smooth in ``alpha`` and ``w``).
    """
    return _stack(*_vndf_xyz(_xyz(w), alpha, u1, u2))


def visible_normal_pdf(w, h, alpha):
    """The density of :func:`sample_visible_normal`: ``G1(w) max(0, w.h) D(h) / w_z`` (1/sr)."""
    return smith_g1(w, alpha) * jnp.maximum(P.dot(w, h), 0.0) * ggx_ndf(h, alpha) / w[..., 2]


# --- what the walk uses -------------------------------------------------------------------


def reflection(wi, wo, eta, alpha, min_mu=1e-6):
    """The reflection outside, ``f_s(wi, wo) = F(wi.h; eta) D(h) G2(wi, wo) / (4 mu_i mu_o)`` in 1/sr.

    ``h = normalize(wi + wo)``; ``wi``, ``wo`` above the surface (``mu`` floored
    at ``min_mu``), broadcast against each other. An exact term of the BSDF,
    never sampled.
    """
    d = wi + wo
    n2 = P.dot(d, d)
    ok = n2 > 1e-20
    # wi.h = |wi + wo| / 2 for unit vectors: symmetric, and no cancellation in 1 + wi.wo at grazing mirror pairs
    c = 0.5 * jnp.sqrt(jnp.where(ok, n2, 1.0))
    mu_i = jnp.maximum(wi[..., 2], min_mu)
    mu_o = jnp.maximum(wo[..., 2], min_mu)
    value = fresnel(c, eta) * ggx_ndf(d, alpha) * smith_g2(wi, wo, alpha) / (4.0 * mu_i * mu_o)
    return jnp.where(ok, value, 0.0)


def enter(wi, eta, alpha, u1, u2):
    """Light from ``wi`` (above, ``wi_z > 0``) meets the boundary: one visible normal, both of its branches.

    Returns ``(u, w_t, w_r, lost)``:

    * ``u``: the refracted propagation direction (``u_z < 0``; ``-z`` where the
      refracted ray would leave the stack, whose weight is 0),
    * ``w_t = (1 - F(wi.h; eta)) G2(wi, u) / G1(wi)`` (0 unless ``u_z < 0``): the
      walk's starting throughput, ``f_t(wi -> u) |u_z| / pdf(u)``,
    * ``w_r = F(wi.h; eta) G2(wi, r) / G1(wi)`` (0 unless ``r_z > 0``), ``r`` the
      reflection through the same normal: a sample of the reflection's
      directional albedo ``int f_s mu_o`` (the reflection itself is :func:`reflection`),
    * ``lost = 1 - w_t - w_r >= 0``: a sample of the energy removed by shadowing.
    """
    w = _xyz(wi)
    h = _vndf_xyz(w, alpha, u1, u2)
    f = fresnel(w[0] * h[0] + w[1] * h[1] + w[2] * h[2], eta)
    t, _ = _refract_xyz(w, h, eta)  # always exists entering a denser medium
    r = _reflect_xyz(w, h)
    s_w = _smith_xyz(*w, alpha)
    ok_t = t[2] < 0
    ok_r = r[2] > 0
    w_t = jnp.where(ok_t, (1.0 - f) * _g2(s_w, _smith_xyz(*t, alpha), True), 0.0)
    w_r = jnp.where(ok_r, f * _g2(s_w, _smith_xyz(*r, alpha), True), 0.0)
    u = _stack(jnp.where(ok_t, t[0], 0.0), jnp.where(ok_t, t[1], 0.0), jnp.where(ok_t, t[2], -1.0))
    return u, w_t, w_r, 1.0 - w_t - w_r


def leave(wo, eta, alpha, u1, u2):
    """A direction ``v`` inside (propagating up, ``v_z > 0``) that leaves towards ``wo``, and its bracket.

    ``v`` is the reverse of the refraction of ``wo`` through a normal visible
    from ``wo``; the bracket is ``f_t(wo <- v) |v_z| / pdf(v) =
    (1 - F(wo.h; eta)) G2(wo, v) / (G1(wo) eta^2)`` (0, and ``v = +z``, where the
    refracted ray would not enter the stack).
    """
    w = _xyz(wo)
    h = _vndf_xyz(w, alpha, u1, u2)
    f = fresnel(w[0] * h[0] + w[1] * h[1] + w[2] * h[2], eta)
    t, _ = _refract_xyz(w, h, eta)
    ok = t[2] < 0
    bracket = jnp.where(ok, (1.0 - f) * _g2(_smith_xyz(*w, alpha), _smith_xyz(*t, alpha), True) / (eta * eta), 0.0)
    v = _stack(jnp.where(ok, -t[0], 0.0), jnp.where(ok, -t[1], 0.0), jnp.where(ok, -t[2], 1.0))
    return v, bracket


def reflect_inside(w, eta, alpha, u1, u2):
    """Light propagating up along ``w`` (``w_z > 0``) meets the boundary from below.

    In the frame mirrored in the boundary, ``a = flip(-w)`` is above it; a
    normal visible from ``a`` is drawn, and both branches through it are
    evaluated. Returns ``(r, w_r, w_t, lost)``:

    * ``r``: the reflected propagation direction (``r_z < 0``; ``-z`` where the
      reflection would leave the stack, whose weight is 0),
    * ``w_r = F(a.h; 1 / eta) G2(a, r) / G1(a)`` (``F = 1`` at total internal
      reflection): the walk's throughput factor,
    * ``w_t = (1 - F) G2(a, t) / G1(a)`` for the refracted ``t`` (0 at total
      internal reflection): a sample of the fraction that leaves (a tally;
      next-event estimation accounts for that light),
    * ``lost = 1 - w_r - w_t >= 0``: the fraction removed by shadowing.
    """
    x, y, z = _xyz(w)
    a = (-x, -y, z)  # flip(-w)
    h = _vndf_xyz(a, alpha, u1, u2)
    n = 1.0 / eta
    f = fresnel(a[0] * h[0] + a[1] * h[1] + a[2] * h[2], n)
    r = _reflect_xyz(a, h)
    t, exists = _refract_xyz(a, h, n)
    s_a = _smith_xyz(*a, alpha)
    ok_r = r[2] > 0
    ok_t = jnp.logical_and(exists, t[2] < 0)
    w_r = jnp.where(ok_r, f * _g2(s_a, _smith_xyz(*r, alpha), True), 0.0)
    w_t = jnp.where(ok_t, (1.0 - f) * _g2(s_a, _smith_xyz(*t, alpha), True), 0.0)
    r = _stack(jnp.where(ok_r, r[0], 0.0), jnp.where(ok_r, r[1], 0.0), jnp.where(ok_r, -r[2], -1.0))
    return r, w_r, w_t, 1.0 - w_r - w_t
