"""The accuracy benchmark: what a Monte Carlo budget buys, in error and in time.

Every number jaxcos reports is a Monte Carlo estimate with a budget: walks per
incidence direction and bounces per walk. :func:`accuracy_benchmark` measures,
for a dewy and a matte product on the standard grid (``theta_i`` 0..75 step 5,
``theta_o`` -85..85 step 5, as ``measurements/standard_angles.csv``):

* the RMS relative error of the BSDF against a reference at a far higher
  budget (:attr:`Settings.reference`), with exact and with Monte Carlo single
  scattering, along two sweeps: walks at full bounces (the noise) and bounces
  at fixed walks (the truncation bias, measured apart under common random
  numbers: a walk of ``b`` bounces is the prefix of the same walk of 512);
* the energy left in unfinished walks, the forward time and the time of the
  fit's Jacobian (``Problem.jacobian``: differences of the same walks against
  12 parameters, 13 evaluations);
* end to end, fits of a synthetic set whose truth is known
  (``measurements/matte2.csv``, truth ``jaxcos.published("matte2")``, 2 % + 0.002
  noise) at several budgets: the fit time, the chi-square of the fitted
  material evaluated accurately (independent key, high budget) against the
  data, the RMS relative difference between the fitted and the true BSDF on
  the standard grid, and the parameter errors.

The synthetic set is read from the package (``jaxcos/data/matte2.csv``, a
copy of ``measurements/matte2.csv``), so the benchmark runs from an installed
wheel. It returns every number as one JSON-ready dict;
:func:`jaxcos.report.write_accuracy` writes the tables and figures, and
``jaxcos bench accuracy`` does both.

Timings are the best of the repeated runs after compilation, wall-clock and
CPU (all threads of the process), taken on whatever else the machine is doing:
the load average is recorded with each. CPU time is disturbed by contention
far less than wall time (on a quiet two-core machine a run uses about 1.6
cores: wall is about CPU / 1.6).
"""

import dataclasses
import importlib.resources
import os
import platform
import sys
import time

import numpy as np

from .._errors import InputError


@dataclasses.dataclass(frozen=True)
class Settings:
    """What the benchmark sweeps. :data:`FULL` is the recorded run, :data:`QUICK` a smoke test.

    Attributes:
        products: published products swept on the standard grid.
        walks: walks per incidence of the walks sweep, at ``walks_bounces`` bounces.
        bounces: bounces of the bounces sweep, at ``bounces_walks`` walks.
        jacobian: ``(walks, bounces)`` budgets at which the Jacobian is timed
            (exact single scattering only: the fit's estimator).
        seeds: independent keys per budget; the error is the RMS over them.
        reference: ``(walks, bounces)`` of the reference, run in batches of
            ``reference_batch`` walks, exact single scattering.
        max_reference_rel_stderr: points whose reference relative standard
            error (worst channel) exceeds this are left out of every error.
        fit_product: the synthetic set fitted end to end (:func:`synthetic_set`,
            truth ``jaxcos.published(NAME)``).
        fit_budgets: ``(walks, bounces)`` of the fits.
        fit_multistart: the fit's default multi-start (else one start, the default one).
        check_budget: ``(walks, bounces)`` at which fitted materials are evaluated.
        efficiency_products: products of the efficiency comparison
            (:func:`efficiency_material`), each on its own grid.
        efficiency_budgets: ``(walks, bounces)`` at which the estimator and its
            reference (every walk makes every step) are compared side by side.
        efficiency_seeds: independent keys per estimator and budget.
    """

    products: tuple
    walks: tuple
    walks_bounces: int
    bounces: tuple
    bounces_walks: int
    jacobian: tuple
    seeds: int
    reference: tuple
    reference_batch: int
    max_reference_rel_stderr: float
    fit_product: str
    fit_budgets: tuple
    fit_multistart: bool
    check_budget: tuple
    efficiency_products: tuple = ()
    efficiency_budgets: tuple = ()
    efficiency_seeds: int = 2


FULL = Settings(
    products=("dewy1", "matte2"),
    walks=(8, 16, 32, 64, 128, 256, 512, 1024),
    walks_bounces=512,
    bounces=(8, 16, 32, 64, 128, 256, 512),
    bounces_walks=256,
    jacobian=((8, 512), (32, 512), (128, 512), (512, 512), (256, 32), (256, 128)),
    seeds=3,
    reference=(32768, 512),
    reference_batch=4096,
    max_reference_rel_stderr=0.01,
    fit_product="matte2",
    fit_budgets=((64, 64), (128, 128), (256, 128), (1024, 128)),
    fit_multistart=True,
    check_budget=(8192, 256),
    efficiency_products=("dewy1", "dewy2", "matte1", "matte2", "matte1 over skin", "slab"),
    efficiency_budgets=((1024, 128), (128, 512)),
    efficiency_seeds=6,
)
QUICK = Settings(
    products=("matte2",),
    walks=(8,),
    walks_bounces=8,
    bounces=(8,),
    bounces_walks=8,
    jacobian=((8, 8),),
    seeds=2,
    reference=(128, 8),
    reference_batch=64,
    max_reference_rel_stderr=0.5,
    fit_product="matte2",
    fit_budgets=((8, 8),),
    fit_multistart=False,
    check_budget=(32, 8),
    efficiency_products=("matte2",),
    efficiency_budgets=((8, 32),),
    efficiency_seeds=2,
)


def standard_grid():
    """``(theta_i, theta_o)`` of the standard grid: 16 incidences 0..75 by 35 outgoing -85..85, step 5."""
    ti = np.repeat(np.arange(0.0, 80.0, 5.0), 35)
    to = np.tile(np.arange(-85.0, 90.0, 5.0), 16)
    return ti, to


def machine_record():
    """Platform, CPU count, versions and the load average now."""
    import jax

    from .. import __version__

    return dict(platform=platform.platform(), processor=platform.processor(), cpus=os.cpu_count(),
                python=sys.version.split()[0], jax=jax.__version__, backend=jax.default_backend(),
                devices=[str(d) for d in jax.devices()], float=str(jax.numpy.result_type(float)),
                jaxcos=__version__, load_average=list(os.getloadavg()))


def _load():
    return [round(v, 2) for v in os.getloadavg()]


def _timed(fn, *args, cpu=None):
    """``fn(*args)`` after ``block_until_ready``, and its wall time; its CPU time (all threads) appended to ``cpu``."""
    import jax

    t0, c0 = time.perf_counter(), time.process_time()
    out = jax.block_until_ready(fn(*args))
    if cpu is not None:
        cpu.append(time.process_time() - c0)
    return out, time.perf_counter() - t0


# --- the reference ----------------------------------------------------------------


def reference(material, query, settings, say):
    """Mean and standard error ``(N, 3)`` of the BSDF at the reference budget (batches of independent keys).

    Every walk makes every step (``thin_after=None``).
    """
    import jax

    from ..model import simulate

    walks, bounces = settings.reference
    batch = min(settings.reference_batch, walks)
    run = jax.jit(lambda key: simulate(material, query, key, walks=batch, bounces=bounces, thin_after=None))
    means, errors = [], []
    t0 = time.perf_counter()
    for b in range(walks // batch):
        est = run(jax.random.fold_in(jax.random.key(7), b))
        means.append(np.asarray(est.f, float))
        errors.append(np.asarray(est.stderr, float))
    k = len(means)
    say(f"  reference {k * batch} walks x {bounces} bounces: {time.perf_counter() - t0:.0f} s")
    return np.mean(means, axis=0), np.sqrt(np.sum(np.square(errors), axis=0)) / k


# --- one budget -------------------------------------------------------------------


def _forward(material, query, walks, bounces, single, seeds, **options):
    """Compile and run one budget on ``seeds`` keys: estimates, timings, load. ``options`` go to ``simulate``."""
    import jax

    from ..model import lobe_probabilities, simulate

    lp = lobe_probabilities(material)
    run = jax.jit(lambda key: simulate(material, query, key, walks=walks, bounces=bounces, lobe_probs=lp,
                                       single_scattering=single, **options))
    load_before = _load()
    keys = [jax.random.key(1000 + s) for s in range(seeds)]
    first, t_first = _timed(run, keys[0])
    estimates, runs, cpu = [first], [], []
    for key in keys:
        est, t = _timed(run, key, cpu=cpu)
        runs.append(t)
        if key is not keys[0]:
            estimates.append(est)
    return estimates, dict(compile_s=max(t_first - min(runs), 0.0), forward_s=min(runs), forward_runs_s=runs,
                           forward_cpu_s=min(cpu), forward_load=[load_before, _load()])


def bsdf_problem(material, query, key, walks, bounces):
    """The fit's least-squares ``Problem`` of the BSDF itself, and ``x`` at ``material``.

    Two-lobe parameterization (12 entries of ``x``), residuals ``f`` (zero
    data, unit weights), lobe probabilities of ``material``: its Jacobian is
    the fit's (:meth:`~jaxcos.inference.Problem.jacobian`, coloured differences of the same walks).
    """
    import jax.numpy as jnp

    from ._fit import Problem, parameterization
    from ..model import lobe_probabilities

    param = parameterization("two_lobe", template=material)
    n = query.pair_i.shape[0]
    problem = Problem(param=param, query=query, measured=jnp.zeros((n, 3)), sigma=jnp.ones((n, 3)), scale=1.0,
                      key=key, lobe_probs=lobe_probabilities(material), walks=walks, bounces=bounces)
    return problem, param.from_material(material)


def _jacobian(material, query, walks, bounces):
    """Time the fit's Jacobian of the BSDF against its 12 parameters (:func:`bsdf_problem`)."""
    import jax
    import jax.numpy as jnp

    problem, x0 = bsdf_problem(material, query, jax.random.key(1000), walks, bounces)
    jac = lambda x: problem.jacobian(x)[0]
    load_before = _load()
    _, t_first = _timed(jac, x0)
    cpu = []
    runs = [_timed(jac, x0, cpu=cpu)[1] for _ in range(2 if walks * bounces <= 128 * 512 else 1)]
    return dict(jacobian_s=min(runs), jacobian_runs_s=runs, jacobian_cpu_s=min(cpu),
                jacobian_compile_s=max(t_first - min(runs), 0.0),
                jacobian_load=[load_before, _load()], n_params=int(jnp.size(x0)),
                n_evaluations=problem.param.jacobian_evaluations())


def _errors(estimates, ref, keep):
    """RMS (over kept points, channels and keys) and median of the relative error."""
    rel = np.stack([(np.asarray(e.f, float) - ref) / ref for e in estimates])[:, keep]
    return float(np.sqrt(np.mean(rel ** 2))), float(np.median(np.abs(rel)))


def sweep_product(product, settings, say):
    """All budgets of both sweeps and both strategies for one published product; a list of records."""
    from ..model import make_query, published

    material = published(product)
    query = make_query(*standard_grid())
    say(f"{product}: reference")
    ref, ref_se = reference(material, query, settings, say)
    ref_rel = np.max(ref_se / np.maximum(ref, 1e-30), axis=-1)
    keep = ref_rel <= settings.max_reference_rel_stderr
    ref_info = dict(walks=settings.reference[0], bounces=settings.reference[1], points=int(ref.shape[0]),
                    kept=int(keep.sum()), max_rel_stderr_kept=float(ref_rel[keep].max()),
                    median_rel_stderr=float(np.median(ref_rel)),
                    rms_rel_stderr_kept=float(np.sqrt(np.mean((ref_se / ref)[keep] ** 2))))
    budgets = [(w, settings.walks_bounces, "walks") for w in settings.walks]
    budgets += [(settings.bounces_walks, b, "bounces") for b in settings.bounces]
    records, cache = [], {}
    for single in ("exact", "mc"):
        for walks, bounces, sweep in budgets:
            if (walks, bounces, single) in cache:
                rec = dict(cache[(walks, bounces, single)][0], sweep=sweep)
                records.append(rec)
                continue
            estimates, timing = _forward(material, query, walks, bounces, single, settings.seeds)
            rms, med = _errors(estimates, ref, keep)
            stderr = np.median([np.median(np.asarray(e.stderr) / np.maximum(np.asarray(e.f), 1e-30))
                                for e in estimates])
            rec = dict(product=product, strategy=single, sweep=sweep, walks=walks, bounces=bounces,
                       rms_rel_error=rms, median_abs_rel_error=med, median_rel_stderr=float(stderr),
                       unfinished_max=float(max(np.max(np.asarray(e.unfinished)) for e in estimates)), **timing)
            if single == "exact" and (walks, bounces) in settings.jacobian:
                rec.update(_jacobian(material, query, walks, bounces))
            cache[(walks, bounces, single)] = (rec, estimates)
            records.append(rec)
            jac = f", Jacobian {rec['jacobian_s']:.2f} s" if "jacobian_s" in rec else ""
            say(f"  {single:5s} {walks:5d} walks x {bounces:3d} bounces: error {100 * rms:6.2f} %, "
                f"forward {1e3 * rec['forward_s']:7.1f} ms{jac}, unfinished {rec['unfinished_max']:.1e} "
                f"(load {rec['forward_load'][1][0]:.1f})")
        # Truncation bias under common random numbers: walks of b bounces are prefixes of those of the most.
        full = cache.get((settings.bounces_walks, max(settings.bounces), single))
        for rec in records:
            if rec["strategy"] == single and rec["sweep"] == "bounces" and full is not None:
                part = cache[(rec["walks"], rec["bounces"], single)][1]
                diff = np.mean([(np.asarray(a.f, float) - np.asarray(b.f, float)) / ref
                                for a, b in zip(part, full[1])], axis=0)[keep]
                rec["truncation_bias_rms"] = float(np.sqrt(np.mean(diff ** 2)))
    return records, ref_info


# --- efficiency: the estimator against its reference, side by side ----------------------


def efficiency_material(name):
    """A product of the efficiency comparison and its angle pairs ``(theta_i, theta_o)``.

    A published product on the standard grid; ``"matte1 over skin"``: matte1
    at ``t = 2`` over a Lambertian base of albedo (0.6, 0.45, 0.35); ``"slab"``:
    an index-matched Henyey-Greenstein slab (``t = 2``, albedo 0.95, ``g = 0.5``,
    black base) on 60 in-plane pairs (``theta_i`` 0..75 step 15 by ``theta_o``
    -67.5..67.5 step 15), the scene on which a general-purpose renderer was
    measured (issue 32).
    """
    from ..model import Layer, Material, published

    if name == "slab":
        layer = Layer(t=2.0, c_d=1.0, albedo_d=(0.95, 0.95, 0.95), g1=0.5, g2=0.5, w_g=1.0, albedo_p=(0.5, 0.5, 0.5),
                      alpha_p=0.5, theta_p=0.0)
        ti = np.repeat(np.arange(0.0, 90.0, 15.0), 10)
        to = np.tile(np.arange(-67.5, 70.0, 15.0), 6)
        return Material(layers=(layer,), variant="diffusers_only"), (ti, to)
    if name == "matte1 over skin":
        return Material(layers=published("matte1", t=2.0).layers, base_albedo=(0.6, 0.45, 0.35)), standard_grid()
    return published(name), standard_grid()


def efficiency(settings, say):
    """``1 / (RMS relative error^2 x CPU seconds)`` of one forward evaluation, the estimator against its reference.

    For each product and budget of ``settings``, the default estimator
    (fewer walks for the later steps) and the reference one (every walk makes
    every step, ``thin_after=None``) run side by side on the same keys, after
    one reference BSDF per product (:func:`reference`). The error is the RMS
    over kept points, channels and keys; the reference's own RMS relative
    error (the floor) is recorded, not subtracted. Returns a list of records.
    """
    from ..model import make_query

    records = []
    for product in settings.efficiency_products:
        material, angles = efficiency_material(product)
        query = make_query(*angles)
        say(f"efficiency, {product}: reference")
        ref, ref_se = reference(material, query, settings, say)
        ref_rel = np.max(ref_se / np.maximum(ref, 1e-30), axis=-1)
        keep = ref_rel <= settings.max_reference_rel_stderr
        floor = float(np.sqrt(np.mean((ref_se / ref)[keep] ** 2)))
        for walks, bounces in settings.efficiency_budgets:
            row = dict(product=product, walks=walks, bounces=bounces, points=int(ref.shape[0]), kept=int(keep.sum()),
                       reference_floor=floor)
            for label, thin in (("reference", None), ("estimator", "default")):
                options = {} if thin == "default" else dict(thin_after=None)
                estimates, timing = _forward(material, query, walks, bounces, "exact", settings.efficiency_seeds,
                                             **options)
                rms, _ = _errors(estimates, ref, keep)
                bias = float(np.mean([np.mean(((np.asarray(e.f, float) - ref) / ref)[keep]) for e in estimates]))
                row[label] = dict(rms_rel_error=rms, mean_rel_error=bias, forward_s=timing["forward_s"],
                                  forward_cpu_s=timing["forward_cpu_s"], compile_s=timing["compile_s"],
                                  load=timing["forward_load"],
                                  efficiency=1.0 / (rms ** 2 * max(timing["forward_cpu_s"], 1e-9)))
            row["ratio"] = row["estimator"]["efficiency"] / row["reference"]["efficiency"]
            records.append(row)
            say(f"  {walks:5d} walks x {bounces:3d} bounces: error {100 * row['reference']['rms_rel_error']:.2f} -> "
                f"{100 * row['estimator']['rms_rel_error']:.2f} %, CPU {1e3 * row['reference']['forward_cpu_s']:.0f} -> "
                f"{1e3 * row['estimator']['forward_cpu_s']:.0f} ms: efficiency x {row['ratio']:.2f}")
    return records


# --- end to end: fits -------------------------------------------------------------------


def _param_errors(fitted, truth):
    from ..io import material_to_dict

    f, t = material_to_dict(fitted)["layers"][0], material_to_dict(truth)["layers"][0]
    return {k: float(np.max(np.abs(np.asarray(f[k], float) - np.asarray(t[k], float)))) for k in t if k != "t"}


def _check(material, meas, grid_query, truth, settings):
    """Accurate checks of a fitted ``material`` at :attr:`Settings.check_budget`, with an independent key.

    Returns the chi-square against the data and the RMS relative difference of
    its BSDF to the truth's on the standard grid and at the measured angles
    (the same key for both materials: common random numbers make the
    difference far less noisy than either).
    """
    import jax

    from ..model import make_query, simulate

    walks, bounces = settings.check_budget
    key = jax.random.key(99)
    run = lambda m, q: np.asarray(simulate(m, q, key, walks=walks, bounces=bounces).f, float)
    measured = make_query(meas.theta_i, meas.theta_o, meas.phi_o)
    f, f_true = run(material, measured), run(truth, measured)
    chi2 = float(np.sum(((meas.scale * f - meas.values) / meas.std) ** 2))
    a, b = run(material, grid_query), run(truth, grid_query)
    rms = lambda x, y: float(np.sqrt(np.mean(((x - y) / y) ** 2)))
    return chi2, rms(a, b), rms(f, f_true)


def fit_budgets(settings, say):
    """Fit the synthetic set at each budget of ``settings``; a list of records and the truth's own numbers."""
    from ._fit import fit, fixed_starts
    from ..io import material_to_dict
    from ..model import Layer, Material, make_query, published

    meas = synthetic_set(settings.fit_product)
    truth = published(settings.fit_product)
    grid_query = make_query(*standard_grid())
    n_params = 12
    dof = meas.values.size - n_params
    chi2_truth = _check(truth, meas, grid_query, truth, settings)[0]
    truth_info = dict(product=settings.fit_product, path=f"measurements/{settings.fit_product}.csv", n_points=int(meas.n_points),
                      dof=int(dof), reduced_chi2_truth=chi2_truth / dof,
                      median_noise_rel=float(np.median(meas.std / np.abs(meas.values))))
    say(f"fits of {settings.fit_product}: the truth scores reduced chi-square {chi2_truth / dof:.2f} against the data")
    # one start: the fit's default one (the first of its fixed starts), at the protocol's t = 16
    start = None if settings.fit_multistart else Material(layers=(Layer(**fixed_starts(0, 16.0, None, None)[0][2]),))
    records = []
    for walks, bounces in settings.fit_budgets:
        load_before, c0 = _load(), time.process_time()
        result = fit(meas, walks=walks, bounces=bounces, seed=0, start=start)
        load_after, cpu = _load(), time.process_time() - c0
        chi2, appearance, at_measured = _check(result.material, meas, grid_query, truth, settings)
        r = result.record
        rel_mc = np.median(result.model_std / np.maximum(np.abs(result.model), 1e-30))
        rec = dict(walks=walks, bounces=bounces, time_s=r.time_s, cpu_s=cpu, load=[load_before, load_after],
                   iterations=r.iterations, reduced_chi2_fit=r.reduced_chi2,
                   reduced_chi2_noise_only=r.reduced_chi2_noise_only,
                   mc_error_over_noise=r.mc_error_median, mc_rel_error_median=float(rel_mc),
                   reduced_chi2_checked=chi2 / (r.n_points * 3 - r.n_params),
                   bsdf_rms_rel_error=appearance, bsdf_rms_rel_error_measured=at_measured,
                   starts_at_optimum=r.starts_at_optimum,
                   param_abs_errors=_param_errors(result.material, truth),
                   fitted=material_to_dict(result.material)["layers"][0])
        records.append(rec)
        say(f"  fit {walks:5d} walks x {bounces:3d} bounces: {rec['time_s']:6.1f} s (load {load_after[0]:.1f}), "
            f"checked reduced chi-square {rec['reduced_chi2_checked']:.2f}, BSDF error {100 * at_measured:.1f} % "
            f"(measured angles), {100 * appearance:.1f} % (standard grid), "
            f"MC error / noise {rec['mc_error_over_noise']:.2f}")
    return records, truth_info


def synthetic_set(name):
    """The bundled synthetic set ``name`` (``jaxcos/data/NAME.csv``, equal to ``measurements/NAME.csv``).

    Raises:
        InputError: if the package does not hold that set.
    """
    from ..io import load_measurements

    resource = importlib.resources.files("jaxcos") / "data" / f"{name}.csv"
    if not resource.is_file():
        raise InputError(f"jaxcos/data/{name}.csv: the synthetic set of the end-to-end benchmark is missing.")
    with importlib.resources.as_file(resource) as path:
        return load_measurements(path)


def accuracy_benchmark(*, quick=False, progress=None):
    """Run the sweep and the fits; return every number as a JSON-ready dict.

    ``quick`` runs :data:`QUICK` (about a minute, for tests) instead of
    :data:`FULL`. ``progress(message)`` is told about each stage and budget.
    The dict holds ``machine`` (:func:`machine_record`), ``quick``,
    ``settings``, ``sweep`` and ``reference`` (:func:`sweep_product`),
    ``efficiency`` (:func:`efficiency`), ``fits`` and ``fit_truth`` (:func:`fit_budgets`), ``load_after`` and
    ``total_s``.
    """
    say = progress or (lambda msg: None)
    settings = QUICK if quick else FULL
    data = dict(machine=machine_record(), quick=bool(quick), settings=dataclasses.asdict(settings),
                sweep=[], reference={})
    t0 = time.perf_counter()
    for product in settings.products:
        records, ref_info = sweep_product(product, settings, say)
        data["sweep"] += records
        data["reference"][product] = ref_info
    data["efficiency"] = efficiency(settings, say)
    data["fits"], data["fit_truth"] = fit_budgets(settings, say)
    data["load_after"] = list(os.getloadavg())
    data["total_s"] = time.perf_counter() - t0
    return data
