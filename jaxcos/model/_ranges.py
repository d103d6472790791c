"""The ranges of the material parameters: the one table of them.

Per parameter of docs/model.md sections 2 and 3a: its physically valid domain
(with open or closed ends), against which ``params.json`` is validated
(:mod:`jaxcos.io`), and how a fit reaches it (:mod:`jaxcos.inference`): the map
from an unbounded coordinate ``x`` and the fit's bounds, inside the domain,
which are also the support of a posterior's uniform prior. ``theta_p`` and
``phi_p`` are in degrees.

The fit's maps: ``"logistic"``, ``low + (high - low) sigmoid(x)``;
``"loglogistic"``, ``low (high / low)^sigmoid(x)`` (for a roughness that spans
decades); ``"tanh"``, ``high tanh(x)`` (``low = -high``); ``"exp"``, ``exp(x)``
onto ``(0, inf)``, ``high`` bounding the prior alone.
"""

import dataclasses
import math

G_MAX = 0.9999
"""The fit's bound on ``|g1|``, ``|g2|``: ``|g| = 1`` is a delta function, and the map keeps float32 iterates off it."""
ALPHA_MIN = 1e-4
"""The fit's lower bound on ``alpha_p``: ``alpha_p = 0`` is a mirror with no width."""


@dataclasses.dataclass(frozen=True)
class Range:
    """One parameter's physical domain and the fit's map onto part of it.

    Attributes:
        key: its key in ``params.json`` (docs/formats.md).
        kind: ``"scalar"``, or ``"rgb"`` (three values, one per channel).
        low, high: the ends of the physical domain.
        low_open, high_open: whether that end is excluded.
        fit_map: the fit's map from an unbounded coordinate (module docstring), or ``None``: never fitted.
        fit_low, fit_high: the fit's bounds, the support of a uniform prior.
    """

    key: str
    kind: str
    low: float
    high: float
    low_open: bool
    high_open: bool
    fit_map: str | None = None
    fit_low: float | None = None
    fit_high: float | None = None

    @property
    def size(self):
        """Entries of the parameter: 3 for an RGB one, else 1."""
        return 3 if self.kind == "rgb" else 1

    def contains(self, value):
        """Whether the number ``value`` lies in the physical domain."""
        above = value > self.low if self.low_open else value >= self.low
        below = value < self.high if self.high_open else value <= self.high
        return above and below

    def interval(self):
        """The domain as written in messages, e.g. ``(0, 1]``."""
        lo, hi = ("(" if self.low_open else "["), (")" if self.high_open else "]")
        return f"{lo}{self.low:g}, {self.high:g}{hi}"


LAYER_RANGES = {
    # field of Layer: its range, in the order of a params.json layer
    "t": Range("t", "scalar", 0.0, math.inf, False, True, "exp", 0.0, 1e3),
    "c_d": Range("c_d", "scalar", 0.0, 1.0, False, False, "logistic", 0.0, 1.0),
    "albedo_d": Range("albedo_d", "rgb", 0.0, 1.0, False, False, "logistic", 0.0, 1.0),
    "g1": Range("g1", "scalar", -1.0, 1.0, True, True, "tanh", -G_MAX, G_MAX),
    "g2": Range("g2", "scalar", -1.0, 1.0, True, True, "tanh", -G_MAX, G_MAX),
    "w_g": Range("w_g", "scalar", 0.0, 1.0, False, False, "logistic", 0.0, 1.0),
    "albedo_p": Range("albedo_p", "rgb", 0.0, 1.0, False, False, "logistic", 0.0, 1.0),
    "alpha_p": Range("alpha_p", "scalar", 0.0, 1.0, True, False, "logistic", ALPHA_MIN, 1.0),
    "theta_p": Range("theta_p_deg", "scalar", 0.0, 90.0, False, False, "logistic", 0.0, 90.0),
}
"""The parameters a ``params.json`` layer must give, by field of :class:`~jaxcos.Layer`."""

PHI_RANGE = Range("phi_p_deg", "scalar", -360.0, 360.0, False, False, "tanh", -180.0, 180.0)
"""``phi_p``, the platelets' tilt azimuth: optional in a layer of ``params.json`` (default 0)."""

INTERFACE_RANGES = {
    # eta = 1 is no interface (leave the key out; a variant, never a value); alpha_s log-logistic in a fit,
    # since gloss spans decades of roughness
    "eta": Range("eta", "scalar", 1.0, 3.0, True, False, "logistic", 1.01, 2.5),
    "alpha_s": Range("alpha_s", "scalar", 0.0, 1.0, True, False, "loglogistic", 0.005, 1.0),
}
"""The parameters of a top :class:`~jaxcos.Interface`, its ``"interface"`` object in ``params.json``."""

BASE_ALBEDO_RANGE = Range("albedo", "rgb", 0.0, 1.0, False, False)
"""The albedo of a Lambertian base (never fitted)."""

RANGES = {**LAYER_RANGES, "phi_p": PHI_RANGE, **INTERFACE_RANGES}
"""Every fitted parameter's :class:`Range`, by name: the layer's, ``phi_p`` and the interface's."""
