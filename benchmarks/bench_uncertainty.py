"""Posterior spreads: coverage of random truths, and one bundled report's cost.

    python benchmarks/bench_uncertainty.py coverage --n 40 --seed 3 --out /tmp/coverage
    python benchmarks/bench_uncertainty.py coverage --n 40 --seed 3 --no-std --out /tmp/coverage_nostd
    python benchmarks/bench_uncertainty.py coverage --n 40 --seed 3 --interface --out /tmp/coverage_interface
    python benchmarks/bench_uncertainty.py coverage --quick --out /tmp/coverage_quick   # 2 sets, small budgets
    python benchmarks/bench_uncertainty.py report [--data measurements/matte2.csv]

**Coverage.** Set ``i`` is set ``i`` of the randomized recovery benchmark
(``bench_recovery.py``, generator ``default_rng([seed, i])``): a random
one-layer material from the priors of issue 31 on the instrument's angles for
one product, simulated at ``--sim-walks`` walks under its own keys (four
times the recovery benchmark's: the simulation's own error is then a quarter
of the noise in the median), with the bundled sets' noise and std columns
that hold the noise and that error in quadrature (the value's deviation from
the truth's curve) (``--no-std`` removes them: the posterior
then estimates the noise, :class:`jaxcos.inference.NoiseModel`; ``--interface``
puts each truth under a top interface, whose ``eta`` and ``alpha_s`` are then
sampled too). The fit starts
from the truth in the truth's variant (``jaxcos.fit(meas, variant=...,
start=truth, finer=False)``), so that a failure of the search (issue 31) is not counted as
one of the error bars (the posterior searches its own anchor from there, so the
fit's last refinement at four times the walks is left out, as in the sets run
before it existed); ``jaxcos.uncertainty`` then runs with its defaults.
``--from-default`` fits as a user's ``jaxcos uncertainty`` does instead, from
the default start with the fit's whole search: the anchor search starts
where the fit ends, and a fit that missed counts against the intervals.

Per set and parameter: the truth's place in the posterior (the fraction of
draws below it, the chain's draws plus their Monte Carlo shift, as the
intervals are made), whether the 68% and 95% intervals hold it, and whether
the data identify the parameter (its 95% interval narrower than half the prior).
The same is recorded for the chain's draws alone (``chain_only``: the
intervals without the Monte Carlo shift), a row of the table, and for the
quantities of the parameters that ``jaxcos uncertainty`` reports besides them
(``derived``: the diffusers' mean cosine ``g_mean`` of a two-lobe set), a row
each.
A calibrated posterior holds the truth at each nominal level within the
binomial band. Each set is appended to ``sets.jsonl`` as it finishes (a rerun
into the same ``--out`` resumes); ``summary.md`` and ``coverage.png``
(coverage against nominal level) are rewritten after each.

**Report.** ``jaxcos uncertainty`` on a bundled file with its defaults; writes
``benchmarks/results/uncertainty_report.json``.
"""

import argparse
import dataclasses
import json
import os
import sys
import time
from pathlib import Path

import numpy as np
from scipy.stats import binom

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)

import jaxcos  # noqa: E402
from jaxcos.inference._bench import machine_record  # noqa: E402
from jaxcos.inference._fit import ordered_lobes  # noqa: E402
from jaxcos.inference._posterior import HI_WALKS, derived  # noqa: E402
from bench_recovery import append_record, make_set, pending_sets  # noqa: E402

LEVELS = np.linspace(0.05, 0.95, 19)
"""Nominal levels of the coverage curve (central intervals)."""


def _place(draws, true):
    """``(P,)``: the fraction of ``draws`` (``(S, P)``) below each truth, ties counted half (the truth's PIT); a
    scalar for ``(S,)`` draws of one quantity."""
    return np.mean(draws < true, axis=0) + 0.5 * np.mean(draws == true, axis=0)


def _holds(q, truth):
    """Whether the intervals of percentiles ``q`` (2.5, 16, 50, 84, 97.5) hold ``truth``, and its offset ``z``.

    ``z``: median minus truth over the 68% half-width.
    """
    return dict(in68=bool(q[1] <= truth <= q[3]), in95=bool(q[0] <= truth <= q[4]),
                z=float((q[2] - truth) / max(0.5 * (q[3] - q[1]), 1e-300)))


def _interval(s, truth, pit):
    """A record's row for one quantity: its summary ``s``'s percentiles, the truth, its PIT, and :func:`_holds`."""
    return dict(truth=float(truth), median=s["median"], p16=s["p16"], p84=s["p84"], p2_5=s["p2.5"], p97_5=s["p97.5"],
                pit=float(pit), **_holds([s[k] for k in ("p2.5", "p16", "median", "p84", "p97.5")], truth))


def run_set(args, index):
    started = time.perf_counter()
    meas, truth, variant, product, rng, mc_ratio = make_set(args.seed, index, args.sim_walks, args.sim_bounces,
                                                            interface=args.interface, mc_in_std=True)
    if args.no_std:
        meas = dataclasses.replace(meas, std=None)
    t0 = time.perf_counter()
    if args.from_default:  # as `jaxcos uncertainty` runs: the fit's own search, its finer stage included
        fitted = jaxcos.fit(meas, variant=variant, seed=args.fit_seed)
    else:
        fitted = jaxcos.fit(meas, variant=variant, start=truth, seed=args.fit_seed, finer=False)
    fit_time = time.perf_counter() - t0
    t0 = time.perf_counter()
    post = jaxcos.uncertainty(meas, fitted, seed=args.fit_seed, hi_walks=args.hi_walks)
    post_time = time.perf_counter() - t0
    param = fitted.param
    # every value with the diffusers' lobes labelled as the posterior reports them, the more forward first
    ordered = lambda v: ordered_lobes(post.labels, v)
    true = ordered(np.asarray(param.to_physical(param.from_material(truth)), float))
    low, high = param.bounds()
    # the draws the intervals are percentiles of: the chain's, each shifted by a draw of its Monte Carlo error
    shift = rng.multivariate_normal(np.zeros(param.size), post.mc_cov, size=post.chain.samples.shape[0],
                                    method="eigh")
    draws = ordered(np.clip(post.chain.samples + shift, low, high))
    pit = _place(draws, true)
    # the chain's own draws, without the Monte Carlo shift: the intervals of a posterior that leaves it out
    chain = ordered(np.clip(post.chain.samples, low, high))
    chain_q = np.percentile(chain, [2.5, 16, 50, 84, 97.5], axis=0)
    chain_pit = _place(chain, true)
    rows = {}
    for i, name in enumerate(post.labels):
        s = post.summary[name]
        rows[name] = dict(**_interval(s, true[i], pit[i]),
                          identified=bool(s["p97.5"] - s["p2.5"] < 0.5 * (high[i] - low[i])),
                          unresolved=name in post.record.unresolved,
                          mc_sd=s["mc_sd"], laplace_sd=s["laplace_sd"],
                          chain_only=dict(pit=float(chain_pit[i]), **_holds(chain_q[:, i], true[i])))
    # quantities of the parameters (the diffusers' mean cosine of a two-lobe fit), over the same draws
    true_derived, draws_derived = derived(post.labels, true), derived(post.labels, draws)
    derived_rows = {}
    for name, s in post.derived.items():
        t = true_derived[name]
        derived_rows[name] = dict(**_interval(s, t, _place(draws_derived[name], t)),
                                  identified=bool(s["p97.5"] - s["p2.5"] < 1.0))  # half of [-1, 1]
    record = dict(
        set=index, seed=args.seed, fit_seed=args.fit_seed, variant=variant, product=product, no_std=args.no_std,
        interface=args.interface, fit_start="default" if args.from_default else "truth",
        n_points=int(meas.values.shape[0]), mc_noise_ratio=round(mc_ratio, 3), converged=post.converged, chain_in_tau=post.record.chain_in_tau,
        min_ess=float(np.min(post.chain.ess)), fit_time_s=round(fit_time, 1), posterior_time_s=round(post_time, 1),
        total_time_s=round(time.perf_counter() - started, 1), hi_walks=args.hi_walks,
        noise_relative=post.record.noise_relative, noise_absolute=post.record.noise_absolute,
        chi2_high_budget_at_anchor=post.record.chi2_high_budget_at_anchor, parameters=rows, derived=derived_rows,
        load_average=[round(v, 2) for v in os.getloadavg()],
    )
    append_record(args.out, record)
    return record


def band(n, p):
    """The central 95% binomial band of a coverage fraction at nominal ``p`` from ``n`` pairs."""
    return binom.ppf(0.025, n, p) / n, binom.ppf(0.975, n, p) / n


def _bootstrap(chosen, key, draws=2000):
    """The central 95% interval of the fraction of ``chosen`` pairs with ``key`` over resamples of their sets."""
    by_set = {}
    for set_index, _, p in chosen:
        by_set.setdefault(set_index, []).append(bool(p[key]))
    hits = np.array([sum(v) for v in by_set.values()], float)
    counts = np.array([len(v) for v in by_set.values()], float)
    pick = np.random.default_rng(0).integers(0, hits.size, (draws, hits.size))
    fractions = hits[pick].sum(axis=1) / counts[pick].sum(axis=1)
    return np.percentile(fractions, [2.5, 97.5])


def _group(name):
    """A parameter's group for the tables: RGB channels together."""
    return name.split("[")[0]


def coverage_curve(pits):
    """Fraction of central intervals at each of :data:`LEVELS` that hold the truth, from the truths' PIT values."""
    pits = np.asarray(pits, float)
    return np.array([np.mean(np.abs(pits - 0.5) <= level / 2) for level in LEVELS])


def write_reports(args, records):
    out = Path(args.out)
    sets = sorted(records.values(), key=lambda r: r["set"])
    pairs = [(r["set"], name, p) for r in sets for name, p in r["parameters"].items()]
    identified = [(s, n, p) for s, n, p in pairs if p["identified"]]
    groups = list(dict.fromkeys(_group(n) for _, n, _ in pairs))
    machine = machine_record()
    times = [r["total_time_s"] for r in sets]
    lines = [
        "# Posterior coverage of random truths", "",
        f"Command: `python benchmarks/bench_uncertainty.py {' '.join(sys.argv[1:])}`", "",
        f"- sets: {len(sets)} random materials (generator seed {args.seed}, fit seed {args.fit_seed}), "
        f"{'std columns removed, noise estimated' if args.no_std else 'with std columns'}"
        f"{', under a top interface' if args.interface else ''}"
        f"{'; fits from the default start' if args.from_default else '; fits from the truth'}; data at "
        f"{args.sim_walks} walks x {args.sim_bounces} bounces; posterior at {args.hi_walks} walks",
        f"- chains converged: {sum(r['converged'] for r in sets)} of {len(sets)}; smallest ESS "
        f"{min((r['min_ess'] for r in sets), default=float('nan')):.0f}",
        f"- time per set (fit + posterior): median {np.median(times) if times else float('nan'):.0f} s, total "
        f"{sum(times):.0f} s",
        f"- machine: {machine['platform']}, {machine['cpus']} CPUs, jax {machine['jax']} ({machine['backend']}), "
        f"load average now {machine['load_average']}", "",
        "Coverage: the fraction of (set, parameter) pairs whose interval holds the truth, with the central 95% "
        "binomial band of a calibrated posterior at that count (`band`), which takes the pairs as independent, "
        "and the 95% interval of the fraction over bootstrap resamples of the sets (`sets`): the parameters of one "
        "set are correlated, so its pairs tend to hold or miss together. `identified`: the pairs whose 95% "
        "interval is narrower than half the prior.", "",
        "| parameters | pairs | 68% | band | sets | 95% | band | sets | identified pairs | 68% | 95% |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]

    def row(label, chosen):
        n = len(chosen)
        if not n:
            return None
        ident = [p for _, _, p in chosen if p["identified"]]
        c68 = np.mean([p["in68"] for _, _, p in chosen])
        c95 = np.mean([p["in95"] for _, _, p in chosen])
        b68, b95 = band(n, 0.68), band(n, 0.95)
        flag = lambda c, b: "" if b[0] <= c <= b[1] else " **out**"
        i68 = f"{np.mean([p['in68'] for p in ident]):.3f}" if ident else "-"
        i95 = f"{np.mean([p['in95'] for p in ident]):.3f}" if ident else "-"
        s68, s95 = (_bootstrap(chosen, k) for k in ("in68", "in95"))
        return (f"| {label} | {n} | {c68:.3f}{flag(c68, b68)} | [{b68[0]:.3f}, {b68[1]:.3f}] | "
                f"[{s68[0]:.3f}, {s68[1]:.3f}] | {c95:.3f}{flag(c95, b95)} | [{b95[0]:.3f}, {b95[1]:.3f}] | "
                f"[{s95[0]:.3f}, {s95[1]:.3f}] | {len(ident)} | {i68} | {i95} |")

    variants = {r["set"]: r["variant"] for r in sets}

    def with_variants(label, variant_label, chosen):
        lines.append(row(label, chosen))
        if len(set(variants.values())) > 1:  # a posterior's width depends on the variant: each on its own
            for v in sorted(set(variants.values())):
                lines.append(row(variant_label.format(v.replace("_", "-")), [x for x in chosen if variants[x[0]] == v]))

    with_variants("all", "all, {} sets", pairs)
    for g in groups:
        lines.append(row(f"`{g}`", [x for x in pairs if _group(x[1]) == g]))
    derived_pairs = [(r["set"], name, p) for r in sets for name, p in r.get("derived", {}).items()]
    for name in dict.fromkeys(n for _, n, _ in derived_pairs):  # sets run since it was recorded
        lines.append(row(f"derived: `{name}`", [x for x in derived_pairs if x[1] == name]))
    chain_only = [(s, n, dict(p["chain_only"], identified=p["identified"])) for s, n, p in pairs if "chain_only" in p]
    if chain_only:  # the same chains' intervals without the Monte Carlo shift (sets run since it was recorded)
        with_variants("all, chain only (no Monte Carlo shift)", "{} sets, chain only", chain_only)
    lines += ["", "| set | variant | product | points | converged | chain in tau | min ESS | time s | held at 68% | "
              "held at 95% | not identified | farthest (median - truth over the 68% half-width) |",
              "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in sets:
        ps = r["parameters"]
        worst = max(ps, key=lambda n: abs(ps[n]["z"]))
        lines.append(f"| {r['set']} | {r['variant']} | {r['product']} | {r['n_points']} | "
                     f"{'yes' if r['converged'] else '**no**'} | {r['chain_in_tau']:.0f} | {r['min_ess']:.0f} | "
                     f"{r['total_time_s']:.0f} | {sum(p['in68'] for p in ps.values())}/{len(ps)} | "
                     f"{sum(p['in95'] for p in ps.values())}/{len(ps)} | "
                     f"{', '.join(n for n, p in ps.items() if not p['identified']) or '-'} | "
                     f"{worst} {ps[worst]['z']:+.1f} |")
    if args.no_std:
        lines += ["", "Estimated noise (the data's: std = sqrt((0.02 v)^2 + 0.002^2)): relative "
                  + ", ".join(f"{r['noise_relative']:.3g}" for r in sets) + "; absolute "
                  + ", ".join(f"{r['noise_absolute']:.2g}" for r in sets) + "."]
    (out / "summary.md").write_text("\n".join(x for x in lines if x is not None) + "\n")
    _figure(pairs, identified, groups, variants, derived_pairs, out / "coverage.png")
    return pairs


def _figure(pairs, identified, groups, variants, derived_pairs, path):
    from matplotlib.figure import Figure

    fig = Figure(figsize=(9, 4.2), constrained_layout=True)
    ax, bx = fig.subplots(1, 2)
    n = len(pairs)
    lo, hi = zip(*(band(n, p) for p in LEVELS))
    for axis in (ax, bx):
        axis.plot([0, 1], [0, 1], color="0.5", lw=0.8)
        axis.set_xlabel("nominal level of the central interval")
        axis.set_ylabel("fraction holding the truth")
        axis.set_xlim(0, 1)
        axis.set_ylim(0, 1)
    ax.fill_between(LEVELS, lo, hi, color="0.85", label=f"binomial 95% band ({n} pairs)")
    ax.plot(LEVELS, coverage_curve([p["pit"] for _, _, p in pairs]), "k.-", label="all parameters")
    if identified:
        ax.plot(LEVELS, coverage_curve([p["pit"] for _, _, p in identified]), ".--", color="tab:blue",
                label=f"identified ({len(identified)} pairs)")
    if len(set(variants.values())) > 1:
        for v, colour in zip(sorted(set(variants.values())), ("tab:orange", "tab:green")):
            chosen = [p["pit"] for s, _, p in pairs if variants[s] == v]
            ax.plot(LEVELS, coverage_curve(chosen), ".:", color=colour,
                    label=f"{v.replace('_', '-')} sets ({len(chosen)} pairs)")
    ax.legend(fontsize=8, loc="upper left")
    ax.set_title("all parameters")
    for g in groups:
        chosen = [p["pit"] for _, name, p in pairs if _group(name) == g]
        bx.plot(LEVELS, coverage_curve(chosen), ".-", lw=0.8, ms=3, label=f"{g} ({len(chosen)})")
    for name in dict.fromkeys(n for _, n, _ in derived_pairs):  # quantities of the parameters, dashed
        chosen = [p["pit"] for _, n, p in derived_pairs if n == name]
        bx.plot(LEVELS, coverage_curve(chosen), "k.--", lw=1.2, ms=3, label=f"{name} ({len(chosen)}, derived)")
    bx.legend(fontsize=7, loc="upper left", ncol=2)
    bx.set_title("per parameter")
    fig.savefig(path, dpi=90)


def coverage(args):
    if args.quick:
        args.n, args.sim_walks, args.hi_walks = min(args.n, 2), 8192, 2048
    done, todo = pending_sets(args)
    for index in todo:
        r = run_set(args, index)
        done[index] = r
        ps = r["parameters"].values()
        print(f"set {index}: {r['variant']} on {r['product']}, held at 68% {sum(p['in68'] for p in ps)}/{len(ps)}, "
              f"at 95% {sum(p['in95'] for p in ps)}/{len(ps)}, {r['total_time_s']:.0f} s", flush=True)
        write_reports(args, done)
    pairs = write_reports(args, done)
    print(f"coverage over {len(pairs)} pairs: 68% {np.mean([p['in68'] for _, _, p in pairs]):.3f}, "
          f"95% {np.mean([p['in95'] for _, _, p in pairs]):.3f}; wrote {args.out}/summary.md and coverage.png")


def report(args):
    from jaxcos.cli import main

    out = os.path.join("/tmp", "jaxcos-bench-uncertainty")
    t0 = time.perf_counter()
    status = main(["uncertainty", args.data, "--out", out, "--force"])
    elapsed = time.perf_counter() - t0
    with open(os.path.join(out, "posterior.json"), encoding="utf-8") as fh:
        doc = json.load(fh)
    result = dict(machine=machine_record(), data=args.data, exit_status=status, time_s=elapsed,
                  fit_time_s=doc["fit"].get("time_s"), posterior_time_s=doc["record"]["time_s"],
                  sampling_time_s=doc["record"]["sampling_time_s"], diagnostics=doc["diagnostics"],
                  mc={k: doc["record"][k] for k in ("mc_anchor_error_over_noise", "mc_model_error_over_noise")},
                  parameters=doc["parameters"])
    os.makedirs(os.path.join(HERE, "results"), exist_ok=True)
    target = os.path.join(HERE, "results", "uncertainty_report.json")
    with open(target, "w", encoding="utf-8") as fh:
        json.dump(result, fh, indent=1, default=float)
    print(f"{args.data}: exit {status} in {elapsed:.0f} s; wrote {target}")


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="what", required=True)
    c = sub.add_parser("coverage", help="coverage of random truths")
    c.add_argument("--n", type=int, default=40, help="number of sets (default 40)")
    c.add_argument("--seed", type=int, default=3, help="the generator's seed (default 3)")
    c.add_argument("--fit-seed", type=int, default=0, help="the fit's and the posterior's seed (default 0)")
    c.add_argument("--sets", default="", help="run only these sets, e.g. 0-9,12 (default: all N)")
    c.add_argument("--out", required=True, help="output folder (outside the repository, e.g. /tmp/coverage)")
    c.add_argument("--no-std", action="store_true", help="remove the std columns: the posterior estimates the noise")
    c.add_argument("--interface", action="store_true",
                   help="truths under a top interface (bench_recovery.draw_interface): eta and alpha_s sampled too")
    c.add_argument("--from-default", action="store_true",
                   help="fit from the default start, as `jaxcos uncertainty` does (search failures count)")
    c.add_argument("--quick", action="store_true", help="2 sets at small budgets")
    c.add_argument("--report-only", action="store_true", help="rewrite summary.md and coverage.png from sets.jsonl")
    c.add_argument("--sim-walks", type=int, default=65536, help="walks of the simulated data (default 65536)")
    c.add_argument("--sim-bounces", type=int, default=128, help="bounces of the simulated data (default 128)")
    c.add_argument("--hi-walks", type=int, default=HI_WALKS,
                   help="walks of the posterior's linearisation (default: uncertainty's)")
    c.set_defaults(func=coverage)
    r = sub.add_parser("report", help="one bundled report's cost")
    r.add_argument("--data", default="measurements/matte2.csv")
    r.set_defaults(func=report)
    args = parser.parse_args()
    args.func(args)


if __name__ == "__main__":
    main()
