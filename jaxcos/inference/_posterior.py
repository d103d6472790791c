"""Posterior spreads of fitted parameters: emcee, a Laplace cross-check, and sensitivities.

The posterior of the physical parameters ``v`` (the :meth:`Parameterization.labels`
entries: ``c_d``, ``albedo_d[0..2]``, ..., ``theta_p`` in degrees) is

    p(v | y) ∝ U(v; bounds) exp(-1/2 sum ((m(v) - y) / sigma)^2)

with a uniform prior on the physical ranges and a Gaussian likelihood. The
model ``m`` is a Monte Carlo estimate, and with a fixed key its error is not
noise the chain can average. A cheap estimate in the loop makes the posterior
too narrow and biased: the expected loss of a fixed-key estimate is the true
loss plus the estimate's variance, so its error acts as a penalty that grows
away from where it was fixed and pulls towards parameters where the variance
is small. By default the chain therefore samples the *high-budget
linearisation* within the prior's bounds,

    m(v) = M_hi(v0) + J_hi (v - v0),

from one estimate at the anchor ``v0`` (8192 walks per incidence). The
anchor starts at the fit and moves by up to two Gauss-Newton steps towards
the optimum of the last linearisation, where the linearisation is made
again: the fit's own cheap estimate leaves it two or more Laplace widths from
the optimum. Each step is clipped to ``TRUST`` difference steps per parameter,
and kept only if the data fit the new anchor better. The chain stays within
``REGION`` difference steps of the anchor, where the linearisation holds;
the report says when a posterior reaches that edge. The slopes ``J_hi`` are
central differences under common random numbers with steps of half a
posterior width (from a pilot at an eighth of the budget), not forward-mode
derivatives: along the parameters that move
sampled directions (``g1``, ``alpha_p``, ...) the fixed-key estimate has
narrow steep features, its pointwise derivative is heavy-tailed, and
``J^T J`` from it overstated the information about ``g1`` up to six-fold,
depending on the key. ``J_hi`` is the mean of two halves under independent
keys: ``N = D^T D / 4``, with ``D`` their whitened difference, is the
expected share of ``J^T J`` that is the slopes' own noise, and the
log-likelihood adds ``dv^T N dv / 2`` back. The remaining error of ``M_hi``
at ``v0`` is mapped through the sensitivities into a Monte Carlo spread of
the parameters that the reported intervals include.

``lo_walks > 0`` adds the curvature of a cheap estimate (a Taylor control
variate, ``M_lo(v) - M_lo(v0) - J_lo (v - v0)``) for posteriors far from
Gaussian; its coverage is measured in ``benchmarks/RESULTS.md`` and is worse.
The report compares the sampled model at posterior draws with independent
high-budget estimates.

Example::

    import jaxcos
    meas = jaxcos.load_measurements("measurements/matte2.csv")
    post = jaxcos.uncertainty(meas, jaxcos.fit(meas))
    post.summary["alpha_p"]          # median, 16/84 and 2.5/97.5 percentiles
    jaxcos.write_uncertainty(post, meas, "out/matte2_posterior")
"""

import dataclasses
import json
import os
import sys
import time

import emcee
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._errors import InputError, refuse_overwrite, staged_outputs
from ._fit import FIT_BOUNCES, fit, make_problem
from ..model import lobe_probabilities, simulate

UNCERTAINTY_FILES = ("posterior.json", "report.md", "corner.png", "predictive.png", "sensitivity.png")

WALKERS = 32
"""Ensemble size: more than twice the twelve parameters of the two-lobe model."""
MAX_STEPS = 20000
"""The longest chain, in ensemble steps, that :func:`uncertainty` runs by default."""
CHAIN_TAUS = 50
"""A chain shorter than this many integrated autocorrelation times is reported as too short (emcee's rule)."""
LO_WALKS, LO_BOUNCES = 0, 64
"""The budget of the cheap estimate ``M_lo`` evaluated at every step of the chain (0: the linearisation alone)."""
HI_WALKS = 8192
"""Walks per incidence of the value ``M_hi(v0)`` and slopes ``J_hi(v0)`` at the anchor (bounces as in the fit)."""
ANCHORS = 3
"""Linearisations made at most: at the fit, then after each Gauss-Newton step towards the last one's optimum
(kept while the data fit better)."""
TRUST = 4.0
"""The longest Gauss-Newton step of the anchor, per parameter, in central-difference steps (two pilot sd)."""
REGION = 16.0
"""Half-width of the region the chain may explore around the anchor, per parameter, in central-difference
steps (eight pilot sd, or the whole prior for a parameter the data hardly constrain)."""


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
    sampler._random = np.random.mtrand.RandomState(int(rng.integers(2 ** 31)))
    t0 = time.perf_counter()
    state = emcee.State(start, log_prob=lp)
    tau = np.full(n_par, np.inf)
    steps = 0
    while steps < max_steps:
        n = min(check_every, max_steps - steps)
        state = sampler.run_mcmc(state, n, progress=False)
        steps += n
        tau = _tau(sampler)
        if progress:
            progress(f"{steps} steps; autocorrelation time up to {np.max(tau):.0f} steps "
                     f"({steps / np.max(tau):.0f} of the {CHAIN_TAUS} needed)")
        if steps >= CHAIN_TAUS * np.max(tau):
            break
    seconds = time.perf_counter() - t0
    tau_max = float(np.max(tau))
    burn = int(min(np.ceil(3 * tau_max), steps // 2))
    tau = _tau(sampler, burn)
    samples = sampler.get_chain(discard=burn, flat=True)
    ess = walkers * (steps - burn) / tau
    return Chain(samples=samples, tau=tau, steps=steps, burn=burn, walkers=walkers,
                 acceptance=np.asarray(sampler.acceptance_fraction), ess=ess,
                 converged=bool(steps >= CHAIN_TAUS * np.max(tau)), seconds=seconds)


def _tau(sampler, discard=0):
    """Integrated autocorrelation times; emcee's estimate without its length check (reported instead)."""
    import logging

    chain = sampler.get_chain(discard=discard)
    logger = logging.getLogger("emcee.autocorr")
    level = logger.level
    logger.setLevel(logging.ERROR)  # the length check is reported by the caller, not logged per parameter
    try:
        return np.array([emcee.autocorr.integrated_time(chain[:, :, i], quiet=True)[0]
                         for i in range(chain.shape[2])])
    finally:
        logger.setLevel(level)


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


class _Target(eqx.Module):
    """The control-variate model and Gaussian log-likelihood with a uniform prior.

    ``model(v) = M_lo(v) + [M_hi(v0) - M_lo(v0)] + [J_hi(v0) - J_lo(v0)] (v - v0)``: the
    value and slope at ``v0`` are the high-budget ones; the cheap estimate
    contributes only its curvature, whose error vanishes to second order at ``v0``.
    """

    param: object
    query: object
    measured: jnp.ndarray
    sigma: jnp.ndarray
    anchor: jnp.ndarray
    slope: jnp.ndarray
    jac_noise: jnp.ndarray
    v0: jnp.ndarray
    key: jnp.ndarray
    lobe_probs: jnp.ndarray
    low: jnp.ndarray
    high: jnp.ndarray
    scale: float = eqx.field(static=True)
    walks: int = eqx.field(static=True)
    bounces: int = eqx.field(static=True)

    def model(self, v):
        """The model in the file's quantity, ``(N, 3)``."""
        if self.walks == 0:  # the linearisation alone
            return self.anchor + self.slope @ (v - self.v0)
        return self.scale * _estimate(self, v).f + self.anchor + self.slope @ (v - self.v0)

    def log_prob(self, v):
        inside = jnp.all((v >= self.low) & (v <= self.high))
        r = (self.model(jnp.clip(v, self.low, self.high)) - self.measured) / self.sigma
        d = jnp.clip(v, self.low, self.high) - self.v0
        return jnp.where(inside, -0.5 * jnp.sum(r * r) + 0.5 * d @ self.jac_noise @ d, -jnp.inf)


def _estimate(problem, v):
    """The estimate at the physical values ``v`` under the key, budget and lobe probabilities of ``problem``."""
    return simulate(problem.param.physical_to_material(v), problem.query, problem.key, walks=problem.walks,
                    bounces=problem.bounces, lobe_probs=problem.lobe_probs, connection=problem.connection)


@eqx.filter_jit
def _batch_estimate(problem, vs):
    return jax.vmap(lambda v: _estimate(problem, v))(vs)


def _first_steps(param, v):
    """Pilot finite-difference steps: 1% of each parameter's range, 5% of the value for ``alpha_p`` and ``t``."""
    low, high = param.bounds()
    step = 0.01 * (high - low)
    i = 0
    for name, part in param._split(np.asarray(v, float)):
        if name in ("alpha_p", "t"):
            step[i:i + part.shape[0]] = 0.05 * np.abs(part)
        i += part.shape[0]
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


@eqx.filter_jit
def _batch_log_prob(target, vs):
    return jax.vmap(target.log_prob)(vs)


@eqx.filter_jit
def _batch_model(target, vs):
    return jax.vmap(target.model)(vs)


def _in_batches(fn, batch, dtype):
    """``fn`` on any number of rows, called on batches of exactly ``batch`` rows (one compilation)."""

    def call(vs):
        vs = np.asarray(vs, float)
        n = vs.shape[0]
        padded = np.concatenate([vs, np.repeat(vs[-1:], (-n) % batch, axis=0)])
        out = [np.asarray(fn(jnp.asarray(padded[i:i + batch], dtype)), float) for i in range(0, padded.shape[0], batch)]
        return np.concatenate(out)[:n]

    return call


@dataclasses.dataclass
class Posterior:
    """The outcome of :func:`uncertainty`.

    Attributes:
        labels: parameter names, one per entry of ``v`` (``theta_p`` in degrees).
        summary: per label ``median``, ``p16``, ``p84``, ``p2.5``, ``p97.5``
            (Monte Carlo error included), ``p16_noise_only``, ``p84_noise_only``,
            ``mc_sd``, ``laplace_sd``, ``tau``, ``ess`` and ``fit`` (the fitted value).
        correlation: ``(P, P)`` posterior correlations.
        chain: the :class:`Chain` with its diagnostics.
        laplace_cov: ``(P, P)`` the Laplace covariance at the fit.
        sensitivity: ``(P, N, 3)`` ``dv / dy`` at the fit.
        record: everything else written to ``posterior.json`` (budgets, noise, Monte Carlo checks).
        predictive: ``(D, N, 3)`` the model at ``D`` posterior draws.
        fit: the :class:`~jaxcos.FitResult` the chain started from.
    """

    labels: list
    summary: dict
    correlation: np.ndarray
    chain: Chain
    laplace_cov: np.ndarray
    sensitivity: np.ndarray
    record: dict
    predictive: np.ndarray
    fit: object

    @property
    def converged(self):
        return self.chain.converged


def uncertainty(meas, fit_result=None, *, seed=0, walkers=WALKERS, max_steps=MAX_STEPS, lo_walks=LO_WALKS,
                lo_bounces=LO_BOUNCES, hi_walks=HI_WALKS, checks=16, replicas=24, progress=None):
    """Posterior spreads of the parameters of a fit to ``meas``.

    Args:
        meas: from :func:`jaxcos.load_measurements`.
        fit_result: a :class:`~jaxcos.FitResult` of ``meas`` to start from; by
            default :func:`jaxcos.fit` runs first.
        seed: seeds the Monte Carlo keys and the sampler.
        walkers, max_steps: the ensemble and the longest chain.
        lo_walks, lo_bounces: budget of a cheap estimate whose curvature is
            added to the linearisation at each step; ``0`` (the default)
            samples the high-budget linearisation alone.
        hi_walks: walks per incidence of the anchor at the fit (bounces as in the fit).
        checks: posterior draws at which the control-variate model is compared
            with independent high-budget estimates.
        replicas: independent high-budget estimates at the fit whose spread,
            mapped through the sensitivities, is the parameters' Monte Carlo error.
        progress: ``progress(message)`` told about each stage.

    Returns:
        A :class:`Posterior`.
    """
    say = progress or (lambda msg: None)
    t0 = time.perf_counter()
    if fit_result is None:
        fit_result = fit(meas, seed=seed, progress=progress)
    param = fit_result.param
    labels = param.labels()
    v0 = np.asarray(param.to_physical(fit_result.x), float)
    low, high = param.bounds()
    material = param.physical_to_material(jnp.asarray(v0, jnp.result_type(float)))
    probs = lobe_probabilities(material)
    bounces = int(fit_result.record.get("bounces", FIT_BOUNCES))
    dtype = jnp.result_type(float)

    keys = jax.random.split(jax.random.key(seed), 4)
    hi = make_problem(meas, param, key=keys[0], walks=hi_walks, bounces=bounces, lobe_probs=probs)
    lo = make_problem(meas, param, key=keys[1], walks=lo_walks, bounces=lo_bounces, lobe_probs=probs)
    n_res = meas.values.size
    if meas.std is not None:
        noise = np.asarray(meas.std, float)
        noise_scale = None
    else:  # one noise level for the whole file, from the residuals at the fit
        resid = fit_result.model - meas.values
        noise_scale = float(np.sqrt(np.sum(resid ** 2) / max(n_res - param.size, 1)))
        noise = np.full_like(meas.values, noise_scale)

    # Steps of half a posterior width, from a pilot at an eighth of the budget.
    say(f"slopes at the fit by central differences: a pilot with {max(hi_walks // 8, 1)} walks per incidence")
    first = _first_steps(param, v0)
    pilot = dataclasses.replace(hi, key=keys[3], walks=max(hi_walks // 8, 1))
    _, jac_pilot, _ = _value_and_secants(pilot, v0, first)
    pilot_sd = np.sqrt(np.maximum(np.diag(laplace((jac_pilot / noise[..., None]).reshape(-1, param.size))), 0.0))
    step = np.clip(0.5 * pilot_sd, 0.01 * first, np.minimum(10 * first, 0.25 * (high - low)))

    # The fit's own estimate is cheap and biased towards parameters where its
    # Monte Carlo variance is small: Gauss-Newton steps on the high-budget
    # linearisation move the anchor towards that linearisation's optimum.
    def linearise(at, rank):
        say(f"value and slopes at {'the fit' if rank == 0 else 'a refined anchor'} with {hi_walks} walks "
            "per incidence")
        # Two halves under independent keys: their mean is the estimate, their
        # difference measures the slopes' own noise, which J^T J would count as information.
        halves = [_value_and_secants(dataclasses.replace(hi, key=k, walks=max(hi_walks // 2, 1)), at, step)
                  for k in jax.random.split(jax.random.fold_in(keys[0], rank))]
        m_hi = 0.5 * (halves[0][0] + halves[1][0])
        jac_hi = 0.5 * (halves[0][1] + halves[1][1])
        est_hi = halves[0][2]
        rel_hi = float(np.median(np.asarray(est_hi.stderr) / np.maximum(np.abs(np.asarray(est_hi.f)), 1e-12)))
        rel_hi /= np.sqrt(2.0)
        sigma = np.sqrt(noise ** 2 + (rel_hi * m_hi) ** 2)
        diff = ((halves[0][1] - halves[1][1]) / sigma[..., None]).reshape(-1, param.size)
        jac_noise = 0.25 * diff.T @ diff  # E[J^T J] - J_true^T J_true for the mean of the halves
        jac_v = (jac_hi / sigma[..., None]).reshape(-1, param.size)
        resid = ((m_hi - meas.values) / sigma).reshape(-1)
        return dict(at=at, m_hi=m_hi, jac_hi=jac_hi, rel_hi=rel_hi, sigma=sigma, jac_noise=jac_noise, jac_v=jac_v,
                    resid=resid, chi2=float(resid @ resid))

    lin = linearise(v0, 0)
    chi2_at_fit = lin["chi2"]
    for rank in range(1, ANCHORS):
        # A Gauss-Newton step to the linearisation's optimum, kept where the
        # linearisation holds (TRUST steps of the differences per parameter: an
        # unidentified direction would otherwise send it across the prior) and
        # off the bounds (the walkers' starting ball must be inside the prior).
        move = -laplace(lin["jac_v"], lin["jac_noise"]) @ lin["jac_v"].T @ lin["resid"]
        move = np.clip(move, -TRUST * step, TRUST * step)
        margin = 1e-3 * (high - low)
        trial = linearise(np.clip(lin["at"] + move, low + margin, high - margin), rank)
        if trial["chi2"] >= lin["chi2"]:
            break
        lin = trial
    anchor, m_hi, jac_hi, rel_hi, sigma, jac_noise, jac_v = (
        lin[k] for k in ("at", "m_hi", "jac_hi", "rel_hi", "sigma", "jac_noise", "jac_v"))
    v0j = jnp.asarray(anchor, dtype)
    # The linearisation holds near its anchor only: the chain stays within REGION
    # difference steps of it, and the report says when the posterior reaches that edge.
    box_low, box_high = np.maximum(low, anchor - REGION * step), np.minimum(high, anchor + REGION * step)
    if lo_walks:
        m_lo, jac_lo, _ = _value_and_secants(lo, anchor, step)
    else:
        m_lo, jac_lo = np.zeros_like(m_hi), np.zeros_like(jac_hi)
    target = _Target(param=param, query=lo.query, measured=jnp.asarray(meas.values, dtype),
                     sigma=jnp.asarray(sigma, dtype), anchor=jnp.asarray(m_hi - m_lo, dtype),
                     slope=jnp.asarray(jac_hi - jac_lo, dtype), jac_noise=jnp.asarray(jac_noise, dtype), v0=v0j,
                     key=keys[1],
                     lobe_probs=jnp.asarray(probs, dtype), low=jnp.asarray(box_low, dtype),
                     high=jnp.asarray(box_high, dtype),
                     scale=lo.scale, walks=lo_walks, bounces=lo_bounces)

    say("Laplace covariance and sensitivities from those slopes")
    cov = laplace(jac_v, jac_noise)
    sens = sensitivity(jac_v, sigma.reshape(-1), jac_noise).reshape(param.size, *meas.values.shape)
    laplace_sd = np.sqrt(np.maximum(np.diag(cov), 0.0))

    rng = np.random.default_rng(seed + 1)
    say(f"sampling with {walkers} walkers (emcee, differential-evolution moves)")
    log_prob = _in_batches(lambda vs: _batch_log_prob(target, vs), walkers // 2, dtype)
    width = np.where(np.isfinite(laplace_sd) & (laplace_sd > 0), laplace_sd, 1e-3 * (high - low))
    width = np.minimum(width, 0.1 * (high - low))
    chain = run_ensemble(log_prob, anchor, width, seed=seed, walkers=walkers, max_steps=max_steps,
                         progress=say)

    say(f"propagating the Monte Carlo error of the anchor: {replicas} independent estimates at the fit")
    reps = np.stack([hi.scale * np.asarray(_estimate(dataclasses.replace(hi, key=k), v0j).f, float)
                     for k in jax.random.split(keys[2], replicas)])
    shifts = (reps - reps.mean(axis=0)).reshape(replicas, -1) @ sens.reshape(param.size, -1).T
    mc_cov = np.atleast_2d(np.cov(shifts.T))
    # The chain samples the posterior of one fixed-key estimate of the model; a
    # different key would shift it by a draw of the Monte Carlo error mapped
    # through the sensitivities. The reported spreads include that shift.
    shift = rng.multivariate_normal(np.zeros(param.size), mc_cov, size=chain.samples.shape[0], method="eigh")
    samples = np.clip(chain.samples + shift, low, high)
    q = np.percentile(samples, [2.5, 16, 50, 84, 97.5], axis=0)
    q_noise = np.percentile(chain.samples, [16, 84], axis=0)
    summary = {}
    for i, name in enumerate(labels):
        summary[name] = dict(fit=float(v0[i]), anchor=float(anchor[i]), median=float(q[2, i]),
                             p16=float(q[1, i]), p84=float(q[3, i]),
                             **{"p2.5": float(q[0, i]), "p97.5": float(q[4, i])},
                             p16_noise_only=float(q_noise[0, i]), p84_noise_only=float(q_noise[1, i]),
                             mc_sd=float(np.sqrt(mc_cov[i, i])), laplace_sd=float(laplace_sd[i]),
                             tau=float(chain.tau[i]), ess=float(chain.ess[i]))
    corr = np.corrcoef(samples.T) if samples.shape[0] > 1 else np.eye(param.size)

    say(f"checking the control-variate model at {checks} posterior draws against independent estimates")
    draws = chain.samples[rng.choice(samples.shape[0], size=min(max(checks, 64), samples.shape[0]), replace=False)]
    predictive = _in_batches(lambda vs: _batch_model(target, vs), walkers // 2, dtype)(draws)
    check = dataclasses.replace(hi, key=keys[2])
    indep = np.stack([hi.scale * np.asarray(_estimate(check, jnp.asarray(d, dtype)).f) for d in draws[:checks]])
    # The independent estimate has an error of its own, as large as the anchor's;
    # what the discrepancy has beyond it is the error of the sampled model.
    disc2 = np.mean(((predictive[:checks] - indep) / noise) ** 2)
    model_error = float(np.sqrt(max(disc2 - np.mean((rel_hi * m_hi / noise) ** 2), 0.0)))

    record = dict(
        labels=labels, variant=param.variant, n_points=int(meas.values.shape[0]), n_params=int(param.size),
        walkers=int(chain.walkers), steps=int(chain.steps), burn=int(chain.burn),
        acceptance_fraction=float(np.mean(chain.acceptance)),
        acceptance_fraction_min=float(np.min(chain.acceptance)),
        chain_in_tau=float(chain.steps / np.max(chain.tau)), converged=chain.converged,
        sampling_time_s=round(chain.seconds, 2), time_s=round(time.perf_counter() - t0, 2), seed=int(seed),
        prior={name: [float(a), float(b)] for name, a, b in zip(labels, low, high)},
        linear_region={name: [float(a), float(b)] for name, a, b in zip(labels, box_low, box_high)},
        budget=dict(lo_walks=int(lo_walks), lo_bounces=int(lo_bounces), hi_walks=int(hi_walks), bounces=bounces),
        noise="file std columns" if noise_scale is None else "estimated from the fit's residuals",
        noise_scale=noise_scale,
        slope_steps={name: float(h) for name, h in zip(labels, step)},
        chi2_high_budget_at_fit=chi2_at_fit, chi2_high_budget_at_anchor=lin["chi2"],
        mc_anchor_relative_error=rel_hi,
        mc_anchor_error_over_noise=float(np.median(rel_hi * m_hi / noise)),
        mc_model_error_over_noise=model_error,
    )
    return Posterior(labels=labels, summary=summary, correlation=corr, chain=chain, laplace_cov=cov,
                     sensitivity=sens, record=record, predictive=predictive, fit=fit_result)


def start_from_params(meas, path, *, seed=0, progress=None):
    """A :class:`~jaxcos.FitResult` of ``meas`` refined by Levenberg-Marquardt from the params.json at ``path``.

    The fitted set of parameters (``t``, ``phi_p``) follows the file's
    ``"fit"`` record when it has one.
    """
    from ..io import load_params

    material = load_params(path)
    with open(path, encoding="utf-8") as fh:
        fitted = json.load(fh).get("fit", {}).get("fitted", [])
    return fit(meas, variant=material.variant, seed=seed, start=material, fit_t="t" in fitted,
               fit_phi="phi_p" in fitted, t=float(material.layers[0].t), progress=progress)


# --- what it writes -------------------------------------------------------------------


def _json_safe(x):
    if isinstance(x, dict):
        return {k: _json_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple, np.ndarray)):
        return [_json_safe(v) for v in np.asarray(x, dtype=object).tolist()] if np.ndim(x) else _json_safe(x.item())
    if isinstance(x, (bool, np.bool_)):
        return bool(x)
    if isinstance(x, (int, np.integer)):
        return int(x)
    if isinstance(x, (float, np.floating)):
        return float(x) if np.isfinite(x) else None
    return x


def _laplace_notes(post):
    """One sentence per parameter where the Laplace spread and the chain's disagree, or the prior cuts the posterior."""
    notes = []
    prior = post.record["prior"]
    region = post.record["linear_region"]
    for name, s in post.summary.items():
        half = 0.5 * (s["p84_noise_only"] - s["p16_noise_only"])
        low, high = prior[name]
        span = high - low
        a, b = region[name]
        if (a > low and s["p2.5"] <= a + 1e-3 * span) or (b < high and s["p97.5"] >= b - 1e-3 * span):
            notes.append(f"`{name}`: the posterior reaches the edge of the region [{a:.4g}, {b:.4g}] where the "
                         "model is linearised; the fit is far from the optimum of the high-budget model. Refit "
                         "with more walks (`jaxcos fit --walks 4096`) and pass it with `--params`.")
        elif s["p2.5"] <= low + 1e-3 * span or s["p97.5"] >= high - 1e-3 * span:
            notes.append(f"`{name}`: the posterior reaches the edge of its prior [{low:g}, {high:g}]; "
                         "the Gaussian approximation does not apply.")
        elif not np.isfinite(s["laplace_sd"]) or s["laplace_sd"] > 0.5 * span:
            notes.append(f"`{name}`: the Jacobian barely constrains it (Laplace sd {s['laplace_sd']:.3g}); "
                         "the data hardly identify it.")
        elif half > 0 and not 2 / 3 <= half / s["laplace_sd"] <= 3 / 2:
            notes.append(f"`{name}`: chain half-width {half:.3g} against Laplace sd {s['laplace_sd']:.3g}; "
                         "the posterior is not Gaussian at this scale.")
    return notes


def uncertainty_report(post, meas):
    """The human-readable ``report.md`` of a :class:`Posterior`."""
    r = post.record
    c = post.chain
    lines = [
        f"# Posterior spreads for {os.path.basename(meas.path) or 'measurements'}",
        "",
        f"Variant `{r['variant']}`, {r['n_points']} points x 3 channels, {r['n_params']} parameters, "
        f"uniform priors on their physical ranges, Gaussian likelihood ({r['noise']}"
        + (f": {r['noise_scale']:.4g}" if r["noise_scale"] is not None else "") + ").",
        "",
    ]
    if not post.converged:
        lines += [f"**The chain is too short:** {c.steps} steps are {r['chain_in_tau']:.1f} autocorrelation times; "
                  f"{CHAIN_TAUS} are needed for reliable spreads. Run longer (`--steps`).", ""]
    lines += [
        "## Parameters",
        "",
        "Intervals include the Monte Carlo error of the model (column `MC sd`); `68% (noise only)` is the chain's "
        "own interval for one fixed-key estimate of the model.",
        "",
        "| parameter | fit | median | 68% | 95% | 68% (noise only) | MC sd | Laplace sd | tau | ESS |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name, s in post.summary.items():
        lines.append(f"| `{name}` | {s['fit']:.4g} | {s['median']:.4g} | [{s['p16']:.4g}, {s['p84']:.4g}] | "
                     f"[{s['p2.5']:.4g}, {s['p97.5']:.4g}] | [{s['p16_noise_only']:.4g}, {s['p84_noise_only']:.4g}] | "
                     f"{s['mc_sd']:.3g} | {s['laplace_sd']:.3g} | {s['tau']:.0f} | {s['ess']:.0f} |")
    notes = _laplace_notes(post)
    lines += ["", "## Laplace cross-check", "",
              "The Laplace spread is `(J^T J - N)^-1` at the anchor, with `J` the slopes of the high-budget "
              "estimate (central "
              "differences over half a posterior width, under common random numbers; the forward-mode Jacobian of "
              "the fit is heavy-tailed in the direction parameters) and `N` their own noise. "
              + ("Where it disagrees with the chain:" if notes else "It agrees with the chain within a factor 1.5 "
                 "for every parameter."), ""]
    lines += [f"- {n}" for n in notes]
    pairs = [(abs(post.correlation[i, j]), i, j) for i in range(len(post.labels)) for j in range(i)]
    strong = [p for p in sorted(pairs, reverse=True) if p[0] >= 0.7][:6]
    if strong:
        lines += ["", "Strongest posterior correlations: " + ", ".join(
            f"`{post.labels[i]}`-`{post.labels[j]}` {post.correlation[i, j]:+.2f}" for _, i, j in strong) + "."]
    lines += [
        "", "## Diagnostics", "",
        "| quantity | value |", "|---|---|",
        f"| walkers x steps | {c.walkers} x {c.steps} (burn-in {c.burn} discarded) |",
        f"| chain length in autocorrelation times | {r['chain_in_tau']:.1f} (needed: {CHAIN_TAUS}) |",
        f"| acceptance fraction | {r['acceptance_fraction']:.2f} (lowest walker {r['acceptance_fraction_min']:.2f}) |",
        f"| smallest effective sample size | {np.min(c.ess):.0f} |",
        f"| sampling time | {r['sampling_time_s']:.0f} s (total {r['time_s']:.0f} s) |",
        "", "## Monte Carlo error of the model", "",
        (f"The chain evaluates the linearisation of one estimate at the anchor ({r['budget']['hi_walks']} walks x "
         f"{r['budget']['bounces']} bounces; slopes by central differences), within the region given in "
         "`posterior.json` (`linear_region`). " if not r["budget"]["lo_walks"] else
         f"The chain evaluates a Taylor control variate: value and slopes at the anchor from "
         f"{r['budget']['hi_walks']} walks x {r['budget']['bounces']} bounces, curvature from "
         f"{r['budget']['lo_walks']} walks x {r['budget']['lo_bounces']} bounces under one fixed key. ")
        + f"High-budget chi-square at the fit {r['chi2_high_budget_at_fit']:.1f}, at the anchor "
        f"{r['chi2_high_budget_at_anchor']:.1f}. "
        f"Median error of the anchor relative to the measurement noise: {r['mc_anchor_error_over_noise']:.2f} (included "
        f"in the likelihood). RMS error of the sampled model at posterior draws, against independent estimates: "
        f"{r['mc_model_error_over_noise']:.2f} of the noise. Its effect on the parameters, the `MC sd` column, comes "
        "from independent estimates at the fit mapped through the sensitivities; the intervals include it.",
        "", "![corner plot](corner.png)", "", "![posterior predictive](predictive.png)", "",
        "## What each measurement constrains", "",
        "`sensitivity.png`: for each parameter, the change of its fitted value when one measured value moves by "
        "its standard deviation (summed over r, g, b), by implicit differentiation of the optimum.",
        "", "![sensitivities](sensitivity.png)", "",
    ]
    return "\n".join(lines)


def _corner(post, path):
    import corner
    import matplotlib

    matplotlib.use("Agg", force=False)
    thin = max(int(np.max(post.chain.tau) / 2), 1)
    samples = post.chain.samples[::thin]
    fig = corner.corner(samples, labels=post.labels, truths=[s["fit"] for s in post.summary.values()],
                        quantiles=[0.16, 0.5, 0.84], label_kwargs=dict(fontsize=8))
    fig.savefig(path, dpi=70)


def _predictive(post, meas, path, slices=4):
    from matplotlib.figure import Figure

    rows = np.unique(meas.theta_i)
    pick = rows[np.unique(np.linspace(0, rows.size - 1, min(slices, rows.size)).round().astype(int))]
    fig = Figure(figsize=(4 * pick.size, 3.4), constrained_layout=True)
    axes = np.atleast_1d(fig.subplots(1, pick.size))
    lo, hi = np.percentile(post.predictive, [2.5, 97.5], axis=0)
    unit = "reflectance factor" if meas.quantity == "reflectance_factor" else "BRDF (1/sr)"
    for ax, ti in zip(axes, pick):
        sel = np.flatnonzero(meas.theta_i == ti)
        sel = sel[np.argsort(meas.theta_o[sel])]
        to = meas.theta_o[sel]
        for ch, colour in enumerate(("tab:red", "tab:green", "tab:blue")):
            ax.fill_between(to, lo[sel, ch], hi[sel, ch], color=colour, alpha=0.3, lw=0)
            err = None if meas.std is None else meas.std[sel, ch]
            ax.errorbar(to, meas.values[sel, ch], yerr=err, fmt=".", color=colour, ms=3, lw=0.8)
        ax.set_title(f"theta_i = {ti:g} deg")
        ax.set_xlabel("theta_o (deg)")
        ax.set_ylabel(unit)
    fig.suptitle("measured (points, 1 std) and 95% band of the posterior model")
    fig.savefig(path, dpi=90)


def _sensitivity_maps(post, meas, path):
    from matplotlib.figure import Figure

    from ..io._plot import _edges

    rows, cols = np.unique(meas.theta_i), np.unique(meas.theta_o)
    std = meas.std if meas.std is not None else np.full_like(meas.values, post.record["noise_scale"])
    n = len(post.labels)
    ncol = min(n, 4)
    fig = Figure(figsize=(4 * ncol, 2.8 * -(-n // ncol)), constrained_layout=True)
    axes = np.atleast_1d(fig.subplots(-(-n // ncol), ncol)).ravel()
    ri = np.searchsorted(rows, meas.theta_i)
    ci = np.searchsorted(cols, meas.theta_o)
    for ax, name, sens in zip(axes, post.labels, post.sensitivity):
        grid = np.full((rows.size, cols.size), np.nan)
        grid[ri, ci] = np.sum(sens * std, axis=1)
        scale = np.nanmax(np.abs(grid)) or 1.0
        mesh = ax.pcolormesh(_edges(cols), _edges(rows, half=2.5), grid, cmap="coolwarm", vmin=-scale, vmax=scale)
        ax.set_ylim(ax.get_ylim()[::-1])
        ax.set_facecolor("0.85")
        ax.set_title(name, fontsize=9)
        ax.set_xlabel("theta_o (deg)", fontsize=8)
        ax.set_ylabel("theta_i (deg)", fontsize=8)
        fig.colorbar(mesh, ax=ax, shrink=0.8)
    for ax in axes[n:]:
        ax.set_visible(False)
    fig.savefig(path, dpi=80)


def write_uncertainty(post, meas, out_dir, *, force=False):
    """Write ``posterior.json``, ``report.md``, ``corner.png``, ``predictive.png`` and ``sensitivity.png``.

    Written into a temporary folder first and moved in at the end; existing
    files are kept unless ``force``.
    """
    c = post.chain
    data = dict(
        parameters=post.summary,
        correlation=dict(labels=post.labels, matrix=post.correlation),
        laplace=dict(labels=post.labels, covariance=post.laplace_cov),
        diagnostics=dict(tau=dict(zip(post.labels, c.tau)), ess=dict(zip(post.labels, c.ess)), steps=c.steps,
                         burn=c.burn, walkers=c.walkers, chain_in_tau=post.record["chain_in_tau"],
                         acceptance_fraction=post.record["acceptance_fraction"], converged=c.converged,
                         required_chain_in_tau=CHAIN_TAUS),
        record=post.record,
        fit=post.fit.record,
    )
    with staged_outputs(out_dir, UNCERTAINTY_FILES, force) as tmp:
        with open(os.path.join(tmp, "posterior.json"), "w", encoding="utf-8") as fh:
            json.dump(_json_safe(data), fh, indent=1)
        with open(os.path.join(tmp, "report.md"), "w", encoding="utf-8") as fh:
            fh.write(uncertainty_report(post, meas))
        _corner(post, os.path.join(tmp, "corner.png"))
        _predictive(post, meas, os.path.join(tmp, "predictive.png"))
        _sensitivity_maps(post, meas, os.path.join(tmp, "sensitivity.png"))
    return [os.path.join(out_dir, name) for name in UNCERTAINTY_FILES]


# --- the command ----------------------------------------------------------------------


def _cmd(args):
    from ..cli._main import progress
    from ..io import load_measurements

    say = progress("uncertainty")

    if args.walkers < 4 or args.steps < 1:
        raise InputError("--walkers must be at least 4 and --steps at least 1.")
    refuse_overwrite([os.path.join(args.out, name) for name in UNCERTAINTY_FILES], args.force)
    meas = load_measurements(args.measurements)
    if args.params:
        if not os.path.isfile(args.params):
            raise InputError(f"{args.params}: no such file.")
        start = start_from_params(meas, args.params, seed=args.seed, progress=say)
    else:
        start = fit(meas, seed=args.seed, progress=say)
    post = uncertainty(meas, start, seed=args.seed, walkers=args.walkers, max_steps=args.steps, progress=say)
    paths = write_uncertainty(post, meas, args.out, force=args.force)
    worst = min(post.summary, key=lambda k: post.summary[k]["ess"])
    print(f"sampled {post.chain.walkers} walkers x {post.chain.steps} steps in {post.record['sampling_time_s']:.0f} s: "
          f"chain {post.record['chain_in_tau']:.1f} autocorrelation times long, smallest effective sample size "
          f"{post.summary[worst]['ess']:.0f} ({worst}). Wrote {', '.join(paths)}.")
    if not post.converged:
        print(f"jaxcos uncertainty: the chain is shorter than {CHAIN_TAUS} autocorrelation times; its spreads are "
              "not reliable (run longer with --steps).", file=sys.stderr)
        return 3
    return 0


def add_command(sub):
    """Register ``jaxcos uncertainty``."""
    p = sub.add_parser("uncertainty", help="posterior spreads of a fit's parameters (emcee)",
                       description="Sample the posterior of the parameters of a fit to MEASUREMENTS.csv with emcee, "
                       "starting from a fit (run first unless --params gives one); writes DIR/posterior.json, "
                       "DIR/report.md, DIR/corner.png, DIR/predictive.png and DIR/sensitivity.png. Exit status 3 "
                       "means the chain was too short for its autocorrelation time.")
    p.add_argument("measurements", metavar="MEASUREMENTS.csv")
    p.add_argument("--out", required=True, metavar="DIR")
    p.add_argument("--params", metavar="FIT.json", help="start from this params.json (refined by a short fit)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--walkers", type=int, default=WALKERS, help=f"ensemble size (default {WALKERS})")
    p.add_argument("--steps", type=int, default=MAX_STEPS,
                   help=f"longest chain in steps (default {MAX_STEPS}); it stops at {CHAIN_TAUS} autocorrelation times")
    p.add_argument("--force", action="store_true", help="overwrite an existing result in DIR")
    p.set_defaults(func=_cmd)
