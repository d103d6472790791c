"""Fitting a material to measurements: Levenberg-Marquardt (optimistix) and a Powell baseline.

The objective is the sum of squared residuals ``(model - measured) / std``
(``std = 1`` when the file has no standard deviations), in the file's own
quantity, over every measured point and colour channel. The model is the
Monte Carlo BSDF under a fixed key and fixed lobe-selection probabilities
(common random numbers), so the objective is a deterministic, smooth function
of the parameters and its Jacobian comes from forward-mode differentiation of
the walk (of its first :data:`FIT_JACOBIAN_WALKS` walks: a descent direction
needs no more). The lobe probabilities and the Monte Carlo share of the
weights are fixed numbers within a solver pass, set again at the start of
each of :data:`PASSES` passes. Each refined start is then checked under
independent keys (:func:`check`), which a fit cannot have tuned itself to,
and the best one takes a last Gauss-Newton step on its check's pooled
residuals (:func:`gauss_newton_step`), kept where a check under fresh keys says it
is better.

Parameters are mapped to unbounded coordinates so every iterate is physical:
``c_d``, ``w_g`` and albedos by a logistic function onto ``(0, 1)``, ``g1``,
``g2`` by ``tanh`` onto ``(-0.9999, 0.9999)``, ``alpha_p`` onto ``(1e-4, 1)``, ``theta_p``
onto ``(0, 90)`` degrees, ``t`` by ``exp``, ``phi_p`` by ``180 tanh``.

Example::

    import jaxcos
    meas = jaxcos.load_measurements("measurements/dewy1.csv")
    result = jaxcos.fit(meas)
    result.material, result.record["reduced_chi2"]
"""

import concurrent.futures
import dataclasses
import threading
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx

from .._errors import InputError
from ..model import Layer, Material, check_variant
from ..model import lobe_probabilities, make_query, simulate

FIT_WALKS = 1024
"""Walks per incidence direction of the objective's value in a fit (the
``accurate`` budget). Under one fixed key a fit follows the Monte Carlo error
of its estimate, which is correlated across the outgoing angles of an
incidence and looks like a change of the parameters: at 256 walks (error
about twice a 2% measurement noise) the fitted materials of the bundled sets
scored reduced chi-square 2.5-3.4 under an independent key, at 1024 walks
1.8-2.2 (the truth: 1.0-1.15), with the single-pass fit of that time; the
current fit's materials score 1.07-1.92 before its last step and 1.05-1.68
after it (:data:`FINAL_DAMPING`). About 90% of the error's variance is one
offset per incidence (benchmarks/RESULTS.md). The fit puts the remaining
error into the likelihood (see :func:`with_mc_error`) and reports it."""
FIT_JACOBIAN_WALKS = 128
"""Walks of the objective's Jacobian: the first 128 of the objective's own
walks (same key). Levenberg-Marquardt needs a good descent direction, not an
exact slope; its steps are accepted on the value. A Jacobian at 128 walks
costs an eighth of one at 1024, and the fit is faster than one at 256 walks
throughout (dewy1: 44 s against 63 s)."""
FIT_BOUNCES = 128
"""Bounces per walk in a fit: at most 3.7e-3 of the energy is left in
unfinished walks for the four published products (256 bounces: 2.2e-5), at
half the cost; every fit reports what its walks left unfinished."""

PASSES = 2
"""Solver passes per refined start. A pass holds the lobe-selection
probabilities and the Monte Carlo share of the weights fixed, at their values
at its start (:func:`with_mc_error`); a start far from the optimum sets them
badly (a near-mirror start samples the platelet lobe where the optimum
scatters in the diffusers), so each further pass sets them again where the
previous one ended. On the bundled sets the second pass took the material's
reduced chi-square under an independent key from 1.80 to 1.16 (dewy1) and
from 1.37 to 1.09 (matte1), the truth's being 1.0-1.15, and dewy2's
highlight start from a check chi-square of 61896 to 7058 (of which 6500 the
check's own Monte Carlo error); a third pass changed little."""
SCREEN_STEPS = 5
"""Levenberg-Marquardt steps each start gets in the screen (at half the Jacobian's walks, a quarter of the bounces)."""
CHECK_FACTOR = 16
"""Every refined start is checked with this many times the fit's walks under independent keys
(:func:`check`). The fit is the start whose ``material_chi2`` there is lowest, allowing for the check's
uncertainty: its bound ``material_chi2 + 2 material_chi2_se`` is lowest (not its loss, which another
key need not reproduce). A material whose estimate rare walks dominate (a near-mirror lobe) cannot
win on a lucky batch. With :data:`CHECK_BATCHES` batches each batch has the fit's own walks, so the check
runs the program that sets the fit's weights, with nothing more to compile. At 4 times the walks (batches of
256, a program of their own) a check of the two refined starts took about 3 s less (dewy1: 2 x 2.2 s and
about 2.5 s compiling, against 2 x 5.0 s) for twice the standard error (dewy1's material 1.18 +- 0.09
against 1.23 +- 0.05, dewy2's 1.66 +- 0.23 against 1.66 +- 0.09)."""
FINAL_DAMPING = 0.1
"""Marquardt damping of the fit's last step (:func:`gauss_newton_step`): one damped Gauss-Newton step on the
pooled residuals of the best start's check, kept where a check of its own, under fresh keys, scores it
better. Under one fixed key the fit follows that key's Monte Carlo error; the check's pooled model has a
sixteenth of its variance. On the bundled sets (seed 0, reduced chi-square of the material under yet another
key) the step took dewy1 from 1.19 to 1.16, dewy2 from 1.74 to 1.47, matte1 from 1.09 to 1.08 and matte2
from 1.37 to 1.28; a synthetic dewy2-like product from 1.86 to 1.35 (its truth 1.10). Damping 0.03-1 did
about as well; undamped it took matte2 to 6 (benchmarks/RESULTS.md)."""
CHECK_BATCHES = 16
"""The check's walks run in this many batches under independent keys: pairs of batches estimate
the material's chi-square and its standard error (:func:`_pair_chi2`)."""

# Free parameters of each variant, in order; sizes follow.
_FREE = {
    "two_lobe": ("c_d", "albedo_d", "g1", "g2", "w_g", "albedo_p", "alpha_p", "theta_p"),
    "single_lobe": ("c_d", "albedo_d", "g1", "albedo_p", "alpha_p", "theta_p"),
    "diffusers_only": ("albedo_d", "g1", "g2", "w_g"),
    "platelets_only": ("albedo_p", "alpha_p", "theta_p"),
}
_SIZE = {"albedo_d": 3, "albedo_p": 3}

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
over incidences, its brightest point exceeds both neighbours by more than this factor. On the bundled
sets: dewy2 (``alpha_p = 0.002``) 2.5-2.7 on four of its five incidences; dewy1, matte1 and matte2
(``alpha_p`` 0.13-0.49) at most 1.1."""
_VARIANT_FIXED = {"two_lobe": {}, "single_lobe": {"w_g": 1.0, "g2": 0.0},
                  "diffusers_only": {"c_d": 1.0}, "platelets_only": {"c_d": 0.0}}
_EPS = 1e-5
_G_MAX = 0.9999  # |g| = 1 is a delta function: the map keeps float32 iterates off it
_ALPHA_MIN = 1e-4  # alpha_p = 0 is a mirror with no width


def _unit_to_x(v):
    v = np.clip(np.asarray(v, float), _EPS, 1 - _EPS)
    return np.log(v) - np.log1p(-v)


_BOUNDS = {
    # name: the physical range that the transforms below map onto
    "c_d": (0.0, 1.0), "w_g": (0.0, 1.0), "albedo_d": (0.0, 1.0), "albedo_p": (0.0, 1.0),
    "alpha_p": (_ALPHA_MIN, 1.0), "g1": (-_G_MAX, _G_MAX), "g2": (-_G_MAX, _G_MAX), "theta_p": (0.0, 90.0),
    "t": (0.0, 1e3), "phi_p": (-180.0, 180.0),
}

_TRANSFORMS = {
    # name: (x -> value, value -> x)
    "c_d": (jax.nn.sigmoid, _unit_to_x),
    "w_g": (jax.nn.sigmoid, _unit_to_x),
    "albedo_d": (jax.nn.sigmoid, _unit_to_x),
    "albedo_p": (jax.nn.sigmoid, _unit_to_x),
    "alpha_p": (lambda x: _ALPHA_MIN + (1.0 - _ALPHA_MIN) * jax.nn.sigmoid(x),
                lambda v: _unit_to_x((np.asarray(v) - _ALPHA_MIN) / (1.0 - _ALPHA_MIN))),
    "g1": (lambda x: _G_MAX * jnp.tanh(x), lambda v: np.arctanh(np.clip(np.asarray(v) / _G_MAX, -1 + _EPS, 1 - _EPS))),
    "g2": (lambda x: _G_MAX * jnp.tanh(x), lambda v: np.arctanh(np.clip(np.asarray(v) / _G_MAX, -1 + _EPS, 1 - _EPS))),
    "theta_p": (lambda x: 90.0 * jax.nn.sigmoid(x), lambda v: _unit_to_x(np.asarray(v) / 90.0)),
    "t": (jnp.exp, lambda v: np.log(np.maximum(v, _EPS))),
    "phi_p": (lambda x: 180.0 * jnp.tanh(x), lambda v: np.arctanh(np.clip(np.asarray(v) / 180.0, -1 + _EPS, 1 - _EPS))),
}


class Parameterization(eqx.Module):
    """The map between an unbounded vector ``x`` and a one-layer :class:`Material` of a variant.

    Attributes:
        variant: the model variant (static).
        names: the fitted parameters in order (static); ``t`` and ``phi_p``
            are included when asked for.
        fixed: the values of the parameters that are not fitted.
    """

    variant: str = eqx.field(static=True)
    names: tuple = eqx.field(static=True)
    fixed: dict

    @property
    def size(self):
        return sum(_SIZE.get(n, 1) for n in self.names)

    def labels(self):
        """One label per entry of ``x``, e.g. ``albedo_d[0]``."""
        out = []
        for n in self.names:
            out += [f"{n}[{i}]" for i in range(_SIZE[n])] if n in _SIZE else [n]
        return out

    def _split(self, v):
        i = 0
        for n in self.names:
            k = _SIZE.get(n, 1)
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
        return Material(layers=(Layer(**values),), variant=self.variant)

    def colouring(self):
        """Seeds of the compressed Jacobian: ``(seeds, column, channel)``.

        The residuals are flattened ``(N, 3)`` (colour channel last), and an
        RGB parameter's component ``c`` (``albedo_d[c]``) acts on channel ``c``
        alone: no random decision of a walk looks at colour (the lobe
        probabilities are fixed numbers). The three columns of such a
        parameter never share a row, so one tangent, their sum, gives all
        three (a Curtis-Powell-Reid colouring): the two-lobe model's 12
        columns cost 8 forward-mode tangents. ``seeds`` is ``(K, size)``;
        entry ``j`` of ``x`` reads column ``column[j]`` of the compressed
        Jacobian, at the rows of channel ``channel[j]`` (``-1``: every row).
        """
        seeds, column, channel = [], [], []
        for n in self.names:
            k, j = _SIZE.get(n, 1), len(column)
            seed = np.zeros(self.size)
            seed[j:j + k] = 1.0
            column += [len(seeds)] * k
            channel += list(range(k)) if k > 1 else [-1]
            seeds.append(seed)
        return np.array(seeds), np.array(column), np.array(channel)

    def bounds(self):
        """``(low, high)``: the physical range of each :meth:`labels` entry, the support of a uniform prior."""
        lows, highs = zip(*[_BOUNDS[n] for n in self.names for _ in range(_SIZE.get(n, 1))])
        return np.array(lows), np.array(highs)

    def from_material(self, material):
        layer = material.layers[0]
        parts = [np.atleast_1d(_TRANSFORMS[n][1](np.asarray(getattr(layer, n)))) for n in self.names]
        return jnp.asarray(np.concatenate(parts), dtype=jnp.result_type(float))


def parameterization(variant="two_lobe", *, fit_t=False, fit_phi=False, template=None):
    """The :class:`Parameterization` of ``variant``; non-fitted values come from ``template`` or the defaults."""
    check_variant(variant)
    names = _FREE[variant] + (("t",) if fit_t else ()) + (("phi_p",) if fit_phi else ())
    base = dict(_DEFAULT)
    if template is not None:
        layer = template.layers[0]
        base.update({k: np.asarray(getattr(layer, k)) for k in _DEFAULT})
    base.update(_VARIANT_FIXED[variant])
    fixed = {k: jnp.asarray(v, dtype=jnp.result_type(float)) for k, v in base.items() if k not in names}
    return Parameterization(variant=variant, names=names, fixed=fixed)


# --- the objective ----------------------------------------------------------------


class Problem(eqx.Module):
    """Everything the residuals need: the data, the query, the budget, the key.

    ``residuals(x)`` are ``(model - measured) / std``, flattened over points
    and channels; ``model`` is in the file's quantity. Their value uses
    ``walks`` walks; their Jacobian (forward mode) the first
    ``jacobian_walks`` of them (all when ``None``).
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
    incidence_batch: int = eqx.field(static=True, default=None)
    connection: str = eqx.field(static=True, default="nee")

    def estimate(self, x):
        """The :class:`~jaxcos.Estimate` of the material at ``x`` under this problem's key and budget."""
        return simulate(self.param.to_material(x), self.query, self.key, walks=self.walks,
                        bounces=self.bounces, lobe_probs=self.lobe_probs, incidence_batch=self.incidence_batch,
                        connection=self.connection)

    def model(self, x):
        """The model in the file's quantity, ``(N, 3)``."""
        return self.scale * self.estimate(x).f

    def residuals(self, x):
        return _residuals(self, x)

    def weigh(self, model):
        """The residuals ``(model - measured) / std`` of a model ``(N, 3)`` in the file's quantity, flattened."""
        return ((model - self.measured) / self.sigma).reshape(-1)

    def loss(self, x):
        r = self.residuals(x)
        return jnp.sum(r * r)


@jax.custom_jvp
def _residuals(problem, x):
    return problem.weigh(problem.model(x))


def _jacobian_walks(problem):
    """The walks the Jacobian of ``problem`` is taken from: ``jacobian_walks``, at most ``walks``."""
    return problem.walks if problem.jacobian_walks is None else min(problem.jacobian_walks, problem.walks)


def _jacobian(problem, x):
    """The residuals' Jacobian ``(M, P)`` at ``x`` and the residuals it comes with.

    Batched forward mode, materialised once: linearising the walk instead
    would store every bounce's intermediates (gigabytes). With
    ``jacobian_walks < walks`` it is that of the first ``jacobian_walks`` walks
    (the walks' random numbers do not depend on their count, see
    ``_walk._uniforms``), and so are the residuals returned with it. The colour
    channels' columns share tangents (:meth:`Parameterization.colouring`). The
    incidences are walked one after another: on the standard grid at the
    paper's budget the Jacobian then takes a quarter less time than with all
    incidences vectorised, likely because one incidence's tallies with their
    tangents stay in cache (not profiled); one evaluation is fastest
    vectorised.
    """
    sub = dataclasses.replace(problem, walks=_jacobian_walks(problem), incidence_batch=1)
    fn = lambda v: _residuals.fun(sub, v)
    seeds, column, channel = problem.param.colouring()
    y, packed = jax.vmap(lambda e: jax.jvp(fn, (x,), (e,)), out_axes=(None, -1))(jnp.asarray(seeds, x.dtype))
    row_channel = np.arange(y.shape[0]) % 3
    return packed[:, column] * ((channel < 0) | (channel == row_channel[:, None])), y


@_residuals.defjvp
def _residuals_jvp(primals, tangents):
    problem, x = primals
    _, dx = tangents
    jac, y = _jacobian(problem, x)
    if _jacobian_walks(problem) < problem.walks:
        y = _residuals.fun(problem, x)
    return y, jac @ dx


def make_problem(meas, param, *, key, walks=FIT_WALKS, bounces=FIT_BOUNCES, lobe_probs=None, reference=None,
                 jacobian_walks=None, connection=None):
    """The least-squares :class:`Problem` of fitting ``param`` to measurements ``meas``.

    ``lobe_probs`` are held fixed during the fit (common random numbers); by
    default they are those of ``reference`` (a material) or of the default start.
    ``connection``: the estimator's (:func:`~jaxcos.simulate`); by default
    ``"mis"`` where the data show a highlight narrower than their angular
    sampling (:func:`narrow_highlight`), else ``"nee"``. There, next-event
    estimation through the near-mirror lobe is so spiky that under a fixed
    key at the fit's budget the truth is not a minimum of the objective
    (dewy2: its loss 912.7 against 275.9 at a wrong material; ``"mis"``
    removes the spikes at about 1.5 times the cost of an evaluation, and is
    not spent where the highlight is broad).
    """
    if connection is None:
        connection = "mis" if narrow_highlight(meas) else "nee"
    if lobe_probs is None:
        lobe_probs = (lobe_probabilities(reference) if reference is not None
                      else _lobe_probabilities_at(param, jnp.zeros(param.size)))
    dtype = jnp.result_type(float)
    sigma = np.ones_like(meas.values) if meas.std is None else np.asarray(meas.std)
    if np.any(sigma <= 0):
        raise InputError(f"{meas.path}: every standard deviation must be positive to weight a fit.")
    return Problem(
        param=param,
        query=make_query(meas.theta_i, meas.theta_o, meas.phi_o),
        measured=jnp.asarray(meas.values, dtype),
        sigma=jnp.asarray(sigma, dtype),
        scale=float(np.pi) if meas.quantity == "reflectance_factor" else 1.0,
        key=key,
        lobe_probs=jnp.asarray(lobe_probs, dtype),
        walks=walks,
        bounces=bounces,
        jacobian_walks=jacobian_walks,
        connection=connection,
    )


# --- solvers ----------------------------------------------------------------------


class LevenbergMarquardt(optx.AbstractGaussNewton):
    """optimistix's Levenberg-Marquardt, with a Jacobian only where a step is accepted, and a stop on the loss.

    The trust region accepts or rejects a step on the value at the new point
    alone; optimistix's Gauss-Newton step linearises there too. About half of
    this fit's steps are rejected: near the optimum the 128-walk Jacobian's
    slope is not the 1024-walk value's, and the region shrinks for several
    steps in a row. This solver evaluates the value first and computes the
    Jacobian (materialised, by forward mode; :func:`_jacobian` when ``args``
    is the :class:`Problem` whose residuals ``fn`` returns) only when the step
    is accepted, so a rejected step costs one evaluation instead of a
    Jacobian. Otherwise
    it is optimistix's algorithm: its damped Newton descent, classical trust
    region and Cauchy termination.

    Under a fixed key the objective is rough along the parameters that move
    sampled directions (``docs/derivatives.md``). Near its optimum LM then
    creeps: the damping grows after a few rejected steps, and each accepted
    step lowers the loss by a few hundredths of a chi-square unit, far below
    what the data can tell apart. So this solver also stops after
    ``patience`` consecutive accepted steps that each lowered the loss by less
    than ``loss_rtol`` of it, and after a rejected step already within the
    tolerance on ``y`` (a smaller region would propose a smaller one).
    """

    rtol: float
    atol: float
    norm: object
    descent: optx.DampedNewtonDescent
    search: optx.ClassicalTrustRegion
    verbose: object
    loss_rtol: float
    patience: int

    def __init__(self, rtol, atol, loss_rtol=2e-4, patience=2):
        self.rtol, self.atol, self.norm = rtol, atol, optx.max_norm
        self.descent = optx.DampedNewtonDescent()
        self.search = optx.ClassicalTrustRegion()
        self.verbose = lambda **kwargs: None
        self.loss_rtol, self.patience = loss_rtol, patience

    def init(self, fn, y, args, options, f_struct, aux_struct, tags):
        # The Jacobian is kept as a matrix (optimistix keeps a linearised function). optimistix's
        # init traces a linearisation of fn for the state's structure alone; of the walk's
        # residuals that took seconds of tracing, so it is given a constant of fn's shape instead.
        zeros = lambda _y, _args: (jnp.zeros(f_struct.shape, f_struct.dtype),
                                   jax.tree.map(lambda a: jnp.zeros(a.shape, a.dtype), aux_struct))
        state = super().init(zeros, y, args, options, f_struct, aux_struct, tags)
        f_info = optx.FunctionInfo.ResidualJac(
            jnp.zeros(f_struct.shape, f_struct.dtype),
            lx.MatrixLinearOperator(jnp.zeros(f_struct.shape + y.shape, f_struct.dtype), tags))
        state = eqx.tree_at(lambda s: (s.f_info, s.descent_state), state, (f_info, self.descent.init(y, f_info)))
        return state, jnp.array(0)

    def step(self, fn, y, args, options, state, tags):
        inner, small = state
        residual, aux = fn(inner.y_eval, args)
        probe = eqx.tree_at(lambda f: f.residual, inner.f_info, residual)
        size, accept, found, search_state = self.search.step(inner.first_step, y, inner.y_eval, inner.f_info, probe,
                                                             inner.search_state)

        def accepted(_):
            if isinstance(args, Problem):  # its residuals are fn's; no evaluation at the full budget is traced
                jac = _jacobian(args, inner.y_eval)[0]
            else:
                jac = jax.jacfwd(lambda x: fn(x, args)[0])(inner.y_eval)
            f_info = optx.FunctionInfo.ResidualJac(residual, lx.MatrixLinearOperator(jac, tags))
            y_diff, f_diff = inner.y_eval - y, residual - inner.f_info.residual
            converged = ((self.norm(y_diff / (self.atol + self.rtol * jnp.abs(inner.y_eval))) < 1)
                         & (self.norm(f_diff / (self.atol + self.rtol * jnp.abs(residual))) < 1))
            return inner.y_eval, f_info, aux, self.descent.query(inner.y_eval, f_info, inner.descent_state), converged

        def rejected(_):
            # a rejected step already within the tolerance on y: the next, in a smaller region, would be too
            tiny = self.norm(inner.y_eval - y) < self.atol + self.rtol * self.norm(y)
            return y, inner.f_info, inner.aux, inner.descent_state, tiny

        before, after = jnp.sum(inner.f_info.residual ** 2), jnp.sum(residual ** 2)
        self.verbose(num_steps=("Step", inner.num_steps), step_size=("Step size", size),
                     loss_this_step=("Loss on this step", 0.5 * after),
                     loss_last_accepted_step=("Loss on the last accepted step", 0.5 * before))
        y, f_info, aux, descent_state, terminate = jax.lax.cond(accept, accepted, rejected, None)
        y_descent, result = self.descent.step(size, descent_state)
        small = jnp.where(accept & (inner.num_accepted_steps >= 1),
                          jnp.where(before - after < self.loss_rtol * before, small + 1, 0), small)
        new = dataclasses.replace(
            inner, first_step=jnp.array(False), y_eval=y + y_descent, search_state=search_state, f_info=f_info,
            aux=aux, descent_state=descent_state, terminate=terminate | (small >= self.patience),
            result=optx.RESULTS.where(found == optx.RESULTS.successful, result, found),
            num_steps=inner.num_steps + 1, num_accepted_steps=inner.num_accepted_steps + jnp.where(accept, 1, 0),
            num_steps_since_acceptance=jnp.where(accept, 0, inner.num_steps_since_acceptance + 1))
        return y, (new, small), aux

    def terminate(self, fn, y, args, options, state, tags):
        return super().terminate(fn, y, args, options, state[0], tags)

    def postprocess(self, fn, y, aux, args, options, state, tags, result):
        return super().postprocess(fn, y, aux, args, options, state[0], tags, result)


@eqx.filter_jit
def _lm(problem, x0, max_steps, rtol, atol):
    solver = LevenbergMarquardt(rtol=rtol, atol=atol)
    sol = optx.least_squares(lambda x, p: p.residuals(x), solver, x0, args=problem, max_steps=max_steps, throw=False)
    inner = sol.state[0]
    # the residuals and Jacobian at the last accepted point, the solution (the first step is always accepted):
    # no further evaluation, and so no further copy of the walk in the compiled program
    return (sol.value, jnp.sum(inner.f_info.residual ** 2), sol.stats["num_steps"], inner.num_accepted_steps,
            inner.f_info.jac.as_matrix())


@eqx.filter_jit
def _screen(problem, xs, keys):
    """A few Levenberg-Marquardt steps from each row of ``xs``; the ends and their batch residuals.

    The starts run one after another in one compiled loop (``lax.map``): under
    ``vmap`` the walk was traced and compiled several times over, and the
    solver's accept/reject branch became a select that computed the Jacobian
    at every step (screen compile and run 46.7 s against 29.6 s, under load).
    Each start samples with its own lobe probabilities: a start far from the
    default one would otherwise be simulated with the wrong lobes, noisily.
    Each end is then evaluated under every key of ``keys`` (independent batches,
    for :func:`_pair_chi2`). Returns the ends ``(S, P)`` and residuals ``(S, K, M)``.
    """
    def one(x):
        prob = dataclasses.replace(problem, lobe_probs=_lobe_probabilities_at(problem.param, x))
        end = _lm(prob, x, SCREEN_STEPS, 1e-3, 1e-3)[0]
        prob = dataclasses.replace(prob, lobe_probs=_lobe_probabilities_at(problem.param, end))
        return end, jax.lax.map(lambda k: _residuals.fun(dataclasses.replace(prob, key=k), end), keys)

    return jax.lax.map(one, xs)


def solve_lm(problem, x0, *, max_steps=40, rtol=1e-4, atol=1e-5, jacobian=False):
    """Levenberg-Marquardt from ``x0``; returns ``(x, loss, steps, accepted)``, and the Jacobian at ``x`` if asked.

    Every step evaluates the residuals; the ``accepted`` ones also their Jacobian.
    ``jacobian``: also return the residuals' Jacobian ``(M, P)`` at ``x``, the
    one the last accepted step computed (at ``problem.jacobian_walks``).
    """
    x, loss, steps, accepted, jac = _lm(problem, x0, max_steps, rtol, atol)
    out = x, float(loss), int(steps), int(accepted)
    return out + (jac,) if jacobian else out


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


def _highlights(meas):
    """Per incidence with at least five in-plane points: ``(theta_i, theta_o of its brightest point, ratio)``.

    ``ratio``: the brightest point's value (mean of r, g, b) over the larger of its
    neighbours' in ``theta_o`` (signed, negative on the light's side). Points with an
    infinite std (the padding of :func:`jaxcos._ablate.pad_measurements`) are not measured.
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
        neighbours = np.concatenate([v[max(k - 1, 0):k], v[k + 1:k + 2]])
        out.append((float(ti), float(to[k]), float(v[k] / max(np.max(neighbours), 1e-30))))
    return out


def highlight_tilt(meas):
    """The platelet tilt ``theta_p`` (degrees) that the measured highlight points to, or ``None``.

    Mirror-like platelets tilted by ``theta_p`` in the plane of incidence
    reflect at ``theta_o = theta_i + 2 theta_p`` (docs/model.md section 2). For each
    incidence with at least five in-plane points, its brightest point (mean of
    r, g, b) gives one estimate; the result is their median.
    A narrow highlight (``alpha_p`` of a few thousandths) is invisible to a
    random start: its basin is a fraction of a degree wide in ``theta_p``.
    """
    tilts = [0.5 * (to - ti) for ti, to, _ in _highlights(meas)]
    if not tilts:
        return None
    return float(np.clip(np.median(tilts), 0.0, 89.0))


def narrow_highlight(meas):
    """Whether the measured highlight is narrower than the angular sampling: near-mirror platelets.

    True when, in the median over the incidences of :func:`highlight_tilt`,
    the brightest point exceeds both its neighbours in ``theta_o`` by more
    than :data:`NARROW_RATIO`: a lobe that one viewing step resolves would
    fall off gradually. Such data get the estimator's MIS connection
    (:func:`make_problem`) and a near-mirror start (:func:`fit`).
    """
    ratios = [r for _, _, r in _highlights(meas)]
    return bool(ratios) and float(np.median(ratios)) > NARROW_RATIO


def fixed_starts(starts, t, tilt, connection):
    """The fit's fixed starts, in the screen's order: ``(key, description, Layer values)``.

    ``"default"`` (:data:`_DEFAULT`); with ``starts >= 1`` ``"platelet"``, broad
    tilted platelets (``_PLATELET_START``); with ``starts >= 2``, where the
    objective uses the ``"mis"`` connection (a highlight narrower than the angular
    sampling, :func:`narrow_highlight`) and the variant has a tilt ``tilt``
    (:func:`highlight_tilt`), ``"near-mirror"``, sparse near-mirror platelets at
    that tilt (``_MIRROR_START``). ``t``: the optical thickness of each.
    """
    out = [("default", "default", {**_DEFAULT, "t": t})]
    if starts >= 1:
        out.append(("platelet", "broad tilted platelets", {**_DEFAULT, "t": t, **_PLATELET_START}))
    if starts >= 2 and tilt is not None and connection == "mis":
        out.append(("near-mirror", "near-mirror platelets at the highlight's tilt",
                    {**_DEFAULT, "t": t, **_MIRROR_START, "theta_p": tilt}))
    return out


def random_starts(param, n, rng, tilt=None):
    """``n`` starting vectors, each parameter drawn uniformly from its own range.

    ``c_d`` in [0.05, 0.95], albedos in [0.3, 0.99], ``g1`` in [-0.3, 0.9],
    ``g2`` in [-0.6, 0.3], ``w_g`` in [0.2, 0.95], ``alpha_p`` log-uniformly
    in [0.003, 1], ``theta_p`` in [0, 80] degrees, ``t`` in [1, 30],
    ``phi_p`` 0: clear of the bounds, where the unbounded coordinates
    saturate. ``theta_p`` spans nearly its whole range because the fit's
    basin in the tilt is narrow for broad lobes: drawn below 30 degrees, it
    missed a product tilted by 70 (a synthetic matte2 at ``theta_p = 70``
    scored reduced chi-square 2.64 against its truth's 1.11; now 1.32).

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
        if tilt is not None and i >= n - n // 3:
            values.update(theta_p=np.clip(tilt + rng.uniform(-0.5, 0.5), 0.0, 89.9),
                          alpha_p=10 ** rng.uniform(-3, np.log10(0.05)))
        draws.append(np.concatenate([np.atleast_1d(_TRANSFORMS[n_][1](values[n_])) for n_ in param.names]))
    return jnp.asarray(np.reshape(draws, (n, param.size)), dtype=jnp.result_type(float))


@dataclasses.dataclass
class FitResult:
    """The outcome of :func:`fit`.

    Attributes:
        material: the fitted material.
        record: the ``"fit"`` record of docs/formats.md (plus extra keys).
        model: ``(N, 3)`` the fitted model in the file's quantity.
        model_std: ``(N, 3)`` its Monte Carlo standard error.
        starts: per refined start, ``(label, loss, material_chi2, material_chi2_se)`` (the last two
            from its :func:`check`); the label is
            the screened start's index (0: the default start) or
            ``"default, unscreened"`` (``"near-mirror, unscreened"`` where the highlight is
            narrower than the angular sampling).
        x: the fitted unbounded coordinates; ``param`` maps them.
    """

    material: Material
    record: dict
    model: np.ndarray
    model_std: np.ndarray
    starts: list
    x: jnp.ndarray
    param: Parameterization
    problem: Problem


def with_mc_error(problem, meas, x):
    """``problem`` with lobe probabilities and Monte Carlo error taken at ``x``, both then held fixed.

    The weights become ``1 / sqrt(std^2 + s_mc^2)``: with a fixed key the
    Monte Carlo error is an offset as large as a noise, and counting it as
    information would inflate the chi-square. ``s_mc = r |model|``, with ``r``
    the median relative standard error over the points at ``x``: a per-point
    standard error would come from the same walks as the error itself (a
    point the walks overestimate also gets a large standard error) and the
    weights would bias the fit. Files without std columns stay unweighted.
    """
    problem = dataclasses.replace(problem, lobe_probs=_lobe_probabilities_at(problem.param, x))
    if meas.std is None:
        return problem
    return dataclasses.replace(problem, sigma=_mc_sigma(problem.estimate(x), jnp.asarray(meas.std, problem.sigma.dtype),
                                                        problem.scale))


@eqx.filter_jit
def _mc_sigma(est, std, scale):
    """The weights' ``sqrt(std^2 + s_mc^2)`` of :func:`with_mc_error` (one compiled program, not one per operation)."""
    rel = jnp.median(est.stderr / jnp.maximum(jnp.abs(est.f), 1e-12))
    return jnp.sqrt(std ** 2 + (rel * scale * est.f) ** 2)


@eqx.filter_jit
def _lobe_probabilities_at(param, x):
    """The lobe probabilities of the material at ``x`` (one compiled program, not one per operation)."""
    return lobe_probabilities(param.to_material(x))


def check(problem, meas, x, *, key, walks, batches=CHECK_BATCHES):
    """The material at ``x`` evaluated under independent keys, ``walks`` walks in all, against the data.

    Under its fixed key a fit can follow the Monte Carlo error of that key: a
    near-mirror highlight, for instance, can be matched by a few lucky walks
    that another key does not reproduce. An independent evaluation cannot be
    tuned that way. It runs ``batches`` independent batches of ``walks /
    batches`` walks (keys ``fold_in(key, b)``); per point and channel, with
    ``r_b`` the residual of batch ``b``, the product ``r_b r_c`` of two
    different batches is an unbiased estimate of the squared residual of the
    exact model, free of Monte Carlo variance. Returned (weights: the
    measurement std, or none without std columns):

    * ``chi2``: the sum of squared weighted residuals of the pooled estimate;
    * ``material_chi2``: the mean over batch pairs of the weighted sums of
      ``r_b r_c``, an unbiased estimate of the material's own chi-square (a fit
      keeps the start for which it is lowest: ``chi2`` would also rank the
      materials by how noisy they are to simulate);
    * ``chi2_mc = chi2 - material_chi2``: the check's own Monte Carlo share;
    * ``material_chi2_se``: its standard error (the jackknife over batches,
      :func:`_pair_chi2`). It is large where rare walks dominate the estimate
      (a near-mirror platelet lobe seen off its mirror direction);
    * ``reduced_chi2`` and ``reduced_chi2_se``: the same per degree of
      freedom (files with std columns);
    * ``l2``, ``rmse`` of the pooled estimate, ``walks``, ``batches``, ``bounces``.
    """
    return _check(problem, meas, x, key, walks, batches)[0]


def _check(problem, meas, x, key, walks, batches=CHECK_BATCHES):
    """:func:`check`'s result and the pooled model ``(N, 3)`` (file's quantity) it comes from."""
    if batches < 3 or walks % batches:
        raise ValueError(f"check needs at least 3 batches that divide the walks; got {walks} walks, {batches} batches.")
    sub = dataclasses.replace(problem, walks=walks // batches)
    model = np.stack([problem.scale * np.asarray(dataclasses.replace(sub, key=k).estimate(x).f, float)
                      for k in _batch_keys(key, batches)])
    sigma = np.ones_like(model[0]) if meas.std is None else np.asarray(meas.std, float)
    real = np.all(np.isfinite(sigma), axis=1)  # padded dummy points (jaxcos.ablate) have an infinite std
    r = (model - meas.values)[:, real] / sigma[real]  # (batches, points, 3)

    material, se = _pair_chi2(r)
    resid = (model.mean(axis=0) - meas.values)[real]
    chi2 = float(np.sum((resid / sigma[real]) ** 2))
    out = dict(walks=int(walks), batches=int(batches), bounces=int(problem.bounces), chi2=chi2,
               chi2_mc=chi2 - material, material_chi2=material, material_chi2_se=se, **_l2_rmse(resid))
    if meas.std is not None:
        dof = max(resid.size - problem.param.size, 1)
        out.update(reduced_chi2=material / dof, reduced_chi2_se=se / dof)
    return out, model.mean(axis=0)


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
    damping keeps the step off the directions the data hardly pin down (the
    undamped step took matte2 to a reduced chi-square of 6).
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


def _batch_keys(key, n):
    """``n`` independent keys ``fold_in(key, b)``, stacked: the batches of :func:`check` and of the screen."""
    return jax.vmap(lambda b: jax.random.fold_in(key, b))(jnp.arange(n))


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


def _upper_bound(material_chi2, se):
    """The number a fit ranks materials by: the pair estimate plus twice its SE (see :data:`CHECK_FACTOR`)."""
    return material_chi2 + 2 * se


def _pair_chi2(r):
    """The pair estimate of the exact model's chi-square from batch residuals ``r`` (``(K, ...)``), and its SE.

    With ``r_b = delta + e_b`` (``delta`` the exact model's weighted residuals,
    ``e_b`` batch ``b``'s Monte Carlo error, independent across batches), the
    mean over ordered pairs ``b != c`` of ``r_b . r_c`` is unbiased for
    ``delta . delta``. Its standard error is the delete-one-batch jackknife's.
    That overstates the variance of the part quadratic in the errors
    ``2 (K - 1) / (K - 2)``-fold, a part that falls fast with ``K`` (the same
    walks in more batches): simulated, the jackknife's standard error was
    1.7 times the true one at 4 batches, 1.08 times at 16. An unbiased
    estimate of the variance exists but went negative under heavy-tailed
    errors (a near-mirror lobe).
    """
    k = r.shape[0]
    r = r.reshape(k, -1)
    gram = r @ r.T
    total = gram.sum() - np.trace(gram)
    estimate = float(total) / (k * (k - 1))
    # leaving out batch b removes its row and column of the off-diagonal sum
    leave_one_out = (total - 2 * (gram.sum(axis=1) - np.diag(gram))) / ((k - 1) * (k - 2))
    se = np.sqrt((k - 1) / k * np.sum((leave_one_out - leave_one_out.mean()) ** 2))
    return estimate, float(se)


def _l2_rmse(resid):
    """The paper's L2 (sum of squared differences) and the RMSE of the differences ``resid``."""
    return dict(l2=float(np.sum(resid ** 2)), rmse=float(np.sqrt(np.mean(resid ** 2))))


def fit_statistics(meas, model, loss, n_free):
    resid = model - meas.values
    n = resid.size
    dof = max(n - n_free, 1)
    stats = dict(loss=float(loss), **_l2_rmse(resid), n_points=int(meas.values.shape[0]))
    if meas.std is not None:
        stats["reduced_chi2"] = float(loss / dof)
        stats["reduced_chi2_noise_only"] = float(np.sum((resid / meas.std) ** 2) / dof)
    return stats


def fit(meas, *, variant="two_lobe", method="lm", seed=0, walks=FIT_WALKS, bounces=FIT_BOUNCES,
        jacobian_walks=FIT_JACOBIAN_WALKS, starts=15, refine=1, fit_t=False, fit_phi=False, start=None, t=16.0,
        final_step=True, progress=None):
    """Fit a one-layer material of ``variant`` to the measurements ``meas``.

    Args:
        meas: from :func:`jaxcos.load_measurements`.
        variant: one of :data:`jaxcos.VARIANTS`.
        method: ``"lm"`` (Levenberg-Marquardt, optimistix) or ``"powell"`` (SciPy).
        seed: seeds the Monte Carlo key (fixed for the whole fit) and the random starts.
        walks, bounces: the Monte Carlo budget of the objective.
        jacobian_walks: the walks of its Jacobian, the first of the same walks
            (at most ``walks``); the screen runs at half of them and a quarter
            of the bounces.
        starts: number of starts screened besides the default start: a fixed
            one where broad, tilted platelets dominate (``_PLATELET_START``),
            where the highlight is narrower than the angular sampling
            (:func:`narrow_highlight`) a fixed one of sparse near-mirror
            platelets at its tilt (``_MIRROR_START``), the others random; a
            third of the random ones start at the tilt of
            the measured highlight with a narrow ``alpha_p``
            (:func:`highlight_tilt`). The screen ranks its ends by the pair
            estimate of their chi-square (:func:`_pair_chi2`) over
            :data:`CHECK_BATCHES` independent batches, plus twice its SE.
        refine: number of best screened starts refined at the full budget
            (:data:`PASSES` passes each), besides the default start as it is
            (the near-mirror start where the highlight is narrow; the
            screen's small budget can lead it astray), which is refined in
            a second thread while the screen runs; each is then
            checked with :data:`CHECK_FACTOR` times the walks under
            independent keys (:func:`check`), and the best check is the fit
            (the rule is at :data:`CHECK_FACTOR`), after a last step on its
            check's residuals where that step checks better (LM only;
            :func:`gauss_newton_step`, :data:`FINAL_DAMPING`).
        fit_t, fit_phi: also fit the optical thickness ``t`` (else fixed at ``t``)
            or the tilt azimuth ``phi_p`` (else 0).
        start: a :class:`Material` to start from instead of the multi-start
            (only that start is refined).
        t: the optical thickness when it is not fitted (the paper's protocol: 16).
        final_step: take the last step on the best check's residuals (LM;
            :func:`gauss_newton_step`). ``False`` keeps the minimum of the
            fixed-key objective itself.
        progress: a callable ``progress(message)`` told about each stage.

    Returns:
        A :class:`FitResult`.
    """
    check_variant(variant)
    if method not in ("lm", "powell"):
        raise InputError(f"unknown method {method!r}; choose 'lm' or 'powell'.")
    say = progress or (lambda msg: None)
    t0 = time.perf_counter()
    template = start if start is not None else Material(layers=(Layer(**{**_DEFAULT, "t": t}),))
    param = parameterization(variant, fit_t=fit_t, fit_phi=fit_phi, template=template)
    key = jax.random.key(seed)
    x_default = param.from_material(template)
    if int(jacobian_walks) != jacobian_walks or jacobian_walks < 1:
        raise InputError(f"jacobian_walks must be a positive integer, not {jacobian_walks}.")
    jacobian_walks = min(int(jacobian_walks), int(walks))
    problem = make_problem(meas, param, key=key, walks=walks, bounces=bounces, reference=param.to_material(x_default),
                           jacobian_walks=jacobian_walks)

    # LM: a value per step, a Jacobian (parameters + 1 forwards at jacobian_walks) per accepted step
    per_jacobian = (param.size + 1) * jacobian_walks / walks
    stop = threading.Event()

    def refine_start(label, x):
        """``PASSES`` passes from ``x``: the result ``(label, x, loss, steps, problem, jacobian)`` and its evaluations.

        ``jacobian``: the residuals' at ``x`` (LM), or ``None`` (Powell).
        """
        steps, evaluations, jac = 0, 0.0, None
        for _ in range(PASSES):
            if stop.is_set():
                raise _Abandoned
            prob = with_mc_error(problem, meas, x)
            if method == "lm":
                x, loss, n, accepted, jac = solve_lm(prob, x, jacobian=True)
                evaluations += n + accepted * per_jacobian
            else:
                x, loss, n = solve_powell(prob, x)
                evaluations += n
            steps += n
        return (label, x, loss, steps, prob, jac), evaluations

    fixed = []  # the screen's fixed starts, by their index in it: (key, description, x)
    if start is not None:
        say(f"refining the given start ({method}, {PASSES} passes)")
        outcomes = [refine_start("given", x_default)]
    else:
        rng = np.random.default_rng(seed)
        tilt = highlight_tilt(meas) if "theta_p" in param.names else None
        fixed = [(k, name, param.from_material(Material(layers=(Layer(**values),))))
                 for k, name, values in fixed_starts(starts, t, tilt, problem.connection)]
        # The fixed start refined unscreened besides the best screened one: the default, or where the
        # highlight is narrower than the sampling, near-mirror platelets at its tilt. The screen's budget is
        # blind to such a lobe (a quarter of the bounces leave up to 14% of dewy2's energy unfinished):
        # screened, dewy2's near-mirror start ended at 2.0 and 3.2 in two runs that differed only by
        # float rounding; unscreened, at 2.1 and 2.2 under seeds 0 and 1.
        k, _, x = fixed[-1] if fixed[-1][0] == "near-mirror" else fixed[0]
        pool = jnp.concatenate([jnp.stack([x for _, _, x in fixed]),
                                random_starts(param, starts + 1 - len(fixed), rng, tilt)])
        screen = dataclasses.replace(problem, walks=max(jacobian_walks // 2, 8), bounces=max(bounces // 4, 16),
                                     jacobian_walks=None)
        say(f"refining the {k} start unscreened ({method}, {PASSES} passes) while screening {pool.shape[0]} "
            f"starts with a short Levenberg-Marquardt at {screen.walks} walks and {screen.bounces} bounces")
        # The unscreened start does not wait for the screen: its tracing and compiling, which leave a core
        # idle, overlap the screen's (dewy1 cold, 10 alternating pairs of runs: 6.1 +- 2.1 s less of about
        # 66 s; benchmarks/RESULTS.md).
        unscreened = _in_background(refine_start, f"{k}, unscreened", x)
        try:
            xs, resid = _screen(screen, pool, _batch_keys(jax.random.fold_in(key, 2), CHECK_BATCHES))
            # rank the ends by the pair estimate of their chi-square: the screen's own loss at so few walks
            # also ranks the materials by how noisy they are to simulate (padded points have residual 0)
            ranks = [_upper_bound(*_pair_chi2(r)) if np.all(np.isfinite(r)) else np.inf
                     for r in np.asarray(resid, float)]
            order = np.argsort(ranks)[:refine]
            say(f"refining the best {len(order)} screened start{'s' * (len(order) > 1)} "
                f"({method}, {PASSES} passes)")
            outcomes = [refine_start(str(i), xs[i]) for i in order] + [unscreened.result()]
        finally:
            stop.set()  # an interrupted fit leaves its background start after the pass it is in
    results = [r for r, _ in outcomes]
    n_eval = sum(e for _, e in outcomes)
    check_walks = CHECK_BATCHES * -(-CHECK_FACTOR * walks // CHECK_BATCHES)
    say(f"checking {len(results)} refined start{'s' * (len(results) > 1)} at {check_walks} walks "
        f"in {CHECK_BATCHES} batches under independent keys")
    check_key = jax.random.fold_in(key, 1)
    checks, pooled = zip(*[_check(r[4], meas, r[1], check_key, check_walks) for r in results])
    best = int(np.argmin([_upper_bound(c["material_chi2"], c["material_chi2_se"]) for c in checks]))
    index, x, loss, steps, problem, jac = results[best]
    # Each start's loss has its own weights and lobe probabilities; on the best start's objective the
    # starts are compared on one footing (a check cannot tell near-mirror materials apart).
    common = [float(problem.loss(r[1])) for r in results]
    same = [c for c in common if c - common[best] <= 0.01 * common[best]]
    final = checks[best]
    step_record = None
    if final_step and jac is not None:
        say(f"taking one Gauss-Newton step on the best check's pooled residuals and checking it at {check_walks} "
            "walks under fresh keys")
        x_step = gauss_newton_step(problem, jac, pooled[best], x)
        if np.all(np.isfinite(np.asarray(x_step))):
            c_step = check(problem, meas, x_step, key=jax.random.fold_in(key, 3), walks=check_walks)
            kept = bool(_upper_bound(c_step["material_chi2"], c_step["material_chi2_se"])
                        < _upper_bound(final["material_chi2"], final["material_chi2_se"]))
        else:
            c_step, kept = None, False
        step_record = dict(damping=FINAL_DAMPING, kept=kept, check_before=final, check_after=c_step)
        if kept:
            x, final = x_step, c_step
    est = problem.estimate(x)
    if step_record is not None and step_record["kept"]:  # the objective at the stepped material, from its estimate
        r = problem.weigh(problem.scale * est.f)
        loss = float(jnp.sum(r * r))
    model = np.asarray(problem.scale * est.f)
    model_std = np.asarray(problem.scale * est.stderr)
    elapsed = time.perf_counter() - t0
    record = fit_statistics(meas, model, loss, param.size)
    record.update(
        iterations=int(steps), time_s=round(elapsed, 2), method=method, variant=variant,
        n_evaluations=int(round(n_eval)), walks=int(walks), bounces=int(bounces), jacobian_walks=jacobian_walks,
        seed=int(seed), n_params=int(param.size), connection=problem.connection,
        fitted=list(param.names), fixed_starts=[name for _, name, _ in fixed], starts_refined=len(results),
        starts_at_optimum=len(same),
        unfinished_energy=float(np.max(np.asarray(est.unfinished))),
        mc_error_median=float(np.median(model_std / (meas.std if meas.std is not None else 1.0))),
        check=final, final_step=step_record,
    )
    starts_summary = [(r[0], float(r[2]), c["material_chi2"], c["material_chi2_se"]) for r, c in zip(results, checks)]
    record["reduced_chi2_note"] = ("reduced_chi2 weights residuals by sqrt(std^2 + mc^2), the measurement noise and "
                                   "the model's Monte Carlo error; reduced_chi2_noise_only by std alone.")
    return FitResult(material=param.to_material(x), record=record, model=model, model_std=model_std,
                     starts=starts_summary, x=x, param=param, problem=problem)
