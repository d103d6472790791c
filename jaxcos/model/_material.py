"""Materials: cosmetic layers, stacks, bases and variants.

A :class:`Material` is a pytree. Its array leaves are the physical parameters
of docs/model.md section 2 (differentiable); its structure (number of layers, base
type, model variant) is static and decides at trace time which effects the
simulation contains.

Example::

    import jaxcos
    m = jaxcos.published("dewy1")          # the paper's fit of Dewy 1
    jaxcos.with_variant(m, "single_lobe")  # w_g fixed to 1
"""

import equinox as eqx
import jax.numpy as jnp

from .._errors import InputError
from ._interface import Interface

VARIANTS = ("two_lobe", "single_lobe", "diffusers_only", "platelets_only")
"""Model variants (docs/formats.md): the parts of the model each switches off are
not simulated at all."""

FIXED = {
    "two_lobe": {},
    "single_lobe": {"w_g": 1.0, "g2": 0.0},  # g2: the lobe it does not simulate, written as 0
    "diffusers_only": {"c_d": 1.0},
    "platelets_only": {"c_d": 0.0},
}


def _scalar(x):
    return jnp.asarray(x, dtype=jnp.result_type(float))


def _rgb(x):
    x = jnp.asarray(x, dtype=jnp.result_type(float))
    return jnp.broadcast_to(x, x.shape[:-1] + (3,)) if x.ndim else jnp.full((3,), x)


class Layer(eqx.Module):
    """One index-matched slab of diffusers and platelets (docs/model.md section 2).

    Attributes:
        t: optical thickness in mean free paths of ``sigma_base = 1``, ``>= 0``.
        c_d: fraction of the base extinction due to diffusers, in ``[0, 1]``.
        albedo_d: single-scattering albedo of the diffusers, RGB, in ``[0, 1]``.
        g1, g2: Henyey-Greenstein asymmetries of the two diffuser lobes, in ``(-1, 1)``.
        w_g: weight of lobe ``g1``, in ``[0, 1]``.
        albedo_p: single-scattering albedo of the platelets, RGB, in ``[0, 1]``.
        alpha_p: SGGX platelet roughness, in ``(0, 1]``.
        theta_p: tilt of the mean platelet normal from the surface normal, degrees.
        phi_p: azimuth of that tilt from ``+x``, degrees (0: in the plane of
            incidence, towards the viewer's side).
    """

    t: jnp.ndarray = eqx.field(converter=_scalar)
    c_d: jnp.ndarray = eqx.field(converter=_scalar)
    albedo_d: jnp.ndarray = eqx.field(converter=_rgb)
    g1: jnp.ndarray = eqx.field(converter=_scalar)
    g2: jnp.ndarray = eqx.field(converter=_scalar)
    w_g: jnp.ndarray = eqx.field(converter=_scalar)
    albedo_p: jnp.ndarray = eqx.field(converter=_rgb)
    alpha_p: jnp.ndarray = eqx.field(converter=_scalar)
    theta_p: jnp.ndarray = eqx.field(converter=_scalar)
    phi_p: jnp.ndarray = eqx.field(converter=_scalar, default=0.0)


class Material(eqx.Module):
    """A stack of :class:`Layer` (top to bottom) over a black or Lambertian base, optionally under a rough top.

    Attributes:
        layers: the layers, top first.
        base_albedo: RGB albedo of a Lambertian base, or ``None`` for a black
            base (the measurement substrate). Static: it decides the structure.
        variant: one of :data:`VARIANTS`, static. ``diffusers_only`` simulates
            no platelets (``c_d = 1``), ``platelets_only`` no diffusers
            (``c_d = 0``), ``single_lobe`` one Henyey-Greenstein lobe
            (``w_g = 1``); the switched-off parameters are ignored.
        interface: a rough dielectric top boundary (:class:`Interface`,
            docs/model.md section 3a), or ``None`` (the default): an
            index-matched top, as in the paper. Like the base, a structural
            choice: ``None`` simulates exactly the index-matched stack, with no
            work for an interface.

    Example::

        m = Material(layers=(Layer(...),), interface=Interface(eta=1.5, alpha_s=0.1))
    """

    layers: tuple
    base_albedo: jnp.ndarray | None = eqx.field(default=None, converter=lambda x: None if x is None else _rgb(x))
    variant: str = eqx.field(static=True, default="two_lobe")
    interface: Interface | None = None

    def __check_init__(self):
        if self.variant not in VARIANTS:
            raise ValueError(f"unknown variant {self.variant!r}; expected one of {', '.join(VARIANTS)}")
        if not isinstance(self.layers, tuple) or not self.layers:
            raise ValueError("a Material needs a non-empty tuple of Layers")
        if self.interface is not None and not isinstance(self.interface, Interface):
            raise ValueError(f"interface must be an Interface or None, not {type(self.interface).__name__}")

    @property
    def has_diffusers(self):
        return self.variant != "platelets_only"

    @property
    def has_platelets(self):
        return self.variant != "diffusers_only"

    @property
    def two_lobes(self):
        return self.variant in ("two_lobe", "diffusers_only")

    @property
    def base(self):
        return "black" if self.base_albedo is None else "lambertian"


def check_variant(variant):
    """Raise :class:`InputError` unless ``variant`` is one of :data:`VARIANTS`."""
    if variant not in VARIANTS:
        raise InputError(f"unknown variant {variant!r}; choose one of {', '.join(VARIANTS)}.")


def with_variant(material, variant):
    """``material`` under another variant, its switched-off parameters set to their fixed values."""
    check_variant(variant)
    fixed = FIXED[variant]
    layers = tuple(eqx.tree_at(lambda l: [getattr(l, k) for k in fixed], layer, [_scalar(v) for v in fixed.values()])
                   if fixed else layer for layer in material.layers)
    return Material(layers=layers, base_albedo=material.base_albedo, variant=variant, interface=material.interface)


# --- the published fits (docs/model.md section 5) -----------------------------------

_PUBLISHED = {
    "dewy1": dict(alpha_p=0.13, theta_p=1.47, albedo_p=(0.75, 0.85, 0.99), c_d=0.90,
                  albedo_d=(0.99, 0.98, 0.95), g1=0.55, g2=0.09, w_g=1.0),
    "dewy2": dict(alpha_p=0.002, theta_p=5.5, albedo_p=(0.8, 0.8, 0.8), c_d=0.99,
                  albedo_d=(0.97, 0.93, 0.87), g1=0.77, g2=-0.23, w_g=0.79),
    "matte1": dict(alpha_p=0.15, theta_p=2.01, albedo_p=(0.91, 0.89, 0.85), c_d=0.89,
                   albedo_d=(0.95, 0.94, 0.91), g1=0.37, g2=-0.25, w_g=0.62),
    "matte2": dict(alpha_p=0.49, theta_p=52.2, albedo_p=(0.93, 0.83, 0.71), c_d=0.29,
                   albedo_d=(0.9, 0.9, 0.84), g1=0.24, g2=-0.22, w_g=0.51),
}
PRODUCTS = tuple(_PUBLISHED)
"""Names of the products whose published fits :func:`published` returns."""


def published(name, t=16.0):
    """The paper's fit (Lanza et al. 2024, Table 2) of ``dewy1``, ``dewy2``, ``matte1`` or ``matte2``.

    One layer of optical thickness ``t`` over a black base, ``phi_p = 0``. The
    albedos are the published numbers as they stand (CIE 1931 RGB in the
    paper); jaxcos reads them as linear sRGB.
    """
    if name not in _PUBLISHED:
        raise InputError(f"unknown product {name!r}; choose one of {', '.join(PRODUCTS)}.")
    return Material(layers=(Layer(t=t, **_PUBLISHED[name]),))
