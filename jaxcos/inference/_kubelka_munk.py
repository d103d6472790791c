"""The fit of the Kubelka-Munk baseline of Huang et al. 2013 (docs/model.md section 6) by Levenberg-Marquardt.

The model, :class:`jaxcos.KubelkaMunk`, is a Kubelka-Munk layer of scattering
``S`` and absorption ``K`` per unit length and thickness ``X`` over a
substrate, plus a Kelemen/Szirmay-Kalos specular lobe (Beckmann roughness
``m``, Schlick's ``F0``); its formulas are in :mod:`jaxcos.model`.

A fit uses the unbounded coordinates ``x = (logit R_inf[3], log(S X)[3],
logit m', logit F0)`` with ``R_inf = a - b`` the reflectance of an infinitely
thick layer, ``m = 1e-3 + (1 - 1e-3) m'``: ``K / S = (1 - R_inf)^2 / (2 R_inf)``,
``a = (1 + R_inf^2) / (2 R_inf)`` and ``b = (1 - R_inf^2) / (2 R_inf)`` are then
smooth in ``x`` and every iterate is physical. Only the products ``S X``
and ``K X`` are seen by a reflectance measurement, so a fit reports ``S``
and ``K`` per unit thickness of the layer (``X = 1``).

The residuals are ``(model - measured) / std`` in the file's quantity
(``pi f`` for a reflectance factor), ``std = 1`` when the file has none
(docs/formats.md).

Example::

    import jaxcos
    meas = jaxcos.load_measurements("measurements/matte2.csv")
    result = jaxcos.fit_kubelka_munk(meas)
    result.material, result.record.l2
"""

import dataclasses
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from .._errors import InputError
from ..model import KubelkaMunk, directions, km_remission
from ._fit import FitSummary, WeightedLeastSquares, fit_statistics

KM_PARAMETERS = ("r_inf", "sx", "roughness", "f0")
"""Fitted parameters of the Kubelka-Munk baseline, in the order of ``x``."""
KM_N_PARAMS = 8
"""Their count: ``R_inf`` and ``S X`` per channel, the Beckmann roughness, Schlick's ``F0``."""
_ROUGH_MIN = 1e-3  # Beckmann m = 0 is a mirror with no width


def _asarray(x):
    return jnp.asarray(x, dtype=jnp.result_type(float))


# --- coordinates ----------------------------------------------------------------------


def km_from_x(x, substrate=0.0):
    """The :class:`KubelkaMunk` (thickness 1) at the unbounded fit coordinates ``x`` (8,) (module docstring)."""
    r_inf = jax.nn.sigmoid(x[0:3])
    s = jnp.exp(x[3:6])
    return KubelkaMunk(scattering=s, absorption=s * km_remission(r_inf), thickness=1.0,
                       roughness=_ROUGH_MIN + (1.0 - _ROUGH_MIN) * jax.nn.sigmoid(x[6]), f0=jax.nn.sigmoid(x[7]),
                       substrate=substrate)


def _logit(v):
    v = np.clip(np.asarray(v, float), 1e-6, 1 - 1e-6)
    return np.log(v) - np.log1p(-v)


def km_to_x(r_inf, sx, roughness, f0):
    """The unbounded fit coordinates of ``R_inf`` (RGB), ``S X`` (RGB), roughness and ``F0``."""
    parts = [_logit(np.broadcast_to(r_inf, (3,))), np.log(np.maximum(np.broadcast_to(sx, (3,)), 1e-30)),
             [_logit((roughness - _ROUGH_MIN) / (1.0 - _ROUGH_MIN))], [_logit(f0)]]
    return _asarray(np.concatenate([np.ravel(p) for p in parts]))


def km_labels():
    """One label per entry of ``x``."""
    return [f"r_inf[{i}]" for i in range(3)] + [f"sx[{i}]" for i in range(3)] + ["roughness", "f0"]


# --- the fit -----------------------------------------------------------------------------


class KMProblem(WeightedLeastSquares):
    """Least squares of the Kubelka-Munk baseline: residuals ``(model - measured) / std``, flattened.

    ``model`` is in the file's quantity (``pi f`` for a reflectance factor);
    ``std = 1`` when the file has no standard deviations (:class:`~jaxcos.inference.WeightedLeastSquares`).
    """

    wi: jnp.ndarray
    wo: jnp.ndarray
    measured: jnp.ndarray
    sigma: jnp.ndarray
    substrate: jnp.ndarray
    scale: float = eqx.field(static=True)

    def material(self, x):
        return km_from_x(x, self.substrate)

    def model(self, x):
        """The model in the file's quantity, ``(N, 3)``."""
        return self.scale * self.material(x).bsdf_directions(self.wi, self.wo)


def make_km_problem(meas, substrate=0.0):
    """The :class:`KMProblem` of the measurements ``meas`` over a substrate of reflectance ``substrate`` (RGB)."""
    sigma = np.ones_like(meas.values) if meas.std is None else np.asarray(meas.std)
    if np.any(sigma <= 0):
        raise InputError(f"{meas.path}: every standard deviation must be positive to weight a fit.")
    rg = np.broadcast_to(np.asarray(substrate, float), (3,))
    if np.any(~np.isfinite(rg)) or np.any(rg < 0) or np.any(rg >= 1):
        raise InputError(f"substrate reflectance {rg.tolist()} must lie in [0, 1).")
    wi, wo = directions(meas.theta_i, meas.theta_o, meas.phi_o)
    return KMProblem(wi=wi, wo=wo, measured=_asarray(meas.values), sigma=_asarray(sigma), substrate=_asarray(rg),
                     scale=float(meas.scale))


@eqx.filter_jit
def _km_lm(problem, x0s, max_steps):
    solver = optx.LevenbergMarquardt(rtol=1e-6, atol=1e-8)

    def one(x0):
        sol = optx.least_squares(lambda x, p: p.residuals(x), solver, x0, args=problem, max_steps=max_steps,
                                 throw=False)
        return sol.value, problem.loss(sol.value), sol.stats["num_steps"]

    return jax.vmap(one)(x0s)


def km_starts(meas, n, rng):
    """The default start (``R_inf`` from the data's median diffuse level, ``S X = 10``, ``m = 0.2``,
    ``F0 = 0.04``) and ``n`` random starts, as a ``(n + 1, 8)`` array of fit coordinates.

    Points with an infinite std (zero weight) do not count in the median.
    """
    to_rf = np.pi / meas.scale  # to a reflectance factor
    real = np.ones(meas.n_points, bool) if meas.std is None else np.all(np.isfinite(meas.std), axis=1)
    level = np.clip(np.median(meas.values[real] * to_rf, axis=0), 0.05, 0.95)
    draws = [km_to_x(level, 10.0, 0.2, 0.04)]
    for _ in range(n):
        draws.append(km_to_x(rng.uniform(0.05, 0.95, 3), np.exp(rng.uniform(np.log(0.3), np.log(30.0), 3)),
                             10 ** rng.uniform(-1.7, -0.1), 10 ** rng.uniform(-2.3, -0.3)))
    return jnp.stack(draws)


@dataclasses.dataclass(frozen=True, kw_only=True)
class KMFitRecord(FitSummary):
    """What a Kubelka-Munk fit did and how well it fits: its ``"fit"`` record (:meth:`to_json`).

    The fields of :class:`FitSummary` mean what they mean for the Monte Carlo
    fits, so the ablation reads both fits alike (``reduced_chi2`` and
    ``reduced_chi2_noise_only`` are equal: the model has no Monte Carlo error).

    Attributes (besides those of :class:`FitSummary`):
        seed: seeds the random starts.
        n_params, fitted: :data:`KM_N_PARAMS` and :data:`KM_PARAMETERS`.
        starts_refined: starts refined (all of them); ``starts_at_optimum``:
            those whose loss is within ``1e-3 loss + 1`` of the best's.
        substrate: the substrate's reflectance (RGB).
        parameters: the fitted model as plain numbers (``scattering``,
            ``absorption``, ``r_inf``, RGB lists; ``thickness``, ``roughness``, ``f0``).
    """

    method: str = "lm"
    variant: str = "kubelka_munk"
    seed: int
    n_params: int = KM_N_PARAMS
    fitted: tuple = KM_PARAMETERS
    starts_refined: int
    starts_at_optimum: int
    substrate: tuple
    parameters: dict

    def to_json(self):
        """The ``"fit"`` object of the Kubelka-Munk fit (``fits.json`` of the ablation)."""
        out = dict(loss=self.loss, l2=self.l2, rmse=self.rmse, n_points=self.n_points)
        if self.reduced_chi2 is not None:
            out.update(reduced_chi2=self.reduced_chi2, reduced_chi2_noise_only=self.reduced_chi2_noise_only)
        out.update(iterations=self.iterations, time_s=self.time_s, method=self.method, variant=self.variant,
                   n_params=self.n_params, fitted=list(self.fitted), starts_refined=self.starts_refined,
                   starts_at_optimum=self.starts_at_optimum, seed=self.seed, substrate=list(self.substrate),
                   parameters=self.parameters)
        return out


@dataclasses.dataclass
class KMFitResult:
    """The outcome of :func:`fit_kubelka_munk`, with the attributes of :class:`jaxcos.FitResult` that apply.

    Attributes:
        material: the fitted :class:`KubelkaMunk` (thickness 1).
        record: its :class:`KMFitRecord` (``record.to_json()``: the ``"fit"`` record).
        model: ``(N, 3)`` the fitted model in the file's quantity.
        model_std: ``None``: the model is deterministic, without Monte Carlo error.
        starts: per start, ``(start index, loss)``.
        x: the fitted unbounded coordinates (:func:`km_from_x`).
        problem: the :class:`KMProblem` that was solved.
    """

    material: KubelkaMunk
    record: KMFitRecord
    model: np.ndarray
    model_std: np.ndarray | None
    starts: list
    x: jnp.ndarray
    problem: KMProblem

    @property
    def model_params(self):
        """The same as :attr:`material`."""
        return self.material


def fit_kubelka_munk(meas, *, seed=0, starts=15, substrate=0.0, max_steps=200, progress=None):
    """Fit the Kubelka-Munk baseline to measurements by Levenberg-Marquardt (optimistix) from a multi-start.

    The model is deterministic and cheap: every start (the default one and
    ``starts`` random ones) is refined in one batched (``vmap``) solve, and the
    best is kept.

    Args:
        meas: from :func:`jaxcos.load_measurements`.
        seed: seeds the random starts.
        starts: random starts besides the default one.
        substrate: the substrate's diffuse reflectance ``Rg`` (RGB or scalar);
            the bundled files lie on a black substrate (0).
        max_steps: Levenberg-Marquardt steps per start.
        progress: a callable ``progress(message)`` (default: none).

    Returns:
        A :class:`KMFitResult`.
    """
    say = progress or (lambda msg: None)
    t0 = time.perf_counter()
    problem = make_km_problem(meas, substrate)
    x0s = km_starts(meas, int(starts), np.random.default_rng(seed))
    say(f"Kubelka-Munk: refining {x0s.shape[0]} starts by Levenberg-Marquardt in one batch")
    xs, losses, steps = _km_lm(problem, x0s, int(max_steps))
    losses = np.where(np.isfinite(np.asarray(losses)), np.asarray(losses), np.inf)
    best = int(np.argmin(losses))
    x, loss = xs[best], float(losses[best])
    model = np.asarray(problem.model(x), dtype=float)
    params = problem.material(x)
    same = int(np.sum(np.abs(losses - loss) <= 1e-3 * loss + 1.0))
    record = KMFitRecord(
        **fit_statistics(meas, model, loss, KM_N_PARAMS),
        iterations=int(steps[best]), time_s=round(time.perf_counter() - t0, 2), starts_refined=int(x0s.shape[0]),
        starts_at_optimum=same, seed=int(seed), substrate=tuple(float(v) for v in np.asarray(params.substrate)),
        parameters=dict(scattering=[float(v) for v in np.asarray(params.scattering)],
                        absorption=[float(v) for v in np.asarray(params.absorption)],
                        r_inf=[float(v) for v in np.asarray(params.r_inf)], thickness=1.0,
                        roughness=float(params.roughness), f0=float(params.f0)),
    )
    return KMFitResult(material=params, record=record, model=model, model_std=None,
                       starts=[(i, float(v)) for i, v in enumerate(losses)], x=x, problem=problem)
