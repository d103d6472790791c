"""The Kubelka-Munk model of Huang et al. 2013 (docs/model.md section 6): a two-flux layer plus a specular lobe.

A cosmetic layer is a Kubelka-Munk (two-flux) slab with scattering ``S`` and
absorption ``K`` per unit length (per colour channel) and thickness ``X`` in
the same length unit, over a substrate of diffuse reflectance ``Rg`` (the
measurement files' matte black substrate: ``Rg = 0``). Its diffuse
reflectance ``R`` is that of the layer over the substrate,

    a = 1 + K/S,  b = sqrt(a^2 - 1),  y = b S X
    R0 = sinh y / (a sinh y + b cosh y),   T = b / (a sinh y + b cosh y)
    R  = R0 + T^2 Rg / (1 - R0 Rg)

(``R = R0`` on a black substrate), spread uniformly over the hemisphere
(``R / pi`` in 1/sr): Kubelka-Munk has no angular dependence, which is the
point Lanza et al. 2024 make against it. On top sits the specular lobe of
Kelemen and Szirmay-Kalos (2001) that Huang et al. use, with a Beckmann
distribution ``D`` (roughness ``m``) and Schlick's Fresnel term (normal
reflectance ``F0``):

    f_spec(wi, wo) = D(h) F(h . wi) / |wi + wo|^2,    h = (wi + wo) / |wi + wo|

(``|wi + wo|^2 = 2 (1 + wi . wo) = 4 (h . wi)^2``: the Cook-Torrance lobe with
Kelemen's approximation of the shadowing term). The BSDF is
``f = R / pi + f_spec`` in 1/sr, RGB on the last axis; like Huang et al. the
two terms are added (no energy coupling between them).

Directions follow docs/model.md section 1: ``wi = (-sin ti, 0, cos ti)``,
``wo = (sin to cos po, sin to sin po, cos to)``, angles in degrees; ``to = ti``
is the mirror direction and ``to < 0`` the light's side.

The layer formulas are written in forms that stay finite, with finite and
correct gradients, at their limits (``K = 0``, ``S = 0``, ``X = 0``,
``X -> inf``) in float32: ``R0 = sigma tc / ((sigma + kappa) tc + 1)`` and
``T = sech(y) / ((sigma + kappa) tc + 1)`` with ``sigma = S X``,
``kappa = K X``, ``y^2 = kappa (kappa + 2 sigma)`` and ``tc = tanh(y) / y``
(both even in ``y``, so evaluated from ``y^2``).

The fit of this model to measurements is :func:`jaxcos.fit_kubelka_munk`.

Example::

    import jaxcos
    S, K = jaxcos.km_invert(r_inf=0.8, r=0.5, rg=0.05, thickness=0.15)   # per mm for a 0.15 mm layer
    km = jaxcos.KubelkaMunk(scattering=S, absorption=K, thickness=0.15, roughness=0.2, f0=0.04)
    km.bsdf([30.0], [30.0])   # (1, 3), 1/sr
"""

import equinox as eqx
import jax.numpy as jnp


def _asarray(x):
    return jnp.asarray(x, dtype=jnp.result_type(float))


def _safe_sqrt(x):
    """``sqrt(max(x, 0))`` with a zero (not infinite) gradient at 0."""
    pos = x > 0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, x, 1.0)), 0.0)


def _layer_optical(sigma, kappa):
    """``(R0, T)`` of a layer of scattering thickness ``sigma = S X`` and absorption thickness ``kappa = K X``.

    ``tanh(y) / y`` and ``sech(y)`` are even in ``y``, so they are written as
    functions of ``u = y^2 = kappa (kappa + 2 sigma)``, which is smooth in both:
    the derivatives at ``K = 0`` are then the true ones (a function of ``y``
    would meet the infinite slope of the square root there).
    """
    u = kappa * (kappa + 2.0 * sigma)
    small = u < 1e-4
    y = jnp.sqrt(jnp.where(small, 1.0, u))
    e = jnp.exp(-y)
    tc = jnp.where(small, 1.0 - u / 3.0 + 2.0 * u * u / 15.0, jnp.tanh(y) / y)
    sech = jnp.where(small, 1.0 - u / 2.0 + 5.0 * u * u / 24.0, 2.0 * e / (1.0 + e * e))
    denom = (sigma + kappa) * tc + 1.0
    return sigma * tc / denom, sech / denom


def km_layer(scattering, absorption, thickness):
    """Kubelka-Munk reflectance ``R0`` and transmittance ``T`` of a layer alone (docs/model.md section 6).

    Args:
        scattering: ``S >= 0`` per unit length (any shape; RGB on the last axis by convention).
        absorption: ``K >= 0`` per unit length, broadcast against ``S``.
        thickness: ``X >= 0`` in the same length unit.

    Returns:
        ``(R0, T)``: diffuse reflectance and transmittance in ``[0, 1]``, with
        ``R0 + T <= 1`` (equality when ``K = 0``); the rest is absorbed.
        ``X = 0`` gives ``(0, 1)``; ``X -> inf`` gives ``(R_inf, 0)``;
        ``S = 0`` gives ``(0, exp(-K X))``.
    """
    s, k, x = _asarray(scattering), _asarray(absorption), _asarray(thickness)
    return _layer_optical(s * x, k * x)


def km_r_inf(scattering, absorption):
    """Reflectance of an infinitely thick layer, ``R_inf = a - b = S / (S + K + sqrt(K (K + 2 S)))``.

    Undefined (NaN) for ``S = K = 0``; ``0`` for ``S = 0 < K``; ``1`` for ``K = 0 < S``, where its
    derivative in ``K`` is infinite (``R_inf ~ 1 - sqrt(2 K / S)``; the gradient returned there is 0).
    """
    s, k = _asarray(scattering), _asarray(absorption)
    return s / (s + k + _safe_sqrt(k * (k + 2.0 * s)))


def km_remission(r_inf):
    """The Kubelka-Munk remission function ``K / S = (1 - R_inf)^2 / (2 R_inf)``, the inverse of :func:`km_r_inf`.

    ``r_inf`` in ``(0, 1]``; the result is unitless (a ratio of two coefficients per unit length).
    """
    return (1.0 - r_inf) ** 2 / (2.0 * r_inf)


def km_combine(r1, t1, r2, t2):
    """Reflectance and transmittance of layer 1 over layer 2 (light arriving on layer 1).

    ``R12 = R1 + T1^2 R2 / (1 - R1 R2)``, ``T12 = T1 T2 / (1 - R1 R2)``: the
    geometric series of inter-reflections between diffuse layers (Kubelka-Munk
    layers are symmetric, so one ``R`` and ``T`` serve both sides).
    """
    r1, t1, r2, t2 = map(_asarray, (r1, t1, r2, t2))
    inter = 1.0 / (1.0 - r1 * r2)
    return r1 + t1 * t1 * r2 * inter, t1 * t2 * inter


def km_over_background(scattering, absorption, thickness, background):
    """Diffuse reflectance ``R`` of a layer over an opaque background of reflectance ``Rg``.

    ``R = R0 + T^2 Rg / (1 - R0 Rg)`` (:func:`km_combine` with ``T2 = 0``);
    ``Rg = 0`` (a black substrate) gives ``R0``.
    """
    r0, t = km_layer(scattering, absorption, thickness)
    return km_combine(r0, t, background, 0.0)[0]


def km_invert(r_inf, r, rg, thickness):
    """Scattering ``S`` and absorption ``K`` per unit length from measured reflectances (Huang et al. eqs. 6-7).

    Args:
        r_inf: reflectance of a layer thick enough to be opaque, in ``(0, 1)``.
        r: reflectance of a layer of ``thickness`` over the background.
        rg: reflectance of the background alone.
        thickness: that layer's thickness ``D > 0``; ``S`` and ``K`` come out
            per the same length unit.

    Returns:
        ``(S, K)`` with ``a = (1/R_inf + R_inf) / 2``, ``b = sqrt(a^2 - 1)``,
        ``S = (arccoth((a - R) / b) - arccoth((a - Rg) / b)) / (b D)`` and
        ``K = S (a - 1)``. The arccoth difference is evaluated as
        ``ln[(1/R_inf - R)(R_inf - Rg) / ((R_inf - R)(1/R_inf - Rg))] / 2``,
        which equals the paper's form for ``Rg < R < R_inf`` and extends it to
        a light background, ``R_inf < R < Rg``. ``R`` must lie strictly between
        ``Rg`` and ``R_inf``; otherwise no Kubelka-Munk layer explains the data
        and the result is NaN.
    """
    ri, r, rg, d = map(_asarray, (r_inf, r, rg, thickness))
    a = 0.5 * (1.0 / ri + ri)
    b = 0.5 * (1.0 / ri - ri)
    ratio = (1.0 / ri - r) * (ri - rg) / ((ri - r) * (1.0 / ri - rg))
    valid = (ri > 0) & (ri < 1) & (ratio > 1) & (d > 0)
    bsx = 0.5 * jnp.log(jnp.where(valid, ratio, 2.0))
    s = jnp.where(valid, bsx / (b * jnp.where(valid, d, 1.0)), jnp.nan)
    return s, s * (a - 1.0)


# --- the specular lobe ---------------------------------------------------------------


def directions(theta_i_deg, theta_o_deg, phi_o_deg=None):
    """Unit vectors ``(wi, wo)``, ``(N, 3)`` each, of the in-plane convention of docs/model.md section 1."""
    ti = jnp.deg2rad(_asarray(theta_i_deg))
    to = jnp.deg2rad(_asarray(theta_o_deg))
    po = jnp.zeros_like(to) if phi_o_deg is None else jnp.deg2rad(_asarray(phi_o_deg))
    ti, to, po = jnp.broadcast_arrays(jnp.atleast_1d(ti), to, po)
    wi = jnp.stack([-jnp.sin(ti), jnp.zeros_like(ti), jnp.cos(ti)], axis=-1)
    wo = jnp.stack([jnp.sin(to) * jnp.cos(po), jnp.sin(to) * jnp.sin(po), jnp.cos(to)], axis=-1)
    return wi, wo


def beckmann(cos_h, roughness):
    """Beckmann normal distribution ``D = exp(-tan^2 th / m^2) / (pi m^2 cos^4 th)`` (1/sr).

    Normalised so that ``integral D(h) cos th_h dw_h = 1`` over the hemisphere.
    """
    c2 = jnp.maximum(_asarray(cos_h) ** 2, 1e-12)
    m2 = _asarray(roughness) ** 2
    return jnp.exp(-(1.0 - c2) / (c2 * m2)) / (jnp.pi * m2 * c2 * c2)


def schlick(cos_theta, f0):
    """Schlick's Fresnel approximation ``F0 + (1 - F0) (1 - cos)^5``."""
    c = jnp.clip(_asarray(cos_theta), 0.0, 1.0)
    return f0 + (1.0 - f0) * (1.0 - c) ** 5


def kelemen_specular(wi, wo, roughness, f0):
    """The Kelemen/Szirmay-Kalos specular BSDF ``D(h) F(h . wi) / |wi + wo|^2`` in 1/sr.

    Args:
        wi, wo: ``(..., 3)`` unit directions towards the light and the viewer
            (both with positive ``z``).
        roughness: Beckmann ``m > 0``.
        f0: Schlick's reflectance at normal incidence.

    Returns:
        ``(...)`` values; with ``|wi + wo| = 2 cos(h, wi)`` this is
        ``D F / (4 (h . wi)^2)``. Written around the unnormalised half vector
        ``s = wi + wo`` (``tan^2 th_h = (s_x^2 + s_y^2) / s_z^2``), exact at the mirror.
    """
    s = wi + wo
    sxy2 = s[..., 0] ** 2 + s[..., 1] ** 2
    sz2 = jnp.maximum(s[..., 2] ** 2, 1e-12)
    s2 = sxy2 + sz2
    m2 = _asarray(roughness) ** 2
    d = jnp.exp(-sxy2 / (sz2 * m2)) * s2 * s2 / (jnp.pi * m2 * sz2 * sz2)
    return d * schlick(0.5 * jnp.sqrt(s2), f0) / s2


# --- the model -----------------------------------------------------------------------


class KubelkaMunk(eqx.Module):
    """Kubelka-Munk layer over a substrate, plus a Kelemen/Szirmay-Kalos specular lobe.

    Attributes:
        scattering: ``S``, RGB, per unit length (``>= 0``).
        absorption: ``K``, RGB, per unit length (``>= 0``).
        thickness: ``X``, same length unit (a fit uses 1: ``S``, ``K`` per layer thickness).
        roughness: Beckmann roughness ``m`` (RMS slope of the microfacets), ``> 0``.
        f0: Schlick's specular reflectance at normal incidence, in ``[0, 1]``.
        substrate: diffuse reflectance ``Rg`` of the substrate, RGB (0: black).
    """

    scattering: jnp.ndarray
    absorption: jnp.ndarray
    thickness: jnp.ndarray
    roughness: jnp.ndarray
    f0: jnp.ndarray
    substrate: jnp.ndarray

    def __init__(self, scattering, absorption, thickness=1.0, roughness=0.2, f0=0.04, substrate=0.0):
        rgb = lambda v: jnp.broadcast_to(_asarray(v), (3,))
        self.scattering = rgb(scattering)
        self.absorption = rgb(absorption)
        self.thickness = _asarray(thickness)
        self.roughness = _asarray(roughness)
        self.f0 = _asarray(f0)
        self.substrate = rgb(substrate)

    @property
    def r_inf(self):
        """Reflectance of an infinitely thick layer of this material, RGB."""
        return km_r_inf(self.scattering, self.absorption)

    def diffuse_reflectance(self):
        """``R``: the layer's Kubelka-Munk reflectance over the substrate, RGB (hemispherical, unitless)."""
        return km_over_background(self.scattering, self.absorption, self.thickness, self.substrate)

    def bsdf_directions(self, wi, wo):
        """``f(wi, wo) = R / pi + f_spec`` in 1/sr, ``(..., 3)``, for unit direction arrays ``(..., 3)``."""
        spec = kelemen_specular(wi, wo, self.roughness, self.f0)
        return self.diffuse_reflectance() / jnp.pi + spec[..., None]

    def bsdf(self, theta_i_deg, theta_o_deg, phi_o_deg=None):
        """The BSDF ``f`` in 1/sr, ``(N, 3)`` linear RGB, at angle pairs in degrees (docs/model.md section 1).

        Example::

            >>> import jaxcos
            >>> km = jaxcos.KubelkaMunk(scattering=20.0, absorption=(0.5, 1.0, 2.0), roughness=0.2, f0=0.05)
            >>> km.bsdf([30.0, 30.0], [-20.0, 30.0]).shape
            (2, 3)
        """
        wi, wo = directions(theta_i_deg, theta_o_deg, phi_o_deg)
        return self.bsdf_directions(wi, wo)
