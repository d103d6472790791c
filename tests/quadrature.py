"""Quadrature shared by the statistical tests (imported by them; pytest puts this folder on the path)."""

import numpy as np


def half_hemisphere_grid(nmu, nphi):
    """Directions and weights of ``int f(wo) cos(theta_o) dwo`` for a BSDF symmetric under ``y -> -y``.

    Gauss-Legendre in ``mu``; in ``phi``, the trapezoidal rule on ``[0, 180]``
    degrees (endpoints at half weight), which for an even function of ``phi``
    is the trapezoidal rule on the full circle with ``2 (nphi - 1)`` nodes
    (spectrally accurate for smooth periodic integrands).
    """
    x, w = np.polynomial.legendre.leggauss(nmu)
    mu, w_mu = (x + 1) / 2, w / 2
    phi = np.linspace(0.0, 180.0, nphi)
    w_phi = np.full(nphi, 2 * np.pi / (2 * (nphi - 1)))
    w_phi[1:-1] *= 2
    MU, PHI = np.meshgrid(mu, phi, indexing="ij")
    return np.degrees(np.arccos(MU)).ravel(), PHI.ravel(), np.outer(w_mu * mu, w_phi).ravel()
