"""Tests of ``jaxcos.model._phase``: Henyey-Greenstein and SGGX specular phase functions and samplers.

The code under test runs in float32 (the JAX default). Reference values and all
quadratures are float64 numpy. The four groups follow docs/model.md sections 2 and 7:

1. Normalisation by deterministic quadrature (HG, the two-lobe mixture, the
   SGGX specular phase function, the SGGX projected-area identity).
2. Float32 stability of the SGGX forms against float64 textbook matrices.
3. Samplers against their densities: chi-square goodness of fit in the manner
   of Mitsuba 3, Sidak-corrected over ``N_SAMPLER_TESTS`` tests, plus tests
   showing that the statistic rejects a perturbed density.
4. Finite values and gradients at the hard cases.

Tolerances of the quadrature tests have three parts, each computed or bounded
in the test (never tuned to pass):

* ``quad``: the quadrature error, estimated as the difference between the
  float64 reference integrated on two grids (the finer has twice as many
  panels per decade); the finer grid is asserted to integrate the reference to
  1 within ``1e-6``.
* ``rounding``: the change of the float64 reference's integral when its inputs
  (nodes, ``w``, ``m``) are rounded to float32 as the float32 code receives them.
  It is a property of the problem's conditioning, not of the code: at
  ``alpha = 0.002`` and grazing incidence the specular lobe is 4e-5 rad wide in
  one direction, only ~700 float32 ulps.
* ``F32_TOL = 1e-6`` (plus, for HG, the rounding of ``g * g``): the relative
  error of evaluating the formula in float32 at the same float32 inputs.
"""

import numpy as np
import pytest
import jax
import jax.numpy as jnp
from scipy import stats

from jaxcos.model import _phase as P

EPS32 = 2.0**-24  # unit roundoff of float32
F32_TOL = 1e-6  # float32 evaluation error of a phase function, relative (see module docstring)


# --------------------------------------------------------------------------- quadrature helpers


def _breaks(lo, hi, centres=(), finest=1e-3, per_decade=6):
    """Panel boundaries on ``[lo, hi]`` graded geometrically towards each of ``centres``.

    Around every centre the panel widths grow from ``finest`` by a factor
    ``10 ** (1 / per_decade)``; the union of all these points is returned sorted.
    """
    pts = [lo, hi]
    ratio = 10.0 ** (1.0 / per_decade)
    for c in centres:
        if lo <= c <= hi:
            pts.append(c)
        d = finest
        while d < hi - lo:
            pts.extend([c - d, c + d])
            d *= ratio
    pts = np.unique(np.clip(np.asarray(pts, np.float64), lo, hi))
    keep = np.concatenate([[True], np.diff(pts) > 1e-13 * (hi - lo)])
    return pts[keep]


def _gauss(breaks, k):
    """Composite ``k``-point Gauss-Legendre rule on the panels ``breaks``: ``(nodes, weights)``."""
    x, w = np.polynomial.legendre.leggauss(k)
    a, b = breaks[:-1, None], breaks[1:, None]
    return ((a + b) / 2 + (b - a) / 2 * x).ravel(), ((b - a) / 2 * w).ravel()


def _frame(p, toward):
    """Right-handed float64 frame ``(u, v, p)`` with ``u`` along the part of ``toward`` normal to ``p``."""
    p = np.asarray(p, np.float64)
    p = p / np.linalg.norm(p)
    u = np.asarray(toward, np.float64)
    u = u - (u @ p) * p
    if np.linalg.norm(u) < 1e-9:
        u = np.array([1.0, 0.0, 0.0]) if abs(p[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        u = u - (u @ p) * p
    u = u / np.linalg.norm(u)
    return u, np.cross(p, u), p


def _polar(frame, rho, w_rho, phi, w_phi):
    """Directions at polar angle ``rho`` and azimuth ``phi`` about ``frame[2]``, and solid-angle weights."""
    u, v, p = frame
    r, f = np.meshgrid(rho, phi, indexing="ij")
    d = (
        np.cos(r)[..., None] * p
        + (np.sin(r) * np.cos(f))[..., None] * u
        + (np.sin(r) * np.sin(f))[..., None] * v
    )
    return d, (w_rho * np.sin(rho))[:, None] * w_phi[None, :]


def _angle(d, p):
    """Angle between the rows of ``d`` and ``p``, accurate at small angles."""
    return np.arctan2(np.linalg.norm(np.cross(d, p), axis=-1), d @ p)


def _eval32(fn, pts, *args):
    """``fn(pts, *args)`` in float32 for ``(..., 3)`` float64 points, returned as float64.

    The points are padded to a power-of-two count so that the jitted ``fn``
    compiles for a handful of shapes only.
    """
    flat = np.asarray(pts, np.float32).reshape(-1, 3)
    size = 1 << 12
    while size < flat.shape[0]:
        size *= 2
    pad = np.tile(np.float32([0.0, 0.0, 1.0]), (size, 1))
    pad[: flat.shape[0]] = flat
    args = [jnp.asarray(np.asarray(a, np.float32)) for a in args]
    out = np.asarray(fn(jnp.asarray(pad), *args), np.float64)
    return out[: flat.shape[0]].reshape(np.shape(pts)[:-1])


def _r32(x):
    """Round to float32 and return as float64 (what the float32 code receives)."""
    return np.asarray(x, np.float32).astype(np.float64)


_HG32 = jax.jit(lambda d, w, g: P.hg(w, d, g))
_SPEC32 = jax.jit(lambda d, w, m, a: P.specular_phase(w, d, m, a))
_NDF32 = jax.jit(lambda n, m, a: P.sggx_ndf(n, m, a))


# --------------------------------------------------------------------------- float64 references


def _hg64(w, d, g):
    """HG in float64 with ``1 + g^2 - 2 g c`` as ``(1 -+ g)^2 +- g |d -+ w|^2`` (equal for unit vectors).

    For non-unit (float32-rounded) inputs this is the function the code evaluates.
    """
    dm, dp = d - w, d + w
    base = np.where(
        g >= 0,
        (1 - g) ** 2 + g * np.einsum("...i,...i", dm, dm),
        (1 + g) ** 2 - g * np.einsum("...i,...i", dp, dp),
    )
    return (1 - g) * (1 + g) / (4 * np.pi * base**1.5)


def _ndf64(n, m, a):
    """SGGX ``D(n)`` in float64, ``alpha^2 / (pi (|n x m|^2 + alpha^2 (n.m)^2)^2)``."""
    c = np.cross(n, m)
    nm = n @ m
    q = np.einsum("...i,...i", c, c) + a * a * nm * nm
    return a * a / (np.pi * q * q)


def _sigma64(w, m, a):
    c = np.cross(w, m)
    wm = w @ m
    return np.sqrt(a * a * np.einsum("...i,...i", c, c) + wm * wm)


def _spec64(w, d, m, a):
    h = d - w
    h = h / np.linalg.norm(h, axis=-1, keepdims=True)
    return _ndf64(h, m, a) / (4 * _sigma64(w, m, a))


def _sggx_matrix(m, a, dtype=np.float64):
    m = np.asarray(m, dtype)
    a = dtype(a)
    return a * a * np.eye(3, dtype=dtype) + (dtype(1) - a * a) * np.outer(m, m)


def _textbook_ndf(n, m, a, dtype=np.float64):
    """``D(n) = 1 / (pi sqrt(det S) (n^T S^-1 n)^2)`` with numpy matrices in ``dtype``."""
    S = _sggx_matrix(m, a, dtype)
    Si = np.linalg.inv(S)
    n = np.asarray(n, dtype)
    quad = np.einsum("...i,ij,...j->...", n, Si, n)
    return dtype(1) / (dtype(np.pi) * np.sqrt(np.linalg.det(S)) * quad * quad)


def _textbook_sigma(w, m, a, dtype=np.float64):
    S = _sggx_matrix(m, a, dtype)
    w = np.asarray(w, dtype)
    return np.sqrt(np.einsum("...i,ij,...j->...", w, S, w))


def _reflect(w, m):
    r = w - 2 * (w @ m) * m
    return r / np.linalg.norm(r)


# --------------------------------------------------------------------------- directions


def _unit(v):
    v = np.asarray(v, np.float64)
    return v / np.linalg.norm(v)


def _w_incident(theta_i_deg):
    """Propagation direction of light arriving from ``wi = (-sin ti, 0, cos ti)`` (docs/model.md section 1)."""
    t = np.deg2rad(theta_i_deg)
    return np.array([np.sin(t), 0.0, -np.cos(t)])


W_GRAZE_DOWN = _unit([np.sqrt(1 - 1e-4), 0.0, -0.01])  # w.z = -0.01
W_GRAZE_UP = _unit([np.sqrt(1 - 1e-4), 0.0, 0.01])  # w.z = +0.01
W_GENERIC = _unit([0.3, -0.7, -0.5])


def _m32(theta_p, phi_p):
    return np.asarray(P.mean_normal(jnp.float32(theta_p), jnp.float32(phi_p)))


# =========================================================================== 1. normalisation

HG_G = [-0.999, -0.9, -0.3, 0.0, 0.3, 0.9, 0.999]


def _hg_grid(w, g_max_abs, per_decade):
    """Polar grid about ``w`` graded towards both poles (the HG peak is at ``w`` or ``-w``)."""
    finest = min(max(1e-3 * (1 - g_max_abs), 1e-7), 1e-3)
    rho, w_rho = _gauss(_breaks(0.0, np.pi, [0.0, np.pi], finest, per_decade), 8)
    n_phi = 8  # HG is axially symmetric: the azimuthal rule only sees float32 rounding
    phi = 2 * np.pi * (np.arange(n_phi) + 0.5) / n_phi
    return _polar(_frame(w, [0.3, 0.5, 0.1]), rho, w_rho, phi, np.full(n_phi, 2 * np.pi / n_phi))


def _hg_f32_tol(g):
    """``F32_TOL`` plus the rounding of ``g * g`` in ``1 - g * g`` relative to ``1 - g^2``.

    That term is ``EPS32 g^2 / (1 - g^2)``, 3e-5 at ``|g| = 0.999``, unless XLA
    contracts ``1 - g * g`` into an FMA (it does on x86 CPUs, giving ~1e-7).
    """
    return F32_TOL + EPS32 * g * g / (1 - g * g)


def _check_normalised(density32, density64, grid_lo, grid_hi, w32, f32_tol, label):
    """Assert that ``density32`` integrates to 1 (see the module docstring for the tolerance).

    ``grid_*`` are lists of ``(directions, weights)``; ``density64(w, d)`` is the
    float64 reference, ``density32(d)`` the float32 code.
    """
    w64 = np.asarray(w32, np.float64)
    wn = w64 / np.linalg.norm(w64)
    ref_lo = sum((wt * density64(wn, d, False)).sum() for d, wt in grid_lo)
    ref_hi = sum((wt * density64(wn, d, False)).sum() for d, wt in grid_hi)
    ref_rounded = sum((wt * density64(w64, _r32(d), True)).sum() for d, wt in grid_hi)
    code = sum((wt * density32(d)).sum() for d, wt in grid_hi)
    quad = abs(ref_hi - ref_lo)
    rounding = abs(ref_rounded - ref_hi)
    assert abs(ref_hi - 1) < 1e-6 and quad < 1e-6, (label, ref_hi - 1, quad)
    assert rounding < 1e-3, (label, rounding)
    tol = quad + rounding + f32_tol
    assert abs(code - 1) <= tol, f"{label}: integral - 1 = {code - 1:.3e} > tol {tol:.2e}"
    return code - 1, quad, rounding


@pytest.mark.parametrize("w", [np.array([0.0, 0.0, 1.0]), W_GENERIC], ids=["w=z", "w=generic"])
@pytest.mark.parametrize("g", HG_G)
def test_hg_normalised(g, w):
    """HG integrates to 1 over the sphere, with the peak resolved by log-spaced polar angles down to 1e-7 rad."""
    w32 = np.float32(w)
    grid_lo, grid_hi = [_hg_grid(w, abs(g), 4)], [_hg_grid(w, abs(g), 8)]
    _check_normalised(
        lambda d: _eval32(_HG32, d, w32, g),
        lambda wv, d, rounded: _hg64(wv, d, float(np.float32(g)) if rounded else g),
        grid_lo,
        grid_hi,
        w32,
        _hg_f32_tol(g),
        f"g={g}",
    )


@pytest.mark.parametrize("g1,g2,w_g", [(0.9, -0.3, 0.7), (0.999, -0.999, 0.5), (0.3, 0.0, 0.25)])
def test_two_lobe_mixture_normalised(g1, g2, w_g):
    """``w_g f_HG(g1) + (1 - w_g) f_HG(g2)``, as the walk forms it, integrates to 1."""
    w32 = np.float32(W_GENERIC)
    gmax = max(abs(g1), abs(g2))

    def code(d):
        return w_g * _eval32(_HG32, d, w32, g1) + (1 - w_g) * _eval32(_HG32, d, w32, g2)

    def ref(wv, d, rounded):
        r = (lambda g: float(np.float32(g))) if rounded else (lambda g: g)
        return w_g * _hg64(wv, d, r(g1)) + (1 - w_g) * _hg64(wv, d, r(g2))

    tol = max(_hg_f32_tol(g1), _hg_f32_tol(g2))
    grid_lo, grid_hi = [_hg_grid(W_GENERIC, gmax, 4)], [_hg_grid(W_GENERIC, gmax, 8)]
    _check_normalised(code, ref, grid_lo, grid_hi, w32, tol, f"mixture {g1},{g2},{w_g}")


SGGX_ALPHA = [0.002, 0.01, 0.13, 0.49, 1.0]
SGGX_ORIENT = [(0.0, 0.0), (5.5, 0.0), (5.5, 90.0), (52.2, 0.0), (52.2, 90.0)]  # (theta_p, phi_p)


def _sggx_incoming(m32):
    """Incoming propagation directions: normal and 60 deg incidence, grazing both ways, generic, along -m."""
    return {
        "in0": _w_incident(0.0),
        "in60": _w_incident(60.0),
        "graze-": W_GRAZE_DOWN,
        "graze+": W_GRAZE_UP,
        "generic": W_GENERIC,
        "-m": -np.asarray(m32, np.float64),
    }


def _bump(d, w, delta):
    """Partition of unity: ``(1 - s)^4`` for ``s = (1 - d.w) / (1 - cos delta) < 1``, else 0 (C^3)."""
    s = (1 - d @ w) / (1 - np.cos(delta))
    return np.where(s < 1, (1 - np.minimum(s, 1)) ** 4, 0.0)


def _specular_grids(w, m, alpha, per_decade, k=6):
    """Quadrature for ``f_p(w -> .)`` as two weighted grids whose weights sum to the sphere's measure.

    ``f_p`` peaks at the mirror direction ``r`` of ``w`` about ``m``; the lobe is
    ``2 alpha`` wide along the great circle through ``r`` and ``w`` and
    ``2 alpha |w.m|`` across it. It also has a direction-dependent limit at
    ``w' = w`` (the half vector of the forward direction does not exist), which
    a grid about ``r`` would resolve only to ~1e-4. So a smooth bump
    ``chi`` about ``w`` splits the integrand: ``(1 - chi) f`` on a polar grid
    about ``r`` (graded in polar angle from ``alpha |w.m| / 20`` and towards
    ``w``, in azimuth towards the long axis of the lobe) and ``chi f`` on a polar
    grid about ``w``, on which ``f`` is smooth.
    """
    wm = w @ m
    b = max(abs(wm), 1e-3)
    r = _reflect(w, m)
    rho0 = _angle(r, w)
    delta = min(0.5 * rho0, 0.5)
    rho, w_rho = _gauss(_breaks(0.0, np.pi, [0.0, rho0], 0.05 * alpha * b, per_decade), k)
    phi, w_phi = _gauss(_breaks(-np.pi, np.pi, [-np.pi, 0.0, np.pi], b / 8, per_decade), k)
    d1, wt1 = _polar(_frame(r, w), rho, w_rho, phi, w_phi)
    rho, w_rho = _gauss(_breaks(0.0, delta, [0.0], 1e-3 * delta, per_decade), k)
    phi, w_phi = _gauss(_breaks(-np.pi, np.pi, [-np.pi, 0.0, np.pi], np.hypot(b, alpha) / 8, per_decade), k)
    d2, wt2 = _polar(_frame(w, m), rho, w_rho, phi, w_phi)
    return [(d1, wt1 * (1 - _bump(d1, w, delta))), (d2, wt2 * _bump(d2, w, delta))]


@pytest.mark.parametrize("theta_p,phi_p", SGGX_ORIENT)
@pytest.mark.parametrize("alpha", SGGX_ALPHA)
def test_specular_phase_normalised(alpha, theta_p, phi_p):
    """``f_p(w -> .)`` integrates to 1 for six incoming directions (grazing ones and along -m included).

    Measured (x86 CPU): ``|integral - 1| <= 8.0e-5``, all of it the rounding term
    (alpha = 0.002, theta_p = 0, w.z = +-0.01; median over the 150 cases 4e-8);
    ``|integral - 1| - quad - rounding <= 1.7e-7``; ``quad <= 2.8e-7``.
    """
    m32 = _m32(theta_p, phi_p)
    m64 = np.asarray(m32, np.float64)
    mn = m64 / np.linalg.norm(m64)
    for name, w in _sggx_incoming(m32).items():
        w32 = np.float32(w)
        wn = _unit(np.asarray(w32, np.float64))
        _check_normalised(
            lambda d: _eval32(_SPEC32, d, w32, m32, alpha),
            lambda wv, d, rounded: _spec64(wv, d, m64 if rounded else mn, alpha),
            _specular_grids(wn, mn, alpha, 3),
            _specular_grids(wn, mn, alpha, 6),
            w32,
            F32_TOL,
            f"alpha={alpha} theta_p={theta_p} phi_p={phi_p} w={name}",
        )


def _projected_area_rule(w, m, alpha, per_decade, k=8):
    """Quadrature for ``int <w, n>+ g(n) dn``: a polar grid about ``m`` restricted to ``w.n > 0``.

    With ``w = c m + s u`` the half-space is ``cos phi > -c cot(rho) / s``; each
    ring of the grid is integrated by Gauss-Legendre over exactly that arc, so
    the kink of ``<w, n>+`` is never inside a panel. Polar panels are graded
    towards ``rho = 0`` and ``pi`` (the peaks of ``D``, width ``alpha``, at
    ``m`` and ``-m``) and towards the
    angles where the arc is born or closes.
    """
    u, v, p = _frame(m, w)
    c, s = w @ p, w @ u
    rho1 = np.arctan2(abs(c), s)
    rb = _breaks(0.0, np.pi, [0.0, rho1, np.pi - rho1, np.pi], alpha / 100, per_decade)
    rho, w_rho = _gauss(rb, k)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = -c * np.cos(rho) / (s * np.sin(rho))
    t = np.where(s * np.sin(rho) > 0, t, np.where(c * np.cos(rho) > 0, -np.inf, np.inf))
    half = np.arccos(np.clip(t, -1.0, 1.0))  # arc is (-half, half)
    x, wx = np.polynomial.legendre.leggauss(k)
    phi = half[:, None] * x[None, :]
    w_phi = half[:, None] * wx[None, :]
    d = (
        np.cos(rho)[:, None, None] * p
        + (np.sin(rho)[:, None] * np.cos(phi))[..., None] * u
        + (np.sin(rho)[:, None] * np.sin(phi))[..., None] * v
    )
    cos_wn = np.clip(d @ w, 0.0, None)
    return d, (w_rho * np.sin(rho))[:, None] * w_phi * cos_wn


@pytest.mark.parametrize("theta_p,phi_p", SGGX_ORIENT)
@pytest.mark.parametrize("alpha", SGGX_ALPHA)
def test_sggx_projected_area_identity(alpha, theta_p, phi_p):
    """``int <w, n>+ D(n) dn = sigma_S(w)`` (the SGGX normalisation), and ``D(m) = 1 / (pi alpha^2)``.

    The integral of the float32 ``sggx_ndf`` must match the float32
    ``sggx_sigma`` to ``quad + rounding + 2 F32_TOL`` relative. Measured
    (x86 CPU): ``|integral / sigma - 1| <= 1.1e-6``, within the rounding term
    (<= 1.3e-6); ``quad <= 2e-11``; ``D(m) pi alpha^2 - 1 <= 4.5e-7``.
    """
    m32 = _m32(theta_p, phi_p)
    m64 = np.asarray(m32, np.float64)
    mn = m64 / np.linalg.norm(m64)
    peak = float(P.sggx_ndf(jnp.asarray(m32), jnp.asarray(m32), jnp.float32(alpha)))
    a32 = float(np.float32(alpha))
    # D(m) = 1 / (pi alpha^2 |m|^8) for the float32-rounded m: a few roundings plus 4 | |m|^2 - 1 |.
    assert abs(peak * np.pi * a32 * a32 - 1) < 8 * EPS32 + 4 * abs(m64 @ m64 - 1)
    for name, w in _sggx_incoming(m32).items():
        w32 = np.float32(w)
        wn = _unit(np.asarray(w32, np.float64))
        sigma32 = float(P.sggx_sigma(jnp.asarray(w32), jnp.asarray(m32), jnp.float32(alpha)))
        sigma64 = _sigma64(wn, mn, alpha)
        d_lo, wt_lo = _projected_area_rule(wn, mn, alpha, 4)
        d_hi, wt_hi = _projected_area_rule(wn, mn, alpha, 8)
        ref_lo = (wt_lo * _ndf64(d_lo, mn, alpha)).sum() / sigma64
        ref_hi = (wt_hi * _ndf64(d_hi, mn, alpha)).sum() / sigma64
        ref_rounded = (wt_hi * _ndf64(_r32(d_hi), m64, alpha)).sum() / _sigma64(_r32(w32), m64, alpha)
        code = (wt_hi * _eval32(_NDF32, d_hi, m32, alpha)).sum() / sigma32
        quad, rounding = abs(ref_hi - ref_lo), abs(ref_rounded - ref_hi)
        label = f"alpha={alpha} theta_p={theta_p} phi_p={phi_p} w={name}"
        assert abs(ref_hi - 1) < 1e-6 and quad < 1e-6, (label, ref_hi - 1, quad)
        tol = quad + rounding + 2 * F32_TOL
        assert abs(code - 1) <= tol, f"{label}: int <w,n>+ D / sigma - 1 = {code - 1:.2e} > {tol:.1e}"


# =========================================================================== 2. float32 stability

STAB_ALPHA, STAB_THETA_P = 0.002, 5.5
STAB_TOL_D = 5e-5  # D and f_p; measured <= 5.7e-6 (D, at rho = alpha), <= 9.0e-7 (f_p)
STAB_TOL_SIGMA = 2e-5  # measured <= 2.0e-6


def _near_peak_normals(m):
    """Normals at ``rho in {0, 0.1, 0.5, 1, 2, 5, 20} alpha`` from ``m``, 16 azimuths each."""
    rho = np.array([0.0, 0.1, 0.5, 1.0, 2.0, 5.0, 20.0]) * STAB_ALPHA
    phi = np.linspace(0, 2 * np.pi, 16, endpoint=False)
    n, _ = _polar(_frame(m, [1.0, 0.0, 0.0]), rho, np.ones_like(rho), phi, np.ones_like(phi))
    return n.reshape(-1, 3)


@pytest.mark.parametrize("phi_p", [0.0, 90.0])
def test_sggx_float32_stable_near_peak(phi_p):
    """Float32 ``sggx_ndf``, ``sggx_sigma``, ``specular_phase`` against float64 textbook matrices.

    alpha = 0.002, theta_p = 5.5 deg. The reference takes the very float32
    inputs the code gets (upcast, not renormalised), so only the evaluation is
    compared. Measured maximum relative errors (x86 CPU): D 5.7e-6 (at
    ``rho = alpha``, where the float32 rounding of ``n x m``, ~1e-8 absolute, is
    largest relative to ``q = |n x m|^2 + alpha^2 (n.m)^2``), sigma 2.0e-6, f_p
    9.0e-7. Tolerances ``STAB_TOL_D = 5e-5`` and ``STAB_TOL_SIGMA = 2e-5``
    leave ~10x margin.

    The textbook forms evaluated in float32 fail them. With the same inputs::

        S = a*a*np.eye(3) + (1 - a*a)*np.outer(m, m)      # float32, a = float32(0.002)
        D = 1 / (np.pi*np.sqrt(np.linalg.det(S))*(n @ np.linalg.inv(S) @ n)**2)
        sigma = np.sqrt(w @ S @ w)

    give relative errors up to 1.5e-3 in D (LAPACK float32 ``det(S) = 1.60025e-11``
    against ``alpha^4 = 1.60000e-11``) and 1.5e-4 in sigma (at ``w`` normal to
    ``m``, where ``w^T S w = alpha^2`` is the difference of O(1) entries); Heitz et
    al.'s adjugate form ``det(S)^1.5 / (pi (n^T adj(S) n)^2)`` gives 7.6e-4.
    """
    a32 = np.float32(STAB_ALPHA)
    a64 = float(a32)
    m32 = _m32(STAB_THETA_P, phi_p)
    m64 = np.asarray(m32, np.float64)
    mn = m64 / np.linalg.norm(m64)

    n32 = np.float32(_near_peak_normals(mn))
    d_code = np.asarray(P.sggx_ndf(jnp.asarray(n32), jnp.asarray(m32), a32), np.float64)
    d_ref = _textbook_ndf(n32.astype(np.float64), m64, a64)
    err_d = np.max(np.abs(d_code / d_ref - 1))
    assert err_d < STAB_TOL_D, err_d

    beta = np.deg2rad([0.0, 1.0, 45.0, 89.0, 89.9, 89.99, 90.0, 90.01, 91.0, 135.0, 180.0])
    phi = np.linspace(0, 2 * np.pi, 16, endpoint=False)
    w, _ = _polar(_frame(mn, [1.0, 0.0, 0.0]), beta, np.ones_like(beta), phi, np.ones_like(phi))
    w32 = np.float32(w.reshape(-1, 3))
    s_code = np.asarray(P.sggx_sigma(jnp.asarray(w32), jnp.asarray(m32), a32), np.float64)
    s_ref = _textbook_sigma(w32.astype(np.float64), m64, a64)
    err_s = np.max(np.abs(s_code / s_ref - 1))
    assert err_s < STAB_TOL_SIGMA, err_s

    n = _near_peak_normals(mn)
    for w in [_w_incident(30.0), W_GRAZE_DOWN, W_GENERIC]:
        w32 = np.float32(w)
        w64 = w32.astype(np.float64)
        wo32 = np.float32(n - 2 * (n @ w64)[:, None] * n)  # mirror of w about normals near m
        f_code = np.asarray(
            P.specular_phase(jnp.asarray(w32), jnp.asarray(wo32), jnp.asarray(m32), a32), np.float64
        )
        h = wo32.astype(np.float64) - w64
        h /= np.linalg.norm(h, axis=-1, keepdims=True)
        f_ref = _textbook_ndf(h, m64, a64) / (4 * _textbook_sigma(w64, m64, a64))
        err_f = np.max(np.abs(f_code / f_ref - 1))
        assert err_f < STAB_TOL_D, (w, err_f)


# =========================================================================== 3. samplers: chi-square

N_SAMPLES = 200_000
HG_SAMPLER_G = [-0.999, -0.9, 0.0, 1e-6, 0.5, 0.99, 0.999]
SGGX_SAMPLER_CASES = [(1.0, 0.0), (0.5, 30.0), (0.13, 1.47), (0.02, 5.5), (0.49, 52.2)]  # (alpha, theta_p)
SGGX_SAMPLER_W = {"in30": _w_incident(30.0), "graze-": W_GRAZE_DOWN, "generic": W_GENERIC}
COSINE_N = {"z": np.array([0.0, 0.0, 1.0]), "generic": W_GENERIC}
# 7 HG + 5 x 3 SGGX + 2 cosine + 1 uniform-sphere = 25 goodness-of-fit tests share a 1%
# family-wise false-alarm rate.
N_SAMPLER_TESTS = len(HG_SAMPLER_G) + len(SGGX_SAMPLER_CASES) * len(SGGX_SAMPLER_W) + len(COSINE_N) + 1
P_MIN = 1.0 - (1.0 - 0.01) ** (1.0 / N_SAMPLER_TESTS)  # Sidak: 4.02e-4 for 25 tests

_HG_SAMPLE = jax.jit(P.hg_sample)
_SGGX_SAMPLE = jax.jit(P.sggx_sample)
_COSINE_SAMPLE = jax.jit(P.cosine_sample)
_UNIFORM_SPHERE = jax.jit(P.uniform_sphere)


def _random_inputs(seed):
    """``(u1, s)``: ``N_SAMPLES`` uniforms in [0, 1) and independent uniform unit vectors."""
    u = jax.random.uniform(jax.random.key(seed), (3, N_SAMPLES), dtype=jnp.float32)
    return u[0], _UNIFORM_SPHERE(u[1], u[2])


def _cell_edges(marginal, n_bins):
    """Panel-boundary indices splitting ``marginal`` into ~equal-probability cells.

    Boundaries where the density switches between zero and non-zero are always
    kept, so that a cell is either wholly of zero density or not.
    """
    cdf = np.concatenate([[0.0], np.cumsum(marginal)]) / marginal.sum()
    idx = np.searchsorted(cdf, np.linspace(0.0, 1.0, n_bins + 1)[1:-1])
    zero = marginal == 0
    switch = np.nonzero(zero[1:] != zero[:-1])[0] + 1
    return np.unique(np.concatenate([[0], idx, switch, [len(marginal)]]))


def _chi2_test(samples, frame, rho_breaks, phi_breaks, density, n_rho=40, n_phi=24, k=4):
    """Chi-square goodness of fit of unit-vector ``samples`` to ``density`` (Mitsuba 3's recipe).

    Cells are products of polar-angle and azimuth intervals about ``frame[2]``,
    made of whole quadrature panels (``rho_breaks`` x ``phi_breaks``) chosen at
    ~equal-probability quantiles of the two marginals. The expected count of a
    cell is ``N`` times the density integrated over it by ``k x k``-point
    Gauss-Legendre per panel. Cells expecting fewer than 5 samples are pooled;
    a sample in a cell of zero density fails outright.

    Returns ``(p_value, statistic, dof, integral of the density)``.
    """
    samples = np.asarray(samples, np.float64)
    n = samples.shape[0]
    assert np.all(np.isfinite(samples)), "non-finite sample"
    # A loose sanity check only (the statistic uses angles, which ignore length; section 4
    # checks lengths): the azimuth of hg_sample normalises s - (s.n) n, whose relative
    # rounding ~EPS32 / |s - (s.n) n| can exceed 1e-5 for the rare s within ~1e-2 of +-n.
    assert np.max(np.abs(np.linalg.norm(samples, axis=-1) - 1)) < 1e-3, "sample not unit"

    rho, w_rho = _gauss(rho_breaks, k)
    phi, w_phi = _gauss(phi_breaks, k)
    d, wt = _polar(frame, rho, w_rho, phi, w_phi)
    mass = (wt * density(d)).reshape(len(rho_breaks) - 1, k, len(phi_breaks) - 1, k).sum(axis=(1, 3))
    ir = _cell_edges(mass.sum(axis=1), n_rho)
    ip = _cell_edges(mass.sum(axis=0), n_phi)
    expected = n * np.add.reduceat(np.add.reduceat(mass, ir[:-1], axis=0), ip[:-1], axis=1)

    u, v, p = frame
    s_rho = np.arctan2(np.linalg.norm(np.cross(samples, p), axis=-1), samples @ p)
    s_phi = np.arctan2(samples @ v, samples @ u)
    observed, _, _ = np.histogram2d(s_rho, s_phi, bins=[rho_breaks[ir], phi_breaks[ip]])
    assert observed.sum() == n

    bad = (expected == 0) & (observed > 0)
    assert not bad.any(), f"{int(observed[bad].sum())} samples where the density is zero"
    small = expected < 5
    obs = np.append(observed[~small], observed[small & (expected > 0)].sum())
    exp = np.append(expected[~small], expected[small].sum())
    keep = exp > 0
    stat = np.sum((obs[keep] - exp[keep]) ** 2 / exp[keep])
    dof = int(keep.sum()) - 1
    return stats.chi2.sf(stat, dof), stat, dof, mass.sum()


def _hg_chi2(g_sample, g_density, seed):
    w32 = np.float32(W_GENERIC)
    u1, sphere = _random_inputs(seed)
    w_batch = jnp.broadcast_to(jnp.asarray(w32), sphere.shape)
    samples = _HG_SAMPLE(w_batch, jnp.float32(g_sample), u1, sphere)
    w = np.asarray(w32, np.float64)
    frame = _frame(w if g_density >= 0 else -w, [0.0, 0.0, 1.0])
    finest = max(1.0 - abs(g_density), 1e-3) / 20
    rho_breaks = _breaks(0.0, np.pi, [0.0, np.pi], finest, 6)
    phi_breaks = np.linspace(-np.pi, np.pi, 25)
    return _chi2_test(samples, frame, rho_breaks, phi_breaks, lambda d: _eval32(_HG32, d, w32, g_density))


@pytest.mark.parametrize("g", HG_SAMPLER_G)
def test_hg_sample_matches_density(g):
    """``hg_sample`` draws from ``hg`` (chi-square, cells about the peak ``+-w``)."""
    p, stat, dof, total = _hg_chi2(g, g, seed=100 + HG_SAMPLER_G.index(g))
    assert abs(total - 1) < 1e-3, total
    assert p > P_MIN, f"g={g}: chi2={stat:.1f} dof={dof} p={p:.2e} < {P_MIN:.2e}"


@pytest.mark.parametrize("g", [-0.999, -0.5, 0.0, 0.5, 0.999])
def test_hg_sample_polar_angle_accurate(g):
    """The polar angle of ``hg_sample`` matches the float64 inverse CDF to 2e-6 rad, and ``|w'| = 1``.

    ``theta = acos((1 + g^2 - ((1 - g^2) / (1 - g + 2 g u))^2) / (2 g))`` in float64
    (``2 u - 1`` at ``g = 0``) for the same float32 ``u``. Measured <= 2.0e-7 rad.
    A sampler that rounds the cosine to float32 and takes ``sqrt(1 - c^2)`` is off by
    up to 2.4e-4 rad near ``c = +-1`` (a quarter of the lobe at ``|g| = 0.999``); the
    form ``c = (2 (1 + g^2) u (1 - g + g u) - (1 - g)^2) / d^2`` errs by 0.2 in ``c``
    at ``g = -0.999``, ``u -> 1``.
    """
    u1, sphere = _random_inputs(600)
    w = jnp.broadcast_to(jnp.float32([0.0, 0.0, 1.0]), sphere.shape)
    x = np.asarray(_HG_SAMPLE(w, jnp.float32(g), u1, sphere), np.float64)
    u = np.asarray(u1, np.float64)
    g64 = float(np.float32(g))
    if g64 == 0.0:
        c = 2 * u - 1
    else:
        c = (1 + g64 * g64 - ((1 - g64 * g64) / (1 - g64 + 2 * g64 * u)) ** 2) / (2 * g64)
    theta = np.arctan2(np.hypot(x[:, 0], x[:, 1]), x[:, 2])
    err = np.abs(theta - np.arccos(np.clip(c, -1, 1)))
    assert err.max() < 2e-6, f"g={g}: max polar-angle error {err.max():.2e} rad"
    _assert_unit(f"g={g}", x)


def _sggx_chi2(alpha_sample, theta_p_sample, w, seed, alpha_density=None, theta_p_density=None):
    alpha_density = alpha_sample if alpha_density is None else alpha_density
    theta_p_density = theta_p_sample if theta_p_density is None else theta_p_density
    w32 = np.float32(w)
    _, sphere = _random_inputs(seed)
    m_s = jnp.asarray(_m32(theta_p_sample, 0.0))
    samples = _SGGX_SAMPLE(jnp.asarray(w32), m_s, jnp.float32(alpha_sample), sphere)
    m32 = _m32(theta_p_density, 0.0)
    mn = _unit(np.asarray(m32, np.float64))
    wn = _unit(np.asarray(w32, np.float64))
    b = max(abs(wn @ mn), 1e-3)
    r = _reflect(wn, mn)
    # Cells about the mirror direction r, graded to the lobe (alpha |w.m| across, alpha along
    # the great circle through r and w, which is azimuth 0 and pi of this frame).
    rho_breaks = _breaks(0.0, np.pi, [0.0, _angle(r, wn)], 0.05 * alpha_density * b, 6)
    phi_breaks = _breaks(-np.pi, np.pi, [-np.pi, 0.0, np.pi], b / 8, 6)
    return _chi2_test(
        samples,
        _frame(r, wn),
        rho_breaks,
        phi_breaks,
        lambda d: _eval32(_SPEC32, d, w32, m32, alpha_density),
    )


@pytest.mark.parametrize("w_name", list(SGGX_SAMPLER_W))
@pytest.mark.parametrize("alpha,theta_p", SGGX_SAMPLER_CASES)
def test_sggx_sample_matches_density(alpha, theta_p, w_name):
    """``sggx_sample`` draws from ``specular_phase`` (chi-square, cells about the mirror direction)."""
    seed = 200 + 10 * SGGX_SAMPLER_CASES.index((alpha, theta_p)) + list(SGGX_SAMPLER_W).index(w_name)
    p, stat, dof, total = _sggx_chi2(alpha, theta_p, SGGX_SAMPLER_W[w_name], seed)
    assert abs(total - 1) < 1e-3, total
    assert p > P_MIN, f"alpha={alpha} theta_p={theta_p} w={w_name}: chi2={stat:.1f} dof={dof} p={p:.2e}"


@pytest.mark.parametrize("n_name", list(COSINE_N))
def test_cosine_sample_matches_density(n_name):
    """``cosine_sample`` draws from ``<w, n>+ / pi``; no sample may fall below the horizon of ``n``."""
    n = COSINE_N[n_name]
    n32 = np.float32(n)
    _, sphere = _random_inputs(300 + list(COSINE_N).index(n_name))
    samples = _COSINE_SAMPLE(jnp.asarray(n32), sphere)
    nn = _unit(np.asarray(n32, np.float64))
    rho_breaks = np.union1d(np.linspace(0.0, np.pi, 37), [np.pi / 2])
    p, stat, dof, total = _chi2_test(
        samples,
        _frame(nn, [1.0, 0.0, 0.0]),
        rho_breaks,
        np.linspace(-np.pi, np.pi, 25),
        lambda d: np.maximum(d @ nn, 0.0) / np.pi,
    )
    assert abs(total - 1) < 1e-6, total
    assert p > P_MIN, f"n={n_name}: chi2={stat:.1f} dof={dof} p={p:.2e}"


def test_uniform_sphere_matches_density():
    """``uniform_sphere`` (the azimuth source of every sampler) is uniform: density ``1 / (4 pi)``."""
    u = jax.random.uniform(jax.random.key(350), (2, N_SAMPLES), dtype=jnp.float32)
    samples = _UNIFORM_SPHERE(u[0], u[1])
    p, stat, dof, total = _chi2_test(
        samples,
        _frame(_unit([0.2, 0.3, 0.9]), [1.0, 0.0, 0.0]),
        np.linspace(0.0, np.pi, 37),
        np.linspace(-np.pi, np.pi, 25),
        lambda d: np.full(d.shape[:-1], 1 / (4 * np.pi)),
    )
    assert abs(total - 1) < 1e-6, total
    assert p > P_MIN, f"chi2={stat:.1f} dof={dof} p={p:.2e}"


def test_chi2_rejects_perturbed_densities():
    """The statistic has power: samples tested against a slightly wrong density are rejected.

    HG samples at g = 0.5 against the density at g = 0.55; SGGX samples at
    alpha = 0.13 against alpha = 0.14 (theta_p = 1.47, w at 30 deg); SGGX
    samples at theta_p = 1.47 against theta_p = 2 (alpha = 0.13).
    """
    p, stat, dof, _ = _hg_chi2(0.5, 0.55, seed=400)
    assert p < P_MIN, (p, stat, dof)
    p, stat, dof, _ = _sggx_chi2(0.13, 1.47, _w_incident(30.0), 401, alpha_density=0.14)
    assert p < P_MIN, (p, stat, dof)
    p, stat, dof, _ = _sggx_chi2(0.13, 1.47, _w_incident(30.0), 402, theta_p_density=2.0)
    assert p < P_MIN, (p, stat, dof)


# =========================================================================== 4. hard cases

UNIT_TOL = 1e-5  # | |w'| - 1 | of a sampled direction: ~170 float32 ulps (a normalise and a reflection
#                  round to a few ulps; measured <= 1.3e-6 over all the cases below)
G_HARD = [-0.999, 0.0, 0.999]
ALPHA_HARD = [1e-4, 0.002, 1.0]
THETA_P_HARD = [0.0, 5.5, 52.2, 90.0]
U_HARD = [0.0, 1e-7, 0.5, 1.0 - 2.0**-24]  # uniforms in [0, 1), both ends included


def _hard_dirs():
    """Float32 unit directions: +-z, grazing with z = +-1e-7 and z = +-cos(89.9 deg), a generic one."""
    c = np.cos(np.deg2rad(89.9))
    dirs = [[0, 0, 1], [0, 0, -1], [1, 0, 1e-7], [1, 0, -1e-7], [np.sqrt(1 - c * c), 0, c], [0, np.sqrt(1 - c * c), -c]]
    return np.float32([_unit(d) for d in dirs] + [W_GENERIC])


def _hard_spheres():
    """Uniform unit vectors from ``uniform_sphere`` at the corners of its domain (the poles included)."""
    u1, u2 = np.meshgrid(np.float32(U_HARD), np.float32([0.0, 0.3, 1.0 - 2.0**-24]), indexing="ij")
    return np.asarray(P.uniform_sphere(jnp.asarray(u1.ravel()), jnp.asarray(u2.ravel())))


def _assert_finite(label, *arrays):
    for i, a in enumerate(arrays):
        a = np.asarray(a)
        assert np.all(np.isfinite(a)), f"{label}: output {i} has {np.sum(~np.isfinite(a))} non-finite entries"


def _assert_unit(label, x):
    err = np.abs(np.linalg.norm(np.asarray(x, np.float64), axis=-1) - 1)
    assert err.max() <= UNIT_TOL, f"{label}: | |w'| - 1 | = {err.max():.2e} (worst of {err.size})"


@pytest.mark.parametrize("g", G_HARD)
def test_hg_hard_cases_finite(g):
    """``hg`` and ``d hg / d g`` are finite for all pairs of hard directions, forward (w' = w) included.

    ``d hg / d g`` is also checked against the float64 derivative of the
    textbook formula, and across ``g = 0`` (the code switches between
    ``|w' - w|`` and ``|w' + w|`` forms there): at ``g = 0`` it must be
    ``3 c / (4 pi)``. Measured derivative error <= 2.5e-7 of the size of its terms.
    """
    dirs = _hard_dirs()
    dirs = np.concatenate([dirs, -dirs])
    w = np.repeat(dirs, len(dirs), axis=0)
    wo = np.tile(dirs, (len(dirs), 1))
    f = jax.jit(jax.vmap(jax.value_and_grad(lambda w, wo, g: P.hg(w, wo, g), argnums=2), in_axes=(0, 0, None)))
    val, dg = f(jnp.asarray(w), jnp.asarray(wo), jnp.float32(g))
    _assert_finite(f"g={g}", val, dg)
    assert np.all(np.asarray(val) > 0)
    # float64 derivative of the same function of the float32 inputs (with non-unit inputs,
    # 1 + g^2 - 2 g w.w' and the code's (1 - |g|)^2 + |g| |w' -+ w|^2 differ; at w' = w and
    # g = 0.999 by 10%)
    g64 = float(np.float32(g))
    sign = 1.0 if g64 >= 0 else -1.0
    d = wo.astype(np.float64) - sign * w.astype(np.float64)
    d2 = np.einsum("ij,ij->i", d, d)
    base = (1 - abs(g64)) ** 2 + abs(g64) * d2
    dbase = sign * (-2 * (1 - abs(g64)) + d2)
    f64 = (1 - g64 * g64) / (4 * np.pi * base**1.5)
    d64 = f64 * (-2 * g64 / (1 - g64 * g64) - 1.5 * dbase / base)
    # float32 error of the derivative: ~1e-6 relative to the size of its two terms
    scale = f64 * (2 * abs(g64) / (1 - g64 * g64) + 1.5 * (2 * (1 - abs(g64)) + d2) / base)
    err = np.abs(np.asarray(dg) - d64) / scale
    assert err.max() < 1e-5, err.max()
    c = np.einsum("ij,ij->i", w.astype(np.float64), wo.astype(np.float64))
    if g == 0.0:
        near = [f(jnp.asarray(w), jnp.asarray(wo), jnp.float32(e))[1] for e in (-1e-6, 1e-6)]
        np.testing.assert_allclose(np.asarray(dg), 3 * c / (4 * np.pi), rtol=1e-6, atol=1e-7)
        for d in near:
            np.testing.assert_allclose(np.asarray(d), np.asarray(dg), rtol=1e-4, atol=1e-6)


@pytest.mark.parametrize("g", G_HARD)
def test_hg_sample_hard_cases_finite(g):
    """``hg_sample`` gives finite unit vectors, and a finite Jacobian in ``g``, at the hard cases.

    Includes ``w = +-z`` with ``s = uniform_sphere(0, .) = +z``, i.e. ``s = +-w``
    exactly: normal incidence at the first event of a walk meets it with
    probability ~1e-7 per path.
    """
    dirs, spheres = _hard_dirs(), _hard_spheres()
    w = np.repeat(dirs, len(U_HARD) * len(spheres), axis=0)
    u1 = np.tile(np.repeat(np.float32(U_HARD), len(spheres)), len(dirs))
    s = np.tile(spheres, (len(dirs) * len(U_HARD), 1))

    def sample(w, g, u1, s):
        return P.hg_sample(w, g, u1, s)

    f = jax.jit(jax.vmap(lambda w, g, u1, s: (sample(w, g, u1, s), jax.jacfwd(sample, argnums=1)(w, g, u1, s)),
                         in_axes=(0, None, 0, 0)))
    x, dx = f(jnp.asarray(w), jnp.float32(g), jnp.asarray(u1), jnp.asarray(s))
    _assert_finite(f"g={g}", x, dx)
    _assert_unit(f"g={g}", x)


def _sggx_hard_inputs():
    """``(w, theta_p, alpha)`` rows: hard directions, and ``w = +-m`` exactly, for every theta_p and alpha."""
    rows = []
    for theta_p in THETA_P_HARD:
        m = _m32(theta_p, 0.0)
        for w in list(_hard_dirs()) + [m, -m]:
            for alpha in ALPHA_HARD:
                rows.append((np.float32(w), np.float32(theta_p), np.float32(alpha)))
    w, t, a = zip(*rows)
    return np.stack(w), np.asarray(t), np.asarray(a)


def _grads_theta_alpha(fn):
    """``x -> (fn(..., theta_p, alpha), d fn / d theta_p, d fn / d alpha)``, vmapped and jitted."""

    def one(*args):
        *rest, theta_p, alpha = args
        value = fn(*rest, theta_p, alpha)
        jac = jax.jacfwd(fn, argnums=(len(rest), len(rest) + 1))(*rest, theta_p, alpha)
        return value, jac

    return jax.jit(jax.vmap(one))


def test_sggx_sigma_ndf_hard_cases_finite():
    """``sggx_sigma`` and ``sggx_ndf`` (at ``n = +-m``, the peak, and at hard normals) with their gradients."""
    w, t, a = _sggx_hard_inputs()
    sig = _grads_theta_alpha(lambda w, t, a: P.sggx_sigma(w, P.mean_normal(t, 0.0), a))
    val, (dt, da) = sig(jnp.asarray(w), jnp.asarray(t), jnp.asarray(a))
    _assert_finite("sggx_sigma", val, dt, da)
    val = np.asarray(val, np.float64)
    assert np.all(val >= a * (1 - 1e-6)) and np.all(val <= 1 + 1e-6), "sigma outside [alpha, 1]"
    ndf = _grads_theta_alpha(lambda n, t, a: P.sggx_ndf(n, P.mean_normal(t, 0.0), a))
    val, (dt, da) = ndf(jnp.asarray(w), jnp.asarray(t), jnp.asarray(a))
    _assert_finite("sggx_ndf", val, dt, da)
    at_m = np.array([np.allclose(wi, _m32(ti, 0.0)) or np.allclose(wi, -_m32(ti, 0.0)) for wi, ti in zip(w, t)])
    a64 = a.astype(np.float64)
    np.testing.assert_allclose(np.asarray(val)[at_m], 1 / (np.pi * a64[at_m] ** 2), rtol=1e-6)


def test_specular_phase_hard_cases_finite():
    """``specular_phase`` and ``flake_reflection`` with gradients at w' = w, at the mirror peak, at -w, grazing.

    The forward direction ``w' = w`` has no half vector: the documented value is 0.
    """
    w, t, a = _sggx_hard_inputs()
    m = np.stack([_m32(ti, 0.0) for ti in t]).astype(np.float64)
    w64 = w.astype(np.float64)
    mirror = np.float32(w64 - 2 * np.einsum("ij,ij->i", w64, m)[:, None] * m)
    outs = {"forward": w, "mirror": mirror, "backward": -w, "graze": np.tile(_hard_dirs()[2], (len(w), 1))}
    for name, fn in [("specular_phase", P.specular_phase), ("flake_reflection", P.flake_reflection)]:
        f = _grads_theta_alpha(lambda w, wo, t, a, fn=fn: fn(w, wo, P.mean_normal(t, 0.0), a))
        for out_name, wo in outs.items():
            val, (dt, da) = f(jnp.asarray(w), jnp.asarray(wo), jnp.asarray(t), jnp.asarray(a))
            _assert_finite(f"{name} w'={out_name}", val, dt, da)
            assert np.all(np.asarray(val) >= 0)
            if out_name == "forward":
                assert np.all(np.asarray(val) == 0) and np.all(np.asarray(dt) == 0) and np.all(np.asarray(da) == 0)


def test_sggx_sample_hard_cases_finite():
    """``sggx_sample`` gives finite unit vectors and finite Jacobians in ``theta_p`` and ``alpha``.

    Hard directions and ``w = +-m``, alpha down to 1e-4, ``s`` at the poles
    and corners of ``uniform_sphere``.
    """
    w, t, a = _sggx_hard_inputs()
    spheres = _hard_spheres()
    idx = np.repeat(np.arange(len(w)), len(spheres))
    s = np.tile(spheres, (len(w), 1))
    f = _grads_theta_alpha(lambda w, s, t, a: P.sggx_sample(w, P.mean_normal(t, 0.0), a, s))
    x, (dt, da) = f(jnp.asarray(w[idx]), jnp.asarray(s), jnp.asarray(t[idx]), jnp.asarray(a[idx]))
    _assert_finite("sggx_sample", x, dt, da)
    _assert_unit("sggx_sample", x)


@pytest.mark.parametrize("alpha", [1e-4, 0.002, 0.02])
def test_sggx_sample_unit_at_small_alpha(alpha):
    """Over ``N_SAMPLES`` jitted draws per case, every ``sggx_sample`` output is a unit vector.

    Near-specular flakes make the visible-normal map ill-conditioned where
    ``v`` grazes the horizon of ``k`` (``d n / d v ~ 1 / alpha``); a formulation that
    rounds differently in the different XLA fusions that recompute the same
    intermediate returns directions of norm up to 1.3 at alpha = 1e-4.
    """
    _, spheres = _random_inputs(500)
    for theta_p in (0.0, 5.5, 52.2):
        m = jnp.asarray(_m32(theta_p, 0.0))
        for name, w in {"in30": _w_incident(30.0), "graze-": W_GRAZE_DOWN, "generic": W_GENERIC}.items():
            x = _SGGX_SAMPLE(jnp.asarray(np.float32(w)), m, jnp.float32(alpha), spheres)
            _assert_finite(f"theta_p={theta_p} w={name}", x)
            _assert_unit(f"alpha={alpha} theta_p={theta_p} w={name}", x)


def test_cosine_and_uniform_sphere_hard_cases():
    """``cosine_sample`` about ``n(theta_p)`` (incl. ``s = +-n`` exactly) and ``uniform_sphere`` at its corners."""
    spheres = _hard_spheres()
    _assert_finite("uniform_sphere", spheres)
    _assert_unit("uniform_sphere", spheres)
    thetas = np.float32([0.0, 5.5, 90.0, 179.99, 180.0])
    rows_t, rows_s = [], []
    for theta in thetas:
        n = _m32(theta, 0.0)
        for s in list(spheres) + [n, -n]:
            rows_t.append(theta)
            rows_s.append(s)
    t, s = jnp.asarray(np.float32(rows_t)), jnp.asarray(np.float32(rows_s))

    def sample(t, s):
        return P.cosine_sample(P.mean_normal(t, 0.0), s)

    f = jax.jit(jax.vmap(lambda t, s: (sample(t, s), jax.jacfwd(sample)(t, s))))
    x, dx = f(t, s)
    _assert_finite("cosine_sample", x, dx)
    _assert_unit("cosine_sample", x)
    n = np.stack([_m32(ti, 0.0) for ti in rows_t]).astype(np.float64)
    assert np.all(np.einsum("ij,ij->i", np.asarray(x, np.float64), n) >= -1e-6), "sample below the horizon of n"


def test_mean_normal_convention():
    """``m = (sin tp cos pp, sin tp sin pp, cos tp)`` (docs/model.md section 2); ``phi_p = 90`` tilts towards +y."""
    for tp, pp in [(0.0, 0.0), (5.5, 0.0), (52.2, 90.0), (30.0, 45.0)]:
        t, p = np.deg2rad(tp), np.deg2rad(pp)
        ref = [np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)]
        np.testing.assert_allclose(_m32(tp, pp), ref, atol=2e-7)


def test_float32_under_test():
    """The code under test runs in float32 (JAX's default): x64 must not be switched on for these tests."""
    assert not jax.config.jax_enable_x64
    assert P.hg(jnp.ones(3) / jnp.sqrt(3.0), jnp.ones(3) / jnp.sqrt(3.0), 0.5).dtype == jnp.float32
