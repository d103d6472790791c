"""Phase functions and their samplers: Henyey-Greenstein and SGGX specular flakes.

Conventions (docs/model.md sections 1, 2 and 7):

* Directions are unit 3-vectors on the last axis, ``(..., 3)``. A phase function
  ``f(w -> w')`` takes *propagation* directions: ``w`` is where light travels
  before the event, ``w'`` after it. Values are densities over the sphere of
  ``w'`` in 1/sr; each integrates to 1.
* Henyey-Greenstein ``g > 0`` scatters forward (``w' = w``).
* SGGX platelets have mean normal ``m`` (unit vector) and roughness
  ``alpha`` in ``(0, 1]``; their matrix is ``S = alpha^2 I + (1 - alpha^2) m m^T``.

Every formula is written so that float32 stays accurate and gradients stay
finite at the hard cases: ``|g|`` near 0 and near 1, ``alpha`` down to 1e-4,
the exact forward direction ``w' = w`` and grazing directions. Samplers are
reparameterized: given uniform numbers (and a uniform point on the sphere) they return a
direction that is a smooth function of the parameters.
"""

import jax
import jax.numpy as jnp

_TINY = 1e-30


def dot(a, b):
    """Dot product over the last axis.

    Written out per component: elementwise arithmetic fuses into one loop in
    XLA, where a reduction over an axis of length 3 would break the fusion of
    the hot next-event loop.
    """
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


def safe_normalize(v, fallback):
    """``v / |v|``, or ``fallback`` (broadcastable, unit) where ``|v|`` is ~0.

    A double ``where`` keeps the gradient finite at ``v = 0``.
    """
    n2 = dot(v, v)
    ok = n2 > 1e-20
    n2_safe = jnp.where(ok, n2, 1.0)
    return jnp.where(ok[..., None], v / jnp.sqrt(n2_safe)[..., None], fallback)


def normalize(v):
    """``v / |v|`` for vectors known to be far from zero."""
    return v / jnp.sqrt(dot(v, v))[..., None]


def uniform_sphere(u1, u2):
    """A uniformly distributed unit vector from two uniforms in ``[0, 1)``."""
    z = 1.0 - 2.0 * u1
    r = jnp.sqrt(jnp.maximum((1.0 - z) * (1.0 + z), 0.0))
    phi = 2.0 * jnp.pi * u2
    return jnp.stack([r * jnp.cos(phi), r * jnp.sin(phi), z], axis=-1)


def _any_perp(n):
    """A unit vector normal to the unit vector ``n``: the fallback of :func:`_around` where ``s = +-n``.

    (``uniform_sphere(0, .)`` is exactly ``+z``, so ``s = +-n`` does occur, e.g. at
    normal incidence, where ``n = -z``.) Discontinuous in ``n``, which is harmless
    at an isolated random point; finite, with finite gradients, everywhere.
    """
    x, y, z = n[..., 0], n[..., 1], n[..., 2]
    zero = jnp.zeros_like(x)
    t = jnp.where(
        (jnp.abs(z) < 0.9)[..., None],
        jnp.stack([-y, x, zero], axis=-1),
        jnp.stack([zero, -z, y], axis=-1),
    )
    return normalize(t)


def _around(n, cos_theta, s, sin_theta=None):
    """The direction at polar angle ``acos(cos_theta)`` about ``n``, azimuth given by ``s``.

    ``s`` is a uniform point on the sphere (:func:`uniform_sphere`); its
    component perpendicular to ``n`` is a uniformly distributed azimuth. No
    tangent frame is built: every frame field on the sphere is discontinuous
    somewhere (a branchless one along a whole great circle), and under common
    random numbers a walk crossing it would jump. This construction is
    singular only at the isolated random point ``s = +-n``. ``sin_theta``, if
    given, must equal ``sqrt(1 - cos_theta^2)``; callers that can form it without
    the cancellation in ``1 -+ cos_theta`` near the poles should.
    """
    perp = safe_normalize(s - dot(s, n)[..., None] * n, _any_perp(n))
    if sin_theta is None:
        sin_theta = jnp.sqrt(jnp.maximum((1.0 - cos_theta) * (1.0 + cos_theta), 1e-20))
    return cos_theta[..., None] * n + sin_theta[..., None] * perp


# --- Henyey-Greenstein -------------------------------------------------------


def hg(w, w_out, g):
    """Henyey-Greenstein phase function ``f_HG(w . w'; g)`` in 1/sr.

    ``1 + g^2 - 2 g c`` is formed as the sum of non-negative terms
    ``(1 - |g|)^2 + |g| |w' - sign(g) w|^2``, so it keeps its relative accuracy
    near the peak as ``|g| -> 1``.
    """
    a = jnp.abs(g)
    d = w_out - jnp.where(g >= 0, 1.0, -1.0)[..., None] * w
    base = jnp.maximum((1.0 - a) ** 2 + a * dot(d, d), _TINY)
    r = jax.lax.rsqrt(base)
    return (1.0 - g * g) * (0.25 / jnp.pi) * (r * r * r)


def hg_sample(w, g, u1, s):
    """Draw ``w'`` from ``f_HG(w -> .; g)``: ``u1`` in ``[0, 1)`` sets the polar angle, ``s`` the azimuth.

    ``s``: a uniform unit vector (:func:`uniform_sphere`). The polar angle
    inverts the CDF of the cosine.

    The usual inverse ``(1 + g^2 - s^2) / (2 g)`` divides by ``g``; the
    algebraically equal form
    ``c = (2 (1 + g^2) u (1 - g + g u) - (1 - g)^2) / (1 - g + 2 g u)^2``
    does not, so ``g = 0`` (isotropic) needs no special case. That form still
    cancels O(4) terms down to ``O(d^2)``, ``d = 1 - g + 2 g u``, where ``g -> -1``
    and ``u -> 1`` (cosine errors of 0.2 at ``g = -0.999``), and rounding ``c`` to
    float32 (steps of 6e-8 below 1) puts the polar angle near ``c = +-1`` on a
    grid of ``sqrt(2k) 2.4e-4`` rad, as wide as the ``1 - |g|`` lobe at
    ``|g| = 0.999``. So, with ``a = |g|`` and ``f_HG(c; -a) = f_HG(-c; a)``
    (i.e. ``c(u; -a) = -c(1 - u; a)``), ``1 - c`` and ``1 + c`` are formed as
    products of sums of non-negative terms,
    ``2 (1 -+ a)^2 (1 - u or u) (1 + a u or 1 - a + a u) / d^2`` with
    ``d = 1 - a + 2 a u``, and the sine as the square root of their product.
    """
    sign = jnp.where(g >= 0, 1.0, -1.0)
    a = sign * g  # |g|, with derivative sign(g) (+1 at g = 0)
    u = jnp.where(g >= 0, u1, 1.0 - u1)
    d = (1.0 - a) + 2.0 * a * u
    dd = d * d
    one_minus_c = 2.0 * (1.0 - a) ** 2 * (1.0 - u) * (1.0 + a * u) / dd
    one_plus_c = 2.0 * (1.0 + a) ** 2 * u * ((1.0 - a) + a * u) / dd
    cos_a = jnp.where(one_minus_c < one_plus_c, 1.0 - one_minus_c, one_plus_c - 1.0)
    prod = u * (1.0 - u) * (1.0 + a * u) * ((1.0 - a) + a * u)
    sin_theta = 2.0 * (1.0 - a) * (1.0 + a) * jnp.sqrt(jnp.maximum(prod, 1e-30)) / dd
    return _around(w, sign * cos_a, s, sin_theta)


# --- SGGX specular platelets ---------------------------------------------------


def mean_normal(theta_p_deg, phi_p_deg):
    """Mean platelet normal ``m`` from its tilt and azimuth in degrees."""
    th = jnp.deg2rad(theta_p_deg)
    ph = jnp.deg2rad(phi_p_deg)
    return jnp.stack([jnp.sin(th) * jnp.cos(ph), jnp.sin(th) * jnp.sin(ph), jnp.cos(th)], axis=-1)


def _cross2(a, b):
    """``|a x b|^2``, accurate when ``a`` and ``b`` are nearly parallel."""
    cx = a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1]
    cy = a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2]
    cz = a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]
    return cx * cx + cy * cy + cz * cz


def sggx_sigma(w, m, alpha):
    """Projected area ``sigma_S(w) = sqrt(w^T S w)``, in ``[alpha, 1]``; 1 along ``m``."""
    wm = dot(w, m)
    return jnp.sqrt(alpha * alpha * _cross2(w, m) + wm * wm)


def sggx_ndf(n, m, alpha):
    """SGGX normal distribution ``D(n)`` in 1/sr, normalised so that ``int <w, n>+ D(n) dn = sigma_S(w)``.

    ``D(n) = alpha^2 / (pi (|n x m|^2 + alpha^2 (n.m)^2)^2)``, the form of
    docs/model.md section 7 multiplied through by ``alpha^4``; its peak
    ``1 / (pi alpha^2)`` (8e4 at ``alpha = 0.002``) is exact in float32.
    """
    nm = dot(n, m)
    q = _cross2(n, m) + alpha * alpha * nm * nm
    return alpha * alpha / (jnp.pi * q * q)


def flake_reflection(w, w_out, m, alpha):
    """``sigma_S(w) f_p(w -> w') = D(h) / 4`` in 1/sr, ``h = normalize(w' - w)``.

    The specular phase function times the projected area, the form in which
    it enters the collision weight (docs/model.md eq. 8), cheaper than
    :func:`specular_phase` by a square root and a division. ``D`` is
    homogeneous of degree -4, so it is evaluated on the unnormalised
    ``d = w' - w``: ``D(h) = alpha^2 |d|^4 / (pi (|d x m|^2 + alpha^2 (d.m)^2)^2)``.
    At the exact forward direction ``w' = w`` the half vector does not exist
    (only edge-on flakes could send light there): the value is 0 there and
    the gradient finite.
    """
    d = w_out - w
    n2 = dot(d, d)
    dm = dot(d, m)
    ok = n2 > 1e-12
    # q / |d|^2 lies in [alpha^2, 1] (up to rounding). Without that division the value is
    # alpha^2 |d|^4 / (4 pi q^2), whose gradient forms q^4: at the mirror peak under grazing
    # incidence q ~ alpha^2 |d|^2 ~ 1e-13 (alpha = 1e-4, w.m = 1.7e-3), q^4 underflows
    # float32 and the gradient was inf / nan.
    q = jnp.where(ok, (_cross2(d, m) + alpha * alpha * dm * dm) / jnp.where(ok, n2, 1.0), 1.0)
    return jnp.where(ok, alpha * alpha / (4.0 * jnp.pi * q * q), 0.0)


def specular_phase(w, w_out, m, alpha):
    """Specular microflake phase function ``f_p(w -> w') = D(h) / (4 sigma_S(w))`` in 1/sr."""
    return flake_reflection(w, w_out, m, alpha) / sggx_sigma(w, m, alpha)


def _sqrt_s(v, m, alpha):
    """``S^(1/2) v`` with ``S^(1/2) = alpha I + (1 - alpha) m m^T``."""
    return alpha[..., None] * v + ((1.0 - alpha) * dot(v, m))[..., None] * m


def sggx_sample(w, m, alpha, s):
    """Draw ``w'`` from ``f_p(w -> .)`` by visible-normal sampling and reflection.

    ``s``: a uniform unit vector (:func:`uniform_sphere`). A normal ``n`` is
    drawn from ``<-w, n> D(n) / sigma_S(w)``: ``v`` is cosine-distributed about
    ``k = normalize(S^(1/2) (-w))`` and ``n = normalize(S^(1/2) v)`` (no
    inverse, no determinant); then ``w' = w - 2 (w . n) n``. The density of
    ``w'`` is exactly :func:`specular_phase`.
    """
    alpha = jnp.broadcast_to(alpha, s.shape[:-1])
    k = normalize(_sqrt_s(-w, m, alpha))
    # v = k + s (cosine_sample(k, s) before its normalisation): n depends only on the
    # direction of v. Normalising v first made k + s, which nearly cancels where v grazes
    # the horizon of k, be rounded differently in the XLA fusions that recompute it, and
    # n is ill-conditioned there (d n / d v ~ 1 / alpha): jitted samples came out with
    # norms up to 1.3 at alpha = 1e-4 (1e-3 at alpha = 0.002).
    n = safe_normalize(_sqrt_s(k + s, m, alpha), m)
    return w - (2.0 * dot(w, n))[..., None] * n


def cosine_sample(n, s):
    """A direction cosine-distributed about the unit vector ``n`` (density ``<w, n> / pi``).

    ``normalize(n + s)`` with ``s`` uniform on the sphere is exactly
    cosine-distributed, and needs no tangent frame (see :func:`_around`).
    """
    return safe_normalize(n + s, jnp.broadcast_to(n, s.shape))
