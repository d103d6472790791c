"""Posterior spreads: coverage over synthetic replicates with a known truth, and one bundled report's cost.

    python benchmarks/bench_uncertainty.py coverage [--replicates 20] [--hi-walks 8192]
    python benchmarks/bench_uncertainty.py report [--data measurements/matte2.csv]

Writes ``benchmarks/results/uncertainty_coverage_hi<N>.json`` or ``uncertainty_report.json``.

Coverage: the single-lobe problem of ``tests/test_posterior.py`` (4 incidences x
13 viewing angles, 10 parameters, 5% + 0.005 noise on the truth's curve from
a 2^18-walk estimate, whose own error is 0.02 noise-sd per point). Each
replicate draws new noise and uses new
Monte Carlo keys, fits from the truth and samples the posterior. Reported: the
fraction of (replicate, parameter) pairs whose truth lies in the 68% interval
(expected 0.68), the same for the Laplace interval, and for the chain's
noise-only interval.
"""

import argparse
import json
import os
import platform
import sys
import time

import jax
import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, "..", "tests"))

import jaxcos  # noqa: E402


def _machine():
    return dict(platform=platform.platform(), python=platform.python_version(), cpus=os.cpu_count(),
                jax=jax.__version__, load_average=os.getloadavg())


TRUTH_WALKS = 1 << 18


def coverage(replicates, hi_walks):
    from test_posterior import TRUTH, _synthetic

    rows = []
    t0 = time.perf_counter()
    for r in range(replicates):
        data = _synthetic(seed=100 + r, walks=TRUTH_WALKS)
        start = jaxcos.fit(data, variant="single_lobe", walks=128, bounces=48, start=TRUTH, seed=r)
        post = jaxcos.uncertainty(data, start, seed=r, walkers=24, max_steps=1000, hi_walks=hi_walks, checks=4,
                                  replicas=12)
        truth = np.asarray(start.param.to_physical(start.param.from_material(TRUTH)), float)
        row = dict(replicate=r, converged=post.converged, chain_in_tau=post.record.chain_in_tau,
                   min_ess=float(np.min(post.chain.ess)), in68=[], in95=[], in68_noise_only=[], in68_laplace=[],
                   z=[], z_fit=[], fit=[], median=[])
        for name, value in zip(post.labels, truth):
            s = post.summary[name]
            row["in68"].append(bool(s["p16"] <= value <= s["p84"]))
            row["in95"].append(bool(s["p2.5"] <= value <= s["p97.5"]))
            row["in68_noise_only"].append(bool(s["p16_noise_only"] <= value <= s["p84_noise_only"]))
            row["in68_laplace"].append(bool(abs(value - s["fit"]) <= s["laplace_sd"]))
            # (median - truth) over the half-width of the 68% interval, and the fit's offset over the Laplace sd
            row["z"].append((s["median"] - value) / (0.5 * (s["p84"] - s["p16"])))
            row["z_fit"].append((s["fit"] - value) / s["laplace_sd"])
            row["fit"].append(s["fit"])
            row["median"].append(s["median"])
        rows.append(row)
        print(f"replicate {r}: 68% {np.mean(row['in68']):.2f}, 95% {np.mean(row['in95']):.2f}, "
              f"{time.perf_counter() - t0:.0f} s", flush=True)
    frac = {k: float(np.mean([row[k] for row in rows])) for k in ("in68", "in95", "in68_noise_only", "in68_laplace")}
    n = replicates * len(rows[0]["in68"])
    z = np.array([row["z"] for row in rows])
    return dict(machine=_machine(), replicates=replicates, truth_walks=TRUTH_WALKS, hi_walks=hi_walks,
                mean_z=z.mean(axis=0).tolist(), rms_z=np.sqrt((z ** 2).mean(axis=0)).tolist(),
                pairs=n, coverage=frac,
                binomial_se_68=float(np.sqrt(0.68 * 0.32 / n)), labels=list(post.labels), rows=rows,
                time_s=time.perf_counter() - t0)


def report(path):
    from jaxcos.cli import main

    out = os.path.join("/tmp", "jaxcos-bench-uncertainty")
    t0 = time.perf_counter()
    status = main(["uncertainty", path, "--out", out, "--force"])
    elapsed = time.perf_counter() - t0
    with open(os.path.join(out, "posterior.json"), encoding="utf-8") as fh:
        doc = json.load(fh)
    return dict(machine=_machine(), data=path, exit_status=status, time_s=elapsed,
                sampling_time_s=doc["record"]["sampling_time_s"], diagnostics=doc["diagnostics"],
                mc=dict((k, doc["record"][k]) for k in ("mc_anchor_error_over_noise", "mc_model_error_over_noise")),
                parameters=doc["parameters"])


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("what", choices=("coverage", "report"))
    parser.add_argument("--replicates", type=int, default=20)
    parser.add_argument("--data", default="measurements/matte2.csv")
    parser.add_argument("--hi-walks", type=int, default=8192, help="walks of the value and Jacobian at the fit")
    args = parser.parse_args()
    result = coverage(args.replicates, args.hi_walks) if args.what == "coverage" else report(args.data)
    os.makedirs(os.path.join(HERE, "results"), exist_ok=True)
    suffix = f"_hi{args.hi_walks}" if args.what == "coverage" else ""
    target = os.path.join(HERE, "results", f"uncertainty_{args.what}{suffix}.json")
    with open(target, "w", encoding="utf-8") as fh:
        json.dump(result, fh, indent=1, default=float)
    print(f"wrote {target}")


if __name__ == "__main__":
    main()
