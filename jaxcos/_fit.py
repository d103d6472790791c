"""Fitting a material to measurements: Levenberg-Marquardt (optimistix) and a Powell baseline.

The objective is the sum of squared residuals ``(model - measured) / std``
(``std = 1`` when the file has no standard deviations), in the file's own
quantity, over every measured point and colour channel. The model is the
Monte Carlo BSDF under a fixed key and fixed lobe-selection probabilities
(common random numbers), so the objective is a deterministic, smooth function
of the parameters and its Jacobian comes from forward-mode differentiation of
the walk.

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

import dataclasses
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from ._errors import InputError
from ._material import Layer, Material, check_variant
from ._walk import lobe_probabilities, make_query, simulate

FIT_WALKS = 256
"""Walks per incidence direction in a fit. At 128 walks the Monte Carlo error
of a point is about 4% (twice a 2% measurement noise); the fit puts that
error into the likelihood (see :func:`fit`) and reports it."""
FIT_BOUNCES = 128
"""Bounces per walk in a fit: at most 3.7e-3 of the energy is left in
unfinished walks for the four published products (256 bounces: 2.2e-5), at
half the cost; every fit reports what its walks left unfinished."""

SCREEN_STEPS = 5
"""Levenberg-Marquardt steps each start gets in the screen (at a sixteenth of the fit's budget)."""

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
    and channels; ``model`` is in the file's quantity.
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

    def estimate(self, x):
        """The :class:`~jaxcos.Estimate` of the material at ``x`` under this problem's key and budget."""
        return simulate(self.param.to_material(x), self.query, self.key, walks=self.walks,
                        bounces=self.bounces, lobe_probs=self.lobe_probs)

    def model(self, x):
        """The model in the file's quantity, ``(N, 3)``."""
        return self.scale * self.estimate(x).f

    def residuals(self, x):
        return _residuals(self, x)

    def loss(self, x):
        r = self.residuals(x)
        return jnp.sum(r * r)


@jax.custom_jvp
def _residuals(problem, x):
    return ((problem.model(x) - problem.measured) / problem.sigma).reshape(-1)


@_residuals.defjvp
def _residuals_jvp(primals, tangents):
    # The Jacobian by batched forward mode, materialised once: linearising the
    # walk instead would store every bounce's intermediates (gigabytes).
    problem, x = primals
    _, dx = tangents
    fn = lambda v: _residuals.fun(problem, v)
    y, jac = jax.vmap(lambda e: jax.jvp(fn, (x,), (e,)), out_axes=(None, -1))(jnp.eye(x.shape[0], dtype=x.dtype))
    return y, jac @ dx


def make_problem(meas, param, *, key, walks=FIT_WALKS, bounces=FIT_BOUNCES, lobe_probs=None, reference=None):
    """The least-squares :class:`Problem` of fitting ``param`` to measurements ``meas``.

    ``lobe_probs`` are held fixed during the fit (common random numbers); by
    default they are those of ``reference`` (a material) or of the default start.
    """
    if lobe_probs is None:
        lobe_probs = lobe_probabilities(reference if reference is not None else param.to_material(jnp.zeros(param.size)))
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
    )


# --- solvers ----------------------------------------------------------------------


class LevenbergMarquardt(optx.AbstractGaussNewton):
    """optimistix's Levenberg-Marquardt, also stopped when the loss stops falling.

    Under a fixed key the objective is rough along the parameters that move
    sampled directions (``docs/derivatives.md``). Near its optimum LM then
    creeps: the damping grows after a few rejected steps, and each accepted
    step lowers the loss by a few hundredths of a chi-square unit, far below
    what the data can tell apart, at the cost of a Jacobian per step. Besides
    optimistix's Cauchy test on ``rtol`` and ``atol``, this solver stops after
    ``patience`` consecutive accepted steps that each lowered the loss by less
    than ``loss_rtol`` of it.
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
        return super().init(fn, y, args, options, f_struct, aux_struct, tags), jnp.array(0)

    def step(self, fn, y, args, options, state, tags):
        inner, small = state
        y, new, aux = super().step(fn, y, args, options, inner, tags)
        before, after = jnp.sum(inner.f_info.residual ** 2), jnp.sum(new.f_info.residual ** 2)
        accepted = (new.num_accepted_steps > inner.num_accepted_steps) & (inner.num_accepted_steps >= 1)
        small = jnp.where(accepted, jnp.where(before - after < self.loss_rtol * before, small + 1, 0), small)
        new = eqx.tree_at(lambda s: s.terminate, new, new.terminate | (small >= self.patience))
        return y, (new, small), aux

    def terminate(self, fn, y, args, options, state, tags):
        return super().terminate(fn, y, args, options, state[0], tags)

    def postprocess(self, fn, y, aux, args, options, state, tags, result):
        return super().postprocess(fn, y, aux, args, options, state[0], tags, result)


@eqx.filter_jit
def _lm(problem, x0, max_steps, rtol, atol):
    solver = LevenbergMarquardt(rtol=rtol, atol=atol)
    sol = optx.least_squares(lambda x, p: p.residuals(x), solver, x0, args=problem, max_steps=max_steps, throw=False)
    return sol.value, problem.loss(sol.value), sol.stats["num_steps"]


@eqx.filter_jit
def _screen(problem, xs):
    """A few Levenberg-Marquardt steps from each row of ``xs``, batched; returns the ends and their losses."""
    ends, losses, _ = jax.vmap(lambda x: _lm(problem, x, SCREEN_STEPS, 1e-3, 1e-3))(xs)
    return ends, losses


def solve_lm(problem, x0, *, max_steps=40, rtol=1e-4, atol=1e-5):
    """Levenberg-Marquardt from ``x0``; returns ``(x, loss, steps)``."""
    x, loss, steps = _lm(problem, x0, max_steps, rtol, atol)
    return x, float(loss), int(steps)


def solve_powell(problem, x0, *, max_evaluations=20000, xtol=1e-4, ftol=1e-8):
    """SciPy's modified Powell on the same objective (the paper's method); returns ``(x, loss, evaluations)``."""
    from scipy.optimize import minimize

    loss = jax.jit(lambda x: problem.loss(x))
    res = minimize(lambda x: float(loss(jnp.asarray(x, dtype=jnp.result_type(float)))), np.asarray(x0, float),
                   method="Powell", options=dict(maxfev=max_evaluations, xtol=xtol, ftol=ftol))
    return jnp.asarray(res.x, dtype=jnp.result_type(float)), float(res.fun), int(res.nfev)


# --- starts -----------------------------------------------------------------------


def highlight_tilt(meas):
    """The platelet tilt ``theta_p`` (degrees) that the measured highlight points to, or ``None``.

    Mirror-like platelets tilted by ``theta_p`` in the plane of incidence
    reflect at ``theta_o = theta_i + 2 theta_p`` (MODEL.md section 2). For each
    incidence with at least five in-plane points, its brightest point (mean of
    r, g, b) gives one estimate; the result is their median.
    A narrow highlight (``alpha_p`` of a few thousandths) is invisible to a
    random start: its basin is a fraction of a degree wide in ``theta_p``.
    """
    inplane = np.isclose(np.asarray(meas.phi_o, float) % 180.0, 0.0)
    values = np.mean(meas.values, axis=1)
    tilts = []
    for ti in np.unique(meas.theta_i[inplane]):
        sel = inplane & (meas.theta_i == ti)
        if sel.sum() < 5:
            continue
        to = np.where(np.isclose(meas.phi_o[sel] % 360.0, 180.0), -meas.theta_o[sel], meas.theta_o[sel])
        tilts.append(0.5 * (to[np.argmax(values[sel])] - ti))
    if not tilts:
        return None
    return float(np.clip(np.median(tilts), 0.0, 89.0))


def random_starts(param, n, rng, tilt=None):
    """``n`` starting vectors drawn uniformly over the physical ranges (``alpha_p`` log-uniformly in [0.003, 1]).

    With a ``tilt`` (from :func:`highlight_tilt`), a third of them take that
    ``theta_p`` (within half a degree) and a narrow ``alpha_p`` (log-uniform in
    [0.001, 0.05]): the starts of a near-mirror highlight.
    """
    draws = []
    for i in range(n):
        values = dict(
            c_d=rng.uniform(0.05, 0.95), albedo_d=rng.uniform(0.3, 0.99, 3), g1=rng.uniform(-0.3, 0.9),
            g2=rng.uniform(-0.6, 0.3), w_g=rng.uniform(0.2, 0.95), albedo_p=rng.uniform(0.3, 0.99, 3),
            alpha_p=10 ** rng.uniform(-2.5, 0), theta_p=rng.uniform(0, 30), t=rng.uniform(1, 30), phi_p=0.0,
        )
        if tilt is not None and i >= n - n // 3:
            values.update(theta_p=np.clip(tilt + rng.uniform(-0.5, 0.5), 0.0, 89.9),
                          alpha_p=10 ** rng.uniform(-3, np.log10(0.05)))
        draws.append(np.concatenate([np.atleast_1d(_TRANSFORMS[n_][1](values[n_])) for n_ in param.names]))
    return jnp.asarray(np.stack(draws), dtype=jnp.result_type(float))


@dataclasses.dataclass
class FitResult:
    """The outcome of :func:`fit`.

    Attributes:
        material: the fitted material.
        record: the ``"fit"`` record of FORMATS.md (plus extra keys).
        model: ``(N, 3)`` the fitted model in the file's quantity.
        model_std: ``(N, 3)`` its Monte Carlo standard error.
        starts: per refined start, ``(start index, loss)``.
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
    problem = dataclasses.replace(problem, lobe_probs=lobe_probabilities(problem.param.to_material(x)))
    if meas.std is None:
        return problem
    est = problem.estimate(x)
    rel = jnp.median(est.stderr / jnp.maximum(jnp.abs(est.f), 1e-12))
    sigma = jnp.sqrt(jnp.asarray(meas.std, problem.sigma.dtype) ** 2 + (rel * problem.scale * est.f) ** 2)
    return dataclasses.replace(problem, sigma=sigma)


def _statistics(meas, model, loss, n_free):
    resid = model - meas.values
    n = resid.size
    dof = max(n - n_free, 1)
    stats = dict(loss=float(loss), l2=float(np.sum(resid ** 2)), rmse=float(np.sqrt(np.mean(resid ** 2))),
                 n_points=int(meas.values.shape[0]))
    if meas.std is not None:
        stats["reduced_chi2"] = float(loss / dof)
        stats["reduced_chi2_noise_only"] = float(np.sum((resid / meas.std) ** 2) / dof)
    return stats


def fit(meas, *, variant="two_lobe", method="lm", seed=0, walks=FIT_WALKS, bounces=FIT_BOUNCES, starts=15,
        refine=2, fit_t=False, fit_phi=False, start=None, t=16.0, progress=None):
    """Fit a one-layer material of ``variant`` to the measurements ``meas``.

    Args:
        meas: from :func:`jaxcos.load_measurements`.
        variant: one of :data:`jaxcos.VARIANTS`.
        method: ``"lm"`` (Levenberg-Marquardt, optimistix) or ``"powell"`` (SciPy).
        seed: seeds the Monte Carlo key (fixed for the whole fit) and the random starts.
        walks, bounces: the Monte Carlo budget of the objective.
        starts: number of random starts screened, besides the default start; a
            third of them start at the tilt of the measured highlight with a
            narrow ``alpha_p`` (:func:`highlight_tilt`).
        refine: number of best screened starts refined at the full budget.
        fit_t, fit_phi: also fit the optical thickness ``t`` (else fixed at ``t``)
            or the tilt azimuth ``phi_p`` (else 0).
        start: a :class:`Material` to start from instead of the multi-start
            (only that start is refined).
        t: the optical thickness when it is not fitted (the paper's protocol: 16).
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
    problem = make_problem(meas, param, key=key, walks=walks, bounces=bounces, reference=param.to_material(x_default))

    if start is not None:
        candidates = [(0, x_default)]
    else:
        rng = np.random.default_rng(seed)
        tilt = highlight_tilt(meas) if "theta_p" in param.names else None
        pool = jnp.concatenate([x_default[None], random_starts(param, starts, rng, tilt)])
        screen = dataclasses.replace(problem, walks=max(walks // 4, 8), bounces=max(bounces // 4, 16))  # 1/16 cost
        say(f"screening {pool.shape[0]} starts with a short Levenberg-Marquardt at a quarter of the walks and bounces")
        xs, losses = _screen(screen, pool)
        losses = np.where(np.isfinite(np.asarray(losses)), np.asarray(losses), np.inf)
        order = np.argsort(losses)[:refine]
        candidates = [(int(i), xs[i]) for i in order]

    results = []
    n_eval = 0
    for rank, (index, x0) in enumerate(candidates):
        say(f"refining start {rank + 1} of {len(candidates)} ({method})")
        prob = with_mc_error(problem, meas, x0)
        if method == "lm":
            x, loss, steps = solve_lm(prob, x0)
            n_eval += (steps + 1) * (param.size + 1)
        else:
            x, loss, steps = solve_powell(prob, x0)
            n_eval += steps
        results.append((index, x, loss, steps, prob))
    index, x, loss, steps, problem = min(results, key=lambda r: r[2])
    same = [r for r in results if abs(r[2] - loss) <= 1e-3 * loss + 1.0]
    say("evaluating the fitted model")
    est = problem.estimate(x)
    model = np.asarray(problem.scale * est.f)
    model_std = np.asarray(problem.scale * est.stderr)
    elapsed = time.perf_counter() - t0
    record = _statistics(meas, model, loss, param.size)
    record.update(
        iterations=int(steps), time_s=round(elapsed, 2), method=method, variant=variant, n_evaluations=int(n_eval),
        walks=int(walks), bounces=int(bounces), seed=int(seed), n_params=int(param.size),
        fitted=list(param.names), starts_refined=len(results), starts_at_optimum=len(same),
        unfinished_energy=float(np.max(np.asarray(est.unfinished))),
        mc_error_median=float(np.median(model_std / (meas.std if meas.std is not None else 1.0))),
    )
    starts_summary = [(int(r[0]), float(r[2])) for r in results]
    record["reduced_chi2_note"] = ("reduced_chi2 weights residuals by sqrt(std^2 + mc^2), the measurement noise and "
                                   "the model's Monte Carlo error; reduced_chi2_noise_only by std alone.")
    return FitResult(material=param.to_material(x), record=record, model=model, model_std=model_std,
                     starts=starts_summary, x=x, param=param, problem=problem)
