"""Previews: a material tabulated, shaded on a sphere and a flat patch, written as PNG."""

from ._render import render
