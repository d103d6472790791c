"""``jaxcos bench accuracy``: what a Monte Carlo budget buys, in error and in time.

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
  fit's Jacobian (``Problem``'s ``custom_jvp``: batched forward mode against
  12 parameters, 8 tangents);
* end to end, fits of a synthetic set whose truth is known
  (``measurements/matte2.csv``, truth ``jaxcos.published("matte2")``, 2 % + 0.002
  noise) at several budgets: the fit time, the chi-square of the fitted
  material evaluated accurately (independent key, high budget) against the
  data, the RMS relative difference between the fitted and the true BSDF on
  the standard grid, and the parameter errors.

It writes ``accuracy.json`` (every number, with a machine record and the load
average around each timing), ``accuracy.md`` (the tables), ``accuracy.png``
(error against time) and ``accuracy_fit.png`` (the fits) under ``--out``.

    jaxcos bench accuracy --out benchmarks/results [--quick] [--force]
    python benchmarks/bench_accuracy.py                      # the same, into benchmarks/results

Timings are the best of the repeated runs after compilation, wall-clock and
CPU (all threads of the process), taken on whatever else the machine is doing:
the load average is recorded with each. The figures use CPU time, which
contention disturbs far less than wall time (on a quiet two-core machine a
run uses about 1.6 cores: wall is about CPU / 1.6).
"""

import dataclasses
import json
import os
import platform
import sys
import time

import numpy as np

from .._errors import InputError, refuse_overwrite, staged_outputs
from ._fit import FIT_BOUNCES, FIT_WALKS

FILES = ("accuracy.json", "accuracy.md", "accuracy.png", "accuracy_fit.png")
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PAPER_BUDGET = (128, 512)
"""The paper's budget (Lanza et al. 2024): 128 samples per direction, 512 bounces."""
FIT_BUDGET = (FIT_WALKS, FIT_BOUNCES)
"""The fit's default budget, marked in the figure."""


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
        fit_product: the synthetic set fitted end to end (``measurements/NAME.csv``,
            truth ``jaxcos.published(NAME)``).
        fit_budgets: ``(walks, bounces)`` of the fits.
        fit_multistart: the fit's default multi-start (else one start, the default one).
        check_budget: ``(walks, bounces)`` at which fitted materials are evaluated.
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
)


def standard_grid():
    """``(theta_i, theta_o)`` of the standard grid: 16 incidences 0..75 by 35 outgoing -85..85, step 5."""
    ti = np.repeat(np.arange(0.0, 80.0, 5.0), 35)
    to = np.tile(np.arange(-85.0, 90.0, 5.0), 16)
    return ti, to


def machine_record():
    """Platform, CPU count, versions and the load average now."""
    import jax

    import jaxcos

    return dict(platform=platform.platform(), processor=platform.processor(), cpus=os.cpu_count(),
                python=sys.version.split()[0], jax=jax.__version__, backend=jax.default_backend(),
                devices=[str(d) for d in jax.devices()], float=str(jax.numpy.result_type(float)),
                jaxcos=jaxcos.__version__, load_average=list(os.getloadavg()))


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
    """Mean and standard error ``(N, 3)`` of the BSDF at the reference budget (batches of independent keys)."""
    import jax

    from ..model import simulate

    walks, bounces = settings.reference
    batch = min(settings.reference_batch, walks)
    run = jax.jit(lambda key: simulate(material, query, key, walks=batch, bounces=bounces))
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


def _forward(material, query, walks, bounces, single, seeds):
    """Compile and run one budget on ``seeds`` keys: estimates, timings, load."""
    import jax

    from ..model import lobe_probabilities, simulate

    lp = lobe_probabilities(material)
    run = jax.jit(lambda key: simulate(material, query, key, walks=walks, bounces=bounces, lobe_probs=lp,
                                       single_scattering=single))
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
    """The fit's least-squares :class:`~jaxcos._fit.Problem` of the BSDF itself, and ``x`` at ``material``.

    Two-lobe parameterization (12 entries of ``x``), residuals ``f`` (zero
    data, unit weights), lobe probabilities of ``material``: its Jacobian is
    the fit's (``jax.jacfwd(problem.residuals)``, coloured forward mode).
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
    jac = jax.jit(jax.jacfwd(problem.residuals))
    load_before = _load()
    _, t_first = _timed(jac, x0)
    cpu = []
    runs = [_timed(jac, x0, cpu=cpu)[1] for _ in range(2 if walks * bounces <= 128 * 512 else 1)]
    return dict(jacobian_s=min(runs), jacobian_runs_s=runs, jacobian_cpu_s=min(cpu),
                jacobian_compile_s=max(t_first - min(runs), 0.0),
                jacobian_load=[load_before, _load()], n_params=int(jnp.size(x0)),
                n_tangents=len(problem.param.colouring()[0]))


def _errors(estimates, ref, keep):
    """RMS (over kept points, channels and keys) and median of the relative error."""
    rel = np.stack([(np.asarray(e.f, float) - ref) / ref for e in estimates])[:, keep]
    return float(np.sqrt(np.mean(rel ** 2))), float(np.median(np.abs(rel)))


def sweep_product(product, settings, say):
    """All budgets of both sweeps and both strategies for one published product; a list of records."""
    import jaxcos

    material = jaxcos.published(product)
    query = jaxcos.make_query(*standard_grid())
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
    scale = np.pi if meas.quantity == "reflectance_factor" else 1.0
    chi2 = float(np.sum(((scale * f - meas.values) / meas.std) ** 2))
    a, b = run(material, grid_query), run(truth, grid_query)
    rms = lambda x, y: float(np.sqrt(np.mean(((x - y) / y) ** 2)))
    return chi2, rms(a, b), rms(f, f_true)


def fit_budgets(settings, say):
    """Fit the synthetic set at each budget of ``settings``; a list of records and the truth's own numbers."""
    import jaxcos
    from ._fit import _DEFAULT, fit
    from ..model import Layer, Material

    path = os.path.join(ROOT, "measurements", f"{settings.fit_product}.csv")
    if not os.path.exists(path):
        raise InputError(f"{path}: the synthetic set of the end-to-end benchmark is missing.")
    meas = jaxcos.load_measurements(path)
    truth = jaxcos.published(settings.fit_product)
    grid_query = jaxcos.make_query(*standard_grid())
    n_params = 12
    dof = meas.values.size - n_params
    chi2_truth = _check(truth, meas, grid_query, truth, settings)[0]
    truth_info = dict(product=settings.fit_product, path=os.path.relpath(path, ROOT), n_points=int(meas.n_points),
                      dof=int(dof), reduced_chi2_truth=chi2_truth / dof,
                      median_noise_rel=float(np.median(meas.std / np.abs(meas.values))))
    say(f"fits of {settings.fit_product}: the truth scores reduced chi-square {chi2_truth / dof:.2f} against the data")
    start = None if settings.fit_multistart else Material(layers=(Layer(**_DEFAULT),))
    records = []
    for walks, bounces in settings.fit_budgets:
        load_before, c0 = _load(), time.process_time()
        result = fit(meas, walks=walks, bounces=bounces, seed=0, start=start)
        load_after, cpu = _load(), time.process_time() - c0
        chi2, appearance, at_measured = _check(result.material, meas, grid_query, truth, settings)
        r = result.record
        rel_mc = np.median(result.model_std / np.maximum(np.abs(result.model), 1e-30))
        rec = dict(walks=walks, bounces=bounces, time_s=r["time_s"], cpu_s=cpu, load=[load_before, load_after],
                   iterations=r["iterations"], reduced_chi2_fit=r.get("reduced_chi2"),
                   reduced_chi2_noise_only=r.get("reduced_chi2_noise_only"),
                   mc_error_over_noise=r["mc_error_median"], mc_rel_error_median=float(rel_mc),
                   reduced_chi2_checked=chi2 / (r["n_points"] * 3 - r["n_params"]),
                   bsdf_rms_rel_error=appearance, bsdf_rms_rel_error_measured=at_measured,
                   starts_at_optimum=r["starts_at_optimum"],
                   param_abs_errors=_param_errors(result.material, truth),
                   fitted=jaxcos._material.material_to_dict(result.material)["layers"][0])
        records.append(rec)
        say(f"  fit {walks:5d} walks x {bounces:3d} bounces: {rec['time_s']:6.1f} s (load {load_after[0]:.1f}), "
            f"checked reduced chi-square {rec['reduced_chi2_checked']:.2f}, BSDF error {100 * at_measured:.1f} % "
            f"(measured angles), {100 * appearance:.1f} % (standard grid), "
            f"MC error / noise {rec['mc_error_over_noise']:.2f}")
    return records, truth_info


# --- outputs --------------------------------------------------------------------------------


def _label(rec):
    return f"{rec['walks']}x{rec['bounces']}"


def _cpu(rec, what="forward"):
    """CPU time of a record (wall time for records made before CPU time was recorded)."""
    return rec.get(f"{what}_cpu_s", rec[f"{what}_s"])


def accuracy_figure(data, path):
    """Error against forward time (log-log), one curve per strategy and sweep, per product; then bias and cost."""
    from matplotlib.figure import Figure

    products = data["settings"]["products"]
    fig = Figure(figsize=(5 * max(len(products), 2), 8), constrained_layout=True)
    axes = fig.subplots(2, max(len(products), 2), squeeze=False)
    styles = {("exact", "walks"): ("C0", "-", "o"), ("mc", "walks"): ("C1", "-", "o"),
              ("exact", "bounces"): ("C0", ":", "s"), ("mc", "bounces"): ("C1", ":", "s")}
    s = data["settings"]
    for ax, product in zip(axes[0], products):
        recs = [r for r in data["sweep"] if r["product"] == product]
        for (single, sweep), (color, ls, marker) in styles.items():
            pts = sorted((r for r in recs if r["strategy"] == single and r["sweep"] == sweep),
                         key=lambda r: r["walks"] * r["bounces"])
            if not pts:
                continue
            name = (f"walks {pts[0]['walks']}..{pts[-1]['walks']} at {s['walks_bounces']} bounces" if sweep == "walks"
                    else f"bounces {pts[0]['bounces']}..{pts[-1]['bounces']} at {s['bounces_walks']} walks")
            ax.plot([_cpu(r) for r in pts], [100 * r["rms_rel_error"] for r in pts], color=color, ls=ls,
                    marker=marker, ms=4, label=f"{single} single scattering, {name}")
            for r in pts:
                ax.annotate(str(r["walks"] if sweep == "walks" else r["bounces"]), (_cpu(r), 100 * r["rms_rel_error"]),
                            textcoords="offset points", xytext=(3, 3), fontsize=6, color=color)
        for budget, mark, name in ((PAPER_BUDGET, "*", "paper's budget"), (FIT_BUDGET, "D", "the fit's default")):
            at = [r for r in recs if (r["walks"], r["bounces"]) == budget and r["strategy"] == "exact"]
            if at:
                ax.plot(_cpu(at[0]), 100 * at[0]["rms_rel_error"], marker=mark, ms=12 if mark == "*" else 8,
                        color="k", ls="none", mfc="none" if mark == "D" else "k",
                        label=f"{name} {budget[0]} x {budget[1]} (exact)")
        ref = data["reference"][product]
        ax.axhline(100 * ref["rms_rel_stderr_kept"], color="0.6", lw=0.8, label="reference's own error")
        ax.set_xscale("log")
        ax.set_yscale("log")
        lowest = min([100 * r["rms_rel_error"] for r in recs] + [100 * ref["rms_rel_stderr_kept"]])
        ax.set_ylim(0.7 * lowest, 1.4 * max(100 * r["rms_rel_error"] for r in recs))
        ax.set_xlabel("forward CPU time on the standard grid (s, all threads)")
        ax.set_ylabel("RMS relative error of the BSDF (%)")
        ax.set_title(f"{product}: 560 points x 3 channels", fontsize=10)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=6)
    ax = axes[1][0]
    for k, product in enumerate(products):
        pts = sorted((r for r in data["sweep"] if r["product"] == product and r["strategy"] == "exact"
                      and r["sweep"] == "bounces"), key=lambda r: r["bounces"])
        ax.plot([r["bounces"] for r in pts], [max(r["unfinished_max"], 1e-12) for r in pts], color=f"C{k}",
                marker="o", label=f"{product}: unfinished energy (max over incidences)")
        bias = [(r["bounces"], r["truncation_bias_rms"]) for r in pts if r.get("truncation_bias_rms")]
        if bias:
            ax.plot(*zip(*bias), color=f"C{k}", ls="--", marker="s",
                    label=f"{product}: RMS relative truncation bias of the BSDF")
    ax.set_xscale("log", base=2)
    ax.set_yscale("log")
    ax.set_xlabel("bounces")
    ax.set_title("what too few bounces leave out", fontsize=10)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=6)
    ax = axes[1][1]
    for k, product in enumerate(products):
        pts = [r for r in data["sweep"] if r["product"] == product and r["strategy"] == "exact"]
        ax.plot([r["walks"] * r["bounces"] for r in pts], [_cpu(r) for r in pts], color=f"C{k}", marker="o",
                ls="none", ms=4, label=f"{product}: forward")
        jac = [r for r in pts if "jacobian_s" in r]
        ax.plot([r["walks"] * r["bounces"] for r in jac], [_cpu(r, "jacobian") for r in jac], color=f"C{k}",
                marker="^", ls="none", label=f"{product}: Jacobian (12 parameters)")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("walks x bounces per incidence")
    ax.set_ylabel("CPU time (s, all threads)")
    ax.set_title("cost", fontsize=10)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=6)
    for ax in list(axes[0][len(products):]) + list(axes[1][2:]):
        ax.set_visible(False)
    fig.savefig(path, dpi=72)


def fit_figure(data, path):
    """Fit quality against fit time, one point per budget."""
    from matplotlib.figure import Figure

    fits, truth = data["fits"], data["fit_truth"]
    fig = Figure(figsize=(10, 3.8), constrained_layout=True)
    a, b = fig.subplots(1, 2)
    t = [r.get("cpu_s", r["time_s"]) for r in fits]
    a.plot(t, [r["reduced_chi2_checked"] for r in fits], "o-", label="fitted material, evaluated accurately")
    a.axhline(truth["reduced_chi2_truth"], color="k", ls="--", lw=0.8, label="the truth")
    b.plot(t, [100 * r["bsdf_rms_rel_error"] for r in fits], "o-", color="C2", label="standard grid")
    if all("bsdf_rms_rel_error_measured" in r for r in fits):
        b.plot(t, [100 * r["bsdf_rms_rel_error_measured"] for r in fits], "s-", color="C3", label="measured angles")
        b.axhline(100 * truth["median_noise_rel"], color="k", ls="--", lw=0.8, label="median noise of the data")
    b.legend(fontsize=7)
    for r in fits:
        x = r.get("cpu_s", r["time_s"])
        a.annotate(_label(r), (x, r["reduced_chi2_checked"]), textcoords="offset points", xytext=(3, 3), fontsize=7)
        b.annotate(_label(r), (x, 100 * r["bsdf_rms_rel_error"]), textcoords="offset points", xytext=(3, 3),
                   fontsize=7)
    a.set_ylabel("reduced chi-square against the data")
    b.set_ylabel("RMS relative BSDF error to the truth (%)")
    b.set_yscale("log")
    for ax in (a, b):
        ax.set_xscale("log")
        ax.set_xlabel("fit CPU time (s, all threads)")
        ax.grid(True, which="both", alpha=0.3)
    a.legend(fontsize=7)
    a.set_title(f"fits of {truth['product']} (walks x bounces)", fontsize=10)
    fig.savefig(path, dpi=72)


def accuracy_table(data):
    """The markdown of ``accuracy.md``."""
    s = data["settings"]
    m = data["machine"]
    lines = [
        "# What a Monte Carlo budget buys",
        "",
        f"Machine: {m['platform']}, {m['cpus']} CPUs, jax {m['jax']} ({m['backend']}, {m['float']}), "
        f"Python {m['python']}. Load average before {m['load_average'][0]:.1f}, after "
        f"{data['load_after'][0]:.1f}; every timing carries its own in `accuracy.json`. Times are the best of "
        "the runs after compilation, wall-clock and CPU (all threads of the process); on a shared machine the wall "
        "times are upper bounds of a quiet machine's, the CPU times less affected (a quiet run uses about 1.6 "
        "cores, so CPU is about 1.6x wall there). The figures use CPU time. The load column is the 1-minute "
        "load average after each timing.",
        "",
        f"Reference: {s['reference'][0]} walks x {s['reference'][1]} bounces per incidence, exact single "
        f"scattering, independent keys. Points whose reference relative standard error exceeds "
        f"{100 * s['max_reference_rel_stderr']:.0f}% (worst channel) are left out of every error:",
        "",
    ]
    for product, ref in data["reference"].items():
        lines.append(f"- {product}: {ref['kept']} of {ref['points']} points kept; the reference's own RMS relative "
                     f"error over them is {100 * ref['rms_rel_stderr_kept']:.2f}% (a floor under every error below).")
    lines += [
        "",
        f"Error: RMS over kept points, 3 channels and {s['seeds']} keys of (estimate - reference) / reference. "
        "Unfinished: energy still carried by walks after the last bounce (max over incidences and channels). "
        "Truncation bias: RMS relative difference to the same walks at the sweep's most bounces (common random "
        "numbers, mean over the keys). Jacobian: the fit's (`jax.jacfwd` of its residuals: batched forward mode "
        "against 12 parameters, coloured into 8 tangents since 2026-11-23), exact single scattering only, at a "
        "subset of budgets.",
        "",
    ]
    for product in s["products"]:
        recs = [r for r in data["sweep"] if r["product"] == product]
        lines += [f"## {product}", "",
                  "| single scattering | sweep | walks | bounces | RMS rel. error | truncation bias | unfinished | "
                  "forward wall / CPU | Jacobian wall / CPU | load |",
                  "|---|---|---|---|---|---|---|---|---|---|"]
        for r in recs:
            bias = f"{100 * r['truncation_bias_rms']:.3g}%" if "truncation_bias_rms" in r else ""
            jac = f"{r['jacobian_s']:.2f} / {r.get('jacobian_cpu_s', float('nan')):.2f} s" if "jacobian_s" in r else ""
            mark = " (paper)" if (r["walks"], r["bounces"]) == PAPER_BUDGET else ""
            lines.append(f"| {r['strategy']} | {r['sweep']} | {r['walks']} | {r['bounces']}{mark} | "
                         f"{100 * r['rms_rel_error']:.2f}% | {bias} | {r['unfinished_max']:.1e} | "
                         f"{1e3 * r['forward_s']:.0f} / {1e3 * r.get('forward_cpu_s', float('nan')):.0f} ms | {jac} | "
                         f"{r['forward_load'][1][0]:.1f} |")
        lines.append("")
    t = data["fit_truth"]
    lines += [
        f"## End to end: fits of {t['product']}",
        "",
        f"`{t['path']}`: {t['n_points']} points, synthetic, truth `jaxcos.published(\"{t['product']}\")`, noise "
        f"2% + 0.002 (median {100 * t['median_noise_rel']:.1f}% of the value). `jaxcos.fit` with its defaults "
        f"({'multi-start' if s['fit_multistart'] else 'one start'}, seed 0) at each budget. *Checked*: the fitted "
        f"material evaluated at {s['check_budget'][0]} walks x {s['check_budget'][1]} bounces with an independent "
        f"key against the data (the truth scores {t['reduced_chi2_truth']:.2f}), and its BSDF against the "
        "truth's on the standard grid (same key for both).",
        "",
        "| walks | bounces | fit time wall / CPU | load | MC error / noise | reduced chi-square (fit's own) | "
        "reduced chi-square (checked) | BSDF error to truth, measured angles / standard grid | c_d error | "
        "theta_p error (deg) |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in data["fits"]:
        own = f"{r['reduced_chi2_fit']:.2f}" if r["reduced_chi2_fit"] is not None else ""
        lines.append(f"| {r['walks']} | {r['bounces']} | {r['time_s']:.0f} / {r.get('cpu_s', float('nan')):.0f} s | "
                     f"{r['load'][1][0]:.1f} | "
                     f"{r['mc_error_over_noise']:.2f} | {own} | {r['reduced_chi2_checked']:.2f} | "
                     f"{100 * r.get('bsdf_rms_rel_error_measured', float('nan')):.1f}% / "
                     f"{100 * r['bsdf_rms_rel_error']:.1f}% | {r['param_abs_errors']['c_d']:.2f} | "
                     f"{r['param_abs_errors']['theta_p_deg']:.1f} |")
    lines += ["", "![error against time](accuracy.png)", "", "![fits against budget](accuracy_fit.png)", ""]
    return "\n".join(lines)


def accuracy_benchmark(out_dir, *, quick=False, force=False, progress=None):
    """Run the sweep and the fits, write :data:`FILES` under ``out_dir``; return the data written to JSON.

    ``quick`` runs :data:`QUICK` (about a minute, for tests) instead of :data:`FULL`.
    Existing files are kept unless ``force``; everything is written to a
    temporary folder and moved in at the end.
    """
    say = progress or (lambda msg: None)
    settings = QUICK if quick else FULL
    targets = [os.path.join(out_dir, name) for name in FILES]
    refuse_overwrite(targets, force)
    data = dict(machine=machine_record(), quick=bool(quick), settings=dataclasses.asdict(settings),
                sweep=[], reference={})
    t0 = time.perf_counter()
    for product in settings.products:
        records, ref_info = sweep_product(product, settings, say)
        data["sweep"] += records
        data["reference"][product] = ref_info
    data["fits"], data["fit_truth"] = fit_budgets(settings, say)
    data["load_after"] = list(os.getloadavg())
    data["total_s"] = time.perf_counter() - t0
    targets = write_outputs(data, out_dir, force=force)
    say(f"wrote {', '.join(targets)} in {data['total_s']:.0f} s")
    return data


def write_outputs(data, out_dir, *, force=False):
    """Write :data:`FILES` for the ``data`` of :func:`accuracy_benchmark` (also to redraw them from a JSON)."""
    with staged_outputs(out_dir, FILES, force) as tmp:
        with open(os.path.join(tmp, FILES[0]), "w", encoding="utf-8") as fh:
            json.dump(data, fh, indent=1)
        with open(os.path.join(tmp, FILES[1]), "w", encoding="utf-8") as fh:
            fh.write(accuracy_table(data))
        accuracy_figure(data, os.path.join(tmp, FILES[2]))
        fit_figure(data, os.path.join(tmp, FILES[3]))
    return [os.path.join(out_dir, name) for name in FILES]


# --- the command ------------------------------------------------------------------------------


def _cmd_accuracy(args):
    from ..cli._main import progress

    accuracy_benchmark(args.out, quick=args.quick, force=args.force, progress=progress("bench accuracy"))


def add_command(sub):
    """Register ``jaxcos bench accuracy``."""
    p = sub.add_parser("bench", help="benchmarks of the estimator (accuracy against time)",
                       description="Benchmarks of jaxcos itself.")
    bench = p.add_subparsers(dest="benchmark", required=True, metavar="BENCHMARK")
    a = bench.add_parser("accuracy", help="error, unfinished energy, forward and Jacobian time against the budget",
                         description="Sweep walks per incidence and bounces, with exact and Monte Carlo single "
                         "scattering, for dewy1 and matte2 on the standard grid against a high-budget reference, "
                         "and fit a synthetic set at several budgets; writes " + ", ".join(FILES) + " under DIR. "
                         "The full run took 11 minutes on a quiet two-core machine, the fits 3.5 of them.")
    a.add_argument("--out", required=True, metavar="DIR")
    a.add_argument("--quick", action="store_true", help="tiny budgets, one product, one fit (a smoke test of about a minute): the numbers mean nothing")
    a.add_argument("--force", action="store_true", help="overwrite existing results in DIR")
    a.set_defaults(func=_cmd_accuracy)
