"""Preview images: a material on a sphere and on a flat patch at grazing light.

The picture has two square panels side by side, each ``size x size`` pixels,
so the image is ``size x 2 size``:

* **left**, a sphere seen by an orthographic camera along ``-z`` (the viewer at
  ``+z``), lit by a directional light from the upper left, 40 degrees off the
  viewing axis;
* **right**, a square patch of the plane seen by a perspective camera 15
  degrees above it (30 degree field of view), lit from behind at 75 degrees
  from the normal (grazing light): the centre of the patch repeats the
  gonioreflectometer geometry ``theta_i = theta_o = 75`` (the mirror
  direction), its near and far edges about ``theta_o = 68`` and ``79``; at
  grazing angles dewy and matte finishes differ most.

Both are also lit by a dim uniform environment. The surface is the layered
BSDF of the material over a Lambertian base of skin colour
(:data:`SKIN_ALBEDO` by default; the material's own base is replaced).

**Units and exposure.** The light's irradiance on a surface facing it is
``pi`` (:data:`LIGHT_IRRADIANCE`), so a white Lambertian surface facing the
light has radiance 1; the environment's radiance is 0.1 (:data:`ENVIRONMENT`),
which adds 0.1 times the directional albedo. The background shows the
environment. The linear radiance is multiplied by the exposure (0.8 by
default, :data:`EXPOSURE`) and encoded with the sRGB transfer function of
colour-science, clipped to ``[0, 1]``.

**How the BSDF is evaluated per pixel** (no Monte Carlo per pixel):

* the first scattering order (and the base seen through the layers) is the
  closed form of docs/model.md section 4, exact at every pixel, so sharp platelet
  highlights are not blurred by a grid. The light has an angular radius
  (:data:`LIGHT_RADIUS_DEG`, 3 degrees) whose disc is sampled at fixed points
  for this term, so a near-mirror highlight shows as a small spot instead of
  a point that no pixel hits;
* the orders two and up are smooth: they are tabulated once by
  :func:`tabulate` on a grid of ``(theta_i, theta_o, relative azimuth)`` with
  :func:`jaxcos.simulate` and interpolated multilinearly. A tilted platelet
  normal (``theta_p > 0``) makes the BSDF anisotropic: it then depends on both
  azimuths, not only on their difference, and the table gains an axis for the
  azimuth of ``wi`` (8 nodes; 8 times the cost). The tangent from which
  ``phi_p`` is measured follows the image's horizontal axis (left to right)
  on the sphere and points towards the camera on the patch;
* the environment term is the environment radiance times the directional
  albedo seen from the viewing direction, which by reciprocity is the
  estimate's ``reflected`` energy for light arriving from there; it is
  tabulated on the same grid.

All walks use one key for every grid node (common random numbers), so the
Monte Carlo error of the table is smooth over the grid and shows as a slight
overall offset, not as blotches. Two deliberate biases keep a coarse grid
honest (both affect only the orders two and up):

* **path regularisation**: the higher orders are simulated with the platelet
  roughness raised to at least 0.2. Smooth platelets send part of the
  multiply scattered light into lobes nearly as sharp as their first-order
  highlight (chains of platelet reflections). A table over ``(theta_i,
  theta_o)`` with 10-15 degree cells cannot move such a lobe with the
  mirror direction, only cross-fade it: blocks and swirls around the
  highlight. Widened to about the grid's resolution, these lobes keep their
  energy and lose detail the grid could not hold; the first-order highlight
  stays exact;
* **despeckling**: a table node brighter than twice the median of its eight
  neighbours over ``wo`` is clamped to that bound. Such a node is a rare
  walk of high weight, not a feature (docs/model.md section 7).

Example::

    import jax, jaxcos
    image = jaxcos.render(jaxcos.published("dewy1", t=1.0), key=jax.random.key(0), size=128)
    image.shape  # (128, 256, 3): sRGB in [0, 1]
"""

import dataclasses
import math
import os

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._errors import InputError, refuse_overwrite
from ..model import RENDER_BUDGET, Material
from ..model import Query, interface_reflection, simulate, single_scattering, stack_medium

SKIN_ALBEDO = (0.56, 0.28, 0.21)
"""Default base albedo, linear sRGB: the 'light skin' patch of the X-Rite
ColorChecker (colour-science's ``ColorChecker24 - After November 2014``,
Bradford-adapted to D65; sRGB ``(197, 144, 127)``)."""
EXPOSURE = 0.8
"""Factor applied to the linear radiance before the sRGB transfer function."""
LIGHT_IRRADIANCE = math.pi
"""Irradiance of the directional light on a surface facing it: a white
Lambertian surface facing the light has radiance 1."""
ENVIRONMENT = 0.1
"""Radiance of the uniform environment (in the units of :data:`LIGHT_IRRADIANCE`)."""
LIGHT_RADIUS_DEG = 3.0
"""Angular radius of the light's disc for the exact first-order term."""
RENDER_WALKS = RENDER_BUDGET.walks
"""Walks per grid incidence in a preview (:data:`jaxcos.model.RENDER_BUDGET`)."""
RENDER_BOUNCES = RENDER_BUDGET.bounces
"""Bounces per walk in a preview (:data:`jaxcos.model.RENDER_BUDGET`)."""

_ALPHA_MIN = 0.2  # platelet roughness floor of the tabulated higher orders (path regularisation)
_SPIKE = 2.0  # a table node above this many times its neighbours' median is clamped
_LIGHT_SAMPLES = 32  # fixed points on the light's disc
_SPHERE_LIGHT = np.array([-math.sin(math.radians(40)) * math.sqrt(0.5),
                          math.sin(math.radians(40)) * math.sqrt(0.5),
                          math.cos(math.radians(40))])
_PATCH_LIGHT_DEG = 75.0  # light polar angle on the patch, from its -x side
_PATCH_CAMERA_DEG = 75.0  # camera polar angle, on the +x side (the mirror direction)
_PATCH_DISTANCE = 3.0  # camera distance from the patch centre, in patch half-widths
_PATCH_FOV_DEG = 30.0  # the camera's full field of view, both ways
_SPHERE_RADIUS = 0.9  # in half-widths of the panel


# --- the table ------------------------------------------------------------------------


class BSDFTable(eqx.Module):
    """A material's BSDF for rendering: exact first order, tabulated higher orders.

    Build it with :func:`tabulate`. Directions are unit vectors in the local
    frame of the surface (normal ``+z``, tangent ``+x``, from which ``phi_p``
    is measured), both pointing away from the surface (docs/model.md section 1).

    Attributes:
        material: the material (with its base) the table describes.
        multiple: ``(T, A, T, P, 3)``: the BSDF of the orders two and up, 1/sr,
            for ``wi`` at polar angle ``theta_j = theta_max j / (T - 1)`` and
            azimuth ``180 + 360 a / A`` degrees, ``wo`` at ``theta_l`` and
            azimuth ``360 p / P``. An isotropic BSDF has ``A = 1``: ``wi`` in
            the gonioreflectometer's position (azimuth 180) and ``p`` the
            relative azimuth.
        albedo: ``(T, A, 3)``: the directional-hemispherical reflectance for
            light from the same incidences.
        theta_max_deg: the last polar node, degrees; directions beyond it take
            its values.
    """

    material: Material
    multiple: jnp.ndarray
    albedo: jnp.ndarray
    theta_max_deg: float = eqx.field(static=True)

    @property
    def theta_deg(self):
        """The polar-angle nodes, degrees."""
        return np.linspace(0.0, self.theta_max_deg, self.multiple.shape[0])

    @property
    def phi_i_deg(self):
        """The azimuth nodes of ``wi``, degrees."""
        return 180.0 + np.arange(self.multiple.shape[1]) * 360.0 / self.multiple.shape[1]

    @property
    def phi_o_deg(self):
        """The azimuth nodes of ``wo``, degrees."""
        return np.arange(self.multiple.shape[3]) * 360.0 / self.multiple.shape[3]

    def _theta_axis(self, theta_deg):
        n = self.multiple.shape[0]
        return _axis(theta_deg, self.theta_max_deg / (n - 1), n, False)

    def _phi_i_axis(self, phi_deg):
        n = self.multiple.shape[1]
        return _axis(phi_deg - 180.0, 360.0 / n, n, True)

    @eqx.filter_jit
    def f_multiple(self, wi, wo):
        """Orders two and up, interpolated: ``(..., 3)`` in 1/sr for ``wi``, ``wo`` of shape ``(..., 3)``."""
        theta_i, phi_i = _angles(wi)
        theta_o, phi_o = _angles(wo)
        n_az, n_phi = self.multiple.shape[1], self.multiple.shape[3]
        if n_az == 1:  # isotropic: turn wi to azimuth 180
            phi_o = phi_o - phi_i + 180.0
        axes = [self._theta_axis(theta_i), self._phi_i_axis(phi_i), self._theta_axis(theta_o),
                _axis(phi_o, 360.0 / n_phi, n_phi, True)]
        return _interpolate(self.multiple, axes)

    @eqx.filter_jit
    def f_single(self, wi, wo):
        """The exact first order (and the base seen through the layers): ``(..., 3)`` in 1/sr."""
        shape = jnp.broadcast_shapes(wi.shape, wo.shape)
        wi = jnp.broadcast_to(wi, shape).reshape(-1, 3)
        wo = jnp.broadcast_to(wo, shape).reshape(-1, 3)
        f = exact_part(self.material, wi, wo[:, None, :])[:, 0]
        return f.reshape(shape)

    @eqx.filter_jit
    def f(self, wi, wo):
        """The BSDF ``f(wi, wo)``: ``(..., 3)`` in 1/sr (zero where either direction is below the surface)."""
        up = (wi[..., 2] > 0) & (wo[..., 2] > 0)
        z = jnp.array([0.0, 0.0, 1.0], wi.dtype)
        wi_s, wo_s = jnp.where(up[..., None], wi, z), jnp.where(up[..., None], wo, z)
        return jnp.where(up[..., None], self.f_single(wi_s, wo_s) + self.f_multiple(wi_s, wo_s), 0.0)

    @eqx.filter_jit
    def directional_albedo(self, w):
        """Reflectance ``int f(w, wo) cos(theta_o) dwo`` for light from ``w``, interpolated: ``(..., 3)``.

        By reciprocity it is also the albedo seen from ``w`` under a uniform environment.
        """
        theta, phi = _angles(w)
        return _interpolate(self.albedo, [self._theta_axis(theta), self._phi_i_axis(phi)])


def _angles(w):
    """Polar angle and azimuth of unit vectors, degrees."""
    theta = jnp.rad2deg(jnp.arccos(jnp.clip(w[..., 2], -1.0, 1.0)))
    return theta, jnp.rad2deg(jnp.arctan2(w[..., 1], w[..., 0]))


def _axis(x, step, n, periodic):
    """Lower and upper node indices and the weight of the upper one, for linear interpolation."""
    if n == 1:
        zero = jnp.zeros(jnp.shape(x), jnp.int32)
        return zero, zero, jnp.zeros(jnp.shape(x))
    u = x / step
    if periodic:
        lo = jnp.floor(u)
        weight = u - lo
        lo = jnp.mod(lo.astype(jnp.int32), n)
        return lo, jnp.mod(lo + 1, n), weight
    u = jnp.clip(u, 0.0, n - 1.0)
    lo = jnp.clip(jnp.floor(u), 0, n - 2).astype(jnp.int32)
    return lo, lo + 1, u - lo


def _interpolate(table, axes):
    """Multilinear interpolation of ``table`` (leading axes indexed by ``axes``, RGB last)."""
    total = 0.0
    for corner in range(2 ** len(axes)):
        index, weight = [], 1.0
        for d, (lo, hi, w) in enumerate(axes):
            upper = (corner >> d) & 1
            index.append(hi if upper else lo)
            weight = weight * (w if upper else 1.0 - w)
        total = total + weight[..., None] * table[tuple(index)]
    return total


def is_isotropic(material):
    """Whether the BSDF of ``material`` depends on the azimuths only through their difference.

    True without platelets, or when every layer's platelets are untilted
    (``theta_p = 0``) or isotropic (``alpha_p = 1``).
    """
    if not material.has_platelets:
        return True
    return all(float(layer.theta_p) == 0.0 or float(layer.alpha_p) == 1.0 for layer in material.layers)


def _despeckle(values, limit):
    """Clamp isolated spikes of ``values`` ``(..., T, P, 3)`` over the ``(theta_o, phi_o)`` grid.

    A node whose luminance exceeds ``limit`` times the median of its eight
    neighbours (periodic in ``phi_o``, held at the ends of ``theta_o``) is
    scaled down to that bound. Orders two and up of the BSDF vary on scales
    wider than the grid, so such a spike is a rare walk of high weight (NEE
    through near-mirror platelets, docs/model.md section 7), not a feature.
    """
    y = values @ jnp.array([0.2126, 0.7152, 0.0722], values.dtype)
    padded = jnp.concatenate([y[..., :1, :], y, y[..., -1:, :]], axis=-2)
    n_t = y.shape[-2]
    neighbours = jnp.stack([jnp.roll(padded, -dp, axis=-1)[..., 1 + dt:1 + dt + n_t, :]
                            for dt in (-1, 0, 1) for dp in (-1, 0, 1) if (dt, dp) != (0, 0)])
    bound = limit * jnp.median(neighbours, axis=0)
    scale = jnp.where(y > bound, bound / jnp.maximum(y, 1e-30), 1.0)
    return values * scale[..., None]


def _regularized(material):
    """``material`` with every layer's platelet roughness raised to at least :data:`_ALPHA_MIN`."""
    if not material.has_platelets:
        return material
    layers = tuple(eqx.tree_at(lambda l: l.alpha_p, layer, jnp.maximum(layer.alpha_p, _ALPHA_MIN))
                   for layer in material.layers)
    return dataclasses.replace(material, layers=layers)


def exact_part(material, wi, wo):
    """The part of the BSDF evaluated exactly per pixel, not interpolated: ``(I, J, 3)`` in 1/sr.

    Index-matched, the closed-form first order (and the base seen through
    the layers, docs/model.md section 4). Under a top interface, its outside
    reflection ``f_s`` (docs/model.md section 3a), the sharpest part of a
    glossy product; the rest, the light that crossed the interface, is
    tabulated. ``wi`` ``(I, 3)``, ``wo`` ``(I or 1, J, 3)``.
    """
    top = material.interface
    if top is None:
        return single_scattering(stack_medium(material), material.base_albedo, wi, wo)
    f_s = interface_reflection(wi[:, None, :], wo, top.eta, top.alpha_s)
    return jnp.broadcast_to(f_s[..., None], f_s.shape + (3,))


@eqx.filter_jit
def _table(material, key, theta_deg, phi_i_deg, phi_o_deg, walks, bounces):
    th = jnp.deg2rad(theta_deg)
    t, p = jnp.meshgrid(th, jnp.deg2rad(phi_i_deg), indexing="ij")
    wi = jnp.stack([jnp.sin(t) * jnp.cos(p), jnp.sin(t) * jnp.sin(p), jnp.cos(t)], axis=-1)  # (T, A, 3)
    t, p = jnp.meshgrid(th, jnp.deg2rad(phi_o_deg), indexing="ij")
    wo = jnp.stack([jnp.sin(t) * jnp.cos(p), jnp.sin(t) * jnp.sin(p), jnp.cos(t)], axis=-1).reshape(-1, 3)
    n_out = wo.shape[0]
    first = jax.vmap(lambda w: exact_part(material, w[None], wo[None])[0])

    def incidence(w):  # one key for every incidence: common random numbers over the grid
        query = Query(w[None], wo[None], jnp.zeros(n_out, jnp.int32), jnp.arange(n_out))
        est = simulate(material, query, key, walks=walks, bounces=bounces)
        return est.f, est.reflected[0]

    total, albedo = jax.vmap(incidence)(wi.reshape(-1, 3))
    multiple = jnp.maximum(total - first(wi.reshape(-1, 3)), 0.0)
    albedo = albedo.reshape(wi.shape)
    multiple = multiple.reshape(wi.shape[:2] + (th.shape[0], phi_o_deg.shape[0], 3))
    return _despeckle(multiple, _SPIKE), albedo


def tabulate(material, key, *, walks=RENDER_WALKS, bounces=RENDER_BOUNCES, n_theta=10, n_phi=24,
             n_phi_i=None, theta_max_deg=87.0):
    """Tabulate the BSDF of ``material`` for rendering (see the module docstring).

    Args:
        material: a :class:`~jaxcos.Material`, with the base it is to be shown on.
        key: a JAX PRNG key; the same key gives the same table. Every
            incidence of the grid uses the same random numbers (common random
            numbers), so the Monte Carlo error is smooth over the grid.
        walks, bounces: the Monte Carlo budget per incidence.
        n_theta: polar-angle nodes, from 0 to ``theta_max_deg``, for ``wi`` and ``wo``.
        n_phi: azimuth nodes of ``wo`` over 360 degrees.
        n_phi_i: azimuth nodes of ``wi`` over 360 degrees; default 1 for an
            isotropic BSDF (:func:`is_isotropic`), else 8.
        theta_max_deg: the last polar node; beyond it values are held.

    Returns:
        A :class:`BSDFTable`. The higher orders are path-regularised and
        despeckled (module docstring). Cost: ``n_theta x n_phi_i`` incidences
        of ``walks x bounces`` steps, each connecting to ``n_theta x n_phi``
        outgoing directions; about 3 s for a tilted material at the defaults
        on a 2-core CPU (0.4 s untilted), plus about 8 s of compilation.
    """
    if n_theta < 2 or n_phi < 1:
        raise ValueError(f"need n_theta >= 2 and n_phi >= 1, got {n_theta}, {n_phi}")
    if walks < 2 or bounces < 1:
        raise InputError(f"need at least 2 walks and 1 bounce, not {walks} and {bounces}.")
    if n_phi_i is None:
        n_phi_i = 1 if is_isotropic(material) else 8
    dtype = jnp.result_type(float)
    theta = jnp.linspace(0.0, theta_max_deg, n_theta, dtype=dtype)
    phi_i = 180.0 + jnp.arange(n_phi_i, dtype=dtype) * (360.0 / n_phi_i)
    phi_o = jnp.arange(n_phi, dtype=dtype) * (360.0 / n_phi)
    multiple, albedo = _table(_regularized(material), key, theta, phi_i, phi_o, int(walks), int(bounces))
    return BSDFTable(material=material, multiple=multiple, albedo=albedo, theta_max_deg=float(theta_max_deg))


# --- the scene ---------------------------------------------------------------------------


def _normalize(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _sphere(size):
    """Per pixel of the sphere panel: mask, normal, tangent, view and light directions (world)."""
    c = (np.arange(size) + 0.5) / size * 2.0 - 1.0
    x, y = np.meshgrid(c, -c)  # image rows go down, y goes up
    x, y = x / _SPHERE_RADIUS, y / _SPHERE_RADIUS
    r2 = x * x + y * y
    mask = r2 < 1.0
    z = np.sqrt(np.maximum(1.0 - r2, 0.0))
    n = np.stack([x, y, z], axis=-1)
    n = np.where(mask[..., None], n, [0.0, 0.0, 1.0])
    # the tangent follows the image's horizontal axis: +x projected onto the tangent plane
    t = np.array([1.0, 0.0, 0.0]) - n[..., :1] * n
    ok = np.linalg.norm(t, axis=-1, keepdims=True) > 1e-6
    t = np.where(ok, t, [0.0, 1.0, 0.0])
    view = np.broadcast_to([0.0, 0.0, 1.0], n.shape)
    light = np.broadcast_to(_SPHERE_LIGHT, n.shape)
    return mask, n, _normalize(t), view, light


def _patch(size):
    """Per pixel of the patch panel: mask, normal, tangent, view and light directions (world)."""
    tc = math.radians(_PATCH_CAMERA_DEG)
    camera = _PATCH_DISTANCE * np.array([math.sin(tc), 0.0, math.cos(tc)])
    forward = -camera / np.linalg.norm(camera)
    right = _normalize(np.cross(forward, [0.0, 0.0, 1.0]))
    up = np.cross(right, forward)
    half = math.tan(math.radians(_PATCH_FOV_DEG) / 2)
    c = ((np.arange(size) + 0.5) / size * 2.0 - 1.0) * half
    u, v = np.meshgrid(c, -c)
    ray = _normalize(forward + u[..., None] * right + v[..., None] * up)
    down = ray[..., 2] < -1e-6
    s = np.where(down, -camera[2] / np.where(down, ray[..., 2], -1.0), 0.0)
    hit = camera + s[..., None] * ray
    mask = down & (np.abs(hit[..., 0]) <= 1.0) & (np.abs(hit[..., 1]) <= 1.0)
    n = np.broadcast_to([0.0, 0.0, 1.0], ray.shape)
    t = np.broadcast_to([1.0, 0.0, 0.0], ray.shape)  # towards the camera
    tl = math.radians(_PATCH_LIGHT_DEG)
    light = np.broadcast_to([-math.sin(tl), 0.0, math.cos(tl)], ray.shape)
    return mask, n, t, -ray, light


def _disc(radius_deg, count):
    """``(count, 2)`` polar offsets (angle from the centre, azimuth) covering a disc evenly (Vogel's spiral)."""
    if radius_deg <= 0.0:
        return np.zeros((1, 2))
    k = np.arange(count)
    rho = math.radians(radius_deg) * np.sqrt((k + 0.5) / count)
    return np.stack([rho, k * math.pi * (3.0 - math.sqrt(5.0))], axis=-1)


def _frame(w):
    """Two unit vectors completing the unit vectors ``w`` to an orthonormal frame."""
    a = jnp.where((jnp.abs(w[..., 2]) < 0.9)[..., None], jnp.array([0.0, 0.0, 1.0]), jnp.array([1.0, 0.0, 0.0]))
    u = jnp.cross(a, w)
    u = u / jnp.linalg.norm(u, axis=-1, keepdims=True)
    return u, jnp.cross(w, u)


@eqx.filter_jit
def _shade(table, mask, n, t, view, light, disc, irradiance, environment):
    """Linear radiance ``(P, 3)`` of pixels with unit normal, tangent, view and light directions ``(P, 3)``."""
    b = jnp.cross(n, t)
    local = lambda w: jnp.stack([jnp.sum(w * t, -1), jnp.sum(w * b, -1), jnp.sum(w * n, -1)], axis=-1)
    wo = local(view)
    wo = wo.at[:, 2].set(jnp.maximum(wo[:, 2], 1e-4))
    z = jnp.array([0.0, 0.0, 1.0], wo.dtype)
    u, v = _frame(light)

    def first_order(offset):
        w = local(jnp.cos(offset[0]) * light + jnp.sin(offset[0]) * (jnp.cos(offset[1]) * u + jnp.sin(offset[1]) * v))
        lit = w[:, 2] > 0
        f = table.f_single(jnp.where(lit[:, None], w, z), wo)
        return jnp.where(lit[:, None], f * w[:, 2:3], 0.0)

    direct = jnp.mean(jax.lax.map(first_order, disc), axis=0)
    wi = local(light)
    lit = wi[:, 2] > 0
    higher = jnp.where(lit[:, None], table.f_multiple(jnp.where(lit[:, None], wi, z), wo) * wi[:, 2:3], 0.0)
    radiance = irradiance * (direct + higher) + environment * table.directional_albedo(wo)
    return jnp.where(mask[:, None], radiance, environment)


def shade(table, *, size=256, irradiance=LIGHT_IRRADIANCE, environment=ENVIRONMENT,
          light_radius_deg=LIGHT_RADIUS_DEG):
    """The linear radiance image ``(size, 2 size, 3)`` of the scene (module docstring) under ``table``.

    Deterministic: all randomness is in :func:`tabulate`.
    """
    sphere, patch = _sphere(size), _patch(size)
    mask, n, t, view, light = (np.concatenate([a, b], axis=1).reshape(size * 2 * size, *a.shape[2:])
                               for a, b in zip(sphere, patch))
    dtype = jnp.result_type(float)
    arrays = [jnp.asarray(a, dtype) for a in (n, t, view, light)]
    disc = jnp.asarray(_disc(light_radius_deg, _LIGHT_SAMPLES), dtype)
    radiance = _shade(table, jnp.asarray(mask), *arrays, disc, jnp.asarray(irradiance, dtype),
                      jnp.asarray(environment, dtype))
    return np.asarray(radiance).reshape(size, 2 * size, 3)


# --- the public entry points ---------------------------------------------------------------


def _check_albedo(base_albedo, what="base_albedo"):
    try:
        rgb = np.asarray(base_albedo, dtype=float)
    except (TypeError, ValueError):
        rgb = None
    if rgb is None or rgb.shape != (3,) or not np.all(np.isfinite(rgb)) or np.any(rgb < 0) or np.any(rgb > 1):
        raise InputError(f"{what} must be three numbers r, g, b in [0, 1] (linear sRGB), not {base_albedo!r}.")
    return tuple(float(c) for c in rgb)


def on_base(material, base_albedo=SKIN_ALBEDO):
    """``material`` with its base replaced by a Lambertian one of albedo ``base_albedo`` (linear sRGB)."""
    return dataclasses.replace(material, base_albedo=_check_albedo(base_albedo))


def render(material, *, key, size=256, base_albedo=SKIN_ALBEDO, walks=RENDER_WALKS, bounces=RENDER_BOUNCES,
           exposure=EXPOSURE, environment=ENVIRONMENT, light_radius_deg=LIGHT_RADIUS_DEG, encode=True):
    """A preview of ``material`` on a sphere and on a flat patch at grazing light (module docstring).

    Args:
        material: a :class:`~jaxcos.Material`; its layers are shown over a
            Lambertian base of albedo ``base_albedo``, which replaces its own base.
        key: a JAX PRNG key (the Monte Carlo of the BSDF table); the same key
            gives the same image.
        size: pixels per panel side; the image is ``size x 2 size``.
        base_albedo: linear sRGB albedo of the base, default :data:`SKIN_ALBEDO`
            ``(0.56, 0.28, 0.21)``, the ColorChecker's 'light skin'.
        walks, bounces: the Monte Carlo budget of the table (:func:`tabulate`).
        exposure: factor on the linear radiance before encoding (default 0.8);
            a white Lambertian surface facing the light has radiance 1.
        environment: radiance of the uniform environment (default 0.1).
        light_radius_deg: angular radius of the light (default 3 degrees; 0 is a
            point light).
        encode: return sRGB-encoded values in ``[0, 1]`` after ``exposure``
            (colour-science's sRGB transfer function); ``False`` returns the
            linear radiance, without exposure.

    Returns:
        A NumPy array ``(size, 2 size, 3)``: left the sphere, right the patch.

    Raises:
        InputError: for a bad ``base_albedo``, ``size``, ``exposure``,
            ``environment`` or ``light_radius_deg``.

    Cost: the table (:func:`tabulate`) dominates and does not depend on
    ``size``; shading is about 1 s for ``size = 256`` on a 2-core CPU. The
    first call for a material structure also compiles, 10-15 s.
    """
    if isinstance(size, bool) or not isinstance(size, (int, np.integer)) or not 4 <= size <= 4096:
        raise InputError(f"size must be a whole number of pixels from 4 to 4096, not {size!r}.")
    for name, value, low in (("exposure", exposure, 1e-30), ("environment", environment, 0.0),
                             ("light_radius_deg", light_radius_deg, 0.0)):
        if not (isinstance(value, (int, float, np.floating)) and math.isfinite(value) and value >= low):
            raise InputError(f"{name} must be a finite number {'> 0' if low else '>= 0'}, not {value!r}.")
    table = tabulate(on_base(material, base_albedo), key, walks=walks, bounces=bounces)
    radiance = shade(table, size=int(size), environment=environment, light_radius_deg=light_radius_deg)
    if not encode:
        return radiance
    from ..io import encode_srgb

    return encode_srgb(radiance, exposure).astype(np.float32)


def write_png(image, path, *, overwrite=False):
    """Write an sRGB-encoded image ``(H, W, 3)`` in ``[0, 1]`` as an 8-bit PNG (atomically).

    Raises:
        InputError: if ``path`` exists and not ``overwrite``, or cannot be written.
    """
    from PIL import Image

    path = os.fspath(path)
    refuse_overwrite([path], overwrite)
    image = np.asarray(image, dtype=float)
    if image.ndim != 3 or image.shape[-1] != 3:
        raise ValueError(f"expected an image of shape (H, W, 3), got {image.shape}")
    pixels = np.round(np.clip(np.nan_to_num(image), 0.0, 1.0) * 255.0).astype(np.uint8)
    tmp = path + ".tmp"
    try:
        Image.fromarray(pixels, "RGB").save(tmp, format="PNG")
        os.replace(tmp, path)
    except OSError as err:
        if os.path.exists(tmp):
            os.remove(tmp)
        raise InputError(f"{path}: cannot be written ({err.strerror}).") from None
