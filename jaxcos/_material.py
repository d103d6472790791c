"""Materials: cosmetic layers, stacks, bases, variants, and ``params.json``.

A :class:`Material` is a pytree. Its array leaves are the physical parameters
of MODEL.md section 2 (differentiable); its structure (number of layers, base
type, model variant) is static and decides at trace time which effects the
simulation contains.

Example::

    import jaxcos
    m = jaxcos.published("dewy1")          # the paper's fit of Dewy 1
    jaxcos.save_params(m, "dewy1.json")
    m2 = jaxcos.load_params("dewy1.json")
"""

import json
import math
import os
import warnings

import equinox as eqx
import jax.numpy as jnp

from ._errors import InputError

VARIANTS = ("two_lobe", "single_lobe", "diffusers_only", "platelets_only")
"""Model variants (FORMATS.md): the parts of the model each switches off are
not simulated at all."""

_FIXED = {
    "two_lobe": {},
    "single_lobe": {"w_g": 1.0},
    "diffusers_only": {"c_d": 1.0},
    "platelets_only": {"c_d": 0.0},
}


def _scalar(x):
    return jnp.asarray(x, dtype=jnp.result_type(float))


def _rgb(x):
    x = jnp.asarray(x, dtype=jnp.result_type(float))
    return jnp.broadcast_to(x, x.shape[:-1] + (3,)) if x.ndim else jnp.full((3,), x)


class Layer(eqx.Module):
    """One index-matched slab of diffusers and platelets (MODEL.md section 2).

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
    """A stack of :class:`Layer` (top to bottom) over a black or Lambertian base.

    Attributes:
        layers: the layers, top first.
        base_albedo: RGB albedo of a Lambertian base, or ``None`` for a black
            base (the measurement substrate). Static: it decides the structure.
        variant: one of :data:`VARIANTS`, static. ``diffusers_only`` simulates
            no platelets (``c_d = 1``), ``platelets_only`` no diffusers
            (``c_d = 0``), ``single_lobe`` one Henyey-Greenstein lobe
            (``w_g = 1``); the switched-off parameters are ignored.
    """

    layers: tuple
    base_albedo: jnp.ndarray | None = eqx.field(default=None, converter=lambda x: None if x is None else _rgb(x))
    variant: str = eqx.field(static=True, default="two_lobe")

    def __check_init__(self):
        if self.variant not in VARIANTS:
            raise ValueError(f"unknown variant {self.variant!r}; expected one of {', '.join(VARIANTS)}")
        if not isinstance(self.layers, tuple) or not self.layers:
            raise ValueError("a Material needs a non-empty tuple of Layers")

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
    fixed = _FIXED[variant]
    layers = tuple(eqx.tree_at(lambda l: [getattr(l, k) for k in fixed], layer, [_scalar(v) for v in fixed.values()])
                   if fixed else layer for layer in material.layers)
    return Material(layers=layers, base_albedo=material.base_albedo, variant=variant)


# --- the published fits (MODEL.md section 5) -----------------------------------

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


# --- params.json -----------------------------------------------------------------

_LAYER_KEYS = {
    # key in params.json: (field, kind, low, high, low_open, high_open)
    "t": ("t", "scalar", 0.0, math.inf, False, True),
    "c_d": ("c_d", "scalar", 0.0, 1.0, False, False),
    "albedo_d": ("albedo_d", "rgb", 0.0, 1.0, False, False),
    "g1": ("g1", "scalar", -1.0, 1.0, True, True),
    "g2": ("g2", "scalar", -1.0, 1.0, True, True),
    "w_g": ("w_g", "scalar", 0.0, 1.0, False, False),
    "albedo_p": ("albedo_p", "rgb", 0.0, 1.0, False, False),
    "alpha_p": ("alpha_p", "scalar", 0.0, 1.0, True, False),
    "theta_p_deg": ("theta_p", "scalar", 0.0, 90.0, False, False),
}


def _number(path, where, key, value, low, high, low_open, high_open):
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise InputError(f"{path}: {where} '{key}' must be a number, not {json.dumps(value)}.")
    if not math.isfinite(value):
        raise InputError(f"{path}: {where} '{key}' must be finite, not {value}.")
    too_low = value <= low if low_open else value < low
    too_high = value >= high if high_open else value > high
    if too_low or too_high:
        lo, hi = ("(" if low_open else "["), (")" if high_open else "]")
        raise InputError(f"{path}: {where} '{key}' = {value} is outside its range {lo}{low:g}, {high:g}{hi}.")
    return float(value)


def _value(path, where, key, value, kind, *bounds):
    if kind == "rgb":
        if not isinstance(value, list) or len(value) != 3:
            raise InputError(f"{path}: {where} '{key}' must be a list of three numbers [r, g, b].")
        return [_number(path, where, f"{key}[{i}]", v, *bounds) for i, v in enumerate(value)]
    return _number(path, where, key, value, *bounds)


def material_from_dict(data, path="params.json"):
    """Build a :class:`Material` from the parsed JSON of FORMATS.md; ``path`` names it in errors."""
    if not isinstance(data, dict):
        raise InputError(f"{path}: the top level must be a JSON object with 'layers' and 'base'.")
    variant = data.get("variant", "two_lobe")
    if variant not in VARIANTS:
        raise InputError(f"{path}: unknown variant {variant!r}; choose one of {', '.join(VARIANTS)}.")
    for key in ("layers", "base"):
        if key not in data:
            raise InputError(f"{path}: the key '{key}' is missing.")
    layers = data["layers"]
    if not isinstance(layers, list) or not layers:
        raise InputError(f"{path}: 'layers' must be a non-empty list of layer objects.")
    built = []
    for i, layer in enumerate(layers):
        where = f"layer {i}"
        if not isinstance(layer, dict):
            raise InputError(f"{path}: {where} must be a JSON object.")
        unknown = sorted(set(layer) - set(_LAYER_KEYS) - {"phi_p_deg"})
        if unknown:
            raise InputError(f"{path}: {where} has unknown key '{unknown[0]}'; expected {', '.join(_LAYER_KEYS)} and optionally phi_p_deg.")
        fields = {}
        for key, (field, kind, *bounds) in _LAYER_KEYS.items():
            if key not in layer:
                raise InputError(f"{path}: {where} is missing the key '{key}'.")
            fields[field] = _value(path, where, key, layer[key], kind, *bounds)
        fields["phi_p"] = _number(path, where, "phi_p_deg", layer.get("phi_p_deg", 0.0), -360.0, 360.0, False, False)
        for field, fixed in _FIXED[variant].items():
            if fields[field] != fixed:
                warnings.warn(f"{path}: {where} '{field}' = {fields[field]:g} is ignored: variant {variant} fixes it to {fixed:g}.",
                              stacklevel=3)
            fields[field] = fixed
        built.append(Layer(**fields))
    base = data["base"]
    if not isinstance(base, dict) or base.get("type") not in ("black", "lambertian"):
        raise InputError(f"{path}: 'base' must be {{\"type\": \"black\"}} or {{\"type\": \"lambertian\", \"albedo\": [r, g, b]}}.")
    albedo = None
    if base["type"] == "lambertian":
        if "albedo" not in base:
            raise InputError(f"{path}: a lambertian base needs an 'albedo' [r, g, b].")
        albedo = _value(path, "base", "albedo", base["albedo"], "rgb", 0.0, 1.0, False, False)
    return Material(layers=tuple(built), base_albedo=albedo, variant=variant)


def material_to_dict(material):
    """The JSON-ready dictionary of FORMATS.md for ``material``."""

    def num(x):
        return float(x)

    def rgb(x):
        return [float(v) for v in jnp.broadcast_to(x, (3,))]

    layers = []
    for layer in material.layers:
        entry = {
            "t": num(layer.t), "c_d": num(layer.c_d), "albedo_d": rgb(layer.albedo_d),
            "g1": num(layer.g1), "g2": num(layer.g2), "w_g": num(layer.w_g),
            "albedo_p": rgb(layer.albedo_p), "alpha_p": num(layer.alpha_p), "theta_p_deg": num(layer.theta_p),
        }
        if float(layer.phi_p) != 0.0:
            entry["phi_p_deg"] = num(layer.phi_p)
        layers.append(entry)
    base = {"type": "black"} if material.base_albedo is None else {"type": "lambertian", "albedo": rgb(material.base_albedo)}
    return {"layers": layers, "base": base, "variant": material.variant}


def load_params(path):
    """Read a ``params.json`` (FORMATS.md) into a :class:`Material`, validating every field.

    Raises:
        InputError: with one sentence naming the file and the problem.
    """
    path = os.fspath(path)
    try:
        with open(path, encoding="utf-8") as fh:
            data = json.load(fh)
    except FileNotFoundError:
        raise InputError(f"{path}: no such file.") from None
    except IsADirectoryError:
        raise InputError(f"{path}: is a directory, not a params.json file.") from None
    except UnicodeDecodeError:
        raise InputError(f"{path}: not a text file (is it binary?).") from None
    except json.JSONDecodeError as err:
        raise InputError(f"{path}, line {err.lineno}: not valid JSON ({err.msg}).") from None
    return material_from_dict(data, path)


def save_params(material, path, extra=None, *, overwrite=False):
    """Write ``material`` as ``params.json``; ``extra`` keys (e.g. ``"fit"``) are added.

    The file is written to a temporary name and renamed, so a failure leaves
    nothing half-written. An existing file is kept unless ``overwrite``.
    """
    path = os.fspath(path)
    if os.path.exists(path) and not overwrite:
        raise InputError(f"{path}: already exists; pass overwrite=True (or --force) to replace it.")
    data = material_to_dict(material)
    if extra:
        data.update(extra)
    tmp = path + ".tmp"
    with open(tmp, "w", encoding="utf-8") as fh:
        json.dump(data, fh, indent=2)
        fh.write("\n")
    os.replace(tmp, path)
