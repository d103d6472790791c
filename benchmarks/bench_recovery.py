"""Randomized recovery: does ``jaxcos.fit`` find materials it was never tuned to?

    python benchmarks/bench_recovery.py --n 40 --seed 1 --out /tmp/recovery
    python benchmarks/bench_recovery.py --quick --out /tmp/recovery_quick      # 2 sets, small budgets
    python benchmarks/bench_recovery.py --n 40 --seed 1 --sets 10-19 --out /tmp/recovery   # a subset
    python benchmarks/bench_recovery.py --n 40 --seed 1 --interface --out /tmp/recovery_interface

Each set ``i`` (0 .. N-1) is drawn from its own generator,
``numpy.random.default_rng([seed, i])``, so a set does not depend on which
others are run: ``--sets`` runs a subset, and a rerun into the same ``--out``
skips the sets already in ``sets.jsonl`` (resume). ``--fit-seed`` seeds the
fit (its key and random starts) and nothing else.

A set:

1. **Truth**: one layer, ``t = 16``, black base, ``phi_p = 0``; ``single_lobe``
   or ``two_lobe`` with equal odds; ``c_d`` U(0.3, 0.99), ``albedo_d`` U(0.7, 1)
   per channel, ``g1`` U(0, 0.9), ``g2`` U(-0.6, 0.3), ``w_g`` U(0.3, 1),
   ``albedo_p`` U(0.5, 1) per channel, ``alpha_p`` log-uniform on
   [0.005, 0.6], ``theta_p`` U(0, 30) degrees (the priors of issue 31).
2. **Angles**: the instrument's positions for one of the four products of
   ``jaxcos/data/grid.csv`` (drawn).
3. **Data**: the reflectance factor ``v = pi f`` from :func:`jaxcos.simulate`
   (MIS connection, unbiased and steadier for narrow lobes) at ``--sim-walks``
   walks x ``--sim-bounces`` bounces in batches under keys from the set's own
   generator, plus the bundled sets' noise (``scripts/make_measurements.py``):
   ``s = sqrt((0.02 v)^2 + 0.002^2)``, ``value = v + N(0, s^2)``, ``std = s``.
4. **Fit**: ``jaxcos.fit(meas, seed=fit_seed)``, every other argument its default
   (with ``--no-finer``, ``finer=False``: the selected start not refined again at four times the walks;
   with ``--thin-after N`` or ``none``, the fit's ``thin_after``).
5. **Score**: the fit's material and the truth, each checked as
   ``jaxcos.inference._fit.check`` does (pairs of independent batches: the
   material's own chi-square, free of Monte Carlo variance) at ``--eval-walks``
   walks in 16 batches under keys from the set's generator (independent of the
   fit's), the same keys for both (:func:`score`: their shared Monte Carlo error
   cancels in the ratio), with the fit's estimator (its connection) and each
   material's own lobe probabilities, per degree of freedom (``3 N - 12``). A
   set passes when the fit's is at most ``--tolerance`` (1.2) times the
   truth's. Where the ratio's jackknife SE is above ``--ratio-se`` (0.05) the
   score is taken again at four times the walks, up to ``--max-eval-walks``
   (:func:`settled_score`); the record says how many it took.

With ``--interface`` each truth also has a top interface (:func:`draw_interface`;
simulated with next-event estimation, the connection through it), and the fit
has ``interface=True``.

Writes, in ``--out``: ``data/set_XXX.csv`` (each set, truth in its metadata),
``sets.jsonl`` (one JSON record per set, appended as each finishes), ``sets.csv``
(one row per set) and ``summary.md`` (recovery rate, median time, the machine).
"""

import argparse
import csv
import importlib.resources
import json
import os
import sys
import time
from pathlib import Path

import equinox as eqx
import jax
import numpy as np

import jaxcos
from jaxcos.inference._bench import machine_record
from jaxcos.inference._fit import (LOBE_NAMES, batch_residuals, jackknife_se, make_problem, ordered_lobes, pair_terms,
                                  parameterization)
from jaxcos.io import Measurements, material_to_dict, save_measurements

GRID = importlib.resources.files("jaxcos") / "data" / "grid.csv"
PRODUCTS = (103, 105, 108, 112)
NOISE_RELATIVE, NOISE_ABSOLUTE = 0.02, 0.002  # the bundled sets' (scripts/make_measurements.py)
SIM_BATCH = 4096
CHECK_BATCHES = 16
NAMES = ("c_d", "albedo_d", "g1", "g2", "w_g", "albedo_p", "alpha_p", "theta_p")


# --- the sets -----------------------------------------------------------------------------


def read_grid(product):
    """``(theta_i, theta_o)`` in degrees of one product of the package's ``grid.csv``."""
    with GRID.open(newline="") as fh:
        rows = [r for r in csv.DictReader(fh) if int(r["product"]) == product]
    return np.array([float(r["theta_i"]) for r in rows]), np.array([float(r["theta_o"]) for r in rows])


def draw_truth(rng):
    """A random one-layer material from the priors of issue 31, and its variant."""
    variant = "single_lobe" if rng.uniform() < 0.5 else "two_lobe"
    values = dict(t=16.0, c_d=rng.uniform(0.3, 0.99), albedo_d=rng.uniform(0.7, 1.0, 3), g1=rng.uniform(0.0, 0.9),
                  g2=rng.uniform(-0.6, 0.3), w_g=rng.uniform(0.3, 1.0), albedo_p=rng.uniform(0.5, 1.0, 3),
                  alpha_p=float(np.exp(rng.uniform(np.log(0.005), np.log(0.6)))), theta_p=rng.uniform(0.0, 30.0))
    if variant == "single_lobe":
        values.update(w_g=1.0, g2=0.0)
    material = jaxcos.Material(layers=(jaxcos.Layer(**values),), variant=variant)
    return material, variant


def draw_interface(seed, index):
    """The top interface of set ``index`` with ``--interface``: ``eta`` U(1.2, 1.8), ``alpha_s`` log-uniform on
    [0.02, 0.5], from its own generator ``default_rng([seed, index, 1])``, so that the set's other draws are those
    of the set without it."""
    rng = np.random.default_rng([seed, index, 1])
    return jaxcos.Interface(eta=rng.uniform(1.2, 1.8), alpha_s=float(np.exp(rng.uniform(np.log(0.02), np.log(0.5)))))


@eqx.filter_jit
def _simulate(material, query, key, walks, bounces, connection):
    return jaxcos.simulate(material, query, key, walks=walks, bounces=bounces, connection=connection)


def simulate_set(material, theta_i, theta_o, key, walks, bounces):
    """Reflectance factor ``pi f`` and its standard error, ``(N, 3)``, from ``walks`` walks in batches.

    MIS connection (unbiased and steadier for narrow lobes); next-event estimation under a top interface,
    the only connection through it.
    """
    query = jaxcos.make_query(theta_i, theta_o)
    batch = min(walks, SIM_BATCH)
    connection = "nee" if material.interface is not None else "mis"
    means, errors = [], []
    for b in range(max(walks // batch, 1)):
        est = _simulate(material, query, jax.random.fold_in(key, b), batch, bounces, connection)
        means.append(np.asarray(est.f, float))
        errors.append(np.asarray(est.stderr, float))
    k = len(means)
    return np.pi * np.mean(means, axis=0), np.pi * np.sqrt(np.sum(np.square(errors), axis=0)) / k


def make_set(seed, index, sim_walks, sim_bounces, interface=False, mc_in_std=False):
    """Set ``index`` of generator ``seed``: ``(measurements, truth, variant, product, generator)``.

    The generator (``default_rng([seed, index])``) is returned for the later draws
    of the set (its check keys), so that they too depend on the set alone. With
    ``interface``, the truth has a top interface (:func:`draw_interface`). With
    ``mc_in_std``, the std columns also hold the simulation's own Monte Carlo
    error, ``sqrt(s^2 + mc^2)``: the value's deviation from the truth's curve,
    which a coverage study needs (the noise drawn is still ``s``).
    """
    rng = np.random.default_rng([seed, index])
    truth, variant = draw_truth(rng)
    if interface:
        truth = jaxcos.Material(layers=truth.layers, variant=variant, interface=draw_interface(seed, index))
    product = int(rng.choice(PRODUCTS))
    theta_i, theta_o = read_grid(product)
    sim_key = jax.random.key(int(rng.integers(2 ** 31)))
    v, mc = simulate_set(truth, theta_i, theta_o, sim_key, sim_walks, sim_bounces)
    s = np.sqrt((NOISE_RELATIVE * v) ** 2 + NOISE_ABSOLUTE ** 2)
    values = v + s * rng.standard_normal(v.shape)
    ratio = mc / s
    metadata = {
        "quantity": "reflectance_factor",
        "sample": f"random recovery set {index} of generator seed {seed}, synthetic",
        "parameters": json.dumps(material_to_dict(truth)),
        "angles": f"positions measured for product {product} in jaxcos/data/grid.csv",
        "noise": f"value = v + N(0, s^2), s = sqrt(({NOISE_RELATIVE} v)^2 + {NOISE_ABSOLUTE}^2)",
        "monte_carlo": f"walks = {sim_walks}, bounces = {sim_bounces}, "
                       f"{'NEE' if interface else 'MIS'} connection; MC error / noise std: "
                       f"median {np.median(ratio):.2f}, max {ratio.max():.2f}",
    }
    if mc_in_std:
        metadata["std"] = "sqrt(s^2 + mc^2): the noise and the simulation's Monte Carlo error"
    std = np.sqrt(s ** 2 + mc ** 2) if mc_in_std else s
    meas = Measurements(theta_i=theta_i, theta_o=theta_o, phi_o=np.zeros_like(theta_i), values=values, std=std,
                        metadata=metadata, path=f"set_{index:03d}.csv")
    return meas, truth, variant, product, rng, float(np.median(ratio))


def physical(material):
    """``{name: value or [r, g, b]}`` of the first layer's parameters in :data:`NAMES`."""
    layer = material.layers[0]
    out = {}
    for n in NAMES:
        v = np.asarray(getattr(layer, n), float)
        out[n] = [float(c) for c in v] if v.ndim else float(v)
    return out


def _interface(material):
    """``{"eta": ..., "alpha_s": ...}`` of a material's top interface."""
    return {n: float(getattr(material.interface, n)) for n in ("eta", "alpha_s")}


def _batches(meas, material, key, walks, batches, first):
    """Batches ``first, ..., batches - 1`` of ``material``'s check (``batch_residuals``) and its dof."""
    # the fit's parameterization: its dof and its map
    param = parameterization("two_lobe", interface=material.interface is not None, template=material)
    problem = make_problem(meas, param, key=key, walks=walks // batches, reference=material)
    r = batch_residuals(problem, meas, param.from_material(material), key, walks, batches, first=first)[0]
    return r, max(r[0].size - param.size, 1)


def score(fitted, truth):
    """The fit's and the truth's reduced chi-square under the same independent keys, with their ratio.

    ``fitted``, ``truth``: each material's batch residuals ``(K, N', 3)`` and
    its dof (:func:`_batches`), batch ``b`` under ``fold_in(key, b)`` for
    both (common random numbers: what Monte Carlo error the two share
    cancels in the ratio; narrow lobes share little, a material a little off
    the truth's lobe meeting it on other walks). Each is
    :func:`~jaxcos.inference._fit.check`'s pair estimate. Returns ``(fit,
    fit_se, truth, truth_se, ratio, ratio_se)``, the SEs the delete-one-batch
    jackknife's, the ratio's taken jointly.
    """
    terms = []
    for r, dof in (fitted, truth):
        estimate, leave_one_out = pair_terms(r)
        terms.append((estimate / dof, leave_one_out / dof))
    (f, f_loo), (t, t_loo) = terms
    return f, jackknife_se(f_loo), t, jackknife_se(t_loo), f / t, jackknife_se(f_loo / t_loo)


def settled_score(meas, fitted, truth, key, walks, target, most):
    """:func:`score` at ``walks``, then at four times as many while the ratio's SE is above ``target``.

    At most ``most`` walks. A narrow lobe's pair estimate is heavy-tailed: at
    16384 walks its SE can exceed the 20% that tells a pass from a fail. Each
    score has four times the batches of the one before, of as many walks each,
    its first batches that score's (taken once), so it refines it. Returns
    :func:`score`'s six numbers and the walks they came from.
    """
    batches, taken = CHECK_BATCHES, [None, None]
    while True:
        for i, material in enumerate((fitted, truth)):
            done = 0 if taken[i] is None else len(taken[i][0])
            new, dof = _batches(meas, material, key, walks, batches, done)
            taken[i] = (new if taken[i] is None else np.concatenate([taken[i][0], new]), dof)
        out = score(*taken)
        if out[-1] <= target or 4 * walks > most:
            return out + (walks,)
        walks, batches = 4 * walks, 4 * batches


def errors(fitted, truth, variant):
    """Per parameter: fitted minus true (the largest channel's for RGB; ``alpha_p`` as a log10 ratio).

    For a single-lobe truth, ``g1``'s error is that of the fit's mean cosine
    ``w_g g1 + (1 - w_g) g2`` and ``g2``, ``w_g`` have none (NaN): any ``w_g`` with
    ``g2 = g1`` is the same material. A two-lobe truth is compared with its lobes labelled as the fit labels
    them, the more forward first (``jaxcos.inference._fit.ordered_lobes``).
    """
    fitted = dict(fitted)
    if variant == "single_lobe":
        fitted["g1"] = fitted["w_g"] * fitted["g1"] + (1 - fitted["w_g"]) * fitted["g2"]
    else:
        lobes = ordered_lobes(LOBE_NAMES, [float(truth[n]) for n in LOBE_NAMES])
        truth = {**truth, **dict(zip(LOBE_NAMES, lobes))}
    out = {}
    for n in NAMES:
        f, t = np.asarray(fitted[n]), np.asarray(truth[n])
        d = np.log10(f / t) if n == "alpha_p" else f - t
        out[n] = float(d.flat[np.argmax(np.abs(d))]) if d.ndim else float(d)
    if variant == "single_lobe":
        out.update(g2=float("nan"), w_g=float("nan"))
    return out


def _thin_after(text):
    """``--thin-after``: ``"default"`` (the fit's own), ``None`` for ``"none"`` (every walk making every step), or a
    positive step count."""
    if text in ("default", "none"):
        return None if text == "none" else text
    if not text.isdigit() or int(text) < 1:
        raise argparse.ArgumentTypeError(f"expected a positive step count, 'none' or 'default', not {text!r}")
    return int(text)


def run_set(args, index):
    started = time.perf_counter()
    meas, truth, variant, product, rng, mc_ratio = make_set(args.seed, index, args.sim_walks, args.sim_bounces,
                                                            interface=args.interface)
    data = Path(args.out) / "data"
    data.mkdir(parents=True, exist_ok=True)
    save_measurements(meas, data / f"set_{index:03d}.csv", overwrite=True)
    simulated = time.perf_counter() - started
    stages = []
    t0 = time.perf_counter()
    options = {} if args.thin_after == "default" else dict(thin_after=args.thin_after)
    result = jaxcos.fit(meas, seed=args.fit_seed, interface=args.interface or None, finer=not args.no_finer,
                        progress=lambda m: stages.append(round(time.perf_counter() - t0, 1)), **options)
    fit_time = time.perf_counter() - t0
    eval_key = jax.random.key(int(rng.integers(2 ** 31)))
    fit_chi2, fit_se, truth_chi2, truth_se, ratio, ratio_se, eval_walks = settled_score(
        meas, result.material, truth, eval_key, args.eval_walks, args.ratio_se, args.max_eval_walks)
    fitted, true = physical(result.material), physical(truth)
    record = dict(
        set=index, seed=args.seed, fit_seed=args.fit_seed, finer=not args.no_finer, thin_after=args.thin_after,
        variant=variant, product=product,
        n_points=int(meas.values.shape[0]), mc_noise_ratio=round(mc_ratio, 3),
        fit_chi2=fit_chi2, fit_chi2_se=fit_se, truth_chi2=truth_chi2, truth_chi2_se=truth_se,
        ratio=ratio, ratio_se=ratio_se, passed=bool(ratio <= args.tolerance), scoring="common keys",
        eval_walks=eval_walks,
        fit_time_s=round(fit_time, 1), simulate_time_s=round(simulated, 1), stage_times_s=stages,
        fit_own_check=result.record.check.reduced_chi2, n_evaluations=result.record.n_evaluations,
        iterations=result.record.iterations, load_average=[round(v, 2) for v in os.getloadavg()],
        truth=true, fitted=fitted, error=errors(fitted, true, variant),
        interface=dict(truth=_interface(truth), fitted=_interface(result.material)) if args.interface else None,
        starts=[dict(label=s.label, loss=s.loss, material_chi2=s.material_chi2) for s in result.starts],
        fixed_starts=list(result.record.fixed_starts), connection=result.record.connection,
        final_step=None if result.record.final_step is None else result.record.final_step.to_json(),
    )
    append_record(args.out, record)
    return record


# --- the report ---------------------------------------------------------------------------


def append_record(out, record):
    """Append one set's record to ``OUT/sets.jsonl``."""
    with open(Path(out) / "sets.jsonl", "a") as fh:
        fh.write(json.dumps(record) + "\n")


def pending_sets(args):
    """``(done, todo)``: the records already in ``OUT/sets.jsonl`` (made if absent) and the sets of ``--n`` and
    ``--sets`` still to run (none with ``--report-only``)."""
    Path(args.out).mkdir(parents=True, exist_ok=True)
    done = load_records(args.out)
    return done, [] if args.report_only else [i for i in parse_sets(args.sets, args.n) if i not in done]


def load_records(out):
    """``{set: record}`` of ``OUT/sets.jsonl`` (empty when there is none): the sets already run."""
    path = Path(out) / "sets.jsonl"
    if not path.exists():
        return {}
    records = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    return {r["set"]: r for r in records}


def write_reports(args, records):
    out = Path(args.out)
    rows = sorted(records.values(), key=lambda r: r["set"])
    for r in rows:  # recomputed, so that a report of older records follows errors()
        r["error"] = errors(r["fitted"], r["truth"], r["variant"])
    columns = ["set", "variant", "product", "passed", "fit_chi2", "fit_chi2_se", "truth_chi2", "truth_chi2_se",
               "ratio", "fit_time_s"] + [f"err_{n}" for n in NAMES] + ["best_start"]
    with open(out / "sets.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(columns)
        for r in rows:
            best = min(r["starts"], key=lambda s: s["material_chi2"])["label"]
            w.writerow([r["set"], r["variant"], r["product"], int(r["passed"]), f"{r['fit_chi2']:.3f}",
                        f"{r['fit_chi2_se']:.3f}", f"{r['truth_chi2']:.3f}", f"{r['truth_chi2_se']:.3f}",
                        f"{r['ratio']:.3f}", r["fit_time_s"]] + [f"{r['error'][n]:+.3f}" for n in NAMES] + [best])
    n = len(rows)
    passed = sum(r["passed"] for r in rows)
    times = [r["fit_time_s"] for r in rows]
    machine = machine_record()
    lines = [
        "# Randomized recovery", "",
        f"Command: `python benchmarks/bench_recovery.py {' '.join(sys.argv[1:])}`", "",
        f"- sets: {n} (generator seed {args.seed}, fit seed {args.fit_seed}{', finer=False' * args.no_finer}; "
        f"simulated at {args.sim_walks} walks x "
        f"{args.sim_bounces} bounces, scored at {args.eval_walks} walks under independent keys, the same for fit "
        f"and truth)",
        f"- **recovered: {passed} of {n}** ({100 * passed / max(n, 1):.0f}%): fit's material chi-square "
        f"<= {args.tolerance} x the truth's",
        f"- fit time: median {np.median(times) if times else float('nan'):.1f} s, max "
        f"{max(times) if times else float('nan'):.1f} s",
        f"- machine: {machine['platform']}, {machine['cpus']} CPUs, jax {machine['jax']} ({machine['backend']}), "
        f"load average now {machine['load_average']}", "",
        "| set | variant | product | fit chi2 | truth chi2 | ratio | time s | passed | largest errors |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        worst = sorted([kv for kv in r["error"].items() if np.isfinite(kv[1])],
                       key=lambda kv: -abs(kv[1]) / _scale(kv[0]))[:3]
        lines.append(f"| {r['set']} | {r['variant']} | {r['product']} | {r['fit_chi2']:.2f} +- {r['fit_chi2_se']:.2f} "
                     f"| {r['truth_chi2']:.2f} +- {r['truth_chi2_se']:.2f} | {r['ratio']:.2f}{_se(r)} | "
                     f"{r['fit_time_s']} | "
                     f"{'yes' if r['passed'] else '**no**'} | "
                     + ", ".join(f"{k} {v:+.2f}" for k, v in worst) + " |")
    (out / "summary.md").write_text("\n".join(lines) + "\n")
    return passed, n, times


def _se(record):
    """`` +- SE`` of a record's ratio; empty for a record scored under separate keys (before the ratio's SE)."""
    return f" +- {record['ratio_se']:.2f}" if "ratio_se" in record else ""


def _scale(name):
    """A typical range of a parameter's error, to order them (``alpha_p``: decades)."""
    return {"theta_p": 30.0, "alpha_p": 1.0}.get(name, 1.0)


def parse_sets(text, n):
    if not text:
        return list(range(n))
    out = []
    for part in text.split(","):
        lo, _, hi = part.partition("-")
        out += list(range(int(lo), int(hi or lo) + 1))
    return out


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--n", type=int, default=40, help="number of sets (default 40)")
    parser.add_argument("--seed", type=int, default=1, help="the generator's seed (default 1)")
    parser.add_argument("--fit-seed", type=int, default=0, help="the fit's seed (default 0)")
    parser.add_argument("--sets", default="", help="run only these sets, e.g. 0-9,12 (default: all N)")
    parser.add_argument("--out", required=True, help="output folder (outside the repository, e.g. /tmp/recovery)")
    parser.add_argument("--quick", action="store_true", help="2 sets at small generator and scoring budgets")
    parser.add_argument("--sim-walks", type=int, default=16384, help="walks of the simulated data (default 16384)")
    parser.add_argument("--sim-bounces", type=int, default=128, help="bounces of the simulated data (default 128)")
    parser.add_argument("--eval-walks", type=int, default=16384, help="walks of each score (default 16384)")
    parser.add_argument("--tolerance", type=float, default=1.2, help="pass: fit chi2 <= this x truth's (1.2)")
    parser.add_argument("--ratio-se", type=float, default=0.05,
                        help="score again at 4x the walks while the ratio's SE is above this (default 0.05)")
    parser.add_argument("--max-eval-walks", type=int, default=262144,
                        help="the most walks of a score (default 262144)")
    parser.add_argument("--interface", action="store_true",
                        help="truths under a top interface (draw_interface), fitted with --interface")
    parser.add_argument("--no-finer", action="store_true",
                        help="fit with finer=False (the selected start not refined again at 4x the walks)")
    parser.add_argument("--thin-after", type=_thin_after, default="default",
                        help="the fit's thin_after (jaxcos.fit), a step count or 'none' (default: the fit's own)")
    parser.add_argument("--report-only", action="store_true", help="rewrite sets.csv and summary.md from sets.jsonl")
    args = parser.parse_args()
    if args.quick:
        args.n, args.sim_walks, args.eval_walks, args.max_eval_walks = min(args.n, 2), 8192, 4096, 4096
    done, todo = pending_sets(args)
    for index in todo:
        r = run_set(args, index)
        done[index] = r
        print(f"set {index}: {r['variant']} on {r['product']}, fit {r['fit_chi2']:.2f} truth {r['truth_chi2']:.2f} "
              f"-> {'pass' if r['passed'] else 'FAIL'} in {r['fit_time_s']} s", flush=True)
    passed, n, times = write_reports(args, done)
    median = np.median(times) if times else float("nan")
    print(f"recovered {passed} of {n}; median fit time {median:.1f} s; wrote {args.out}/summary.md")


if __name__ == "__main__":
    main()
