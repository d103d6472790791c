"""``jaxcos render``: a preview of a params.json on a sphere and a flat patch, written as PNG.

    jaxcos render PARAMS --out IMAGE.png [--base-albedo R,G,B] [--size N] [--thickness T] ...

The scene, the units and the exposure are those of :mod:`jaxcos.render`
(:func:`jaxcos.render.tabulate`, :func:`jaxcos.render.shade`); the image is
written by :func:`jaxcos.render.write_png`.
"""

import dataclasses
import math
import os
import time

import equinox as eqx
import jax
import jax.numpy as jnp

from .._errors import InputError, refuse_overwrite
from ..io import encode_srgb, load_params
from ..model import RENDER_BUDGET
from ..render import EXPOSURE, SKIN_ALBEDO, on_base, shade, tabulate, write_png
from ._common import progress


def _parse_rgb(text):
    """The ``r,g,b`` of ``--base-albedo``: three numbers in ``[0, 1]``."""
    try:
        values = [float(p) for p in text.split(",")]
    except ValueError:
        values = []
    if len(values) != 3 or not all(math.isfinite(v) and 0.0 <= v <= 1.0 for v in values):
        raise InputError(f"--base-albedo must be three numbers r,g,b in [0, 1] separated by commas "
                         f"(e.g. 0.56,0.28,0.21), not {text!r}.")
    return tuple(values)


def _with_thickness(material, t):
    """``material`` with the optical thickness of every layer set to ``t``."""
    layers = tuple(eqx.tree_at(lambda l: l.t, layer, jnp.asarray(t, layer.t.dtype)) for layer in material.layers)
    return dataclasses.replace(material, layers=layers)


def _cmd_render(args):
    start = time.perf_counter()
    say = progress("render")
    out = args.out
    if not out.lower().endswith(".png"):
        raise InputError(f"{out}: the image must be a .png file.")
    refuse_overwrite([out], args.force)
    folder = os.path.dirname(out) or "."
    if not os.path.isdir(folder):
        raise InputError(f"{out}: the folder {folder} does not exist.")
    base = SKIN_ALBEDO if args.base_albedo is None else _parse_rgb(args.base_albedo)
    if not 4 <= args.size <= 4096:
        raise InputError(f"--size must be from 4 to 4096 pixels, not {args.size}.")
    if args.walks < 2 or args.bounces < 1:
        raise InputError(f"--walks must be at least 2 and --bounces at least 1, not {args.walks} and {args.bounces}.")
    if not (math.isfinite(args.exposure) and args.exposure > 0):
        raise InputError(f"--exposure must be a positive number, not {args.exposure}.")
    material = load_params(args.params)
    if args.thickness is not None:
        if not (math.isfinite(args.thickness) and args.thickness >= 0):
            raise InputError(f"--thickness must be a number >= 0, not {args.thickness}.")
        material = _with_thickness(material, args.thickness)
    material = on_base(material, base)
    say(f"tabulating the BSDF ({args.walks} walks, {args.bounces} bounces per incidence)")
    table = tabulate(material, jax.random.key(args.seed), walks=args.walks, bounces=args.bounces)
    say(f"shading {args.size} x {2 * args.size} pixels")
    radiance = shade(table, size=args.size)
    write_png(encode_srgb(radiance, args.exposure), out, overwrite=True)
    print(f"wrote {out}: {args.size} x {2 * args.size} pixels, sphere and grazing patch over base "
          f"{', '.join(f'{c:.3g}' for c in base)}, exposure {args.exposure:g}, in {time.perf_counter() - start:.1f} s.")


def add_command(sub):
    """Register ``jaxcos render`` on the argparse sub-parsers ``sub``."""
    p = sub.add_parser("render", help="render a preview of a material on a sphere and a flat patch (PNG)",
                       description="Render the material of PARAMS over a Lambertian skin-coloured base (its own base "
                       "is replaced) on a sphere and on a flat patch at grazing light, lit by a directional light and "
                       "a dim uniform environment. Each panel is SIZE x SIZE pixels; the image is SIZE x 2 SIZE, "
                       "sRGB at a stated exposure (a white Lambertian surface facing the light has radiance 1).")
    p.add_argument("params", metavar="PARAMS", help="params.json (docs/formats.md)")
    p.add_argument("--out", required=True, metavar="IMAGE.png")
    p.add_argument("--base-albedo", metavar="R,G,B", default=None,
                   help="linear sRGB albedo of the base (default %s, the ColorChecker's light skin)"
                   % ",".join(f"{c:g}" for c in SKIN_ALBEDO))
    p.add_argument("--size", type=int, default=256, help="pixels per panel side (default 256)")
    p.add_argument("--seed", type=int, default=0, help="seeds the Monte Carlo key of the BSDF table")
    p.add_argument("--walks", type=int, default=RENDER_BUDGET.walks,
                   help=f"walks per tabulated incidence (default {RENDER_BUDGET.walks})")
    p.add_argument("--bounces", type=int, default=RENDER_BUDGET.bounces,
                   help=f"bounces per walk (default {RENDER_BUDGET.bounces})")
    p.add_argument("--exposure", type=float, default=EXPOSURE,
                   help=f"factor on the linear radiance before sRGB encoding (default {EXPOSURE:g})")
    p.add_argument("--thickness", type=float, default=None,
                   help="set the optical thickness of every layer (e.g. 0.5 for a thin coat on skin; "
                   "default: as in PARAMS)")
    p.add_argument("--force", action="store_true", help="overwrite IMAGE.png if it exists")
    p.set_defaults(func=_cmd_render)
