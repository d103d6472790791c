"""Fitting a material to measurements: Levenberg-Marquardt (optimistix) and a Powell baseline.

The objective is the sum of squared residuals ``(model - measured) / std``
(``std = 1`` when the file has no standard deviations), in the file's own
quantity (docs/formats.md), over every measured point and colour channel. The
model is the Monte Carlo BSDF of docs/model.md under a fixed key and fixed
lobe-selection probabilities (common random numbers), so the objective is a
deterministic function of the parameters, and its Jacobian comes from
differences of the same walks (of its first :data:`FIT_JACOBIAN_WALKS` walks:
a descent direction needs no more; :meth:`Problem.jacobian`). The lobe
probabilities and the Monte Carlo share of the weights are fixed numbers
within a solver pass, set again at the start of each of :data:`PASSES`
passes.

:func:`fit` is a pipeline of named stages: :func:`screen` (a few steps from
every start, ranked), the refinement of the best (:class:`Refiner`,
:data:`PASSES` passes each), :func:`select` (every refined start checked under
independent keys, which a fit cannot have tuned itself to; the best check
wins), :func:`refine_finer` (the winner refined again at :data:`FINE_FACTOR`
times the walks where its objective is rough, kept where its check is
better), :func:`polish` (last Gauss-Newton steps on the winner's pooled
check residuals, each kept where a check under fresh keys says it is better) and
:func:`summarise` (a :class:`FitResult` with its typed :class:`FitRecord`).
Why each stage is there, with the measurements that decided it:
docs/method.md.

Parameters are mapped to unbounded coordinates so every iterate is physical
(the fit's maps and bounds of :data:`jaxcos.model.RANGES`): ``c_d``, ``w_g``,
the albedos, ``alpha_p``, ``theta_p`` (degrees) and ``eta`` by a logistic
function onto their bounds, ``alpha_s`` by a log-logistic one, ``g1``, ``g2``
and ``phi_p`` (degrees) by a scaled ``tanh``, ``t`` by ``exp``.

Example::

    import jaxcos
    meas = jaxcos.load_measurements("measurements/dewy1.csv")
    result = jaxcos.fit(meas)
    result.material, result.record.check.reduced_chi2
"""

import abc
import concurrent.futures
import dataclasses
import functools
import threading
import time
from typing import ClassVar, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx

from .._errors import InputError
from ..model import FIT_BUDGET, FIT_JACOBIAN_WALKS, FIXED, RANGES, Interface, Layer, Material, check_variant
from ..model import Budget as _MCBudget
from ..model import boundary_probability, lobe_probabilities, make_query, simulate

FIT_WALKS = FIT_BUDGET.walks
"""Walks per incidence direction of the objective's value in a fit (:data:`jaxcos.model.FIT_BUDGET`)."""
FIT_BOUNCES = FIT_BUDGET.bounces
"""Bounces per walk in a fit (:data:`jaxcos.model.FIT_BUDGET`)."""

PASSES = 2
"""Solver passes per refined start. A pass holds the lobe-selection
probabilities and the Monte Carlo share of the weights fixed, at their values
at its start (:func:`with_mc_error`); a start far from the optimum sets them
badly, so each further pass sets them again where the previous one ended
(docs/method.md)."""
SCREEN_STEPS = 5
"""Levenberg-Marquardt steps each start gets in the screen (at half the Jacobian's walks, a quarter of the bounces)."""
CHECK_FACTOR = 16
"""Every refined start is checked with this many times the fit's walks under independent keys
(:func:`check`). The fit is the start whose ``material_chi2`` there is lowest, allowing for the check's
uncertainty: its bound ``material_chi2 + 2 material_chi2_se`` (:attr:`CheckResult.bound`) is lowest (not
its loss, which another key need not reproduce), so a material whose estimate rare walks dominate (a
near-mirror lobe) cannot win on a lucky batch. With :data:`CHECK_BATCHES` batches each batch has the
fit's own walks, so the check runs the program that sets the fit's weights, with nothing more to
compile (docs/method.md, "Checks under independent keys")."""
FINAL_DAMPING = 0.1
"""Marquardt damping of the fit's last steps (:func:`gauss_newton_step`): damped Gauss-Newton steps on the
pooled residuals of the best start's check, each kept where a check of its own, under fresh keys, scores it
better. Under one fixed key the fit follows that key's Monte Carlo error; the check's pooled model has
``1 / CHECK_FACTOR`` of its variance. Undamped, the step runs along directions the data hardly constrain
(docs/method.md, "The last steps")."""
POLISH_STEPS = 5
"""At most this many Gauss-Newton steps along one Jacobian in the polish stage (:func:`polish`); its steps
along that Jacobian stop at the first one their check does not keep."""
POLISH_ROUNDS = 3
"""At most this many Jacobians in the polish stage (:func:`polish`): where the steps along one kept at least
one, a new Jacobian is taken where they ended and the steps go on along it. A Jacobian taken at the start
describes the objective there; on seed 8's failing recovery sets, where the fit's one round of steps had
ended, a second Jacobian at its end took the score from 1.21, 1.22, 1.45, 1.51 times the truth's chi-square to
1.02, 1.14, 1.09, 1.13, and in whole fits sets 31 and 2 came to pass (1.01, 1.16), for 20-40 s more per fit
(benchmarks/RESULTS.md, "Dewy2 and the final step")."""
POLISH_JACOBIAN_FACTOR = 8
"""The polish's Jacobians (:func:`polish`) are taken from this many times the fit's walks. Where the
objective is rough its columns along the parameters that move directions are rough too: at the fit's 1024
walks, on a recovery set of narrow platelets (seed 8's set 21), the ``g1`` column's cosine with the 8192-walk
one was 0.64 (``alpha_p`` 0.70, ``c_d`` 0.86), and steps along it checked no better; along the 8192-walk one
three steps took the check from 2.25 to 1.35 per degree of freedom (the truth: 1.12; benchmarks/RESULTS.md,
"Dewy2 and the final step")."""
CHECK_BATCHES = 16
"""The check's walks run in this many batches under independent keys: pairs of batches estimate
the material's chi-square and its standard error (:func:`_pair_chi2`)."""
METHODS = ("lm", "powell")
"""The solvers of :func:`fit`: Levenberg-Marquardt (optimistix) and SciPy's modified Powell (the paper's)."""

# Free parameters of each variant, in order (their sizes: jaxcos.model.RANGES).
_FREE = {
    "two_lobe": ("c_d", "albedo_d", "g1", "g2", "w_g", "albedo_p", "alpha_p", "theta_p"),
    "single_lobe": ("c_d", "albedo_d", "g1", "albedo_p", "alpha_p", "theta_p"),
    "diffusers_only": ("albedo_d", "g1", "g2", "w_g"),
    "platelets_only": ("albedo_p", "alpha_p", "theta_p"),
}

# Default values of the parameters a variant does not fit, and the default start.
_DEFAULT = dict(t=16.0, c_d=0.7, albedo_d=(0.8, 0.8, 0.8), g1=0.5, g2=-0.2, w_g=0.7,
                albedo_p=(0.8, 0.8, 0.8), alpha_p=0.2, theta_p=2.0, phi_p=0.0)
# The second fixed start of the screen: platelets dominate, broad and tilted (matte finishes).
_PLATELET_START = dict(c_d=0.3, theta_p=45.0, alpha_p=0.5)
# A third, where the measured highlight is narrower than the angular sampling (:func:`narrow_highlight`):
# sparse near-mirror platelets in the diffusers, tilted to the highlight.
_MIRROR_START = dict(c_d=0.9, alpha_p=0.003)
NARROW_RATIO = 1.5
"""A highlight is narrower than the angular sampling (:func:`narrow_highlight`) when, in the median
over incidences, its brightest point exceeds both neighbours by more than this factor (docs/method.md,
"Near-mirror highlights")."""
END_NARROW_RATIO = 10.0
"""Where no incidence's brightest point has measured neighbours on both sides, one at an end of the range
this many times its neighbour is a narrow highlight's (:func:`_peaks`). A GGX lobe falls from its peak to a
viewing step ``d`` away by at most ``(1 + tan^2(d / 2) / alpha_p^2)^2`` (:func:`highlight_width`), so such a
point bounds ``alpha_p`` below ``tan(d / 2) / 1.47``, a third of what :data:`NARROW_RATIO` bounds between
two neighbours; on the recovery sets whose highlight lay at the range's end, broad lobes (``alpha_p``
0.056-0.113) rose 1.8-2.5 times over the last step, and one of ``alpha_p`` 0.006, seen at one incidence,
342 times (benchmarks/RESULTS.md, "The search on random materials")."""
SURFACE_GROWTH = 2.0
"""The measured gloss is a surface's (:func:`gloss_growth`) when it grows with incidence this many times
faster than single scattering in a medium of diffusers: 2.6 times on the real Clarins 105 (Dewy 1); at
most 1.04 times on the bundled sets and 1.53 on 40 random materials of the recovery benchmark (seeds 2
and 4, sets 0-19), all made without an interface; 2.6-14 times on 6 of 10 random materials under an
interface (seed 2; the other four's surfaces reflect little: 0.96-1.49)."""
# Key streams: fold_in(key, stream) of the fit's key, one per stage that needs walks independent of the
# objective's (which uses the key itself).
CHECK_STREAM = 1
"""The checks of the refined starts (:func:`select`)."""
SCREEN_STREAM = 2
"""The screen's batches (:func:`screen`)."""
POLISH_STREAM = 3
"""The checks of the Gauss-Newton steps (:func:`polish`)."""
FINE_STREAM = 4
"""The check of the finer refinement (:func:`refine_finer`)."""
BOUNDARY_STREAM = 5
"""The evaluations that choose the boundary probability under a top interface (:func:`quietest_boundary_probability`)."""
FINE_FACTOR = 4
"""The selected start is refined once more with this many times the fit's walks under the same key,
connected by MIS under narrow platelets (:func:`finer_problem`, :func:`refine_finer`), and kept where its
check is better. At the fit's own walks the fixed-key objective is too rough to tell apart materials along a
shallow valley or near a narrow lobe: on seed 2's sets 0-7 of the recovery benchmark the fit recovered 5 of 8
with it and 1 of 8 without, on the same data (docs/method.md, "The search")."""
FINE_SHARE = 0.05
"""The finer refinement runs only where the selected start's objective is this rough: its Monte Carlo
share (:func:`objective_mc_share`) at least this fraction of the material's chi-square. Below it, four times
the walks would change the objective by less than this fraction of itself (on the real Clarins 105 with an
interface the share was 0.004, and the finer refinement cost 100 s and lost). The polish's Gauss-Newton
steps (:func:`polish`) run where the same share is at least this at the finally selected start."""
_EPS = 1e-5
INTERFACE_NAMES = ("eta", "alpha_s")
"""The parameters of a top interface (docs/model.md section 3a), fitted with ``interface=True``."""
# The start of a fitted interface: a varnish-like index and a moderately rough surface.
_INTERFACE_DEFAULT = dict(eta=1.5, alpha_s=0.1)
LOBE_NAMES = ("g1", "g2", "w_g")
"""The diffusers' two lobes: their asymmetries and the first one's weight."""


def ordered_lobes(labels, v, complement=lambda w: 1.0 - w):
    """``v`` (``(..., P)``, columns as ``labels``) with the diffusers' lobes labelled so that ``g1 >= g2``.

    The two-lobe phase function ``w_g f_HG(g1) + (1 - w_g) f_HG(g2)`` is
    symmetric in its lobes: ``(g1, g2, w_g)`` and ``(g2, g1, 1 - w_g)`` are the
    same material, and a fit may end in either. jaxcos reports the more
    forward-scattering lobe as the first (as the paper's four materials have
    it), so that the fits of several files and the draws of a posterior
    compare lobe for lobe. Where ``g1 < g2`` the two are exchanged and ``w_g``
    replaced by ``complement(w_g)``: ``1 - w_g`` for physical values (the
    default), ``-x`` for the fit's coordinates (``w_g`` is the logistic function of ``x``, and
    ``g1``, ``g2`` share one map, which keeps their order). ``v`` is returned
    as it is without a second lobe.
    """
    if not set(LOBE_NAMES) <= set(labels):
        return v
    i1, i2, iw = (list(labels).index(n) for n in LOBE_NAMES)
    v = np.array(v, copy=True)
    g1, g2, w = v[..., i1], v[..., i2], v[..., iw]
    swap = g1 < g2
    # every right-hand side is a new array, made before any column is written
    v[..., i1], v[..., i2], v[..., iw] = (np.where(swap, g2, g1), np.where(swap, g1, g2),
                                          np.where(swap, complement(w), w))
    return v



def _unit_to_x(v):
    v = np.clip(np.asarray(v, float), _EPS, 1 - _EPS)
    return np.log(v) - np.log1p(-v)


def _transforms(kind, low, high):
    """``(x -> value, value -> x)`` of a fit map ``kind`` onto ``[low, high]`` (:mod:`jaxcos.model`'s ``RANGES``).

    The inverse works in the value's own dtype.
    """
    if kind == "logistic":
        return (lambda x: low + (high - low) * jax.nn.sigmoid(x),
                lambda v: _unit_to_x((np.asarray(v) - low) / (high - low)))
    if kind == "loglogistic":
        ratio = float(np.log(high / low))
        return (lambda x: low * jnp.exp(ratio * jax.nn.sigmoid(x)),
                lambda v: _unit_to_x(np.log(np.asarray(v) / low) / ratio))
    if kind == "tanh":
        return (lambda x: high * jnp.tanh(x),
                lambda v: np.arctanh(np.clip(np.asarray(v) / high, -1 + _EPS, 1 - _EPS)))
    return jnp.exp, lambda v: np.log(np.maximum(v, _EPS))


_TRANSFORMS = {name: _transforms(r.fit_map, r.fit_low, r.fit_high) for name, r in RANGES.items()}
_STEEPNESS = {"logistic": 1.0, "loglogistic": 1.0, "tanh": 2.0}
"""Per bounded fit map, ``k`` such that the fraction of the fit range covered at ``x`` is ``sigmoid(k x)``
(``tanh(x) = 2 sigmoid(2 x) - 1``)."""
SATURATED = 1e-3
"""A bounded coordinate is saturated where its value lies within this fraction of its fit range from a bound:
the map's slope there is below 0.4% of its largest, and Levenberg-Marquardt, its step damped, no longer moves
it (:func:`release_saturated`)."""
RELEASED = 0.02
"""Where a saturated coordinate is set back to at the start of a solver pass: this fraction of its fit range
from its bound."""


def release_saturated(param, x):
    """``x`` with its saturated coordinates (:data:`SATURATED`) set back to :data:`RELEASED` from their bound.

    On a logistic map a coordinate that has run to a bound (an albedo at 1)
    stays there: its column of the Jacobian falls like ``exp(-|x|)``, and
    with it any step that would bring it back, even after the other
    parameters have moved so that the optimum lies inside. The failed fits
    of the recovery benchmark ended with an albedo or ``w_g`` at its bound
    far more often than the recovered ones (docs/method.md, "The search").
    Released, a coordinate whose optimum is the bound runs back to it. The
    ``exp`` map (``t``) is left alone.
    """
    k, saturated = _saturated(param, x)
    if not saturated.any():
        return x
    x_np = np.asarray(x, float)
    back = float(_unit_to_x(1.0 - RELEASED))
    released = np.where(saturated, np.sign(x_np) * back / np.where(k > 0, k, 1.0), x_np)
    return jnp.asarray(released, jnp.result_type(x))


def _saturated(param, x):
    """``(k, saturated)`` per entry of ``x``: the steepness of its map (0 where unbounded) and whether it is
    saturated (:data:`SATURATED`)."""
    k = np.concatenate([np.full(RANGES[n].size, _STEEPNESS.get(RANGES[n].fit_map, 0.0)) for n in param.names])
    edge = float(_unit_to_x(1.0 - SATURATED))
    return k, (k > 0) & (np.abs(k * np.asarray(x, float)) > edge)


def fixed_values(variant):
    """The values ``variant`` fixes (``jaxcos.model.FIXED``), as a fit writes them."""
    return dict(FIXED[variant])


class Parameterization(eqx.Module):
    """The map between an unbounded vector ``x`` and a one-layer :class:`Material` of a variant.

    Attributes:
        variant: the model variant (static).
        names: the fitted parameters in order (static); ``t`` and ``phi_p``
            are included when asked for, ``eta`` and ``alpha_s`` (last) when
            the material has a top interface.
        fixed: the values of the parameters that are not fitted.
    """

    variant: str = eqx.field(static=True)
    names: tuple = eqx.field(static=True)
    fixed: dict

    @property
    def interface(self):
        """Whether the material has a top interface (its ``eta`` and ``alpha_s`` are then fitted)."""
        return INTERFACE_NAMES[0] in self.names

    @property
    def size(self):
        return sum(RANGES[n].size for n in self.names)

    def labels(self):
        """One label per entry of ``x``, e.g. ``albedo_d[0]``."""
        out = []
        for n in self.names:
            out += [f"{n}[{i}]" for i in range(RANGES[n].size)] if RANGES[n].size > 1 else [n]
        return out

    def _split(self, v):
        i = 0
        for n in self.names:
            k = RANGES[n].size
            yield n, v[i:i + k]
            i += k

    def to_material(self, x):
        """The material at the unbounded coordinates ``x``."""
        return self.physical_to_material(self.to_physical(x))

    def to_physical(self, x):
        """The physical values at ``x``, one per :meth:`labels` entry (``theta_p``, ``phi_p`` in degrees)."""
        return jnp.concatenate([_TRANSFORMS[n][0](part) for n, part in self._split(x)])

    def physical_to_material(self, v):
        """The material with the physical values ``v`` (no bounds are checked)."""
        values = dict(self.fixed)
        values.update({n: part if part.shape[0] > 1 else part[0] for n, part in self._split(v)})
        top = {n: values.pop(n) for n in INTERFACE_NAMES if n in values}
        interface = Interface(**top) if self.interface else None
        return Material(layers=(Layer(**values),), variant=self.variant, interface=interface)

    def colouring(self):
        """Seeds of the compressed Jacobian: ``(seeds, column, channel)``.

        The residuals are flattened ``(N, 3)`` (colour channel last), and an
        RGB parameter's component ``c`` (``albedo_d[c]``) acts on channel ``c``
        alone: no random decision of a walk looks at colour (the lobe
        probabilities are fixed numbers). The three columns of such a
        parameter never share a row, so one move of all three gives all
        three columns (a Curtis-Powell-Reid colouring): the two-lobe model's
        12 columns cost 8 moves (:meth:`Problem.jacobian`). ``seeds`` is ``(K, size)``;
        entry ``j`` of ``x`` reads column ``column[j]`` of the compressed
        Jacobian, at the rows of channel ``channel[j]`` (``-1``: every row).
        """
        seeds, column, channel = [], [], []
        for n in self.names:
            k, j = RANGES[n].size, len(column)
            seed = np.zeros(self.size)
            seed[j:j + k] = 1.0
            column += [len(seeds)] * k
            channel += list(range(k)) if k > 1 else [-1]
            seeds.append(seed)
        return np.array(seeds), np.array(column), np.array(channel)

    def difference_steps(self):
        """``(steps, central)``, each ``(size,)``: the difference step of each entry of ``x`` in the fit's
        Jacobian (:meth:`Problem.jacobian`) and whether the difference is central (:data:`DIFFERENCED`) or
        one-sided (:data:`FORWARD_STEP`)."""
        expand = lambda f: np.concatenate([np.full(RANGES[n].size, f(n)) for n in self.names])
        return expand(lambda n: DIFFERENCED.get(n, FORWARD_STEP)), expand(lambda n: n in DIFFERENCED)

    def moves(self):
        """``(seeds, h, central)``: the moves of the fit's Jacobian (:meth:`Problem.jacobian`).

        ``seeds`` ``(K, size)`` from :meth:`colouring`; ``h`` ``(K,)`` the step
        of each move and ``central`` ``(K,)`` whether it is taken both ways,
        those of the first entry of ``x`` the move reads (:meth:`difference_steps`).
        """
        seeds, column, _ = self.colouring()
        steps, central = self.difference_steps()
        first = [int(np.flatnonzero(column == k)[0]) for k in range(len(seeds))]
        return seeds, steps[first].astype(np.float32), central[first]

    def jacobian_evaluations(self):
        """The evaluations of the objective a Jacobian takes (:meth:`Problem.jacobian`): the point itself, two per
        centrally differenced move, one per other move."""
        _, h, central = self.moves()
        return 1 + len(h) + int(np.sum(central))

    def at_bounds(self, x):
        """``[(label, bound)]``: the entries of ``x`` at a bound of their fit range (saturated,
        :data:`SATURATED`), with the value of that bound.

        There the value is the bound, not an estimate: the data would take it
        further, or are indifferent beyond it (an albedo at 1: more light than
        a non-absorbing medium returns; ``w_g`` at 1: one diffuser lobe).
        """
        _, saturated = _saturated(self, x)
        low, high = self.bounds()
        x_np = np.asarray(x, float)
        return [(label, float(high[i] if x_np[i] > 0 else low[i]))
                for i, label in enumerate(self.labels()) if saturated[i]]

    def bounds(self):
        """``(low, high)``: the fit's bounds of each :meth:`labels` entry (``jaxcos.model.RANGES``), the support of
        a uniform prior."""
        ranges = [RANGES[n] for n in self.names for _ in range(RANGES[n].size)]
        return np.array([r.fit_low for r in ranges]), np.array([r.fit_high for r in ranges])

    def ordered_lobes(self, x):
        """``x`` with the diffusers' lobes labelled so that ``g1 >= g2`` (:func:`ordered_lobes`): the same material."""
        return jnp.asarray(ordered_lobes(self.labels(), np.asarray(x), np.negative), dtype=jnp.asarray(x).dtype)

    def from_material(self, material):
        """The unbounded coordinates of ``material``; without an interface, a fitted one starts at its default."""
        layer = material.layers[0]
        top = _INTERFACE_DEFAULT if material.interface is None else \
            {n: getattr(material.interface, n) for n in INTERFACE_NAMES}
        value = lambda n: top[n] if n in INTERFACE_NAMES else getattr(layer, n)
        parts = [np.atleast_1d(_TRANSFORMS[n][1](np.asarray(value(n)))) for n in self.names]
        return jnp.asarray(np.concatenate(parts), dtype=jnp.result_type(float))


def parameterization(variant="two_lobe", *, fit_t=False, fit_phi=False, interface=False, template=None):
    """The :class:`Parameterization` of ``variant``; non-fitted values come from ``template`` or the defaults.

    The values the variant fixes (:func:`fixed_values`) override both. With
    ``interface``, the material has a top interface whose ``eta`` and
    ``alpha_s`` are fitted with the rest (docs/model.md section 3a).
    """
    check_variant(variant)
    names = (_FREE[variant] + (("t",) if fit_t else ()) + (("phi_p",) if fit_phi else ())
             + (INTERFACE_NAMES if interface else ()))
    base = dict(_DEFAULT)
    if template is not None:
        layer = template.layers[0]
        base.update({k: np.asarray(getattr(layer, k)) for k in _DEFAULT})
    base.update(fixed_values(variant))
    fixed = {k: jnp.asarray(v, dtype=jnp.result_type(float)) for k, v in base.items() if k not in names}
    return Parameterization(variant=variant, names=names, fixed=fixed)


# --- the objective ----------------------------------------------------------------


def weighted_residuals(measured, sigma, model):
    """``(model - measured) / sigma`` of ``(N, 3)`` arrays, flattened over points and channels (channel last)."""
    return ((model - measured) / sigma).reshape(-1)


class WeightedLeastSquares(eqx.Module):
    """A weighted least-squares problem: residuals ``(model(x) - measured) / sigma``, flattened.

    The base of every fit's problem, the Monte Carlo one (:class:`Problem`)
    and the Kubelka-Munk baseline's (``KMProblem``). A subclass declares the
    fields ``measured`` ``(N, 3)`` (in the file's quantity, docs/formats.md),
    ``sigma`` ``(N, 3)`` (the file's std, 1 without std columns) and ``scale``
    (static: the file's quantity per unit BSDF,
    :attr:`jaxcos.io.Measurements.scale`), and gives :meth:`model`.
    """

    measured: eqx.AbstractVar[jnp.ndarray]
    sigma: eqx.AbstractVar[jnp.ndarray]
    scale: eqx.AbstractVar[float]

    @abc.abstractmethod
    def model(self, x):
        """The model at ``x`` in the file's quantity, ``(N, 3)``."""

    def weigh(self, model):
        """The residuals ``(model - measured) / std`` of a model ``(N, 3)`` in the file's quantity, flattened."""
        return weighted_residuals(self.measured, self.sigma, model)

    def residuals(self, x):
        """The residuals at ``x``, flattened over points and channels (colour channel last)."""
        return self.weigh(self.model(x))

    def loss(self, x):
        """The sum of squared residuals at ``x``."""
        r = self.residuals(x)
        return jnp.sum(r * r)

    def levelled_loss(self, x):
        """The loss at ``x`` after the best level per colour channel: ``min_a sum ((a_c m - y) / sigma)^2``.

        ``a_c = sum(m y / sigma^2) / sum(m^2 / sigma^2)`` over the points of
        channel ``c``. A move of the phase function changes the whole
        reflectance's level, which the diffusers' albedo restores in one
        step; this loss compares moves by the shape they leave.
        """
        return self.levelled(self.model(x))

    def levelled(self, m):
        """:meth:`levelled_loss` of a model ``m`` ``(N, 3)`` in the file's quantity."""
        w = 1.0 / self.sigma ** 2
        a = jnp.sum(w * m * self.measured, axis=0) / jnp.maximum(jnp.sum(w * m * m, axis=0), 1e-30)
        return jnp.sum(w * (a * m - self.measured) ** 2)


class Problem(WeightedLeastSquares):
    """Everything the residuals need: the data, the query, the budget, the key.

    ``residuals(x)`` are ``(model - measured) / std``, flattened over points
    and channels (:class:`WeightedLeastSquares`); ``model`` is in the file's quantity (``scale`` times the
    BSDF, :attr:`jaxcos.io.Measurements.scale`). Their value uses ``walks`` walks; their
    Jacobian (:meth:`jacobian`) differences of the first ``jacobian_walks`` of them (all when
    ``None``). ``thin_after``: ``simulate``'s; ``None`` by default, every walk making every
    step.

    Every evaluation runs one compiled program per budget and connection
    (:func:`_estimate`): the value, the Jacobian's differences, the checks'
    batches and the report's estimate at the same walks share it, whatever
    the key, lobe probabilities, weights or start.
    """

    param: Parameterization
    query: object
    measured: jnp.ndarray
    sigma: jnp.ndarray
    scale: float = eqx.field(static=True)
    key: jnp.ndarray
    lobe_probs: jnp.ndarray
    walks: int = eqx.field(static=True)
    bounces: int = eqx.field(static=True)
    jacobian_walks: int = eqx.field(static=True, default=None)
    connection: str = eqx.field(static=True, default="nee")
    boundary_prob: jnp.ndarray = None
    thin_after: int = eqx.field(static=True, default=None)

    def estimate(self, x):
        """The :class:`~jaxcos.Estimate` of the material at ``x`` under this problem's key and budget.

        More walks than :data:`CHUNK_WALKS`, a multiple of them, are walked in
        chunks of that many (walks ``c * CHUNK_WALKS ...`` of the key, the
        same walks as in one evaluation), so that the finer refinement runs
        the compiled program of the fit's own walks and of the checks' batches.
        """
        chunks = self.walks // CHUNK_WALKS if self.walks > CHUNK_WALKS and self.walks % CHUNK_WALKS == 0 else 1
        if chunks == 1:
            return _estimate(self, x, np.int32(0))
        sub = dataclasses.replace(self, walks=CHUNK_WALKS)
        return _pool(concurrently(lambda c: _estimate(sub, x, np.int32(c * CHUNK_WALKS)), range(chunks)))

    def model(self, x):
        """The model in the file's quantity, ``(N, 3)``."""
        return self.scale * self.estimate(x).f

    def residuals(self, x):
        """The residuals at ``x``, flattened over points and channels (colour channel last)."""
        return _weigh(self.measured, self.sigma, self.scale, self.estimate(x).f)

    def jacobian(self, x):
        """The residuals' Jacobian ``(M, P)`` at ``x`` and the residuals it comes with.

        Differences of the first ``jacobian_walks`` walks under the
        problem's key (the walks' random numbers do not depend on their count,
        see ``_walk._uniforms``), one evaluation of the objective's own
        compiled program per moved point: central differences along the
        parameters of :data:`DIFFERENCED`, which move a sampled direction,
        one-sided ones of :data:`FORWARD_STEP` along the others. The colour
        channels' columns share a move (:meth:`Parameterization.colouring`):
        no random decision of a walk looks at colour, so the move of all three
        components of an RGB parameter changes each channel by its own
        component's column. The two-lobe model's 12 columns cost 13
        evaluations at ``jacobian_walks`` (benchmarks/RESULTS.md, decision
        records, "One compiled program per budget, the solver's loop on the host and the Jacobian by
        differences").
        """
        sub = dataclasses.replace(self, walks=_jacobian_walks(self))
        _, column, channel = self.param.colouring()
        seeds, h, back = self.param.moves()
        x = np.asarray(x)
        moves = (seeds * h[:, None]).astype(x.dtype)
        points = np.concatenate([x[None], x + moves, x - moves[back]])
        ys = concurrently(sub.residuals, points)
        return _assemble(ys, h, tuple(back.tolist()), column, channel), ys[0]


CHUNK_WALKS = FIT_WALKS
"""The most walks of one evaluation of a :class:`Problem` (:meth:`Problem.estimate`)."""

EVALUATION_THREADS = 2
"""How many independent evaluations of a :class:`Problem` run at once (:func:`concurrently`)."""


def concurrently(fn, items):
    """``[fn(item) for item in items]``, :data:`EVALUATION_THREADS` items at a time, in the items' order.

    For independent evaluations of the walk (a Jacobian's moved points, the
    checks' batches, the phase moves, a large budget's chunks): one
    evaluation leaves part of the machine idle between the operations of its
    steps (on a 2-core machine, 15 evaluations of 128 walks took 0.37 s one
    after another and 0.29 s two at a time), and two at a time fill it. Each
    result is that of ``fn(item)`` alone: the numbers do not depend on the
    threads. The first item runs first, alone, so that a program is traced
    and compiled once. Items not started when one fails (or the caller is
    interrupted) are cancelled.
    """
    items = list(items)
    if len(items) < 2:
        return [fn(item) for item in items]
    first = fn(items[0])
    pool = concurrent.futures.ThreadPoolExecutor(EVALUATION_THREADS)
    try:
        futures = [pool.submit(fn, item) for item in items[1:]]
        return [first] + [f.result() for f in futures]
    finally:
        pool.shutdown(wait=False, cancel_futures=True)


@eqx.filter_jit
def _estimate(problem, x, first):
    """:meth:`Problem.estimate`'s walks ``first .. first + walks - 1``: one compiled program per static budget
    (``first`` an array, so that every chunk shares it)."""
    return simulate(problem.param.to_material(x), problem.query, problem.key, walks=problem.walks,
                    bounces=problem.bounces, lobe_probs=problem.lobe_probs, connection=problem.connection,
                    boundary_prob=problem.boundary_prob, thin_after=problem.thin_after, first=first)


@jax.jit
def _pool(estimates):
    """The :class:`~jaxcos.Estimate` of the walks of equal chunks ``estimates`` together (a mean of their means)."""
    mean = jax.tree.map(lambda *a: sum(a) / len(a), *estimates)
    stderr = jnp.sqrt(sum(e.stderr ** 2 for e in estimates)) / len(estimates)
    return dataclasses.replace(mean, stderr=stderr)


@jax.jit
def _weigh(measured, sigma, scale, f):
    """:func:`weighted_residuals` of the BSDF ``f`` ``(N, 3)`` times ``scale``, in one small compiled program.

    It reads arrays only, so that every :class:`Problem` of a fit shares it, whatever its budget.
    """
    return weighted_residuals(measured, sigma, scale * f)


@functools.partial(jax.jit, static_argnums=(2,))
def _assemble(ys, h, back, column, channel):
    """The Jacobian ``(M, P)`` from the residuals ``ys`` at the points of :meth:`Problem.jacobian`.

    ``ys``: at ``x``, at ``x + h_k e_k`` for every move ``k``, then at ``x -
    h_k e_k`` for the central ones (``back``, static). Column ``k`` of the
    coloured Jacobian is the difference of move ``k``; entry ``j`` of ``x``
    reads column ``column[j]`` at the rows of its channel ``channel[j]``
    (``-1``: every row).
    """
    y, ahead = ys[0], jnp.stack(ys[1:1 + len(h)], axis=1)
    behind = jnp.stack([y] * len(h), axis=1)
    if any(back):
        behind = behind.at[:, np.flatnonzero(np.array(back))].set(jnp.stack(ys[1 + len(h):], axis=1))
    packed = (ahead - behind) / jnp.where(np.asarray(back), 2.0 * h, h)
    row_channel = jnp.arange(y.shape[0]) % 3
    mask = (channel[None, :] < 0) | (channel[None, :] == row_channel[:, None])
    return packed[:, column] * mask


DIFFERENCED = dict(g1=0.05, g2=0.05, alpha_p=0.02, theta_p=0.02, phi_p=0.02, eta=0.02, alpha_s=0.02)
"""The parameters whose columns of the fit's Jacobian are central differences under the problem's key, with
their steps in the fit's coordinates ``x``. Each moves a sampled direction (a diffuser lobe's, a platelet's
normal, a microfacet's normal or a refracted direction), so that the objective under one key is rough along it:
forward-mode derivatives of the walk were heavy-tailed there (on dewy1's fit at 128 walks the column of ``g1``
was 36 times as long as a 16384-walk difference and uncorrelated with it, cosine -0.02; differences at 128
walks: 0.65-0.81), and differences over a step average the roughness out (benchmarks/RESULTS.md, decision
records)."""

FORWARD_STEP = 0.01
"""The step in ``x`` of the one-sided differences along every parameter not in :data:`DIFFERENCED`: the
albedos, ``c_d``, ``w_g`` and ``t`` only reweight the walks (the lobe probabilities are held fixed), and
their differences at this step had cosines of 0.9999-1.0000 with forward-mode derivatives of the same walks
on the four bundled sets (lengths within 0.6%; benchmarks/RESULTS.md, decision records)."""


def _jacobian_walks(problem):
    """The walks the Jacobian of ``problem`` is taken from: ``jacobian_walks``, at most ``walks``."""
    return problem.walks if problem.jacobian_walks is None else min(problem.jacobian_walks, problem.walks)


def make_problem(meas, param, *, key, walks=FIT_WALKS, bounces=FIT_BOUNCES, lobe_probs=None, reference=None,
                 jacobian_walks=None, connection=None, thin_after=None):
    """The least-squares :class:`Problem` of fitting ``param`` to measurements ``meas``.

    ``thin_after``: the steps every walk makes (:func:`~jaxcos.simulate`); ``None``
    (the default): every walk makes every step.

    ``lobe_probs`` are held fixed during the fit (common random numbers); by
    default they are those of ``reference`` (a material) or of the default start.
    ``connection``: the estimator's (:func:`~jaxcos.simulate`); by default
    ``"mis"`` where the data show a highlight narrower than their angular
    sampling (:func:`narrow_highlight`), else ``"nee"``. There, next-event
    estimation through the near-mirror lobe is so spiky that under a fixed
    key at the fit's budget the truth need not be a minimum of the
    objective; ``"mis"`` removes the spikes at a higher cost per evaluation,
    not spent where the highlight is broad (docs/method.md, "Near-mirror
    highlights"). Under a top interface the connection is ``"nee"``, the
    one :func:`~jaxcos.simulate` has there.

    Under a top interface the boundary probability
    (:func:`~jaxcos.model.boundary_probability`) is held fixed at that of
    ``reference`` or of the default start, as the lobe probabilities are: with
    ``t`` fitted it would otherwise follow ``t``, and the objective under one
    key would jump where a walk's choice between boundary and medium flips.
    """
    if param.interface:
        if connection == "mis":
            raise InputError("the 'mis' connection does not go through a top interface; use 'nee'.")
        connection = "nee"
    elif connection is None:
        connection = "mis" if narrow_highlight(meas) else "nee"
    if lobe_probs is None:
        lobe_probs = (lobe_probabilities(reference) if reference is not None
                      else _lobe_probabilities_at(param, jnp.zeros(param.size)))
    boundary_prob = None
    if param.interface:
        boundary_prob = boundary_probability(reference if reference is not None
                                             else param.to_material(jnp.zeros(param.size)))
    dtype = jnp.result_type(float)
    sigma = np.ones_like(meas.values) if meas.std is None else np.asarray(meas.std)
    if np.any(sigma <= 0):
        raise InputError(f"{meas.path}: every standard deviation must be positive to weight a fit.")
    return Problem(
        param=param,
        query=make_query(meas.theta_i, meas.theta_o, meas.phi_o),
        measured=jnp.asarray(meas.values, dtype),
        sigma=jnp.asarray(sigma, dtype),
        scale=float(meas.scale),
        key=key,
        lobe_probs=jnp.asarray(lobe_probs, dtype),
        walks=walks,
        bounces=bounces,
        jacobian_walks=jacobian_walks,
        connection=connection,
        boundary_prob=boundary_prob,
        thin_after=thin_after,
    )


# --- solvers ----------------------------------------------------------------------


class LevenbergMarquardtState(eqx.Module):
    """The state of :class:`LevenbergMarquardt` between steps.

    Attributes:
        first_step: whether no step has been taken yet (the trust region accepts the first).
        y_eval: the point the next step evaluates.
        search_state: the trust region's state (``optx.ClassicalTrustRegion``).
        f_info: the residuals and Jacobian (a matrix) at the last accepted point.
        aux: ``fn``'s auxiliary output there.
        descent_state: the damped Newton descent's state (``optx.DampedNewtonDescent``).
        terminate: whether the solve has ended; ``result`` says how.
        num_steps, num_accepted_steps, num_steps_since_acceptance: step counts.
        small_steps: consecutive accepted steps that lowered the loss by less than ``loss_rtol``.
    """

    first_step: jnp.ndarray
    y_eval: jnp.ndarray
    search_state: object
    f_info: optx.FunctionInfo.ResidualJac
    aux: object
    descent_state: object
    terminate: jnp.ndarray
    result: optx.RESULTS
    num_steps: jnp.ndarray
    num_accepted_steps: jnp.ndarray
    num_steps_since_acceptance: jnp.ndarray
    small_steps: jnp.ndarray


STALL = 5
""":class:`LevenbergMarquardt` stops after this many consecutive rejected steps."""


def _quiet(**kwargs):
    """The default ``verbose`` of :class:`LevenbergMarquardt`: says nothing."""


class LevenbergMarquardt(optx.AbstractLeastSquaresSolver):
    """Levenberg-Marquardt with a Jacobian only where a step is accepted, and a stop on the loss.

    Built from optimistix's public pieces: its damped Newton descent
    (``optx.DampedNewtonDescent``), classical trust region
    (``optx.ClassicalTrustRegion``) and Cauchy termination on ``y`` and the
    residuals, with a state of its own (:class:`LevenbergMarquardtState`).
    Its iterates are those of ``optx.LevenbergMarquardt``; what differs is
    when the Jacobian is computed: the trust region accepts or rejects a step
    on the value at the new point alone (:meth:`judge`), so this solver
    evaluates the value first and computes the Jacobian only when the step
    is accepted (:meth:`update`). A rejected step then costs one evaluation
    instead of a Jacobian; near the optimum many steps are rejected, the
    few-walk Jacobian's slope not being the full value's.

    It runs under ``optx.least_squares`` like any optimistix solver (its
    :meth:`step` takes the Jacobian by ``jax.jacfwd``), and step by step
    from the host (:func:`solve_lm`), where the value and the Jacobian are
    the Monte Carlo problem's own compiled programs and only the solver's
    arithmetic is compiled here.

    Under a fixed key the objective is rough along the parameters that move
    sampled directions (``docs/derivatives.md``). Near its optimum LM then
    creeps: the damping grows after a few rejected steps, and each accepted
    step lowers the loss far less than the data can tell apart. So this
    solver also stops after ``patience`` consecutive accepted steps that each
    lowered the loss by less than ``loss_rtol`` of it, after a rejected
    step already within the tolerance on ``y`` (a smaller region would
    propose a smaller one), and after ``stall`` consecutive rejected steps
    once it has accepted a step beyond the start. Each rejection shrinks the
    trust region fourfold (``optx.ClassicalTrustRegion``'s
    ``low_constant``), so after ``stall`` of them the step is ``4**-stall``
    of the one the linear model proposed: on the fit's objectives, where
    the few-walk Jacobian's slope is not the objective's, the step that then
    passed lowered the loss by 0-1%, less than the checks' standard error
    (benchmarks/RESULTS.md, decision records, "The fit's objective"). At the
    start of a solve a run of rejections only finds the region's size, and
    is not cut. ``None``: no such stop.
    """

    rtol: float
    atol: float
    norm: object
    descent: optx.DampedNewtonDescent
    search: optx.ClassicalTrustRegion
    verbose: object
    loss_rtol: float
    patience: int
    stall: int | None

    def __init__(self, rtol, atol, loss_rtol=2e-4, patience=2, stall=STALL):
        self.rtol, self.atol, self.norm = rtol, atol, optx.max_norm
        self.descent = optx.DampedNewtonDescent()
        self.search = optx.ClassicalTrustRegion()
        self.verbose = _quiet
        self.loss_rtol, self.patience, self.stall = loss_rtol, patience, stall

    def init(self, fn, y, args, options, f_struct, aux_struct, tags):
        # The Jacobian is kept as a matrix; nothing of fn is traced here.
        f_info = optx.FunctionInfo.ResidualJac(
            jnp.zeros(f_struct.shape, f_struct.dtype),
            lx.MatrixLinearOperator(jnp.zeros(f_struct.shape + y.shape, f_struct.dtype), tags))
        return LevenbergMarquardtState(
            first_step=jnp.array(True), y_eval=y, search_state=self.search.init(y, f_info), f_info=f_info,
            aux=jax.tree.map(lambda a: jnp.zeros(a.shape, a.dtype), aux_struct),
            descent_state=self.descent.init(y, f_info), terminate=jnp.array(False),
            result=optx.RESULTS.successful, num_steps=jnp.array(0), num_accepted_steps=jnp.array(0),
            num_steps_since_acceptance=jnp.array(0), small_steps=jnp.array(0))

    def _converged(self, y_diff, y_eval, f_diff, residual):
        """Cauchy termination: small changes both in ``y`` and in the residuals, in :attr:`norm`."""
        return ((self.norm(y_diff / (self.atol + self.rtol * jnp.abs(y_eval))) < 1)
                & (self.norm(f_diff / (self.atol + self.rtol * jnp.abs(residual))) < 1))

    def judge(self, y, state, residual):
        """The trust region's verdict on the step to ``state.y_eval``, from the residuals there alone.

        Returns ``(size, accept, found, search_state)`` (``optx.ClassicalTrustRegion.step``).
        """
        probe = optx.FunctionInfo.ResidualJac(residual, state.f_info.jac)
        return self.search.step(state.first_step, y, state.y_eval, state.f_info, probe, state.search_state)

    def update(self, y, state, residual, aux, verdict, jac, tags):
        """``(y, state)`` after the step to ``state.y_eval``, given :meth:`judge`'s ``verdict``.

        ``jac``: the Jacobian ``(M, P)`` of the residuals at ``state.y_eval``
        where the step is accepted; where it is rejected it is not read (any
        matrix of that shape).
        """
        size, accept, found, search_state = verdict

        def accepted(_):
            f_info = optx.FunctionInfo.ResidualJac(residual, lx.MatrixLinearOperator(jac, tags))
            converged = self._converged(state.y_eval - y, state.y_eval, residual - state.f_info.residual, residual)
            return state.y_eval, f_info, aux, self.descent.query(state.y_eval, f_info, state.descent_state), converged

        def rejected(_):
            # a rejected step already within the tolerance on y: the next, in a smaller region, would be too
            tiny = self.norm(state.y_eval - y) < self.atol + self.rtol * self.norm(y)
            return y, state.f_info, state.aux, state.descent_state, tiny

        before, after = jnp.sum(state.f_info.residual ** 2), jnp.sum(residual ** 2)
        y, f_info, aux, descent_state, terminate = jax.lax.cond(accept, accepted, rejected, None)
        y_descent, result = self.descent.step(size, descent_state)
        small = jnp.where(accept & (state.num_accepted_steps >= 1),
                          jnp.where(before - after < self.loss_rtol * before, state.small_steps + 1, 0),
                          state.small_steps)
        since = jnp.where(accept, 0, state.num_steps_since_acceptance + 1)
        if self.stall is not None:  # once a step has been accepted beyond the start
            terminate = terminate | ((since >= self.stall) & (state.num_accepted_steps >= 2))
        new = LevenbergMarquardtState(
            first_step=jnp.array(False), y_eval=y + y_descent, search_state=search_state, f_info=f_info, aux=aux,
            descent_state=descent_state, terminate=terminate | (small >= self.patience),
            result=optx.RESULTS.where(found == optx.RESULTS.successful, result, found),
            num_steps=state.num_steps + 1, num_accepted_steps=state.num_accepted_steps + jnp.where(accept, 1, 0),
            num_steps_since_acceptance=since, small_steps=small)
        return y, new

    def step(self, fn, y, args, options, state, tags):
        residual, aux = fn(state.y_eval, args)
        verdict = self.judge(y, state, residual)
        jac = jax.lax.cond(verdict[1], lambda _: jax.jacfwd(lambda x: fn(x, args)[0])(state.y_eval),
                           lambda _: state.f_info.jac.as_matrix(), None)
        self.verbose(num_steps=("Step", state.num_steps), step_size=("Step size", verdict[0]),
                     loss_this_step=("Loss on this step", 0.5 * jnp.sum(residual ** 2)),
                     loss_last_accepted_step=("Loss on the last accepted step",
                                              0.5 * jnp.sum(state.f_info.residual ** 2)))
        y, new = self.update(y, state, residual, aux, verdict, jac, tags)
        return y, new, new.aux

    def terminate(self, fn, y, args, options, state, tags):
        return state.terminate, state.result

    def postprocess(self, fn, y, aux, args, options, state, tags, result):
        return y, aux, {}


@functools.cache
def _solver(rtol, atol):
    """The :class:`LevenbergMarquardt` of these tolerances, held as arrays: one compiled step serves them all."""
    dtype = jnp.result_type(float)
    return LevenbergMarquardt(rtol=jnp.asarray(rtol, dtype), atol=jnp.asarray(atol, dtype))


@eqx.filter_jit
def _lm_init(solver, y, f_struct):
    return solver.init(None, y, None, {}, f_struct, None, frozenset())


@eqx.filter_jit
def _lm_judge(solver, y, state, residual):
    return solver.judge(y, state, residual)


@eqx.filter_jit
def _lm_update(solver, y, state, residual, verdict, jac):
    """:meth:`LevenbergMarquardt.update`, whether to stop, and the loss at the last accepted point."""
    y, state = solver.update(y, state, residual, None, verdict, jac, frozenset())
    stop = state.terminate | (state.result != optx.RESULTS.successful)
    return y, state, stop, jnp.sum(state.f_info.residual ** 2)


def solve_lm(problem, x0, *, max_steps=40, rtol=1e-4, atol=1e-5, jacobian=False):
    """Levenberg-Marquardt from ``x0``; returns ``(x, loss, steps, accepted)``, and the Jacobian at ``x`` if asked.

    Every step evaluates the residuals (:meth:`Problem.residuals`); the
    ``accepted`` ones also their Jacobian (:meth:`Problem.jacobian`). The
    loop runs on the host, :class:`LevenbergMarquardt`'s arithmetic in small
    compiled programs, the walks in the problem's own (:func:`_estimate`):
    a solver compiled as one program held three copies of the walk and
    compiled for each stage anew (benchmarks/RESULTS.md, decision records,
    "Compilation of a cold fit"). Its iterates are those of
    ``optx.least_squares`` with the same solver (``tests/test_fit.py``).
    ``jacobian``: also return the residuals' Jacobian ``(M, P)`` at ``x``,
    the one the last accepted step computed (at ``problem.jacobian_walks``).
    """
    solver = _solver(float(rtol), float(atol))
    y = x0
    state = _lm_init(solver, y, jax.ShapeDtypeStruct((problem.measured.size,), y.dtype))
    steps, loss = 0, np.inf
    while steps < max_steps:
        residual = problem.residuals(state.y_eval)
        verdict = _lm_judge(solver, y, state, residual)
        jac = problem.jacobian(state.y_eval)[0] if bool(verdict[1]) else state.f_info.jac.as_matrix()
        y, state, stop, loss = _lm_update(solver, y, state, residual, verdict, jac)
        steps += 1
        if bool(stop):
            break
    out = y, float(loss), steps, int(state.num_accepted_steps)
    return out + (state.f_info.jac.as_matrix(),) if jacobian else out


def _screen(problem, xs, keys):
    """A few Levenberg-Marquardt steps from each row of ``xs``; the ends and their batch residuals.

    The starts run two at a time (:func:`concurrently`), each sampling with its own lobe
    probabilities: a start far from the default one would otherwise be
    simulated with the wrong lobes, noisily. Each end is then evaluated under
    every key of ``keys`` (independent batches, for :func:`_pair_chi2`).
    Returns the ends ``(S, P)`` and residuals ``(S, K, M)``.
    """

    def one(x):
        prob = dataclasses.replace(problem, lobe_probs=_lobe_probabilities_at(problem.param, x))
        end = solve_lm(prob, x, max_steps=SCREEN_STEPS, rtol=1e-3, atol=1e-3)[0]
        prob = dataclasses.replace(prob, lobe_probs=_lobe_probabilities_at(problem.param, end))
        return end, jnp.stack(concurrently(lambda k: dataclasses.replace(prob, key=k).residuals(end), keys))

    ends, resid = zip(*concurrently(one, np.asarray(xs)))
    return jnp.stack(ends), jnp.stack(resid)


def solve_powell(problem, x0, *, max_evaluations=20000, xtol=1e-4, ftol=1e-8, on_evaluation=None):
    """SciPy's modified Powell on the same objective (the paper's method); returns ``(x, loss, evaluations)``.

    ``on_evaluation(loss)``, if given, is called after each evaluation of the objective.
    """
    from scipy.optimize import minimize

    loss = jax.jit(lambda x: problem.loss(x))

    def objective(x):
        value = float(loss(jnp.asarray(x, dtype=jnp.result_type(float))))
        if on_evaluation is not None:
            on_evaluation(value)
        return value

    res = minimize(objective, np.asarray(x0, float), method="Powell",
                   options=dict(maxfev=max_evaluations, xtol=xtol, ftol=ftol))
    return jnp.asarray(res.x, dtype=jnp.result_type(float)), float(res.fun), int(res.nfev)


# --- starts -----------------------------------------------------------------------


class Highlight(NamedTuple):
    """The brightest in-plane point of one incidence (:func:`_highlights`).

    Attributes:
        theta_i: the incidence (degrees).
        theta_o: the brightest point's viewing angle, signed (negative on the light's side).
        ratio: its value (mean of r, g, b) over the larger of its neighbours' in ``theta_o``.
        spacing: the distance in ``theta_o`` to that neighbour (degrees).
        interior: whether it has a neighbour on both sides (not at an end of the measured range).
        peak: where the highlight peaks between the neighbours (degrees, signed as ``theta_o``):
            the vertex of the parabola through the logarithms of the three values where
            ``interior``, else ``theta_o``.
        value: its value (mean of r, g, b), in the file's quantity.
    """

    theta_i: float
    theta_o: float
    ratio: float
    spacing: float
    interior: bool
    peak: float
    value: float


def _highlights(meas):
    """The :class:`Highlight` of each incidence with at least five in-plane points.

    Points with an infinite std (the padding of ``jaxcos.inference.pad_measurements``) are not measured.
    """
    inplane = np.isclose(np.asarray(meas.phi_o, float) % 180.0, 0.0)
    if meas.std is not None:
        inplane &= np.all(np.isfinite(meas.std), axis=1)
    values = np.mean(meas.values, axis=1)
    out = []
    for ti in np.unique(meas.theta_i[inplane]):
        sel = inplane & (meas.theta_i == ti)
        if sel.sum() < 5:
            continue
        to = np.where(np.isclose(meas.phi_o[sel] % 360.0, 180.0), -meas.theta_o[sel], meas.theta_o[sel])
        order = np.argsort(to)
        to, v = to[order], values[sel][order]
        k = int(np.argmax(v))
        near = [j for j in (k - 1, k + 1) if 0 <= j < v.size]
        n = max(near, key=lambda j: v[j])
        interior = len(near) == 2
        out.append(Highlight(theta_i=float(ti), theta_o=float(to[k]), ratio=float(v[k] / max(v[n], 1e-30)),
                             spacing=float(abs(to[n] - to[k])), interior=interior,
                             peak=_vertex(to[k - 1:k + 2], v[k - 1:k + 2]) if interior else float(to[k]),
                             value=float(v[k])))
    return out


def _vertex(x, v):
    """The abscissa of the vertex of the parabola through ``(x, log v)`` at three points, the middle one the highest.

    Within ``[x[0], x[2]]``; ``x[1]`` where the three are not concave (equal
    values, a plateau). For a lobe that falls off like a Gaussian in the
    viewing angle it is exact; a narrower one still peaks on the side of its
    brighter neighbour, by up to half a viewing step.
    """
    y = np.log(np.maximum(np.asarray(v, float), 1e-30))
    x = np.asarray(x, float)
    d1, d2 = (y[1] - y[0]) / (x[1] - x[0]), (y[2] - y[1]) / (x[2] - x[1])
    curvature = (d2 - d1) / (x[2] - x[0])
    if not curvature < 0.0:
        return float(x[1])
    # y' = 0 where the secant slopes, taken at the intervals' midpoints, interpolate to zero
    vertex = 0.5 * (x[0] + x[1]) - d1 / (2.0 * curvature)
    return float(np.clip(vertex, x[0], x[2]))


def _peaks(meas):
    """The :func:`_highlights` with a measured neighbour on both sides; where none has one, those at an end of the
    range that exceed their neighbour more than :data:`END_NARROW_RATIO` times, or all of them where none does.

    A brightest point at an end of the measured range says little of where
    the lobe peaks (it may lie beyond the range) or how narrow it is (its one
    neighbour may be on the lobe's rising side), unless it stands far above
    that neighbour: then the lobe is narrow and peaks within about a viewing step of it.
    """
    highlights = _highlights(meas)
    return ([h for h in highlights if h.interior] or [h for h in highlights if h.ratio > END_NARROW_RATIO]
            or highlights)


def highlight_tilt(meas):
    """The platelet tilt ``theta_p`` (degrees) that the measured highlight points to, or ``None``.

    Mirror-like platelets tilted by ``theta_p`` in the plane of incidence
    reflect at ``theta_o = theta_i + 2 theta_p`` (docs/model.md section 2). For each
    incidence with at least five in-plane points, where its brightest point (mean of
    r, g, b) peaks between its neighbours (:attr:`Highlight.peak`) gives one
    estimate, over the incidences of :func:`_peaks`; the result is their median.
    On a 10-degree viewing grid the brightest point alone is up to 2.5 degrees
    off the tilt; the peak between the neighbours was within 0.5 degrees for
    most narrow lobes (benchmarks/RESULTS.md, "The search on random materials").
    A narrow highlight (``alpha_p`` of a few thousandths) is invisible to a
    random start: its basin is a fraction of a degree wide in ``theta_p``.
    """
    tilts = [0.5 * (h.peak - h.theta_i) for h in _peaks(meas)]
    if not tilts:
        return None
    return float(np.clip(np.median(tilts), 0.0, 89.0))


def narrow_highlight(meas):
    """Whether the measured highlight is narrower than the angular sampling: near-mirror platelets.

    True when, in the median over the incidences of :func:`_peaks`,
    the brightest point exceeds both its neighbours in ``theta_o`` by more
    than :data:`NARROW_RATIO`: a lobe that one viewing step resolves would
    fall off gradually. Such data get the estimator's MIS connection
    (:func:`make_problem`) and a near-mirror start (:func:`fit`).
    """
    ratios = [h.ratio for h in _peaks(meas)]
    return bool(ratios) and float(np.median(ratios)) > NARROW_RATIO


def highlight_width(meas):
    """The broadest platelet roughness ``alpha_p`` that the measured highlight allows, or ``None``.

    A GGX lobe falls from its peak to a half-vector ``theta_h`` away by
    ``D(0) / D(theta_h) = cos^4 theta_h (1 + tan^2 theta_h / alpha^2)^2``
    (docs/model.md section 2), and a viewing step of ``d`` turns the in-plane
    half vector by ``d / 2``. A brightest point ``R`` times its brighter
    neighbour, ``d`` away, so bounds the roughness by
    ``alpha <= tan(d / 2) / sqrt(sqrt(R) - 1)``: a lobe whose centre lies
    between the two points, or a diffuse background under it, would need a
    narrower lobe for the same ratio. The result is the median of that bound
    over the incidences whose brightest point has a measured neighbour on both
    sides and exceeds them; where the sampling is coarse it is a loose bound
    (nine times the lobe's ``alpha_p`` on a 10-degree grid, in the sets measured), on a fine one close.
    """
    bounds = [np.tan(np.radians(0.5 * h.spacing)) / np.sqrt(np.sqrt(h.ratio) - 1.0)
              for h in _highlights(meas) if h.interior and h.ratio > 1.0 and h.spacing > 0]
    return float(np.median(bounds)) if bounds else None


class GlossGrowth(NamedTuple):
    """How the measured gloss grows with incidence (:func:`gloss_growth`), against a medium's and a surface's.

    Attributes:
        theta_i: the lowest and highest incidences compared (degrees).
        growth: the brightest value at the highest incidence over that at the lowest.
        volume: ``(mu_i + mu_o)`` at the lowest over that at the highest, at their brightest
            points: how single scattering in a medium of diffusers grows.
        surface: ``mu_i mu_o`` at the lowest over that at the highest: how a reflection at
            the surface grows (before Fresnel, which adds to it).
    """

    theta_i: tuple
    growth: float
    volume: float
    surface: float

    @property
    def surface_like(self):
        """Whether the gloss grows :data:`SURFACE_GROWTH` times faster than single scattering in diffusers."""
        return self.growth > SURFACE_GROWTH * self.volume


def gloss_growth(meas):
    """How the brightest point of the measured incidences grows from the lowest to the highest: a :class:`GlossGrowth`.

    ``None`` where fewer than two incidences have a highlight (:func:`_highlights`)
    or they lie less than 20 degrees apart. Single scattering in a medium is
    ``sigma_s f / (sigma_t(wi) mu_o + sigma_t(wo) mu_i)`` (docs/model.md section
    4): from diffusers it grows like ``1 / (mu_i + mu_o)``, and only from a medium
    nearly all platelets, whose extinction falls with the cosine (a dark,
    mirror-like material), like ``1 / (mu_i mu_o)``, as a reflection at a top
    surface does (``F D G / (4 mu_i mu_o)``, docs/model.md section 3a). A gloss
    growing much faster than the first says that a fit without an interface can
    make it only with a mirror-like medium: the real Clarins 105 grows 8.4-fold
    from 20 to 70 degrees, where diffusers grow 3.2-fold and a surface 10-fold,
    and its index-matched fit is a black mirror (``c_d`` 0.001).
    """
    highlights = _highlights(meas)
    if len(highlights) < 2 or highlights[-1].theta_i - highlights[0].theta_i < 20.0:
        return None
    lo, hi = highlights[0], highlights[-1]
    mu = lambda h: (np.cos(np.radians(h.theta_i)), max(np.cos(np.radians(h.theta_o)), 1e-3))
    (ai, ao), (bi, bo) = mu(lo), mu(hi)
    return GlossGrowth(theta_i=(lo.theta_i, hi.theta_i), growth=hi.value / max(lo.value, 1e-30),
                       volume=float((ai + ao) / (bi + bo)), surface=float(ai * ao / (bi * bo)))


class FixedStart(NamedTuple):
    """A fixed start of the fit, screened or refined unscreened: its key, what it is, its ``Layer`` values."""

    key: str
    description: str
    values: dict


def fixed_starts(starts, t, tilt, connection):
    """The fit's fixed starts, in the screen's order: :class:`FixedStart` ``(key, description, Layer values)``.

    ``"default"`` (:data:`_DEFAULT`); with ``starts >= 1`` ``"platelet"``, broad
    tilted platelets (``_PLATELET_START``); with ``starts >= 2``, where the
    objective uses the ``"mis"`` connection (a highlight narrower than the angular
    sampling, :func:`narrow_highlight`) and the variant has a tilt ``tilt``
    (:func:`highlight_tilt`), ``"near-mirror"``, sparse near-mirror platelets at
    that tilt (``_MIRROR_START``). ``t``: the optical thickness of each.
    """
    out = [FixedStart("default", "default", {**_DEFAULT, "t": t})]
    if starts >= 1:
        out.append(FixedStart("platelet", "broad tilted platelets", {**_DEFAULT, "t": t, **_PLATELET_START}))
    if starts >= 2 and tilt is not None and connection == "mis":
        out.append(FixedStart("near-mirror", "near-mirror platelets at the highlight's tilt",
                              {**_DEFAULT, "t": t, **_MIRROR_START, "theta_p": tilt}))
    return out


def highlight_start(t, tilt, width):
    """The :class:`FixedStart` ``"highlight"``: platelets at the tilt ``tilt``, as broad as ``width`` allows.

    ``width`` from :func:`highlight_width`, kept within the near-mirror and
    broad platelet starts' roughnesses. Refined unscreened beside the
    near-mirror start: from the broad side a solver narrows a lobe smoothly,
    where a near-mirror lobe that falls between the sampled directions of a
    coarse grid barely changes the objective as it widens (docs/method.md,
    "Near-mirror highlights").
    """
    alpha = float(np.clip(width, _MIRROR_START["alpha_p"], _PLATELET_START["alpha_p"]))
    return FixedStart("highlight", "platelets as broad as the highlight allows, at its tilt",
                      {**_DEFAULT, "t": t, "alpha_p": alpha, "theta_p": tilt})


def random_starts(param, n, rng, tilt=None):
    """``n`` starting vectors, each parameter drawn uniformly from its own range.

    ``c_d`` in [0.05, 0.95], albedos in [0.3, 0.99], ``g1`` in [-0.3, 0.9],
    ``g2`` in [-0.6, 0.3], ``w_g`` in [0.2, 0.95], ``alpha_p`` log-uniformly
    in [0.003, 1], ``theta_p`` in [0, 80] degrees, ``t`` in [1, 30],
    ``phi_p`` 0: clear of the bounds, where the unbounded coordinates
    saturate. ``theta_p`` spans nearly its whole range because the fit's
    basin in the tilt is narrow for broad lobes (docs/method.md, "The search").

    With a ``tilt`` (from :func:`highlight_tilt`), a third of them take that
    ``theta_p`` (within half a degree) and a narrow ``alpha_p`` (log-uniform in
    [0.001, 0.05]): the starts of a near-mirror highlight.
    """
    draws = []
    for i in range(n):
        values = dict(
            c_d=rng.uniform(0.05, 0.95), albedo_d=rng.uniform(0.3, 0.99, 3), g1=rng.uniform(-0.3, 0.9),
            g2=rng.uniform(-0.6, 0.3), w_g=rng.uniform(0.2, 0.95), albedo_p=rng.uniform(0.3, 0.99, 3),
            alpha_p=10 ** rng.uniform(-2.5, 0), theta_p=rng.uniform(0, 80), t=rng.uniform(1, 30), phi_p=0.0,
        )
        if param.interface:  # drawn after the rest, so that the other parameters' draws do not change
            values.update(eta=rng.uniform(1.2, 1.8), alpha_s=10 ** rng.uniform(-2, np.log10(0.5)))
        if tilt is not None and i >= n - n // 3:
            values.update(theta_p=np.clip(tilt + rng.uniform(-0.5, 0.5), 0.0, 89.9),
                          alpha_p=10 ** rng.uniform(-3, np.log10(0.05)))
        draws.append(np.concatenate([np.atleast_1d(_TRANSFORMS[n_][1](values[n_])) for n_ in param.names]))
    return jnp.asarray(np.reshape(draws, (n, param.size)), dtype=jnp.result_type(float))


def with_mc_error(problem, meas, x):
    """``problem`` with lobe probabilities and Monte Carlo error taken at ``x``, both then held fixed.

    Under a top interface the boundary probability is taken at ``x`` too
    (:func:`quietest_boundary_probability`).

    The weights become ``1 / sqrt(std^2 + s_mc^2)``: with a fixed key the
    Monte Carlo error is an offset as large as a noise, and counting it as
    information would inflate the chi-square. ``s_mc = r |model|``, with ``r``
    the median relative standard error over the points at ``x``: a per-point
    standard error would come from the same walks as the error itself (a
    point the walks overestimate also gets a large standard error) and the
    weights would bias the fit. Files without std columns stay unweighted.
    """
    problem = dataclasses.replace(problem, lobe_probs=_lobe_probabilities_at(problem.param, x))
    if problem.param.interface:
        problem = dataclasses.replace(problem, boundary_prob=quietest_boundary_probability(problem, x))
    if meas.std is None:
        return problem
    return dataclasses.replace(problem, sigma=_mc_sigma(problem.estimate(x), jnp.asarray(meas.std, problem.sigma.dtype),
                                                        problem.scale))


BOUNDARY_FACTORS = (1 / 3, 2 / 3, 1.0, 1.6, 2.7)
"""The boundary probabilities :func:`quietest_boundary_probability` tries, as multiples of
:func:`~jaxcos.model.boundary_probability`'s."""


def quietest_boundary_probability(problem, x):
    """The boundary probability of :data:`BOUNDARY_FACTORS` times the default at ``x`` whose objective is quietest.

    Under a top interface a flight up ends at the top with a fixed probability
    ``p`` (:func:`~jaxcos.model.boundary_probability`; any ``p`` in ``(0, 1)``
    is unbiased). The best ``p`` moves with the material: a weak interface
    (``eta`` near 1) reflects little and wants a smaller one, walks whose
    vertices stay near the top a larger one, and the objective's Monte Carlo
    variance changed by up to five times either way (benchmarks/RESULTS.md,
    decision records, "Where an interface fit's noise is"). Each candidate is
    evaluated once at ``x`` under a key of its own stream (so that the
    objective's walks do not depend on the choice); the one of least Monte
    Carlo chi-square ``sum (scale se / sigma)^2`` is held fixed, like the
    lobe probabilities.
    """
    p0 = float(boundary_probability(problem.param.to_material(x)))
    candidates = [min(max(p0 * f, 0.01), 0.95) for f in BOUNDARY_FACTORS]
    pilot = dataclasses.replace(problem, key=jax.random.fold_in(problem.key, BOUNDARY_STREAM))
    noise = concurrently(lambda p: float(_mc_chi2(pilot, dataclasses.replace(
        pilot, boundary_prob=jnp.asarray(p, problem.sigma.dtype)).estimate(x))), candidates)
    return jnp.asarray(candidates[int(np.argmin(noise))], problem.sigma.dtype)


@eqx.filter_jit
def _mc_chi2(problem, est):
    """The Monte Carlo chi-square ``sum (scale se / sigma)^2`` of an estimate under ``problem``'s weights."""
    return jnp.sum((problem.scale * est.stderr / problem.sigma) ** 2)


@eqx.filter_jit
def _mc_sigma(est, std, scale):
    """The weights' ``sqrt(std^2 + s_mc^2)`` of :func:`with_mc_error` (one compiled program, not one per operation)."""
    rel = jnp.median(est.stderr / jnp.maximum(jnp.abs(est.f), 1e-12))
    return jnp.sqrt(std ** 2 + (rel * scale * est.f) ** 2)


@eqx.filter_jit
def _lobe_probabilities_at(param, x):
    """The lobe probabilities of the material at ``x`` (one compiled program, not one per operation)."""
    return lobe_probabilities(param.to_material(x))


# --- typed results ------------------------------------------------------------------


def _upper_bound(material_chi2, se):
    """The number a fit ranks materials by: the pair estimate plus twice its SE (see :data:`CHECK_FACTOR`)."""
    return material_chi2 + 2 * se


@dataclasses.dataclass(frozen=True, kw_only=True)
class CheckResult:
    """A material evaluated under independent keys against the data (:func:`check`).

    Weights: the measurement std, or none without std columns.

    Attributes:
        walks, batches, bounces: the check's budget, ``walks`` in all in ``batches`` batches.
        chi2: the sum of squared weighted residuals of the pooled estimate.
        chi2_mc: ``chi2 - material_chi2``, the check's own Monte Carlo share.
        material_chi2: the mean over batch pairs of the weighted sums of
            ``r_b r_c``, an unbiased estimate of the material's own chi-square.
        material_chi2_se: its standard error (the jackknife over batches,
            :func:`_pair_chi2`); large where rare walks dominate the estimate
            (a near-mirror platelet lobe seen off its mirror direction).
        l2, rmse: of the pooled estimate (docs/formats.md, "The L2 of the reports").
        reduced_chi2, reduced_chi2_se: ``material_chi2`` and its SE per degree
            of freedom; ``None`` without std columns.
    """

    walks: int
    batches: int
    bounces: int
    chi2: float
    chi2_mc: float
    material_chi2: float
    material_chi2_se: float
    l2: float
    rmse: float
    reduced_chi2: float | None = None
    reduced_chi2_se: float | None = None

    @property
    def bound(self):
        """``material_chi2 + 2 material_chi2_se``: what the fit ranks checked materials by (lower is better)."""
        return _upper_bound(self.material_chi2, self.material_chi2_se)

    def to_json(self):
        """The ``"check"`` object of a fit's record in ``params.json`` (docs/formats.md)."""
        out = dict(walks=self.walks, batches=self.batches, bounces=self.bounces, chi2=self.chi2,
                   chi2_mc=self.chi2_mc, material_chi2=self.material_chi2, material_chi2_se=self.material_chi2_se,
                   l2=self.l2, rmse=self.rmse)
        if self.reduced_chi2 is not None:
            out.update(reduced_chi2=self.reduced_chi2, reduced_chi2_se=self.reduced_chi2_se)
        return out


@dataclasses.dataclass(frozen=True, kw_only=True)
class FinalStep:
    """The fit's last steps (:func:`polish`): their damping, the checks before and after, how many were kept.

    Attributes:
        damping: :data:`FINAL_DAMPING`.
        check_before: the check of the start, before any step.
        check_after: where a step was kept, the check of the last one kept (the fitted material's);
            else the first step's, or ``None`` where it was not finite (and so not taken).
        steps: the steps kept, at most :data:`POLISH_STEPS` times :data:`POLISH_ROUNDS`.
        jacobians: the Jacobians taken, one per round of steps (at most :data:`POLISH_ROUNDS`).
        jacobian_walks: the walks of each Jacobian.
    """

    damping: float
    check_before: CheckResult
    check_after: CheckResult | None
    steps: int = 0
    jacobians: int = 1
    jacobian_walks: int = 0

    @property
    def kept(self):
        """Whether a step was kept."""
        return self.steps > 0

    def to_json(self):
        """The ``"final_step"`` object of a fit's record in ``params.json``."""
        return dict(damping=self.damping, kept=self.kept, steps=self.steps, jacobians=self.jacobians,
                    jacobian_walks=self.jacobian_walks,
                    check_before=self.check_before.to_json(),
                    check_after=None if self.check_after is None else self.check_after.to_json())


class FinerStage(NamedTuple):
    """Whether the fit's finer refinement (:func:`refine_finer`) ran, and why.

    ``share``: the selected start's :func:`objective_mc_share`; ``threshold``:
    :data:`FINE_SHARE`; ``factor``: :data:`FINE_FACTOR`, the walks' multiple.
    """

    share: float
    threshold: float
    factor: int

    @property
    def ran(self):
        """Whether the finer refinement ran: ``share >= threshold``."""
        return bool(self.share >= self.threshold)

    def to_json(self):
        """The ``"finer"`` object of a fit's record in ``params.json``."""
        return dict(share=self.share, threshold=self.threshold, factor=self.factor, ran=self.ran)


@dataclasses.dataclass(frozen=True)
class FitBudget(_MCBudget):
    """The Monte Carlo budget of a fit's objective: a :class:`jaxcos.model.Budget` and the Jacobian's walks.

    ``walks`` per incidence and ``bounces`` per walk (default
    :data:`jaxcos.model.FIT_BUDGET`); ``jacobian_walks``: the walks of its
    Jacobian, the first of the same walks (at most ``walks``). The screen's
    and the check's budgets derive from it.
    """

    walks: int = FIT_BUDGET.walks
    bounces: int = FIT_BUDGET.bounces
    jacobian_walks: int = FIT_JACOBIAN_WALKS

    @classmethod
    def of(cls, walks=FIT_WALKS, bounces=FIT_BOUNCES, jacobian_walks=FIT_JACOBIAN_WALKS):
        """The budget, ``jacobian_walks`` checked and held to at most ``walks``.

        Raises:
            InputError: unless ``jacobian_walks`` is a positive integer.
        """
        if int(jacobian_walks) != jacobian_walks or jacobian_walks < 1:
            raise InputError(f"jacobian_walks must be a positive integer, not {jacobian_walks}.")
        return cls(walks=int(walks), bounces=int(bounces), jacobian_walks=min(int(jacobian_walks), int(walks)))

    @property
    def screen_walks(self):
        """The screen's walks: half the Jacobian's, at least 8."""
        return max(self.jacobian_walks // 2, 8)

    @property
    def screen_bounces(self):
        """The screen's bounces: a quarter of the fit's, at least 16."""
        return max(self.bounces // 4, 16)

    @property
    def check_walks(self):
        """The walks of a check (:func:`check`): :data:`CHECK_FACTOR` times ``walks``, in :data:`CHECK_BATCHES` equal batches."""
        return CHECK_BATCHES * -(-CHECK_FACTOR * self.walks // CHECK_BATCHES)


Budget = FitBudget
"""The fit's budget under its former name (:class:`FitBudget`; the plain budget is :class:`jaxcos.model.Budget`)."""


@dataclasses.dataclass(frozen=True, kw_only=True)
class FitSummary:
    """What every fit reports, the Monte Carlo fits (:class:`FitRecord`) and the Kubelka-Munk baseline alike.

    Attributes:
        loss: the objective at the fitted material, under the fit's key.
        l2, rmse: the paper's L2 (sum of squared differences) and the RMSE, file's quantity.
        n_points: measured points (each with 3 channels).
        reduced_chi2: ``loss`` per degree of freedom, or ``None`` without std columns.
        reduced_chi2_noise_only: the same weighted by the measurement std alone, or ``None``.
        iterations: solver steps of the selected start.
        time_s: wall time of the fit, seconds.
        method, variant: the solver and the model variant.
    """

    loss: float
    l2: float
    rmse: float
    n_points: int
    reduced_chi2: float | None = None
    reduced_chi2_noise_only: float | None = None
    iterations: int
    time_s: float
    method: str
    variant: str


@dataclasses.dataclass(frozen=True, kw_only=True)
class FitRecord(FitSummary):
    """What a fit did and how well it fits: the ``"fit"`` record of ``params.json`` (docs/formats.md).

    Attributes (besides those of :class:`FitSummary`; ``reduced_chi2`` weighs by
    the measurement noise and the model's Monte Carlo error):
        seed: as given to :func:`fit`.
        n_evaluations: forward evaluations at the objective's walks over every
            refined start (a Jacobian counts as parameters + 1 forwards at its walks).
        budget: the objective's :class:`Budget`.
        n_params: fitted parameters (entries of ``x``).
        connection: the estimator's connection (``"nee"`` or ``"mis"``, :func:`make_problem`).
        fitted: the fitted parameters' names.
        fixed_starts: the descriptions of the screen's fixed starts, by their index (empty for a given start).
        starts_refined: refined starts; ``starts_at_optimum``: those whose loss
            on the selected start's objective is within 1% of its own.
        unfinished_energy: the largest energy fraction left in unfinished walks.
        mc_error_median: the model's median Monte Carlo standard error, relative to the std where there is one.
        check: the fitted material's :class:`CheckResult`.
        finer: the :class:`FinerStage`, or ``None`` (Powell, or ``finer=False``).
        final_step: the :class:`FinalStep`, or ``None`` (Powell, or ``final_step=False``).
    """

    REDUCED_CHI2_NOTE: ClassVar[str] = (
        "reduced_chi2 weights residuals by sqrt(std^2 + mc^2), the measurement noise and the model's Monte Carlo "
        "error; reduced_chi2_noise_only by std alone.")

    n_evaluations: int
    budget: Budget
    seed: int
    n_params: int
    connection: str
    fitted: tuple
    fixed_starts: tuple
    starts_refined: int
    starts_at_optimum: int
    unfinished_energy: float
    mc_error_median: float
    check: CheckResult
    finer: FinerStage | None
    final_step: FinalStep | None

    def to_json(self):
        """The ``"fit"`` object of ``params.json``."""
        out = dict(loss=self.loss, l2=self.l2, rmse=self.rmse, n_points=self.n_points)
        if self.reduced_chi2 is not None:
            out.update(reduced_chi2=self.reduced_chi2, reduced_chi2_noise_only=self.reduced_chi2_noise_only)
        out.update(
            iterations=self.iterations, time_s=self.time_s, method=self.method, variant=self.variant,
            n_evaluations=self.n_evaluations, walks=self.budget.walks, bounces=self.budget.bounces,
            jacobian_walks=self.budget.jacobian_walks, seed=self.seed, n_params=self.n_params,
            connection=self.connection, fitted=list(self.fitted), fixed_starts=list(self.fixed_starts),
            starts_refined=self.starts_refined, starts_at_optimum=self.starts_at_optimum,
            unfinished_energy=self.unfinished_energy, mc_error_median=self.mc_error_median,
            check=self.check.to_json(), finer=None if self.finer is None else self.finer.to_json(),
            final_step=None if self.final_step is None else self.final_step.to_json(),
            reduced_chi2_note=self.REDUCED_CHI2_NOTE)
        return out


class StartSummary(NamedTuple):
    """One refined start of a fit: its label, its final loss and its check's material chi-square with SE.

    The label is the screened start's index (0: the default start), ``"given"``, or
    ``"default, unscreened"`` (``"near-mirror, unscreened"`` and ``"highlight, unscreened"`` where the
    highlight is narrower than the angular sampling); a start refined from another one adds to
    its label ``", one lobe"`` or ``", other lobes"`` (:func:`refine_phase`) or ``", 4x walks"``
    (:func:`refine_finer`).
    """

    label: str
    loss: float
    material_chi2: float
    material_chi2_se: float


@dataclasses.dataclass
class FitResult:
    """The outcome of :func:`fit`.

    Attributes:
        material: the fitted material, its diffusers' lobes labelled so that ``g1 >= g2`` (:func:`ordered_lobes`).
        record: its :class:`FitRecord` (``record.to_json()``: the ``"fit"`` record of docs/formats.md).
        model: ``(N, 3)`` the fitted model in the file's quantity.
        model_std: ``(N, 3)`` its Monte Carlo standard error.
        starts: a :class:`StartSummary` per refined start.
        x: the fitted unbounded coordinates; ``param`` maps them to ``material``.
        problem: the selected start's objective (its last pass's weights and lobe probabilities); it
            fitted ``x`` with the lobes as they were, which estimates the same material.
    """

    material: Material
    record: FitRecord
    model: np.ndarray
    model_std: np.ndarray
    starts: list
    x: jnp.ndarray
    param: Parameterization
    problem: Problem


def _l2_rmse(resid):
    """The paper's L2 (sum of squared differences) and the RMSE of the differences ``resid``."""
    return dict(l2=float(np.sum(resid ** 2)), rmse=float(np.sqrt(np.mean(resid ** 2))))


def measured_values(meas):
    """The number of measured values of ``meas``: three per point, the padded points (infinite std) left out."""
    if meas.std is None:
        return int(np.size(meas.values))
    return int(np.sum(np.isfinite(meas.std)))


def check_determined(meas, n_free, model, option="--variant"):
    """Raise :class:`InputError` unless ``meas`` has more measured values than ``model``'s ``n_free`` fitted parameters.

    With as many parameters as values, or more, a least-squares fit has no
    degrees of freedom: its minimum is not unique, and its reduced chi-square
    and posterior spreads are undefined. ``option``: the command-line option
    that chooses the variants, named in the message.
    """
    n = measured_values(meas)
    if n <= n_free:
        raise InputError(f"{meas.path}: {n} measured values ({n // 3} point{'s' * (n // 3 != 1)} x 3 channels) for "
                         f"the {n_free} fitted parameters of {model}; a fit needs more values than parameters, so "
                         f"measure more geometries or fit a variant with fewer parameters ({option}).")


def fit_statistics(meas, model, loss, n_free):
    """``loss``, ``l2``, ``rmse``, ``n_points`` and, with std columns, ``reduced_chi2`` and ``reduced_chi2_noise_only``.

    ``model``: ``(N, 3)`` in the file's quantity; ``loss``: the objective there; ``n_free``: fitted
    parameters. A dictionary with the keys of :class:`FitRecord`'s fields of these names.
    """
    resid = model - meas.values
    n = resid.size
    dof = max(n - n_free, 1)
    stats = dict(loss=float(loss), **_l2_rmse(resid), n_points=int(meas.values.shape[0]))
    if meas.std is not None:
        stats["reduced_chi2"] = float(loss / dof)
        stats["reduced_chi2_noise_only"] = float(np.sum((resid / meas.std) ** 2) / dof)
    return stats


# --- the check under independent keys -----------------------------------------------


def check(problem, meas, x, *, key, walks, batches=CHECK_BATCHES):
    """The material at ``x`` evaluated under independent keys, ``walks`` walks in all: a :class:`CheckResult`.

    Under its fixed key a fit can follow the Monte Carlo error of that key: a
    near-mirror highlight, for instance, can be matched by a few lucky walks
    that another key does not reproduce. An independent evaluation cannot be
    tuned that way. It runs ``batches`` independent batches of ``walks /
    batches`` walks (keys ``fold_in(key, b)``); per point and channel, with
    ``r_b`` the residual of batch ``b``, the product ``r_b r_c`` of two
    different batches is an unbiased estimate of the squared residual of the
    exact model, free of Monte Carlo variance. A fit keeps the start for
    which ``material_chi2``, their mean, is lowest: ``chi2`` would also rank
    the materials by how noisy they are to simulate.
    """
    return _check(problem, meas, x, key, walks, batches)[0]


def _check(problem, meas, x, key, walks, batches=CHECK_BATCHES):
    """:func:`check`'s result and the pooled model ``(N, 3)`` (file's quantity) it comes from."""
    r, model, real, sigma = batch_residuals(problem, meas, x, key, walks, batches)
    material, se = _pair_chi2(r)
    resid = (model.mean(axis=0) - meas.values)[real]
    chi2 = float(np.sum((resid / sigma[real]) ** 2))
    reduced = {}
    if meas.std is not None:
        dof = max(resid.size - problem.param.size, 1)
        reduced = dict(reduced_chi2=material / dof, reduced_chi2_se=se / dof)
    out = CheckResult(walks=int(walks), batches=int(batches), bounces=int(problem.bounces), chi2=chi2,
                      chi2_mc=chi2 - material, material_chi2=material, material_chi2_se=se, **_l2_rmse(resid),
                      **reduced)
    return out, model.mean(axis=0)


def batch_residuals(problem, meas, x, key, walks, batches=CHECK_BATCHES, first=0):
    """The weighted residuals ``(batches - first, N', 3)`` of batches ``first, ..., batches - 1`` of :func:`check`.

    Batch ``b`` runs ``walks / batches`` walks under ``fold_in(key, b)``, so
    a batch does not depend on how many others there are: ``first`` extends
    residuals already taken. ``N'`` counts the measured points (padded ones,
    of infinite std, left out; unit weights without std). Returns ``(r,
    model, real, sigma)``: also each batch's model ``(batches - first, N,
    3)`` in the file's quantity, the mask of measured points and the
    weights' std.
    """
    if batches < 3 or walks % batches:
        raise ValueError(f"check needs at least 3 batches that divide the walks; got {walks} walks, {batches} batches.")
    sub = dataclasses.replace(problem, walks=walks // batches)
    model = problem.scale * np.stack([np.asarray(f, float) for f in concurrently(
        lambda k: dataclasses.replace(sub, key=k).estimate(x).f, _batch_keys(key, batches, first))])
    sigma = np.ones_like(model[0]) if meas.std is None else np.asarray(meas.std, float)
    real = np.all(np.isfinite(sigma), axis=1)  # padded dummy points (jaxcos.ablate) have an infinite std
    return (model - meas.values)[:, real] / sigma[real], model, real, sigma


def pair_terms(r):
    """The pair estimate of :func:`_pair_chi2` and its ``K`` delete-one-batch values, from batch residuals ``r``."""
    k = r.shape[0]
    r = r.reshape(k, -1)
    gram = r @ r.T
    total = gram.sum() - np.trace(gram)
    # leaving out batch b removes its row and column of the off-diagonal sum
    leave_one_out = (total - 2 * (gram.sum(axis=1) - np.diag(gram))) / ((k - 1) * (k - 2))
    return float(total) / (k * (k - 1)), leave_one_out


def jackknife_se(leave_one_out):
    """The delete-one jackknife's standard error from the ``K`` delete-one values of an estimate."""
    k = len(leave_one_out)
    return float(np.sqrt((k - 1) / k * np.sum((leave_one_out - np.mean(leave_one_out)) ** 2)))


def _pair_chi2(r):
    """The pair estimate of the exact model's chi-square from batch residuals ``r`` (``(K, ...)``), and its SE.

    With ``r_b = delta + e_b`` (``delta`` the exact model's weighted residuals,
    ``e_b`` batch ``b``'s Monte Carlo error, independent across batches), the
    mean over ordered pairs ``b != c`` of ``r_b . r_c`` is unbiased for
    ``delta . delta``. Its standard error is the delete-one-batch jackknife's.
    That overstates the variance of the part quadratic in the errors
    ``2 (K - 1) / (K - 2)``-fold, a part that falls fast with ``K`` (the same
    walks in more batches; docs/method.md). An unbiased estimate of the
    variance exists but can go negative under heavy-tailed errors (a
    near-mirror lobe).
    """
    estimate, leave_one_out = pair_terms(r)
    return estimate, jackknife_se(leave_one_out)


def gauss_newton_step(problem, jac, pooled, x, *, damping=FINAL_DAMPING):
    """One damped Gauss-Newton step from ``x`` towards the material that fits the model ``pooled`` best.

    ``pooled``: ``(N, 3)``, a model of the material at ``x`` in the file's
    quantity with less Monte Carlo error than ``problem``'s own (the check's
    pooled estimate: :data:`CHECK_FACTOR` times the walks); ``jac``: the
    Jacobian of ``problem``'s residuals at ``x`` (the one a Levenberg-Marquardt
    pass ended with). The step solves ``(J^T J + damping diag(J^T J)) dx =
    -J^T r`` with ``r`` the residuals of ``pooled`` under ``problem``'s weights
    (Marquardt's scaling). At a minimum of ``problem``'s objective
    ``J^T r`` is what its key's Monte Carlo error pulled the fit away by; the
    damping keeps the step off the directions the data hardly pin down.
    """
    sigma = np.asarray(problem.sigma, float)
    real = np.isfinite(sigma)  # padded dummy points (jaxcos.ablate): infinite std, no residual
    r = np.where(real, (pooled - np.asarray(problem.measured, float)) / np.where(real, sigma, 1.0), 0.0).reshape(-1)
    jac = np.asarray(jac, float)
    a = jac.T @ jac
    d = np.diag(a)
    # a parameter with no effect on the data (a zero column) gets no step
    dx = -np.linalg.solve(a + np.diag(damping * d + 1e-12 * max(float(d.max()), 1e-30)), jac.T @ r)
    return x + jnp.asarray(dx, x.dtype)


def _batch_keys(key, n, first=0):
    """The independent keys ``fold_in(key, b)`` for ``b = first, ..., n - 1``: the batches of :func:`check` and of
    the screen."""
    return [jax.random.fold_in(key, b) for b in range(first, n)]


# --- the stages of a fit --------------------------------------------------------------


class _Abandoned(Exception):
    """Raised in a background refinement whose fit has stopped."""


def _in_background(fn, *args):
    """``fn(*args)`` in a daemon thread; returns its :class:`concurrent.futures.Future`.

    A daemon thread does not hold up the exit of an interrupted process (a
    thread pool's worker would be joined first, up to a pass of a fit later).
    """
    future = concurrent.futures.Future()

    def run():
        try:
            future.set_result(fn(*args))
        except BaseException as err:  # handed to the thread that waits for the result
            future.set_exception(err)

    threading.Thread(target=run, daemon=True).start()
    return future


def _silent(message):
    """The default ``progress``: says nothing."""


@dataclasses.dataclass(frozen=True)
class RefinedStart:
    """A start after :data:`PASSES` solver passes (:class:`Refiner`).

    Attributes:
        label: see :class:`StartSummary`.
        x: where it ended (unbounded coordinates).
        loss: the objective of its last pass there.
        steps: solver steps (LM) or evaluations (Powell), over all passes.
        evaluations: forward evaluations at the objective's walks, a Jacobian counted at its cost.
        problem: the objective of its last pass (its weights and lobe probabilities).
    """

    label: str
    x: jnp.ndarray
    loss: float
    steps: int
    evaluations: float
    problem: Problem


class Refiner:
    """The refine stage: :data:`PASSES` passes of ``method`` from a start, each on :func:`with_mc_error` at its start.

    Each pass starts with the coordinates that have run to a bound released (:func:`release_saturated`).

    ``stop``, once set, abandons a refinement at its next pass (:class:`_Abandoned`): a
    fit that has stopped leaves its background start after the pass it is in.
    """

    def __init__(self, problem, meas, method, budget):
        self.problem, self.meas, self.method = problem, meas, method
        # in forward evaluations at the fit's walks: LM's value per step at the problem's walks, and
        # a Jacobian (its differences' evaluations at jacobian_walks) per accepted step
        self.per_value = problem.walks / budget.walks
        self.per_jacobian = problem.param.jacobian_evaluations() * budget.jacobian_walks / budget.walks
        self.stop = threading.Event()

    def __call__(self, label, x):
        steps, evaluations = 0, 0.0
        for _ in range(PASSES):
            if self.stop.is_set():
                raise _Abandoned
            x = release_saturated(self.problem.param, x)
            prob = with_mc_error(self.problem, self.meas, x)
            if prob.param.interface:  # the boundary probability's candidates (quietest_boundary_probability)
                evaluations += len(BOUNDARY_FACTORS) * self.per_value
            if self.method == "lm":
                x, loss, n, accepted = solve_lm(prob, x)
                evaluations += n * self.per_value + accepted * self.per_jacobian
            else:
                x, loss, n = solve_powell(prob, x)
                evaluations += n * self.per_value
            steps += n
        return RefinedStart(label=label, x=x, loss=loss, steps=steps, evaluations=evaluations, problem=prob)


@dataclasses.dataclass(frozen=True)
class StartPlan:
    """The multi-start: the screen's fixed starts, its pool, and the starts refined unscreened beside it.

    Attributes:
        fixed: the :class:`FixedStart` of each fixed start, first in the pool.
        pool: ``(S, P)`` every start the screen runs, fixed ones then random ones.
        unscreened: the keys of the starts refined unscreened: ``"near-mirror"``, and
            ``"highlight"`` (:func:`highlight_start`) where the highlight bounds its
            width, where there is a near-mirror start (the screen's small budget can
            lead it astray); else ``"default"``.
        x_unscreened: their unbounded coordinates.
    """

    fixed: tuple
    pool: jnp.ndarray
    unscreened: tuple
    x_unscreened: tuple


def plan_starts(meas, param, connection, *, starts, t, rng):
    """The :class:`StartPlan` of ``starts`` screened starts besides the default one (:func:`fit`)."""
    tilt = highlight_tilt(meas) if "theta_p" in param.names else None
    fixed = tuple(fixed_starts(starts, t, tilt, connection))
    to_x = lambda f: param.from_material(Material(layers=(Layer(**f.values),)))
    xs = [to_x(f) for f in fixed]
    pool = jnp.concatenate([jnp.stack(xs), random_starts(param, starts + 1 - len(fixed), rng, tilt)])
    # The screen's budget is blind to a narrow lobe: refined unscreened, these starts do not depend on the
    # screen (docs/method.md, "Near-mirror highlights").
    if fixed[-1].key != "near-mirror":
        return StartPlan(fixed=fixed, pool=pool, unscreened=("default",), x_unscreened=(xs[0],))
    unscreened = [fixed[-1]]
    width = highlight_width(meas)
    if width is not None:
        unscreened.append(highlight_start(t, tilt, width))
    return StartPlan(fixed=fixed, pool=pool, unscreened=tuple(f.key for f in unscreened),
                     x_unscreened=tuple(to_x(f) for f in unscreened))


class ReserveStart(NamedTuple):
    """A screened start ranked just after those refined (:attr:`Screened.reserve`), not yet refined.

    Attributes:
        index: its place in the screen's pool (its label).
        rank: its place in the screen's ranking, 0 the best.
        x: the screen's end (unbounded coordinates).
    """

    index: int
    rank: int
    x: np.ndarray

    @property
    def label(self):
        return str(self.index)

    @property
    def message(self):
        return f"refining screened start {self.index}, ranked {self.rank + 1} by the screen"


@dataclasses.dataclass(frozen=True)
class Screened:
    """The screen's outcome: every start's end, its rank (lower is better), the best ``refine`` of them, and the
    :class:`ReserveStart` of the next :data:`MISSED_SCREENED` (:func:`screen`)."""

    ends: jnp.ndarray
    ranks: list
    order: list
    reserve: list


def screen(problem, pool, key, *, refine, refined_anyway=()):
    """The screen stage: :data:`SCREEN_STEPS` Levenberg-Marquardt steps from each start of ``pool``, ranked.

    ``problem``: the screen's objective (its small budget). The ends are ranked by
    the pair estimate of their chi-square over :data:`CHECK_BATCHES` independent
    batches (keys from ``key``) plus twice its SE (:func:`_pair_chi2`): the screen's
    own loss at so few walks would also rank the materials by how noisy they are to
    simulate. An end with a non-finite residual ranks last, and is never in the reserve.
    Of the best ``refine`` ends (``order``) and the next :data:`MISSED_SCREENED`
    (``reserve``, refined only where the fit misses: :func:`refine_missed`), those
    equal to a point of ``refined_anyway`` (the points refined unscreened) are
    left out: a start whose screen rejected every step ends where it began, and
    refining it again would repeat that refinement to the last bit.
    """
    ends, resid = _screen(problem, pool, _batch_keys(key, CHECK_BATCHES))
    ranks = [_upper_bound(*_pair_chi2(r)) if np.all(np.isfinite(r)) else np.inf for r in np.asarray(resid, float)]
    ends_np = np.asarray(ends)
    ranked = [int(i) for i in np.argsort(ranks)]
    new = lambda i: not any(np.array_equal(ends_np[i], np.asarray(x)) for x in refined_anyway)
    order = [i for i in ranked[:refine] if new(i)]
    reserve = [ReserveStart(i, rank, ends_np[i]) for rank, i in enumerate(ranked)
               if refine <= rank < refine + MISSED_SCREENED and new(i) and np.isfinite(ranks[i])]
    return Screened(ends=ends, ranks=ranks, order=order, reserve=reserve)


PHASE_GRID = dict(g1=(0.2, 0.4, 0.6, 0.8), g2=(-0.6, -0.3, 0.0), w_g=(0.6, 0.8, 0.95))
"""The two-lobe phase functions that :func:`phase_moves` puts in place of a refined start's own: from
forward to nearly isotropic front lobes, from strong to no back lobes, over the priors' weights."""

PHASE_STEPS = dict(g1=(-0.1, -0.05, -0.025, 0.025, 0.05, 0.1), g2=(-0.1, -0.05, -0.025, 0.025, 0.05, 0.1),
                   w_g=(-0.1, -0.05, 0.05, 0.1))
"""The moves of one phase parameter at a time that :func:`phase_moves` also tries: under a forward lobe
(``g1`` 0.6-0.9) the reflectance changes fast with ``g1``, and a fit can stop 0.1 short of it."""


def phase_moves(param, x):
    """``(labels, xs)``: ``x`` with its diffuser phase function replaced, ``xs`` of shape ``(C, P)``.

    First ``"one lobe"``: both lobes made one, ``g1 = g2`` at their mean cosine
    ``w_g g1 + (1 - w_g) g2`` with ``w_g`` kept; then ``"other lobes"``, each
    ``(g1, g2, w_g)`` of :data:`PHASE_GRID`, then ``x``'s own with one of them
    moved by each of :data:`PHASE_STEPS` (kept within the fit's bounds); every
    other parameter kept. ``None`` where ``param`` does not fit both lobes and
    their weight. The phase function's basins are separated by ridges that
    Levenberg-Marquardt does not cross with the rest held near the optimum: a
    single-lobe material (``w_g = 1``, the bound of ``w_g``'s map) fitted with
    two can end with two opposed lobes (``g1 = -g2``) of about the right mean
    cosine, a two-lobe one with its lobes traded against the platelets'
    albedo, and a strongly forward lobe short of its ``g1``, where the
    Jacobian of the fit's few walks hardly sees it (docs/method.md, "The search").
    """
    if not {"g1", "g2", "w_g"} <= set(param.names):
        return None
    labels = param.labels()
    v = np.asarray(param.to_physical(x), float)
    i1, i2, iw = labels.index("g1"), labels.index("g2"), labels.index("w_g")
    mean = v[iw] * v[i1] + (1.0 - v[iw]) * v[i2]
    phases = [(mean, mean, v[iw])] + [(g1, g2, w) for g1 in PHASE_GRID["g1"] for g2 in PHASE_GRID["g2"]
                                      for w in PHASE_GRID["w_g"]]
    low, high = param.bounds()
    margin = 1e-3 * (high - low)
    for k, (name, i) in enumerate((("g1", i1), ("g2", i2), ("w_g", iw))):
        for step in PHASE_STEPS[name]:
            u = [v[i1], v[i2], v[iw]]
            u[k] = float(np.clip(v[i] + step, low[i] + margin[i], high[i] - margin[i]))
            phases.append(tuple(u))
    vs = np.repeat(v[None], len(phases), axis=0)
    vs[:, [i1, i2, iw]] = phases
    xs = jnp.stack([param.from_material(param.physical_to_material(jnp.asarray(u, x.dtype))) for u in vs])
    return ["one lobe"] + ["other lobes"] * (len(phases) - 1), xs


def _levelled_losses(problem, xs):
    """:meth:`~WeightedLeastSquares.levelled_loss` at each row of ``xs``, ``(C,)``: one evaluation each, by the
    objective's own compiled program."""
    return jnp.stack(concurrently(lambda x: _levelled(problem, problem.estimate(x).f), np.asarray(xs)))


@eqx.filter_jit
def _levelled(problem, f):
    return problem.levelled(problem.scale * f)


class PhaseMove(NamedTuple):
    """A refined start's best :func:`phase_moves` move of one kind, not yet refined.

    Attributes:
        ratio: its levelled loss over the start's own, on the start's objective (below 1).
        start: the :class:`RefinedStart` it moves.
        name: ``"one lobe"`` or ``"other lobes"``.
        x: the moved point (unbounded coordinates).
    """

    ratio: float
    start: RefinedStart
    name: str
    x: np.ndarray

    @property
    def label(self):
        return f"{self.start.label}, {self.name}"

    @property
    def message(self):
        lobes = "one diffuser lobe" if self.name == "one lobe" else "other diffuser lobes"
        return f"refining start {self.start.label} with {lobes}, where it fits better"


def best_phase_moves(refined):
    """Each refined start's best move of each kind that lowers its levelled loss, as :class:`PhaseMove`, best
    ratio first.

    Each start is evaluated on its own objective at its :func:`phase_moves`,
    after the best level per channel (:meth:`~WeightedLeastSquares.levelled_loss`).
    """
    moves = []
    for r in refined:
        planned = phase_moves(r.problem.param, r.x)
        if planned is None:
            continue
        names, xs = planned
        losses = np.asarray(_levelled_losses(r.problem, jnp.concatenate([r.x[None], xs])), float)
        best = {}
        for name, loss, x in zip(names, losses[1:], np.asarray(xs)):
            ratio = loss / losses[0]
            if np.isfinite(ratio) and ratio < 1.0 and (name not in best or ratio < best[name].ratio):
                best[name] = PhaseMove(float(ratio), r, name, x)
        moves += best.values()
    return sorted(moves, key=lambda m: m.ratio)


def _refine_pending(pending, refiner, say):
    """Each :class:`PhaseMove` or :class:`ReserveStart` of ``pending`` refined, as :class:`RefinedStart`."""
    out = []
    for m in pending:
        say(m.message)
        out.append(refiner(m.label, m.x))
    return out


MOVE_LOSS_FACTOR = 1.25
"""Where the best refined start's objective is its material's misfit (:func:`movable_starts`), a start
whose loss on that objective is more than this many times the best's is not moved: on the real Clarins 105
under an interface (Monte Carlo share 0.005) ranking the moves of a start at 1.6 times the best's loss and
refining two of them took 26 s of a 99 s fit, and both ended at 1.6 times again (docs/method.md, "The
search")."""


def movable_starts(refined, noise_model):
    """The refined starts whose phase moves :func:`refine_phase` ranks.

    All of them, except where the data have no noise model and the best
    refined start's objective (the lowest loss) is its material's misfit,
    its Monte Carlo share below :data:`FINE_SHARE` (the fixed key's variance,
    :func:`_mc_chi2`, over the loss): every start is then
    evaluated on that objective, where its loss is its misfit, and one more
    than :data:`MOVE_LOSS_FACTOR` times the best's is left out. Where the
    objective is rougher, a loss says little about a start's check (on
    recovery sets a start at 6.5 times the best's loss held the winning
    move), and with a noise model :func:`refine_missed` may need every
    start's moves.
    """
    if noise_model or len(refined) < 2:
        return refined
    best = int(np.argmin([r.loss for r in refined]))
    problem = refined[best].problem
    est = problem.estimate(refined[best].x)
    loss = float(jnp.sum(problem.weigh(problem.scale * est.f) ** 2))
    mc = float(_mc_chi2(problem, est))
    if not mc < FINE_SHARE * loss:
        return refined
    common = concurrently(lambda r: float(problem.loss(r.x)) if r is not refined[best] else loss, refined)
    return [r for r, c in zip(refined, common) if c <= MOVE_LOSS_FACTOR * loss]


def refine_phase(refined, refiner, say, noise_model=True):
    """The refine stage's last moves: refined starts with another diffuser phase function, refined where better.

    Of each kind of move (one lobe, other lobes), the one of
    :func:`best_phase_moves` that lowers its start's levelled loss most,
    relative to the start's own, is refined (:data:`PASSES` passes), and
    joins the refined starts for :func:`select` to judge (a loss under
    another start's weights says little about the check). Only the moves of
    :func:`movable_starts` are ranked (``noise_model``: whether the data
    have one). Returns the new :class:`RefinedStart` of each, and the other
    starts' best moves, not refined (:func:`refine_missed`).
    """
    moves = best_phase_moves(movable_starts(refined, noise_model))
    chosen = {}
    for m in moves:
        chosen.setdefault(m.name, m)
    kept = sorted(chosen.values(), key=lambda m: m.name != "one lobe")
    return _refine_pending(kept, refiner, say), [m for m in moves if all(m is not c for c in kept)]


MISSED_CHI2 = 2.0
"""Where the selected start's material misses data with a noise model by more than this (its reduced
chi-square under independent keys, less twice its SE), :func:`refine_missed` refines the screen's reserve and
the other starts' phase moves too."""

MISSED_SCREENED = 3
"""The screened starts ranked just after the refined ones that :func:`refine_missed` refines (the screen's
reserve, :func:`screen`). The screen ranks its ends after five steps at 64 walks: on a random set (coverage
seed 3, set 32: ``alpha_p`` 0.044) its three best ends all refined to a reduced chi-square of 42 and its fourth
to 1.1, the truth's basin (benchmarks/RESULTS.md, decision records, "The screen's reserve")."""


def refine_missed(refined, selection, pending, refiner, meas, key, walks, say):
    """The screen's reserve and the other starts' phase moves, refined and checked, where the selected start
    misses the data.

    Only for data with a noise model (a reduced chi-square), where the
    selected start's :attr:`CheckResult.reduced_chi2` less twice its SE is
    above :data:`MISSED_CHI2`: its material does not explain the data, and
    the fit's outcome then turns on which start was refined, of the screen's
    ranking (made at a small budget) and of the phase moves
    (benchmarks/RESULTS.md, decision records, "The fit's objective" and
    "The screen's reserve").
    ``pending``: the :class:`ReserveStart` of the screen's reserve, then the
    :class:`PhaseMove` not refined by :func:`refine_phase`. Each is refined
    and checked like the others (:func:`select`'s keys, ``key``), and joins
    them. Returns ``(refined, selection)``.
    """
    c = selection.checks[selection.best]
    if not pending or c.reduced_chi2 is None or c.reduced_chi2 - 2.0 * c.reduced_chi2_se <= MISSED_CHI2:
        return refined, selection
    say(f"the selected start misses the data (reduced chi-square {c.reduced_chi2:.3g}): refining the screen's "
        f"next starts and the other starts' phase moves too")
    more = _refine_pending(pending, refiner, say)
    return refined + more, selection.extended(select(more, meas, key, walks))


def screen_and_refine(plan, problem, refiner, key, *, budget, refine, method, say):
    """The screen and the refinement of its best ``refine`` ends, the plan's unscreened starts refined meanwhile.

    The unscreened starts are refined in other threads while the screen runs:
    their tracing and compiling, which leave a core idle, overlap the screen's.
    Then the best one-lobe point and the best other phase function of them
    are refined too, where they fit better (:func:`refine_phase`). Returns
    the :class:`RefinedStart` of each, the screened ones first, the moved ones
    last, and what :func:`refine_missed` may refine: the :class:`ReserveStart`
    of the screen's reserve, then the other :class:`PhaseMove` not refined.
    """
    screen_problem = dataclasses.replace(problem, walks=budget.screen_walks, bounces=budget.screen_bounces,
                                         jacobian_walks=None, thin_after=None)
    say(f"refining the {' and '.join(plan.unscreened)} start{'s' * (len(plan.unscreened) > 1)} unscreened "
        f"({method}, {PASSES} passes) while screening {plan.pool.shape[0]} starts with a short "
        f"Levenberg-Marquardt at {screen_problem.walks} walks and {screen_problem.bounces} bounces")
    unscreened = [_in_background(refiner, f"{name}, unscreened", x)
                  for name, x in zip(plan.unscreened, plan.x_unscreened)]
    try:
        screened = screen(screen_problem, plan.pool, jax.random.fold_in(key, SCREEN_STREAM), refine=refine,
                          refined_anyway=plan.x_unscreened)
        if screened.order:
            say(f"refining the best {len(screened.order)} screened start{'s' * (len(screened.order) > 1)} "
                f"({method}, {PASSES} passes)")
        else:
            say("the screen's best end is a start refined unscreened: no screened start refined besides")
        refined = [refiner(str(i), screened.ends[i]) for i in screened.order] + [u.result() for u in unscreened]
        moved, pending = refine_phase(refined, refiner, say, noise_model=refiner.meas.std is not None)
        return refined + moved, screened.reserve + pending
    finally:
        refiner.stop.set()  # an interrupted fit leaves its background starts after the pass they are in


@dataclasses.dataclass(frozen=True)
class Selection:
    """The select stage's outcome.

    Attributes:
        checks: the :class:`CheckResult` of each refined start.
    """

    checks: tuple

    @property
    def best(self):
        """The index of the selected start among the refined ones: the lowest :attr:`CheckResult.bound`."""
        return int(np.argmin([c.bound for c in self.checks]))

    def extended(self, other):
        """This selection with the checks of ``other`` (of starts refined later) after its own."""
        return Selection(checks=self.checks + other.checks)


def select(refined, meas, key, walks):
    """The select stage: check each refined start under independent keys; the lowest :attr:`CheckResult.bound` wins."""
    return Selection(checks=tuple(_check(r.problem, meas, r.x, key, walks)[0] for r in refined))


def _at_optimum(refined, best):
    """How many refined starts have a loss within 1% of start ``best``'s on ``best``'s objective.

    Each start's loss has its own weights and lobe probabilities; on the
    selected start's objective the starts are compared on one footing (a
    check cannot tell near-mirror materials apart).
    """
    problem = refined[best].problem
    common = [float(problem.loss(r.x)) for r in refined]
    return len([c for c in common if c - common[best] <= 0.01 * common[best]])


def objective_mc_share(check, walks):
    """The Monte Carlo share of a fixed-key objective at ``walks`` walks, relative to the material's chi-square.

    The check's own share ``chi2_mc`` (:class:`CheckResult`, at ``check.walks`` walks)
    scaled by ``check.walks / walks`` (a variance falls as one over the walks), over
    ``material_chi2``: about ``sum(s_mc^2 / sigma^2) / chi2``, how much of the objective a
    fit minimises at ``walks`` is its own estimate's variance rather than the material's misfit.
    """
    return check.chi2_mc * (check.walks / walks) / max(check.material_chi2, 1e-30)


INTERFACE_THIN_AFTER = 32
"""Under a top interface the refinements' objective makes its later steps with fewer walks from this step on
(:func:`fit`'s ``thin_after``): a walk through the interface costs about twice an index-matched one; so thinned,
the fit of Clarins 105 took 76-97 s instead of 130-150 s for the same material, and on six random sets under an
interface the fits recovered as many as before in about 55% of the time (from step 16: one more set, but
Clarins 105 weighted by ``--noise`` ended in another basin; benchmarks/RESULTS.md, decision records, "Fewer
walks for the later steps")."""

MIS_ALPHA = 0.1
"""The finer refinement connects by MIS where the selected start's platelets are narrower than this
(``alpha_p`` below it; :func:`finer_problem`). At the objective of a set's own data and 4096 walks, MIS
divided the Monte Carlo variance by 1.8-19 where ``alpha_p`` was 0.006-0.023 (seven random sets), by 1.2-1.7
where it was 0.08 on two of three materials, and by 1.02-1.05 from 0.13 up (dewy1, matte1, matte2), where it
costs 1.3-1.5 times the time (benchmarks/RESULTS.md, decision records)."""


def finer_problem(problem, x):
    """The objective of the finer refinement from ``x``: ``problem`` at :data:`FINE_FACTOR` times the walks.

    The same key (the first of the walks are ``problem``'s); its Jacobian
    from the first ``problem.walks`` of them (where ``problem`` takes its
    own from fewer), so that the steps follow slopes of the walks the fit
    already ran (one compiled program) rather than of the refinements' few:
    at 128 walks the slopes of a narrow lobe's objective are mostly noise
    (cosines of 0.2-0.7 with those of 8192 walks); every walk makes every
    step (``thin_after=None``).
    Where the material at ``x`` has platelets narrower than :data:`MIS_ALPHA`
    and no top interface the connection becomes ``"mis"``
    (:func:`~jaxcos.simulate`): the objectives that are mostly their own
    noise are those of narrow, tilted platelet lobes, whose variance sits in
    paths that meet the lobe more than once (benchmarks/RESULTS.md, "Where
    the fit's noise is worst"), which the MIS connection's second strategy
    draws. Under broader lobes it costs more than it removes.
    """
    mis = ("alpha_p" in problem.param.names and not problem.param.interface
           and float(problem.param.to_material(x).layers[0].alpha_p) < MIS_ALPHA)
    return dataclasses.replace(problem, walks=FINE_FACTOR * problem.walks,
                               jacobian_walks=None if problem.jacobian_walks is None else problem.walks,
                               connection="mis" if mis else problem.connection, thin_after=None)


def refine_finer(refined, selection, problem, meas, method, budget, key, say):
    """The finer refinement: the selected start refined again on :func:`finer_problem`, where it is rough.

    ``problem``: the fit's objective (its key and budget). It runs only where
    the selected start's :func:`objective_mc_share` is at least
    :data:`FINE_SHARE`. The result is checked like the others (:func:`_check`,
    keys from ``key``) and joins the refined starts, and becomes the selected
    one where its :attr:`CheckResult.bound` is the lowest. Returns ``(refined,
    selection, stage)``: both extended where it ran, and its :class:`FinerStage`.
    """
    share = objective_mc_share(selection.checks[selection.best], budget.walks)
    stage = FinerStage(share=float(share), threshold=FINE_SHARE, factor=FINE_FACTOR)
    if not stage.ran:
        say(f"no finer refinement: the objective's Monte Carlo share is {share:.2g} of its chi-square "
            f"(below {FINE_SHARE})")
        return refined, selection, stage
    start = refined[selection.best]
    finer = Refiner(finer_problem(problem, start.x), meas, method, budget)
    say(f"refining start {start.label} again at {finer.problem.walks} walks ({method}, {PASSES} passes, "
        f"{finer.problem.connection.upper()} connection) and checking it")
    r = finer(f"{start.label}, {FINE_FACTOR}x walks", start.x)
    return refined + [r], selection.extended(select([r], meas, key, budget.check_walks)), stage


@dataclasses.dataclass(frozen=True)
class Polished:
    """The polish stage's outcome: the fitted ``x``, its :class:`CheckResult`, and the :class:`FinalStep` taken."""

    x: jnp.ndarray
    check: CheckResult
    step: FinalStep | None


def polish(start, meas, key, walks, jacobian_walks, steps=POLISH_STEPS, rounds=POLISH_ROUNDS):
    """The polish stage: damped Gauss-Newton steps from ``start``, each on the pooled residuals of a fresh check.

    It begins with a check of ``start`` under fresh keys (``fold_in(key,
    0)``), not the select stage's: the start was selected for its check, so
    that check's pooled model leans towards the data by its own luck, and a
    step on it sees less of the misfit than there is (on a narrow-lobe
    recovery set, a step on the selecting check's residuals checked 3.0 per
    degree of freedom, no better; on fresh ones 1.7-2.8 in each of thirteen
    tries: docs/method.md, "The last steps"). The steps go in rounds of at
    most ``steps`` (:func:`gauss_newton_step`, :data:`FINAL_DAMPING`), each
    round along one Jacobian of ``start``'s objective taken where the round
    begins, from the first ``jacobian_walks`` walks of its key (the fit's:
    :data:`POLISH_JACOBIAN_FACTOR` times its walks; the refinements' few-walk
    Jacobian is the slope of a rough objective, and a step along it rarely
    checked better). Each step starts where the last kept one ended, on the
    pooled model of that point's check; the ``k``-th step's check, under
    ``fold_in(key, k)``, keeps it where its bound is lower than the last kept
    one's. A round ends at its first step not kept, or after ``steps``; the
    next one begins where it ended, if it kept a step, at most ``rounds`` in
    all.
    """
    check_before, pooled = _check(start.problem, meas, start.x, jax.random.fold_in(key, 0), walks)
    jac_problem = dataclasses.replace(start.problem, walks=jacobian_walks, jacobian_walks=jacobian_walks)
    x, last, first_after, kept, k = start.x, check_before, None, 0, 0
    for jacobians in range(1, rounds + 1):
        jac, kept_before = jac_problem.jacobian(x)[0], kept
        for _ in range(steps):
            k += 1
            x_step = gauss_newton_step(start.problem, jac, pooled, x)
            if not np.all(np.isfinite(np.asarray(x_step))):
                break
            check_after, pooled_after = _check(start.problem, meas, x_step, jax.random.fold_in(key, k), walks)
            first_after = check_after if first_after is None else first_after
            if not check_after.bound < last.bound:
                break
            x, last, pooled, kept = x_step, check_after, pooled_after, kept + 1
        if kept == kept_before:
            break
    step = FinalStep(damping=FINAL_DAMPING, check_before=check_before,
                     check_after=last if kept else first_after, steps=kept, jacobians=jacobians,
                     jacobian_walks=_jacobian_walks(jac_problem))
    return Polished(x=x, check=last, step=step)


def summarise(meas, refined, selection, polished, *, method, variant, seed, budget, fixed, finer, started):
    """The summarise stage: the :class:`FitResult` of the selected start after its polish.

    ``polished``: a :class:`Polished`, its ``step`` ``None`` where there was none;
    ``finer``: the :class:`FinerStage`, ``None`` where there was none;
    ``fixed``: the plan's :class:`FixedStart` (none for a given start); ``started``:
    the fit's ``time.perf_counter()`` at its start.
    """
    start = refined[selection.best]
    problem, param, x, loss = start.problem, start.problem.param, polished.x, start.loss
    est = problem.estimate(x)
    if polished.step is not None and polished.step.kept:  # the objective at the stepped material, from its estimate
        r = problem.weigh(problem.scale * est.f)
        loss = float(jnp.sum(r * r))
    model = np.asarray(problem.scale * est.f)
    model_std = np.asarray(problem.scale * est.stderr)
    elapsed = time.perf_counter() - started
    record = FitRecord(
        **fit_statistics(meas, model, loss, param.size),
        iterations=int(start.steps), time_s=round(elapsed, 2), method=method, variant=variant,
        n_evaluations=int(round(sum(r.evaluations for r in refined))), budget=budget, seed=int(seed),
        n_params=int(param.size), connection=problem.connection, fitted=tuple(param.names),
        fixed_starts=tuple(f.description for f in fixed), starts_refined=len(refined),
        starts_at_optimum=_at_optimum(refined, selection.best),
        unfinished_energy=float(np.max(np.asarray(est.unfinished))),
        mc_error_median=float(np.median(model_std / (meas.std if meas.std is not None else 1.0))),
        check=polished.check, finer=finer, final_step=polished.step,
    )
    starts = [StartSummary(r.label, float(r.loss), c.material_chi2, c.material_chi2_se)
              for r, c in zip(refined, selection.checks)]
    x = param.ordered_lobes(x)
    return FitResult(material=param.to_material(x), record=record, model=model, model_std=model_std,
                     starts=starts, x=x, param=param, problem=problem)


def fit(meas, *, variant="two_lobe", method="lm", seed=0, walks=FIT_WALKS, bounces=FIT_BOUNCES,
        jacobian_walks=FIT_JACOBIAN_WALKS, starts=15, refine=1, fit_t=False, fit_phi=False, start=None, t=16.0,
        interface=None, finer=True, final_step=True, thin_after="auto", progress=None):
    """Fit a one-layer material of ``variant`` to the measurements ``meas``.

    Args:
        meas: from :func:`jaxcos.load_measurements`.
        variant: one of :data:`jaxcos.VARIANTS`.
        method: ``"lm"`` (Levenberg-Marquardt, optimistix) or ``"powell"`` (SciPy).
        seed: seeds the Monte Carlo key (fixed for the whole fit) and the random starts.
        walks, bounces: the Monte Carlo budget of the objective.
        jacobian_walks: the walks of its Jacobian, the first of the same walks
            (at most ``walks``); the screen runs at half of them and a quarter
            of the bounces (:class:`Budget`).
        starts: number of starts screened besides the default start
            (:func:`plan_starts`): a fixed one where broad, tilted platelets
            dominate (``_PLATELET_START``), where the highlight is narrower
            than the angular sampling (:func:`narrow_highlight`) a fixed one
            of sparse near-mirror platelets at its tilt (``_MIRROR_START``),
            the others random; a third of the random ones start at the tilt
            of the measured highlight with a narrow ``alpha_p``
            (:func:`highlight_tilt`). The screen ranks its ends
            (:func:`screen`).
        refine: number of best screened starts refined at the full budget
            (:data:`PASSES` passes each), besides the default start as it is
            (the near-mirror start and :func:`highlight_start` where the
            highlight is narrow), refined in other threads while the screen runs
            (:func:`screen_and_refine`; a screened end that is one of those
            points is not refined again, :func:`screen`); each is then checked with
            :data:`CHECK_FACTOR` times the walks under independent keys, and
            the best check is the fit (:func:`select`), after up to
            :data:`POLISH_STEPS` Gauss-Newton steps on fresh checks' residuals,
            each kept where it checks better (LM only; :func:`polish`).
            Where the data have a noise model and the best
            check misses them, the next :data:`MISSED_SCREENED` screened
            starts and the other starts' best phase moves are refined and
            checked too (:func:`refine_missed`).
        fit_t, fit_phi: also fit the optical thickness ``t`` (else fixed at ``t``)
            or the tilt azimuth ``phi_p`` (else 0).
        start: a :class:`Material` to start from instead of the multi-start
            (only that start is refined).
        t: the optical thickness when it is not fitted (the paper's protocol: 16).
        interface: fit a rough dielectric top interface, its ``eta`` and
            ``alpha_s`` with the rest (docs/model.md section 3a); ``None``
            (the default) fits one exactly when ``start`` has one.
        finer: refine the selected start once more at :data:`FINE_FACTOR` times
            the walks, kept where its check is better (LM only; :func:`refine_finer`),
            where its objective's Monte Carlo share is at least :data:`FINE_SHARE`.
            ``False`` saves that time (nearly half of a fit) and keeps the
            best start at the fit's own walks.
        final_step: take the last Gauss-Newton steps on fresh checks' residuals
            (LM; :func:`polish`), where the objective's Monte Carlo share at the
            selected start is at least :data:`FINE_SHARE` (the steps undo that
            key's pull; below it there is little to undo). ``False`` keeps the
            minimum of the fixed-key objective itself.
        thin_after: the steps every walk of the refinements' objective (and
            so of their checks) makes, later steps made by fewer walks
            (:func:`~jaxcos.simulate`); ``None``: every walk makes every
            step; ``"auto"`` (the default): :data:`INTERFACE_THIN_AFTER`
            under a top interface, else ``None``. The screen and the finer
            refinement make every step with every walk (measured side by
            side in benchmarks/RESULTS.md, decision records, "Fewer walks
            for the later steps").
        progress: a callable ``progress(message)`` told about each stage (default: none).

    Returns:
        A :class:`FitResult`.
    """
    check_variant(variant)
    if method not in METHODS:
        raise InputError(f"unknown method {method!r}; choose 'lm' or 'powell'.")
    say = progress or _silent
    started = time.perf_counter()
    template = start if start is not None else Material(layers=(Layer(**{**_DEFAULT, "t": t}),))
    if interface is None:
        interface = start is not None and start.interface is not None
    if thin_after == "auto":
        thin_after = INTERFACE_THIN_AFTER if interface else None
    param = parameterization(variant, fit_t=fit_t, fit_phi=fit_phi, interface=interface, template=template)
    check_determined(meas, param.size, variant + " with a top interface" * bool(interface))
    key = jax.random.key(seed)
    x_default = param.from_material(template)
    budget = Budget.of(walks, bounces, jacobian_walks)
    problem = make_problem(meas, param, key=key, walks=budget.walks, bounces=budget.bounces,
                           reference=param.to_material(x_default), jacobian_walks=budget.jacobian_walks,
                           thin_after=thin_after)
    refiner = Refiner(problem, meas, method, budget)

    if start is not None:
        say(f"refining the given start ({method}, {PASSES} passes)")
        fixed, refined, pending = (), [refiner("given", x_default)], []
    else:
        plan = plan_starts(meas, param, problem.connection, starts=starts, t=t, rng=np.random.default_rng(seed))
        fixed = plan.fixed
        refined, pending = screen_and_refine(plan, problem, refiner, key, budget=budget, refine=refine,
                                             method=method, say=say)

    say(f"checking {len(refined)} refined start{'s' * (len(refined) > 1)} at {budget.check_walks} walks "
        f"in {CHECK_BATCHES} batches under independent keys")
    check_key = jax.random.fold_in(key, CHECK_STREAM)
    selection = select(refined, meas, check_key, budget.check_walks)
    # the refine stage's refiner has been stopped (screen_and_refine): a fresh one, of the same objective
    refined, selection = refine_missed(refined, selection, pending, Refiner(problem, meas, method, budget), meas,
                                       check_key, budget.check_walks, say)
    stage = None
    if finer and method == "lm":
        refined, selection, stage = refine_finer(refined, selection, problem, meas, method, budget,
                                                 jax.random.fold_in(key, FINE_STREAM), say)
    best = refined[selection.best]
    polished = Polished(x=best.x, check=selection.checks[selection.best], step=None)
    if final_step and method == "lm":
        share = objective_mc_share(polished.check, budget.walks)
        if share >= FINE_SHARE:
            say(f"checking the best start again under fresh keys and taking Gauss-Newton steps on the pooled residuals "
                f"(up to {POLISH_STEPS} along each of up to {POLISH_ROUNDS} Jacobians), each checked at "
                f"{budget.check_walks} walks under fresh keys")
            polished = polish(best, meas, jax.random.fold_in(key, POLISH_STREAM), budget.check_walks,
                              POLISH_JACOBIAN_FACTOR * budget.walks)
        else:
            say(f"no Gauss-Newton steps: the Monte Carlo share of the objective at the best start is {share:.2g} of "
                f"its chi-square (below {FINE_SHARE}), little for them to undo")
    return summarise(meas, refined, selection, polished, method=method, variant=variant, seed=seed, budget=budget,
                     fixed=fixed, finer=stage, started=started)
