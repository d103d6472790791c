"""Previews: a material tabulated, shaded on a sphere and a flat patch, written as PNG."""

from ._render import (
    ENVIRONMENT,
    EXPOSURE,
    LIGHT_IRRADIANCE,
    LIGHT_RADIUS_DEG,
    RENDER_BOUNCES,
    RENDER_WALKS,
    SKIN_ALBEDO,
    BSDFTable,
    on_base,
    render,
    shade,
    tabulate,
    write_png,
)
