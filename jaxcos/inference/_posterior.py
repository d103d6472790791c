"""Posterior spreads of fitted parameters: emcee, a Laplace cross-check, and sensitivities.

The posterior of the physical parameters ``v`` (the :meth:`Parameterization.labels`
entries: ``c_d``, ``albedo_d[0..2]``, ..., ``theta_p`` in degrees, and ``eta``,
``alpha_s`` last when the fit has a top interface) is

    p(v | y) ∝ U(v; bounds) exp(-1/2 sum ((m(v) - y) / sigma)^2)

with a uniform prior on the physical ranges and a Gaussian likelihood:
``sigma`` is the file's std, or for a file without std columns the
:class:`NoiseModel` ``relative * |y| + absolute`` with its two levels
estimated by maximum likelihood with the material. The
model ``m`` is a Monte Carlo estimate, and with a fixed key its error is not
noise the chain can average: the expected loss of a fixed-key estimate is the
true loss plus the estimate's variance, so its error acts as a penalty that
grows away from where it was fixed and pulls towards parameters where the
variance is small. The chain therefore samples the *high-budget
linearisation* within the prior's bounds,

    m(v) = M_hi(v0) + J_hi (v - v0),

from one estimate at the anchor ``v0`` (:data:`HI_WALKS` walks per
incidence). :func:`uncertainty` runs it in stages:

1. :func:`slope_steps`: the difference steps, half a posterior width from a
   pilot at an eighth of the budget.
2. :func:`linearise`: a :class:`Linearisation` at a point. The slopes
   ``J_hi`` are central differences under common random numbers, not
   forward-mode derivatives: along the parameters that move sampled
   directions (``g1``, ``alpha_p``, ...) the fixed-key estimate has narrow
   steep features and its pointwise derivative is heavy-tailed
   (``docs/derivatives.md``). ``J_hi`` is the mean of two halves under
   independent keys: ``N = D^T D / 4``, with ``D`` their whitened difference,
   is the expected share of ``J^T J`` that is the slopes' own noise, and the
   log-likelihood adds ``dv^T N dv / 2`` back, no more than ``J^T J`` holds
   in any direction (:attr:`Linearisation.information`).
3. :func:`find_anchor`: where the slopes at the fit are mostly noise, their
   steps are lengthened (:func:`widen_steps`); the anchor starts at the fit
   and moves by up to ``ANCHORS - 1`` Gauss-Newton steps towards the optimum of the last
   linearisation, each with a line search under common random numbers.
4. :func:`sample`: emcee on the Gaussian with the linearisation's
   information ``J^T J - N`` centred at the anchor (``_Target``), within
   :data:`REGION` difference steps of it, where the linearisation holds
   (the report says when a posterior reaches that edge).
5. :func:`monte_carlo_spread` and :func:`summarise`: the remaining error of
   ``M_hi`` at the anchor (measured by independent estimates of fewer walks,
   scaled), mapped through the sensitivities, is a Monte Carlo spread of the
   parameters that the reported intervals include.
6. :func:`check_model`: the sampled model at posterior draws against
   independent high-budget estimates.

The coverage of the intervals on synthetic data is measured in
``benchmarks/RESULTS.md`` (``benchmarks/bench_uncertainty.py``).

Example::

    import jaxcos
    meas = jaxcos.load_measurements("measurements/matte2.csv")
    post = jaxcos.uncertainty(meas, jaxcos.fit(meas))
    post.summary["alpha_p"]          # median, 16/84 and 2.5/97.5 percentiles
    jaxcos.write_uncertainty(post, meas, "out/matte2_posterior")
"""

import dataclasses
import logging
import time

import emcee
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from .._errors import InputError
from ._fit import LOBE_NAMES, fit, make_problem, ordered_lobes
from ..model import POSTERIOR_BUDGET, lobe_probabilities, simulate

WALKERS = 32
"""Ensemble size: more than twice the twelve parameters of the two-lobe model (:func:`uncertainty` takes
``2 P + 2`` for ``P`` parameters where that is more)."""
MAX_STEPS = 20000
"""The longest chain, in ensemble steps, that :func:`uncertainty` runs by default."""
CHAIN_TAUS = 50
"""A chain shorter than this many integrated autocorrelation times is reported as too short (emcee's rule)."""

HI_WALKS = POSTERIOR_BUDGET.walks
"""Walks per incidence of the value ``M_hi(v0)`` and slopes ``J_hi(v0)`` at the anchor (bounces as in the fit;
:data:`jaxcos.model.POSTERIOR_BUDGET`)."""
ANCHORS = 6
"""Linearisations made at most: at the fit, then after each Gauss-Newton step towards the last one's optimum
(:func:`find_anchor`)."""
LINE = (1.0, 0.5, 0.25, 0.125)
"""The fractions of a Gauss-Newton step of the anchor that :func:`find_anchor` compares."""
REGION = 16.0
"""Half-width of the region the chain may explore around the anchor, per parameter, in central-difference
steps (eight pilot sd, or the whole prior for a parameter the data hardly constrain)."""
SLOPE_NOISE = 0.25
"""The share of a parameter's ``(J^T J)_ii`` that may be its slopes' own noise at the fit before
:func:`find_anchor` lengthens its difference step (:func:`widen_steps`)."""
SPREAD_FRACTION = 8
"""The Monte Carlo spread's replicas use this fraction of the linearisation's walks, and at least 128
(:func:`monte_carlo_spread`)."""

POSTERIOR_THIN_AFTER = 32
"""The linearisations' estimator makes every walk make the first 32 steps (``simulate(thin_after=...)``):
the coverage of random truths (docs/method.md, "Posteriors") was measured so; ``simulate``'s default
thins from step 16."""


# --- a sampler for any batched log-density ---------------------------------------------


@dataclasses.dataclass
class Chain:
    """An ensemble chain and its diagnostics.

    Attributes:
        samples: ``(S, P)`` draws after burn-in, all walkers pooled.
        tau: ``(P,)`` integrated autocorrelation time per parameter, in steps.
        steps: chain length in steps; ``burn``: steps discarded.
        walkers: ensemble size.
        acceptance: ``(walkers,)`` acceptance fraction per walker.
        ess: ``(P,)`` effective sample size per parameter, ``walkers * (steps - burn) / tau``.
        converged: ``steps >= CHAIN_TAUS * max(tau)``.
        seconds: wall time of the sampling.
    """

    samples: np.ndarray
    tau: np.ndarray
    steps: int
    burn: int
    walkers: int
    acceptance: np.ndarray
    ess: np.ndarray
    converged: bool
    seconds: float


def run_ensemble(log_prob, v0, scale, *, seed=0, walkers=WALKERS, max_steps=MAX_STEPS, check_every=250,
                 progress=None):
    """Sample ``log_prob`` with emcee's ensemble sampler, walkers started in a small ball around ``v0``.

    Args:
        log_prob: maps a ``(n, P)`` batch of points to ``(n,)`` log-densities
            (``-inf`` outside the support); called with ``vectorize=True``.
        v0: ``(P,)`` a point of high density.
        scale: ``(P,)`` rough posterior widths; the ball has a tenth of them.
        seed: seeds the ball and the sampler's moves.
        walkers: ensemble size (at least ``2 P + 2``).
        max_steps: the longest chain; it stops earlier once it is
            :data:`CHAIN_TAUS` autocorrelation times long.
        check_every: steps between autocorrelation estimates.
        progress: ``progress(message)`` told at each check.

    Returns:
        A :class:`Chain`.
    """
    v0 = np.asarray(v0, float)
    n_par = v0.size
    if walkers < 2 * n_par + 2:
        raise ValueError(f"walkers must be at least 2 * parameters + 2 = {2 * n_par + 2}, not {walkers}")
    rng = np.random.default_rng(seed)
    start = v0 + 0.1 * np.asarray(scale, float) * rng.standard_normal((walkers, n_par))
    lp = log_prob(start)
    bad = ~np.isfinite(lp)
    for _ in range(100):  # walkers that fell outside the support shrink towards v0
        if not bad.any():
            break
        start[bad] = v0 + 0.5 * (start[bad] - v0)
        lp[bad] = log_prob(start[bad])
        bad = ~np.isfinite(lp)
    if bad.any():
        raise ValueError("the log-density is not finite near v0; the start is outside the support")
    # Differential-evolution moves: on Gaussian-like posteriors in 12 dimensions they
    # reach autocorrelation times about half those of the default stretch move.
    moves = [(emcee.moves.DEMove(), 0.8), (emcee.moves.DESnookerMove(), 0.2)]
    sampler = emcee.EnsembleSampler(walkers, n_par, log_prob, vectorize=True, moves=moves)
    sampler.random_state = np.random.RandomState(int(rng.integers(2 ** 31))).get_state()
    t0 = time.perf_counter()
    state = emcee.State(start, log_prob=lp)
    burn, tau = 0, np.full(n_par, np.inf)
    steps = 0
    while steps < max_steps:
        n = min(check_every, max_steps - steps)
        state = sampler.run_mcmc(state, n, progress=False)
        steps += n
        burn, tau = _burn_and_tau(sampler, steps)
        if progress:
            progress(f"{steps} steps; autocorrelation time up to {np.max(tau):.0f} steps "
                     f"({steps / np.max(tau):.0f} of the {CHAIN_TAUS} needed)")
        if steps >= CHAIN_TAUS * np.max(tau):
            break
    seconds = time.perf_counter() - t0
    samples = sampler.get_chain(discard=burn, flat=True)
    ess = walkers * (steps - burn) / tau
    return Chain(samples=samples, tau=tau, steps=steps, burn=burn, walkers=walkers,
                 acceptance=np.asarray(sampler.acceptance_fraction), ess=ess,
                 converged=bool(steps >= CHAIN_TAUS * np.max(tau)), seconds=seconds)


def _burn_and_tau(sampler, steps):
    """The burn-in, three autocorrelation times of the whole chain and at most half of it, and the
    autocorrelation times after it: the chain stops on, and is judged by, the same estimate."""
    burn = int(min(np.ceil(3 * np.max(_tau(sampler))), steps // 2))
    return burn, _tau(sampler, burn)


def _tau(sampler, discard=0):
    """Integrated autocorrelation times; emcee's estimate without its length check (reported instead).

    A parameter whose chain has not moved (no variance, where emcee's estimate
    is 0/0) gets the chain's length: it has not decorrelated at all.
    """
    chain = sampler.get_chain(discard=discard)
    logger = logging.getLogger("emcee.autocorr")
    level = logger.level
    logger.setLevel(logging.ERROR)  # the length check is reported by the caller, not logged per parameter
    try:
        with np.errstate(invalid="ignore", divide="ignore"):
            tau = np.array([emcee.autocorr.integrated_time(chain[:, :, i], quiet=True)[0]
                            for i in range(chain.shape[2])])
    finally:
        logger.setLevel(level)
    return np.where(np.isfinite(tau), tau, float(chain.shape[0]))


# --- linearised spreads and sensitivities ------------------------------------------


def laplace(jac, jac_noise=None):
    """Covariance ``(J^T J - N)^+`` of a least-squares optimum from the Jacobian of its whitened residuals.

    Args:
        jac: ``(M, P)`` derivatives of ``(model - measured) / sigma`` with
            respect to the parameters.
        jac_noise: ``(P, P)`` the part of ``J^T J`` that is the Jacobian's own
            Monte Carlo noise (see :func:`uncertainty`); none by default.

    Returns:
        ``(P, P)`` covariance: the pseudo-inverse of the information with
        negative eigenvalues (noise larger than signal) set to 0.
    """
    jac = np.asarray(jac, float)
    info = jac.T @ jac - (0.0 if jac_noise is None else np.asarray(jac_noise, float))
    w, u = np.linalg.eigh(0.5 * (info + info.T))
    keep = w > 1e-12 * max(np.max(np.abs(w)), 1e-300)
    return (u[:, keep] / w[keep]) @ u[:, keep].T


def sensitivity(jac, sigma, jac_noise=None):
    """Derivatives of the fitted parameters with respect to each measured value.

    Implicit differentiation of the optimality condition ``J^T r = 0`` of
    residuals ``r = (m(v) - y) / sigma`` (Gauss-Newton Hessian): the optimum
    moves by ``dv = (J^T J)^+ J^T diag(1 / sigma) dy``.

    Args:
        jac: ``(M, P)`` Jacobian of the whitened residuals.
        sigma: ``(M,)`` the standard deviation of each residual.
        jac_noise: as in :func:`laplace`.

    Returns:
        ``(P, M)``: ``dv_p / dy_m``, parameter units per unit of the measured quantity.
    """
    return laplace(jac, jac_noise) @ np.asarray(jac, float).T / np.asarray(sigma, float).reshape(1, -1)


# --- the jaxcos posterior -------------------------------------------------------------


def _estimate(problem, v):
    """The estimate at the physical values ``v`` under the key, budget and lobe probabilities of ``problem``."""
    return simulate(problem.param.physical_to_material(v), problem.query, problem.key, walks=problem.walks,
                    bounces=problem.bounces, lobe_probs=problem.lobe_probs, connection=problem.connection,
                    boundary_prob=problem.boundary_prob, thin_after=problem.thin_after)


@eqx.filter_jit
def _batch_estimate(problem, vs):
    return jax.vmap(lambda v: _estimate(problem, v))(vs)


def _first_steps(param, v):
    """Pilot finite-difference steps: 1% of each parameter's range, 5% of the value for ``alpha_p``, ``t`` and
    ``alpha_s`` (a roughness spans decades)."""
    v = np.asarray(v, float)
    low, high = param.bounds()
    step = 0.01 * (high - low)
    relative = np.array([label in ("alpha_p", "t", "alpha_s") for label in param.labels()])
    step[relative] = 0.05 * np.abs(v[relative])
    return step


def _value_and_secants(problem, v, step):
    """The model ``(N, 3)`` at ``v`` and its slopes ``(N, 3, P)`` by central differences under one key.

    Common random numbers make each difference a smooth function of the step.
    The slope is that of the estimate over ``v +- step`` (clipped to the
    bounds), not its derivative at ``v``: along the parameters that move
    sampled directions the fixed-key estimate has narrow, steep features
    (``docs/derivatives.md``) and its forward-mode derivative is heavy-tailed,
    while the posterior only sees the model over its own width. Returns the
    model, the slopes and the estimate at ``v``.
    """
    v = np.asarray(v, float)
    low, high = problem.param.bounds()
    eye = np.diag(step)
    plus, minus = np.minimum(v + eye, high), np.maximum(v - eye, low)
    dtype = jnp.result_type(float)
    est = _batch_estimate(problem, jnp.asarray(np.concatenate([v[None], plus, minus]), dtype))
    f = problem.scale * np.asarray(est.f, float)
    p = v.shape[0]
    jac = (f[1:p + 1] - f[p + 1:]) / np.diag(plus - minus)[:, None, None]
    return f[0], np.moveaxis(jac, 0, -1), jax.tree.map(lambda a: a[0], est)


def _in_batches(fn, batch, dtype):
    """``fn`` on any number of rows, called on batches of exactly ``batch`` rows (one compilation)."""

    def call(vs):
        vs = np.asarray(vs, float)
        n = vs.shape[0]
        padded = np.concatenate([vs, np.repeat(vs[-1:], (-n) % batch, axis=0)])
        out = [np.asarray(fn(jnp.asarray(padded[i:i + batch], dtype)), float) for i in range(0, padded.shape[0], batch)]
        return np.concatenate(out)[:n]

    return call


@dataclasses.dataclass(frozen=True)
class Linearisation:
    """The high-budget model linearised at an anchor: ``m(v) = value + slopes (v - anchor)``.

    Values are in the file's quantity (reflectance factor or BRDF in 1/sr).

    Attributes:
        anchor: ``(P,)`` the physical values where it is made.
        value: ``(N, 3)`` ``M_hi(anchor)``, the mean of two half-budget
            estimates under independent keys.
        slopes: ``(N, 3, P)`` ``J_hi``, central differences over ``+- step``
            under common random numbers, the mean of the two halves.
        relative_error: the median relative Monte Carlo standard error of ``value``.
        measured: ``(N, 3)`` the measured values.
        noise: ``(N, 3)`` the measurement's standard deviation.
        slope_difference: ``(N, 3, P)`` the difference of the two halves' slopes.
        noise_model: the :class:`NoiseModel` that ``noise`` comes from, where it
            was estimated at this anchor (:func:`find_anchor`), else ``None``.
    """

    anchor: np.ndarray
    value: np.ndarray
    slopes: np.ndarray
    relative_error: float
    measured: np.ndarray
    noise: np.ndarray
    slope_difference: np.ndarray
    noise_model: "NoiseModel | None" = None

    @property
    def mc(self):
        """``(N, 3)``: the Monte Carlo standard error of :attr:`value`, ``relative_error * |value|``."""
        return self.relative_error * np.abs(self.value)

    @property
    def sigma(self):
        """``(N, 3)``: the standard deviation of each residual, the noise and :attr:`mc` in quadrature."""
        return np.sqrt(self.noise ** 2 + self.mc ** 2)

    @property
    def residuals(self):
        """``(3 N,)``: the whitened residuals ``(value - measured) / sigma``, channel last."""
        return ((self.value - self.measured) / self.sigma).reshape(-1)

    @property
    def jac(self):
        """``(3 N, P)``: the slopes of the whitened residuals, rows as in :attr:`residuals`."""
        return (self.slopes / self.sigma[..., None]).reshape(-1, self.anchor.size)

    @property
    def raw_slope_noise(self):
        """``(P, P)``: ``N = D^T D / 4``, ``D`` the whitened :attr:`slope_difference`.

        The expected part of ``J^T J`` that is the slopes' own noise: for the
        mean of two halves, ``E[J^T J] - J_true^T J_true``.
        """
        d = (self.slope_difference / self.sigma[..., None]).reshape(-1, self.anchor.size)
        return 0.25 * d.T @ d

    @property
    def information(self):
        """``(P, P)``: ``H``, the positive part of ``J^T J - N`` (its negative eigenvalues set to 0).

        Along a direction where the slopes' noise :attr:`raw_slope_noise`
        exceeds them, the linearisation resolves no information, and the
        chain's log-density is flat there (within the region) rather than
        rising away from the anchor.
        """
        info = self.jac.T @ self.jac - self.raw_slope_noise
        w, u = np.linalg.eigh(0.5 * (info + info.T))
        return (u * np.maximum(w, 0.0)) @ u.T

    @property
    def slope_noise(self):
        """``(P, P)``: ``J^T J -`` :attr:`information`: :attr:`raw_slope_noise` where it is smaller than ``J^T J``,
        all of ``J^T J`` where it is not."""
        return self.jac.T @ self.jac - self.information

    def noise_dominated(self):
        """``(P,)``: each parameter's share of slope noise, ``N_ii / (J^T J)_ii`` (:attr:`raw_slope_noise`)."""
        jtj = np.einsum("mp,mp->p", self.jac, self.jac)
        return np.diag(self.raw_slope_noise) / np.maximum(jtj, 1e-300)

    @property
    def chi2(self):
        """The sum of the squared whitened residuals at the anchor."""
        return float(self.residuals @ self.residuals)


# --- the noise of a file without std columns -----------------------------------------

@dataclasses.dataclass(frozen=True)
class NoiseModel:
    """The noise of a file without std columns: ``std = relative * |y| + absolute``, ``y`` the measured value.

    The model of ``jaxcos fit --noise REL,ABS``
    (:meth:`jaxcos.Measurements.with_noise`), its two levels estimated by
    maximum likelihood with the material (:func:`estimate_noise`, and
    :func:`find_anchor`, which alternates the two).

    Attributes:
        relative: the relative level (0.02 is 2% of the value).
        absolute: the absolute level, in the file's quantity.
        sd: ``(2,)`` the Laplace standard deviations of ``log10 relative`` and ``log10 absolute``.
    """

    relative: float
    absolute: float
    sd: tuple = (float("nan"), float("nan"))

    def std(self, measured):
        """``(N, 3)``: the standard deviation of each measured value."""
        return self.relative * np.abs(measured) + self.absolute

    @staticmethod
    def bounds(measured):
        """``(low, high)`` of ``log10`` of the levels: the relative in ``[1e-4, 1]``, the absolute within six
        decades below the largest measured value."""
        top = float(np.log10(np.max(np.abs(measured))))
        return np.array([-4.0, top - 6.0]), np.array([0.0, top])


def _noise_nll(log_levels, resid, measured, mc):
    """The negative log-likelihood of ``resid`` under the noise model at ``log_levels`` (constants dropped).

    ``sum (resid / s)^2 / 2 + sum log s`` with ``s^2 = (10^a |y| + 10^b)^2 + mc^2``;
    ``log_levels`` is ``(..., 2)``.
    """
    rel, ab = 10.0 ** log_levels[..., 0, None, None], 10.0 ** log_levels[..., 1, None, None]
    s2 = (rel * jnp.abs(measured) + ab) ** 2 + mc ** 2
    return jnp.sum(0.5 * resid ** 2 / s2 + 0.5 * jnp.log(s2), axis=(-2, -1))


def estimate_noise(resid, measured, mc, *, n_fitted=0):
    """The maximum-likelihood :class:`NoiseModel` of residuals ``resid`` (model minus measured, ``(N, 3)``).

    ``mc`` (``(N, 3)``) is the model's own Monte Carlo error, counted in
    quadrature. A grid of tenth decades over :meth:`NoiseModel.bounds` picks the
    start; BFGS (optimistix) refines it on the bounded levels. The levels are
    then scaled by ``sqrt(M / (M - n_fitted))``, ``M = 3 N`` the values, for the
    degrees of freedom the fitted parameters took (the maximum-likelihood
    variance of a least-squares fit is low by that factor). ``sd``: the
    Laplace sd of each log10 level, from the 2 x 2 Hessian at the optimum.
    """
    dtype = jnp.result_type(float)
    resid, measured, mc = (jnp.asarray(np.asarray(a, float), dtype) for a in (resid, measured, mc))
    low, high = NoiseModel.bounds(np.asarray(measured))
    axes = [np.arange(a, b + 1e-9, 0.1) for a, b in zip(low, high)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 2)
    start = grid[int(np.argmin(np.asarray(_noise_nll(jnp.asarray(grid, dtype), resid, measured, mc))))]
    lo, hi = jnp.asarray(low, dtype), jnp.asarray(high, dtype)

    def to_levels(u):
        return lo + (hi - lo) * jax.nn.sigmoid(u)

    u0 = jnp.asarray(np.log((start - low + 1e-3) / (high - start + 1e-3)), dtype)
    sol = optx.minimise(lambda u, _: _noise_nll(to_levels(u), resid, measured, mc), optx.BFGS(rtol=1e-8, atol=1e-8),
                        u0, max_steps=200, throw=False)
    levels = to_levels(sol.value)
    hess = np.asarray(jax.hessian(lambda a: _noise_nll(a, resid, measured, mc))(levels), float)
    w, u = np.linalg.eigh(0.5 * (hess + hess.T))
    cov = (u[:, w > 0] / w[w > 0]) @ u[:, w > 0].T
    m = resid.size
    dof = np.sqrt(m / max(m - n_fitted, 1))
    levels = np.asarray(levels, float)
    return NoiseModel(relative=float(dof * 10 ** levels[0]), absolute=float(dof * 10 ** levels[1]),
                      sd=tuple(float(x) for x in np.sqrt(np.maximum(np.diag(cov), 0.0))))


def _with_noise_estimated(lin):
    """``lin`` with its noise the maximum-likelihood :class:`NoiseModel` at its anchor (:func:`estimate_noise`)."""
    model = estimate_noise(lin.value - lin.measured, lin.measured, lin.mc, n_fitted=lin.anchor.size)
    return dataclasses.replace(lin, noise=model.std(lin.measured), noise_model=model)


def slope_steps(problem, v, noise, *, key, progress):
    """Central-difference steps of half a posterior width at ``v``, ``(P,)`` in physical units.

    The width is the Laplace sd of a pilot at an eighth of ``problem``'s walks
    under ``key``, with the steps of :func:`_first_steps`; the result is kept
    within 1% and 10 times those steps, and a quarter of each range.
    """
    pilot_walks = max(problem.walks // 8, 1)
    progress(f"slopes at the fit by central differences: a pilot with {pilot_walks} walks per incidence")
    first = _first_steps(problem.param, v)
    _, jac, _ = _value_and_secants(dataclasses.replace(problem, key=key, walks=pilot_walks), v, first)
    pilot_sd = np.sqrt(np.maximum(np.diag(laplace((jac / noise[..., None]).reshape(-1, first.size))), 0.0))
    return np.clip(0.5 * pilot_sd, 0.01 * first, _longest_steps(problem.param, v))


def _longest_steps(param, v):
    """The longest central-difference steps: 10 times :func:`_first_steps`, and a quarter of each range."""
    low, high = param.bounds()
    return np.minimum(10 * _first_steps(param, v), 0.25 * (high - low))


def widen_steps(lin, step, longest):
    """Longer central-difference steps where the slopes of ``lin`` are mostly their own Monte Carlo noise.

    A pilot's Laplace width counts the noise of its slopes as information, so
    a parameter whose slopes are noisy gets a short step, and a short secant is
    noisier still. Where the noise's share ``rho = N_ii / (J^T J)_ii``
    (:meth:`Linearisation.noise_dominated`) exceeds :data:`SLOPE_NOISE`, the
    step grows by ``4 sqrt(rho)`` (at most 8-fold, and to at most ``longest``):
    under common random numbers a secant's noise falls as ``1 / step`` where
    the estimate is smooth, and the share then falls to about 1/16.
    """
    rho = lin.noise_dominated()
    factor = np.where(rho > SLOPE_NOISE, np.minimum(4 * np.sqrt(rho), 8.0), 1.0)
    return np.maximum(step, np.minimum(step * factor, longest))


def linearise(problem, at, step, noise, measured, *, key):
    """The :class:`Linearisation` at ``at`` from two estimates of half ``problem``'s walks under ``split(key)``.

    Their mean is the estimate; their difference measures the slopes' own
    noise, which ``J^T J`` would count as information.
    """
    halves = [_value_and_secants(dataclasses.replace(problem, key=k, walks=max(problem.walks // 2, 1)), at, step)
              for k in jax.random.split(key)]
    est = halves[0][2]
    rel = float(np.median(np.asarray(est.stderr) / np.maximum(np.abs(np.asarray(est.f)), 1e-12)))
    return Linearisation(anchor=at, value=0.5 * (halves[0][0] + halves[1][0]),
                         slopes=0.5 * (halves[0][1] + halves[1][1]), relative_error=rel / np.sqrt(2.0),
                         measured=np.asarray(measured, float), noise=np.asarray(noise, float),
                         slope_difference=halves[0][1] - halves[1][1])


def find_anchor(problem, v0, step, noise, measured, *, key, estimated_noise=False, anchors=ANCHORS, progress):
    """``(at_fit, anchored, step)``: the linearisations at the fit ``v0`` and at the chain's anchor, and their steps.

    Where the slopes at the fit are mostly their own noise, the steps are
    lengthened once (:func:`widen_steps`) and the fit's linearisation made
    again with them under the same key. The fit's own estimate is cheap, and
    its optimum lies off the high-budget model's by its key's Monte Carlo
    error, often by many posterior widths.
    From the fit, Gauss-Newton steps on the last linearisation move the
    anchor towards the optimum: each step's direction is that linearisation's,
    its length the best of :data:`LINE` fractions of it (no parameter moving
    more than :data:`REGION` difference steps), chosen by the chi-square of
    estimates at the anchor and at each candidate under one fresh key, less
    each estimate's own variance (its squared standard error over the
    noise's): a fixed-key chi-square is on average the model's plus that
    variance, which is largest under sharp highlights and would favour
    broader ones (set 10 of the coverage study, ``alpha_p`` 0.0053: a step
    that lowered one key's chi-square from 1106 to 943 raised it, less the
    variance, from 378 to 566, and from 611 to 907 under another). Common
    random numbers make that comparison fair, where two linearisations under
    different keys differ by their Monte Carlo error (an offset per
    incidence, tens of chi-square units at 8192 walks). The search stops when
    the anchor itself is best, or after ``anchors - 1`` steps. Candidates are
    kept off the bounds (the walkers' starting ball must be inside the prior).
    The ``rank``-th linearisation is made under ``fold_in(key, rank)``, the
    line before it under ``fold_in(key, anchors + rank)``. With
    ``estimated_noise`` (a file without std columns), each linearisation's
    noise is the maximum-likelihood :class:`NoiseModel` at its anchor, so
    that the anchor moves towards the joint optimum of material and noise.
    """
    low, high = problem.param.bounds()
    margin = 1e-3 * (high - low)
    dtype = jnp.result_type(float)

    def at(v, rank):
        progress(f"value and slopes at {'the fit' if rank == 0 else 'a refined anchor'} with {problem.walks} walks "
                 "per incidence")
        lin = linearise(problem, v, step, noise, measured, key=jax.random.fold_in(key, rank))
        return _with_noise_estimated(lin) if estimated_noise else lin

    at_fit = lin = at(v0, 0)
    wider = widen_steps(lin, step, _longest_steps(problem.param, v0))
    if np.any(wider > step):
        progress("longer difference steps for " + ", ".join(
            name for name, a, b in zip(problem.param.labels(), step, wider) if b > a))
        step = wider
        at_fit = lin = at(v0, 0)
    for rank in range(1, anchors):
        move = -laplace(lin.jac, lin.slope_noise) @ lin.jac.T @ lin.residuals
        move = move * min(1.0, REGION / max(float(np.max(np.abs(move / step))), 1e-30))
        points = np.stack([lin.anchor] + [np.clip(lin.anchor + s * move, low + margin, high - margin) for s in LINE])
        line = dataclasses.replace(problem, key=jax.random.fold_in(key, anchors + rank))
        est = _batch_estimate(line, jnp.asarray(points, dtype))
        f, se = (problem.scale * np.asarray(a, float) for a in (est.f, est.stderr))
        best = int(np.argmin(np.sum(((f - measured) ** 2 - se ** 2) / lin.sigma ** 2, axis=(1, 2))))
        if best == 0:
            break
        lin = at(points[best], rank)
    return at_fit, lin, step


class _Target(eqx.Module):
    """The linearised model, and a Gaussian log-likelihood at the anchor with a uniform prior on ``[low, high]``.

    ``-1/2 (v - anchor)^T H (v - anchor)`` with ``H = J^T J - N``, the
    information that the slopes resolve (:attr:`Linearisation.information`):
    flat along the directions where they resolve nothing. Its centre is the
    anchor, not the linear model's own optimum ``anchor - H^+ J^T r``: the
    anchor search compared the model itself along that Gauss-Newton step and
    kept the anchor, and the linear model's optimum lies off it by the noise
    of its slopes and the model's curvature (set 1 of the coverage study,
    at 16384 walks under four keys: chi-square 1110-1640 there, 450-680 at
    the anchor, 430-490 at the truth, for 321 values).
    """

    value: jnp.ndarray
    slopes: jnp.ndarray
    anchor: jnp.ndarray
    precision: jnp.ndarray
    low: jnp.ndarray
    high: jnp.ndarray

    def model(self, v):
        """The model in the file's quantity, ``(N, 3)``."""
        return self.value + self.slopes @ (v - self.anchor)

    def log_prob(self, v):
        inside = jnp.all((v >= self.low) & (v <= self.high))
        d = jnp.clip(v, self.low, self.high) - self.anchor
        return jnp.where(inside, -0.5 * d @ self.precision @ d, -jnp.inf)


@eqx.filter_jit
def _batch_log_prob(target, vs):
    return jax.vmap(target.log_prob)(vs)


@eqx.filter_jit
def _batch_model(target, vs):
    return jax.vmap(target.model)(vs)


def _model_in_batches(target, batch):
    """The target's model on any number of rows ``(n, P)``, ``(n, N, 3)``."""
    return _in_batches(lambda vs: _batch_model(target, vs), batch, jnp.result_type(float))


def unresolved(lin, step, labels, share=0.1):
    """The labels with more than ``share`` of their weight, in difference steps, where ``J^T J - N`` is null.

    Along those directions the slopes of ``lin`` are mostly their own Monte
    Carlo noise (:attr:`Linearisation.information`): the chain's log-density
    is flat there, and a parameter's interval is the region's extent.
    """
    scaled = step[:, None] * lin.information * step[None, :]
    w, u = np.linalg.eigh(0.5 * (scaled + scaled.T))
    null = w <= 1e-12 * max(np.max(np.abs(w)), 1e-300)
    weight = np.sum(u[:, null] ** 2, axis=1)
    return [name for name, x in zip(labels, weight) if x > share]


def linear_region(lin, step, low, high):
    """``(low, high)``: the prior's box cut to :data:`REGION` difference steps around the anchor."""
    return np.maximum(low, lin.anchor - REGION * step), np.minimum(high, lin.anchor + REGION * step)


def sample(lin, region, width, *, seed, walkers, max_steps, progress):
    """``(chain, target)``: emcee on the linearisation ``lin`` within ``region``.

    Args:
        lin: the :class:`Linearisation` at the anchor.
        region: ``(low, high)`` of :func:`linear_region`.
        width: ``(P,)`` rough posterior widths for the walkers' starting ball.
        seed, walkers, max_steps, progress: as in :func:`run_ensemble`.

    Returns:
        The :class:`Chain` and the ``_Target`` whose log-density it sampled.
    """
    dtype = jnp.result_type(float)
    target = _Target(value=jnp.asarray(lin.value, dtype), slopes=jnp.asarray(lin.slopes, dtype),
                     anchor=jnp.asarray(lin.anchor, dtype),
                     precision=jnp.asarray(lin.information, dtype),
                     low=jnp.asarray(region[0], dtype), high=jnp.asarray(region[1], dtype))
    progress(f"sampling with {walkers} walkers (emcee, differential-evolution moves)")
    log_prob = _in_batches(lambda vs: _batch_log_prob(target, vs), walkers // 2, dtype)
    chain = run_ensemble(log_prob, lin.anchor, width, seed=seed, walkers=walkers, max_steps=max_steps,
                         progress=progress)
    return chain, target


def monte_carlo_spread(problem, at, sens, *, key, replicas, progress):
    """``(P, P)``: the covariance of the parameters' shift under the Monte Carlo error of the model at ``at``.

    ``replicas`` independent estimates under ``split(key, replicas)`` with
    a :data:`SPREAD_FRACTION` of ``problem``'s walks (at least 128, or all of
    them), their deviations mapped through the sensitivities ``sens``
    (``(P, N, 3)``), and the covariance scaled to ``problem``'s walks: the
    estimate is a mean over independent, identically distributed walks, and
    from 128 walks up its later steps are thinned in the same proportions
    (:func:`jaxcos.model._walk.stages`), so its covariance is inversely
    proportional to the walks.
    """
    walks = max(problem.walks // SPREAD_FRACTION, min(problem.walks, 128))
    progress(f"propagating the Monte Carlo error of the anchor: {replicas} independent estimates with {walks} walks "
             "per incidence")
    v = jnp.asarray(at, jnp.result_type(float))
    small = dataclasses.replace(problem, walks=walks)
    reps = np.stack([problem.scale * np.asarray(_estimate(dataclasses.replace(small, key=k), v).f, float)
                     for k in jax.random.split(key, replicas)])
    shifts = (reps - reps.mean(axis=0)).reshape(replicas, -1) @ sens.reshape(sens.shape[0], -1).T
    return np.atleast_2d(np.cov(shifts.T)) * walks / problem.walks


def derived(labels, v):
    """Quantities of the parameters ``v`` (``(..., P)``, columns as ``labels``) that the data may fix better than
    the parameters themselves: a dict of name to ``(...)`` values, empty where none applies.

    ``g_mean``, for a two-lobe material: the diffusers' mean cosine
    ``w_g g1 + (1 - w_g) g2``, the first Legendre moment of their phase
    function (a Henyey-Greenstein lobe's ``l``-th moment is ``g^l``). Two
    mixtures of nearly the same first three moments scatter nearly alike,
    so the data may fix the mean cosine better than how it is split between
    the lobes (benchmarks/RESULTS.md, "Posterior").
    """
    if not set(LOBE_NAMES) <= set(labels):
        return {}
    g1, g2, w = (np.asarray(v, float)[..., labels.index(n)] for n in LOBE_NAMES)
    return {"g_mean": w * g1 + (1.0 - w) * g2}


def _percentiles(fit, samples):
    """A summary row's fitted value and percentiles of ``samples`` (``(S,)``)."""
    q = np.percentile(samples, [2.5, 16, 50, 84, 97.5])
    return dict(fit=float(fit), median=float(q[2]), p16=float(q[1]), p84=float(q[3]),
                **{"p2.5": float(q[0]), "p97.5": float(q[4])})


def summarise(chain, mc_cov, labels, fit_values, lin, laplace_sd, low, high, *, rng):
    """``(summary, derived_summary, correlation)``: the per-parameter table of :class:`Posterior` with the Monte
    Carlo error, and the same percentiles of the :func:`derived` quantities.

    Draws whose lobes cross (``g1 < g2``, where the fit's two lobes are alike)
    are relabelled (:func:`~jaxcos.inference._fit.ordered_lobes`): the reported intervals are those of the
    posterior with the more forward lobe first, as the fit reports it.

    The chain samples the posterior of one fixed-key estimate of the model; a
    different key would shift it by a draw of the Monte Carlo error mapped
    through the sensitivities (covariance ``mc_cov``). Each draw gets one such
    shift from ``rng``, and the reported spreads include it.
    """
    shift = rng.multivariate_normal(np.zeros(len(labels)), mc_cov, size=chain.samples.shape[0], method="eigh")
    samples = ordered_lobes(labels, np.clip(chain.samples + shift, low, high))
    at_fit = derived(labels, fit_values)
    derived_summary = {name: _percentiles(at_fit[name], d) for name, d in derived(labels, samples).items()}
    q_noise = np.percentile(ordered_lobes(labels, chain.samples), [16, 84], axis=0)
    summary = {}
    for i, name in enumerate(labels):
        row = _percentiles(fit_values[i], samples[:, i])
        summary[name] = dict(fit=row.pop("fit"), anchor=float(lin.anchor[i]), **row,
                             p16_noise_only=float(q_noise[0, i]), p84_noise_only=float(q_noise[1, i]),
                             mc_sd=float(np.sqrt(mc_cov[i, i])), laplace_sd=float(laplace_sd[i]),
                             tau=float(chain.tau[i]), ess=float(chain.ess[i]))
    corr = np.corrcoef(samples.T) if samples.shape[0] > 1 else np.eye(len(labels))
    return summary, derived_summary, corr


def check_model(target, problem, chain, lin, *, key, checks, rng, progress):
    """``(predictive, model_error)``: the sampled model at posterior draws, and its error against independent estimates.

    ``predictive`` is ``(D, N, 3)`` at ``max(checks, 64)`` draws (at most the
    chain's) picked by ``rng``; the first ``checks`` are compared with
    estimates of ``problem``'s budget under ``key``. The independent estimate
    has an error of its own, as large as the anchor's; ``model_error`` is the
    RMS discrepancy beyond it, over the noise.
    """
    progress(f"checking the linearised model at {checks} posterior draws against independent estimates")
    dtype = jnp.result_type(float)
    n = chain.samples.shape[0]
    draws = chain.samples[rng.choice(n, size=min(max(checks, 64), n), replace=False)]
    predictive = _model_in_batches(target, chain.walkers // 2)(draws)
    check = dataclasses.replace(problem, key=key)
    indep = np.stack([problem.scale * np.asarray(_estimate(check, jnp.asarray(d, dtype)).f) for d in draws[:checks]])
    disc2 = np.mean(((predictive[:checks] - indep) / lin.noise) ** 2)
    model_error = float(np.sqrt(max(disc2 - np.mean((lin.mc / lin.noise) ** 2), 0.0)))
    return predictive, model_error


@dataclasses.dataclass(frozen=True, kw_only=True)
class PosteriorRecord:
    """What a run of :func:`uncertainty` did: the ``"record"`` object of ``posterior.json`` (:meth:`to_json`).

    Attributes:
        labels: the sampled parameters, one per entry of ``v`` (``eta`` and
            ``alpha_s`` last for a material with a top interface).
        variant: the model variant.
        n_points: measured points (3 channels each); ``n_params``: sampled parameters.
        walkers, steps, burn: the ensemble size, the chain's length and the steps discarded.
        acceptance_fraction, acceptance_fraction_min: the walkers' mean and lowest.
        chain_in_tau: the chain's length in its longest autocorrelation time.
        converged: at least :data:`CHAIN_TAUS` of them.
        sampling_time_s, time_s: wall time of the sampling and of the whole run, seconds.
        seed: as given.
        prior: per label ``(low, high)``, the uniform prior's support.
        linear_region: per label ``(low, high)``, where the chain may go (:func:`linear_region`).
        hi_walks, bounces: the budget of the linearisation (``"budget"`` in JSON).
        noise: which noise the likelihood uses: ``"file std columns"``, or
            ``"estimated by maximum likelihood with the material: std = relative * |value| + absolute"``
            (a file without them; :class:`NoiseModel`).
        noise_scale: the median estimated standard deviation, else ``None``.
        noise_relative, noise_absolute, noise_log10_sd: the estimated
            :class:`NoiseModel` at the anchor (its levels and the Laplace sd of
            their log10), else ``None``.
        slope_steps: per label, the central-difference step (:func:`slope_steps`).
        chi2_high_budget_at_fit, chi2_high_budget_at_anchor: the linearisations' chi-squares.
        mc_anchor_relative_error: the median relative Monte Carlo error of ``M_hi`` at the anchor.
        mc_anchor_error_over_noise: that error over the measurement noise (median).
        mc_model_error_over_noise: the sampled model's RMS error against independent estimates, over the noise.
        unresolved: the labels along whose directions the slopes at the anchor
            are mostly their own Monte Carlo noise (:func:`unresolved`): the
            chain is flat there within the region, and their intervals are its extent.
    """

    labels: list
    variant: str
    n_points: int
    n_params: int
    walkers: int
    steps: int
    burn: int
    acceptance_fraction: float
    acceptance_fraction_min: float
    chain_in_tau: float
    converged: bool
    sampling_time_s: float
    time_s: float
    seed: int
    prior: dict
    linear_region: dict
    hi_walks: int
    bounces: int
    noise: str
    noise_scale: float | None
    slope_steps: dict
    chi2_high_budget_at_fit: float
    chi2_high_budget_at_anchor: float
    mc_anchor_relative_error: float
    mc_anchor_error_over_noise: float
    mc_model_error_over_noise: float
    noise_relative: float | None = None
    noise_absolute: float | None = None
    noise_log10_sd: list | None = None
    unresolved: list = dataclasses.field(default_factory=list)

    @property
    def interface(self):
        """Whether the material has a top interface (its ``eta`` and ``alpha_s`` are then sampled)."""
        return "eta" in self.labels

    def to_json(self):
        """The ``"record"`` object of ``posterior.json`` (docs/formats.md), keys in this order."""
        return dict(
            labels=list(self.labels), variant=self.variant, n_points=self.n_points, n_params=self.n_params,
            walkers=self.walkers, steps=self.steps, burn=self.burn, acceptance_fraction=self.acceptance_fraction,
            acceptance_fraction_min=self.acceptance_fraction_min, chain_in_tau=self.chain_in_tau,
            converged=self.converged, sampling_time_s=self.sampling_time_s, time_s=self.time_s, seed=self.seed,
            prior={k: list(v) for k, v in self.prior.items()},
            linear_region={k: list(v) for k, v in self.linear_region.items()},
            budget=dict(hi_walks=self.hi_walks, bounces=self.bounces), noise=self.noise,
            noise_scale=self.noise_scale, slope_steps=dict(self.slope_steps),
            chi2_high_budget_at_fit=self.chi2_high_budget_at_fit,
            chi2_high_budget_at_anchor=self.chi2_high_budget_at_anchor,
            mc_anchor_relative_error=self.mc_anchor_relative_error,
            mc_anchor_error_over_noise=self.mc_anchor_error_over_noise,
            mc_model_error_over_noise=self.mc_model_error_over_noise,
            noise_relative=self.noise_relative, noise_absolute=self.noise_absolute,
            noise_log10_sd=self.noise_log10_sd, unresolved=list(self.unresolved),
        )


@dataclasses.dataclass
class Posterior:
    """The outcome of :func:`uncertainty`.

    Attributes:
        labels: parameter names, one per entry of ``v`` (``theta_p`` in degrees).
        summary: per label ``median``, ``p16``, ``p84``, ``p2.5``, ``p97.5``
            (Monte Carlo error included), ``p16_noise_only``, ``p84_noise_only``,
            ``mc_sd``, ``laplace_sd``, ``tau``, ``ess``, ``fit`` (the fitted
            value) and ``anchor`` (the linearisation's).
        correlation: ``(P, P)`` posterior correlations.
        chain: the :class:`Chain` with its diagnostics.
        laplace_cov: ``(P, P)`` the Laplace covariance at the anchor.
        sensitivity: ``(P, N, 3)`` ``dv / dy`` at the anchor.
        record: a :class:`PosteriorRecord`, everything else written to ``posterior.json``
            (budgets, noise, Monte Carlo checks; :meth:`PosteriorRecord.to_json`).
        predictive: ``(D, N, 3)`` the model at ``D`` posterior draws.
        fit: the :class:`~jaxcos.FitResult` the chain started from.
        noise: ``(N, 3)`` the measurement's standard deviation: the file's std
            columns, or the estimated :class:`NoiseModel`'s at its maximum likelihood.
        noise_model: that :class:`NoiseModel`, or ``None`` for a file with std columns.
        mc_cov: ``(P, P)`` the covariance of the parameters' Monte Carlo shift
            (:func:`monte_carlo_spread`); the intervals are percentiles of the
            chain's draws plus such shifts.
        derived: per :func:`derived` quantity (``g_mean`` for a two-lobe
            material) its ``fit``, ``median``, ``p16``, ``p84``, ``p2.5`` and
            ``p97.5`` over the same draws; empty where none applies.
    """

    labels: list
    summary: dict
    correlation: np.ndarray
    chain: Chain
    laplace_cov: np.ndarray
    sensitivity: np.ndarray
    record: PosteriorRecord
    predictive: np.ndarray
    fit: object
    noise: np.ndarray
    mc_cov: np.ndarray
    noise_model: NoiseModel | None = None
    derived: dict = dataclasses.field(default_factory=dict)

    @property
    def converged(self):
        return self.chain.converged

    @property
    def draws(self):
        """``(S, P)`` the chain's samples, the diffusers' lobes labelled so that ``g1 >= g2`` as in the summary
        (the chain itself samples the linearisation's coordinates about the anchor)."""
        return ordered_lobes(self.labels, self.chain.samples)


def uncertainty(meas, fit_result=None, *, seed=0, walkers=None, max_steps=MAX_STEPS, hi_walks=HI_WALKS,
                checks=16, replicas=24, progress=None):
    """Posterior spreads of the parameters of a fit to ``meas``.

    Args:
        meas: from :func:`jaxcos.load_measurements`.
        fit_result: a :class:`~jaxcos.FitResult` of ``meas`` to start from; by
            default :func:`jaxcos.fit` runs first.
        seed: seeds the Monte Carlo keys and the sampler.
        walkers, max_steps: the ensemble (by default :data:`WALKERS`, or
            ``2 P + 2`` for ``P`` parameters where that is more: a two-lobe
            fit with ``t``, ``phi_p`` and an interface has 16) and the longest chain.
        hi_walks: walks per incidence of the linearisation (bounces as in the fit).
        checks: posterior draws at which the sampled model is compared with
            independent high-budget estimates.
        replicas: independent estimates at the anchor whose spread, scaled to ``hi_walks`` walks and
            mapped through the sensitivities, is the parameters' Monte Carlo error.
        progress: ``progress(message)`` told about each stage.

    Returns:
        A :class:`Posterior`.

    Raises:
        InputError: fewer ``walkers`` than ``2 P + 2``.
    """
    say = progress or (lambda msg: None)
    t0 = time.perf_counter()
    if fit_result is None:
        fit_result = fit(meas, seed=seed, progress=progress)
    param = fit_result.param
    low, high = param.bounds()
    # A float32 fit can sit a rounding below a bound that float32 cannot hold (eta 1.01, alpha_s 0.005): the
    # chain's walkers start around the anchor, which must lie in the prior's support.
    v0 = np.clip(np.asarray(param.to_physical(param.ordered_lobes(fit_result.x)), float), low, high)
    estimated = meas.std is None
    if walkers is None:
        walkers = max(WALKERS, 2 * param.size + 2)
    if walkers < 2 * param.size + 2:
        raise InputError(f"walkers must be at least 2 * parameters + 2 = {2 * param.size + 2} for the "
                         f"{param.size} parameters of this fit ({', '.join(param.names)}), not {walkers}.")
    probs = lobe_probabilities(param.physical_to_material(jnp.asarray(v0, jnp.result_type(float))))
    bounces = int(fit_result.record.budget.bounces)
    # (the second key is unused)
    anchor_key, _, check_key, pilot_key = jax.random.split(jax.random.key(seed), 4)
    problem = dataclasses.replace(
        make_problem(meas, param, key=anchor_key, walks=hi_walks, bounces=bounces, lobe_probs=probs),
        thin_after=POSTERIOR_THIN_AFTER)
    if estimated:
        say("estimating the noise (std = relative * |value| + absolute) by maximum likelihood at the fit")
        noise = estimate_noise(fit_result.model - meas.values, meas.values, fit_result.model_std,
                               n_fitted=param.size).std(meas.values)
    else:
        noise = np.asarray(meas.std, float)

    step = slope_steps(problem, v0, noise, key=pilot_key, progress=say)
    at_fit, lin, step = find_anchor(problem, v0, step, noise, meas.values, key=anchor_key,
                                    estimated_noise=estimated, progress=say)
    noise_model = lin.noise_model
    say("Laplace covariance and sensitivities from those slopes")
    cov = laplace(lin.jac, lin.slope_noise)
    sens = sensitivity(lin.jac, lin.sigma.reshape(-1), lin.slope_noise).reshape(param.size, *meas.values.shape)
    laplace_sd = np.sqrt(np.maximum(np.diag(cov), 0.0))
    width = np.where(np.isfinite(laplace_sd) & (laplace_sd > 0), laplace_sd, 1e-3 * (high - low))
    region = linear_region(lin, step, low, high)
    chain, target = sample(lin, region, np.minimum(width, 0.1 * (high - low)), seed=seed, walkers=walkers,
                           max_steps=max_steps, progress=say)
    mc_cov = monte_carlo_spread(problem, lin.anchor, sens, key=check_key, replicas=replicas, progress=say)
    rng = np.random.default_rng(seed + 1)
    summary, derived_summary, corr = summarise(chain, mc_cov, param.labels(), v0, lin, laplace_sd, low, high,
                                               rng=rng)
    predictive, model_error = check_model(target, problem, chain, lin, key=check_key, checks=checks, rng=rng,
                                          progress=say)

    record = _record(meas, param, chain, lin, at_fit, region=region, step=step, noise_model=noise_model,
                     hi_walks=hi_walks, bounces=bounces, seed=seed, model_error=model_error,
                     seconds=time.perf_counter() - t0)
    return Posterior(labels=param.labels(), summary=summary, correlation=corr, chain=chain, laplace_cov=cov,
                     sensitivity=sens, record=record, predictive=predictive, fit=fit_result, noise=lin.noise,
                     mc_cov=mc_cov, noise_model=noise_model, derived=derived_summary)


def _record(meas, param, chain, lin, at_fit, *, region, step, noise_model, hi_walks, bounces, seed, model_error,
            seconds):
    """The :attr:`Posterior.record`: sizes, chain diagnostics, prior and region, budget, noise and Monte Carlo checks."""
    labels = param.labels()
    low, high = param.bounds()
    return PosteriorRecord(
        labels=labels, variant=param.variant, n_points=int(meas.values.shape[0]), n_params=int(param.size),
        walkers=int(chain.walkers), steps=int(chain.steps), burn=int(chain.burn),
        acceptance_fraction=float(np.mean(chain.acceptance)),
        acceptance_fraction_min=float(np.min(chain.acceptance)),
        chain_in_tau=float(chain.steps / np.max(chain.tau)), converged=chain.converged,
        sampling_time_s=round(chain.seconds, 2), time_s=round(seconds, 2), seed=int(seed),
        prior={name: (float(a), float(b)) for name, a, b in zip(labels, low, high)},
        linear_region={name: (float(a), float(b)) for name, a, b in zip(labels, *region)},
        hi_walks=int(hi_walks), bounces=int(bounces),
        noise="file std columns" if noise_model is None else
        "estimated by maximum likelihood with the material: std = relative * |value| + absolute",
        noise_scale=None if noise_model is None else float(np.median(lin.noise)),
        slope_steps={name: float(h) for name, h in zip(labels, step)},
        chi2_high_budget_at_fit=at_fit.chi2, chi2_high_budget_at_anchor=lin.chi2,
        mc_anchor_relative_error=lin.relative_error,
        mc_anchor_error_over_noise=float(np.median(lin.mc / lin.noise)),
        mc_model_error_over_noise=model_error,
        noise_relative=None if noise_model is None else noise_model.relative,
        noise_absolute=None if noise_model is None else noise_model.absolute,
        noise_log10_sd=None if noise_model is None else list(noise_model.sd),
        unresolved=unresolved(lin, step, labels),
    )
