"""``params.json``: a :class:`~jaxcos.Material` as JSON (``docs/formats.md``).

Example::

    import jaxcos
    m = jaxcos.published("dewy1")
    jaxcos.save_params(m, "dewy1.json")
    m2 = jaxcos.load_params("dewy1.json")
"""

import json
import math
import os
import warnings

import jax.numpy as jnp

from .._errors import InputError
from ..model import BASE_ALBEDO_RANGE, FIXED, INTERFACE_RANGES, LAYER_RANGES, PHI_RANGE, VARIANTS
from ..model import Interface, Layer, Material

# key in params.json: the field of Layer it sets (the domains: jaxcos.model.LAYER_RANGES)
_LAYER_KEYS = {r.key: field for field, r in LAYER_RANGES.items()}

TOP_LEVEL_KEYS = ("layers", "base", "variant", "interface", "fit")
"""The keys a ``params.json`` may hold at its top level (docs/formats.md): ``fit`` is the
record a fit writes (``save_params(..., extra={"fit": ...})``); any other key is an error."""


def _number(path, where, key, value, domain):
    """``value`` as a float, checked to be a finite number in ``domain`` (a :class:`jaxcos.model.Range`)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise InputError(f"{path}: {where} '{key}' must be a number, not {json.dumps(value)}.")
    if not math.isfinite(value):
        raise InputError(f"{path}: {where} '{key}' must be finite, not {value}.")
    if not domain.contains(value):
        raise InputError(f"{path}: {where} '{key}' = {value} is outside its range {domain.interval()}.")
    return float(value)


def _value(path, where, value, domain):
    """The value of ``domain.key`` (a :class:`jaxcos.model.Range`): one number, or three for an RGB one."""
    key = domain.key
    if domain.kind == "rgb":
        if not isinstance(value, list) or len(value) != 3:
            raise InputError(f"{path}: {where} '{key}' must be a list of three numbers [r, g, b].")
        return [_number(path, where, f"{key}[{i}]", v, domain) for i, v in enumerate(value)]
    return _number(path, where, key, value, domain)


def material_from_dict(data, path="params.json"):
    """Build a :class:`Material` from the parsed JSON of docs/formats.md; ``path`` names it in errors."""
    if not isinstance(data, dict):
        raise InputError(f"{path}: the top level must be a JSON object with 'layers' and 'base'.")
    unknown = sorted(set(data) - set(TOP_LEVEL_KEYS))
    if unknown:
        raise InputError(f"{path}: unknown top-level key '{unknown[0]}'; expected {', '.join(TOP_LEVEL_KEYS)}.")
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
        unknown = sorted(set(layer) - set(_LAYER_KEYS) - {PHI_RANGE.key})
        if unknown:
            raise InputError(f"{path}: {where} has unknown key '{unknown[0]}'; expected {', '.join(_LAYER_KEYS)} "
                             f"and optionally {PHI_RANGE.key}.")
        fields = {}
        for field, domain in LAYER_RANGES.items():
            if domain.key not in layer:
                raise InputError(f"{path}: {where} is missing the key '{domain.key}'.")
            fields[field] = _value(path, where, layer[domain.key], domain)
        fields["phi_p"] = _value(path, where, layer.get(PHI_RANGE.key, 0.0), PHI_RANGE)
        for field, fixed in FIXED[variant].items():
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
        albedo = _value(path, "base", base["albedo"], BASE_ALBEDO_RANGE)
    return Material(layers=tuple(built), base_albedo=albedo, variant=variant, interface=_interface(data, path))


def _interface(data, path):
    """The optional top ``"interface": {"eta": ..., "alpha_s": ...}`` (absent: index-matched, ``None``)."""
    if "interface" not in data:
        return None
    spec = data["interface"]
    if not isinstance(spec, dict):
        raise InputError(f"{path}: 'interface' must be an object {{\"eta\": ..., \"alpha_s\": ...}}; leave it out for "
                         "an index-matched top.")
    unknown = sorted(set(spec) - set(INTERFACE_RANGES))
    if unknown:
        raise InputError(f"{path}: interface has unknown key '{unknown[0]}'; expected {', '.join(INTERFACE_RANGES)}.")
    values = {}
    for key, domain in INTERFACE_RANGES.items():
        if key not in spec:
            raise InputError(f"{path}: interface is missing the key '{key}'.")
        values[key] = _value(path, "interface", spec[key], domain)
    return Interface(**values)


def material_to_dict(material):
    """The JSON-ready dictionary of docs/formats.md for ``material``."""

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
    out = {"layers": layers, "base": base, "variant": material.variant}
    if material.interface is not None:
        out["interface"] = {"eta": num(material.interface.eta), "alpha_s": num(material.interface.alpha_s)}
    return out


def load_params(path):
    """Read a ``params.json`` (docs/formats.md) into a :class:`Material`, validating every field.

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
