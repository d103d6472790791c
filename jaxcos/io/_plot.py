"""Pictures of reflectance tables, like Figure 4 of Lanza et al. 2024.

A table has ``theta_o`` across and ``theta_i`` down; each measured pair is a
cell coloured in sRGB (the sRGB transfer function of colour-science applied to
``exposure * value``, clipped to ``[0, 1]``), black where there is no data.
Angles may be irregular and sparse (real instruments measure densely near the
mirror direction, coarsely elsewhere, and different ``theta_o`` per
``theta_i``): there is one row per distinct ``theta_i``, and within a row each
point's cell reaches halfway to the neighbouring measured ``theta_o`` of that
row (the nearest-neighbour version of the paper's interpolation). A row is
black outside the range it measured; a hole inside that range is covered by
its neighbours. On a regular grid every cell is one grid step wide.

Example::

    import matplotlib.pyplot as plt
    from jaxcos._plot import draw_reflectance, default_exposure
    fig, (a, b) = plt.subplots(1, 2)
    k = default_exposure(measured)
    draw_reflectance(a, ti, to, measured, exposure=k, title="measured")
    draw_reflectance(b, ti, to, fitted, exposure=k, title="fitted")
"""

import os

import numpy as np
from matplotlib.collections import PolyCollection
from matplotlib.figure import Figure

from .._errors import InputError

EXPOSURE_PERCENTILE = 95.0
EXPOSURE_TARGET = 0.8
"""The default exposure maps the 95th percentile of the values to 0.8 before
the transfer curve: diffuse parts stay visible, only the brightest highlight
cells saturate."""


def default_exposure(rgb):
    """Exposure mapping the 95th percentile of the finite, positive ``rgb`` values to 0.8.

    Args:
        rgb: values of any shape (linear, in any quantity).

    Returns:
        A positive float; 1.0 when no value is positive.
    """
    values = np.asarray(rgb, dtype=float)
    values = values[np.isfinite(values) & (values > 0)]
    if values.size == 0:
        return 1.0
    return float(EXPOSURE_TARGET / np.percentile(values, EXPOSURE_PERCENTILE))


def cell_edges(centres, half=0.5):
    """Cell edges halfway between sorted distinct ``centres``, half a spacing (or ``half``) beyond the ends."""
    if centres.size == 1:
        return np.array([centres[0] - half, centres[0] + half])
    mid = (centres[1:] + centres[:-1]) / 2
    return np.concatenate([[2 * centres[0] - mid[0]], mid, [2 * centres[-1] - mid[-1]]])


def encode_srgb(rgb, exposure):
    """sRGB-encoded colours in ``[0, 1]`` of linear ``rgb`` values scaled by ``exposure``.

    NaN and negative values show black, ``+inf`` white.
    """
    import colour

    linear = np.clip(np.nan_to_num(np.asarray(rgb, dtype=float) * exposure, nan=0.0, posinf=1.0, neginf=0.0), 0.0, 1.0)
    return np.clip(colour.cctf_encoding(linear, function="sRGB"), 0.0, 1.0)


def draw_reflectance(ax, theta_i, theta_o, rgb, *, exposure, title=None):
    """Draw a reflectance table on the matplotlib Axes ``ax``.

    Args:
        ax: a matplotlib Axes.
        theta_i: ``(N,)`` incidence angles, degrees (rows, increasing downward).
        theta_o: ``(N,)`` signed viewing angles, degrees (columns, increasing to the right).
        rgb: ``(N, 3)`` linear sRGB values (any quantity; negative values show black).
        exposure: factor applied to ``rgb`` before the sRGB transfer curve;
            stated in the title.
        title: text above the table; the exposure is appended.

    Returns:
        The ``PolyCollection`` of cells drawn.

    Raises:
        ValueError: if shapes disagree or ``N = 0``, ``exposure`` is not positive, or a
            ``(theta_i, theta_o)`` pair occurs twice.
    """
    theta_i = np.asarray(theta_i, dtype=float)
    theta_o = np.asarray(theta_o, dtype=float)
    rgb = np.asarray(rgb, dtype=float)
    if theta_i.ndim != 1 or not theta_i.size or theta_o.shape != theta_i.shape or rgb.shape != theta_i.shape + (3,):
        raise ValueError(f"expected theta_i, theta_o of shape (N,) and rgb of shape (N, 3) with N > 0, "
                         f"got {theta_i.shape}, {theta_o.shape}, {rgb.shape}")
    if not (np.isfinite(exposure) and exposure > 0):
        raise ValueError(f"exposure must be a positive number, not {exposure}")
    if len(set(zip(theta_i.tolist(), theta_o.tolist()))) != theta_i.size:
        raise ValueError("a (theta_i, theta_o) pair occurs twice; draw out-of-plane points separately")
    rows = np.unique(theta_i)
    row_edges = cell_edges(rows, half=2.5)
    in_row = [np.sort(theta_o[theta_i == t]) for t in rows]
    spacings = np.concatenate([np.diff(o) for o in in_row])
    half = 0.5 * float(np.median(spacings)) if spacings.size else 2.5
    cells, colours = [], []
    colour_of = dict(zip(zip(theta_i.tolist(), theta_o.tolist()), encode_srgb(rgb, exposure)))
    for k, (t, outs) in enumerate(zip(rows, in_row)):
        y0, y1 = row_edges[k], row_edges[k + 1]
        x = cell_edges(outs, half)
        for j, o in enumerate(outs):
            cells.append([(x[j], y0), (x[j + 1], y0), (x[j + 1], y1), (x[j], y1)])
            colours.append(colour_of[(float(t), float(o))])
    mesh = PolyCollection(cells, facecolors=colours, edgecolors="none", antialiased=False)
    ax.add_collection(mesh)
    ax.set_facecolor("black")
    ax.set_xlim(min(c[0][0] for c in cells), max(c[1][0] for c in cells))
    ax.set_ylim(row_edges[-1], row_edges[0])
    ax.set_xlabel("theta_o (degrees)")
    ax.set_ylabel("theta_i (degrees)")
    caption = f"exposure x{exposure:.3g}"
    ax.set_title(f"{title}\n{caption}" if title else caption, fontsize="medium")
    return mesh


def plot_measurements(meas, out_path, *, exposure=None, overwrite=False):
    """Write a PNG of the in-plane points of ``meas`` as a reflectance table.

    The values are shown as reflectance factors (``pi * f``) whatever the
    file's quantity, at ``exposure`` (default :func:`default_exposure`).
    Out-of-plane points (``phi_o != 0``) are left out and counted in the title.
    The figure is drawn without pyplot (Agg, no screen, no global state) and
    written under a temporary name, then renamed.

    Raises:
        InputError: for a bad ``exposure``, no in-plane point, an existing
            ``out_path`` without ``overwrite``, or a path that cannot be written.
    """
    out_path = os.fspath(out_path)
    if os.path.exists(out_path) and not overwrite:
        raise InputError(f"{out_path}: already exists; pass overwrite=True (or --force) to replace it.")
    if exposure is not None and not (np.isfinite(exposure) and exposure > 0):
        raise InputError(f"exposure must be a positive number, not {exposure}.")
    inplane = meas.phi_o == 0
    if not inplane.any():
        raise InputError(f"{meas.path}: no in-plane point (phi_o = 0) to draw.")
    values = meas.to_quantity("reflectance_factor").values[inplane]
    exposure = default_exposure(values) if exposure is None else float(exposure)
    name = meas.metadata.get("sample") or os.path.basename(meas.path) or "measurements"
    title = f"{name}: reflectance factor, sRGB"
    skipped = int((~inplane).sum())
    if skipped:
        title += f" ({skipped} out-of-plane points not shown)"
    fig = Figure(figsize=(8, 4.5), layout="constrained")
    draw_reflectance(fig.subplots(), meas.theta_i[inplane], meas.theta_o[inplane], values,
                     exposure=exposure, title=title)
    tmp = f"{out_path}.tmp"
    try:
        fig.savefig(tmp, format="png", dpi=150)
        os.replace(tmp, out_path)
    except OSError as err:
        if os.path.exists(tmp):
            os.remove(tmp)
        raise InputError(f"{out_path}: cannot be written ({err.strerror}).") from None
