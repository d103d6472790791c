"""Speed of the forward model and of its Jacobian on the standard grid, at the paper's budget.

Standard grid: ``theta_i`` 0..75 step 5 (16), ``theta_o`` -85..85 step 5 (35);
t = 16, 512 bounces, 128 walks per incidence direction. For a dewy and a matte
product it measures compile time, run time (best of several, after
``block_until_ready``), walk-steps per second, peak memory (each case in a
fresh process), the fit's Jacobian against its 12 parameters (batched forward
mode, 8 tangents: ``jaxcos.inference.bsdf_problem``; its ratio to one forward
evaluation from alternating runs in the Jacobian's process), and the variance and cost of
exact against Monte Carlo single scattering. Run time and CPU time (all
threads) are both recorded, with the load average.

    python benchmarks/bench_forward.py            # writes benchmarks/results/forward.json
"""

import json
import multiprocessing as mp
import os
import platform
import resource
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))


def _grid():
    import numpy as np

    ti = np.repeat(np.arange(0, 80, 5.0), 35)
    to = np.tile(np.arange(-85, 90, 5.0), 16)
    return ti, to


def _timed(fn, arg):
    """Wall and CPU seconds (all threads) of ``fn(arg)``, finished."""
    import jax

    t0, c0 = time.perf_counter(), time.process_time()
    jax.block_until_ready(fn(arg))
    return time.perf_counter() - t0, time.process_time() - c0


def _case(kind, product, out):
    import jax
    import jax.numpy as jnp
    import numpy as np

    import jaxcos

    from jaxcos.inference import bsdf_problem

    m = jaxcos.published(product)
    q = jaxcos.make_query(*_grid())
    key = jax.random.key(0)
    lp = jaxcos.lobe_probabilities(m)
    walks, bounces = 128, 512
    single = "mc" if kind == "forward_mc_single" else "exact"
    if kind == "jacobian":  # the fit's Jacobian (coloured forward mode) of the same estimate
        problem, x0 = bsdf_problem(m, q, key, walks, bounces)
        fn, arg = jax.jit(jax.jacfwd(problem.residuals)), x0
    else:
        fn = jax.jit(lambda m: jaxcos.simulate(m, q, key, walks=walks, bounces=bounces, lobe_probs=lp,
                                               single_scattering=single).f)
        arg = m
    first = _timed(fn, arg)[0]
    runs, cpu = zip(*[_timed(fn, arg) for _ in range(5 if kind == "jacobian" else 7)])
    run = min(runs)
    result = dict(kind=kind, product=product, compile_s=first - run, run_s=run, runs_s=runs, cpu_s=min(cpu),
                  load_average=os.getloadavg(),
                  walk_steps_per_s=16 * walks * bounces / run,
                  peak_rss_mb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)
    if kind == "jacobian":
        # The ratio to one forward evaluation from alternating runs in this process: this shared
        # machine's speed drifts by up to a third between processes, much less within a pair of runs.
        forward = jax.jit(lambda m: jaxcos.simulate(m, q, key, walks=walks, bounces=bounces, lobe_probs=lp).f)
        _timed(forward, m)
        pairs = [(_timed(forward, m), _timed(fn, arg)) for _ in range(5)]
        (f_wall, f_cpu), (j_wall, j_cpu) = [[min(p[i][k] for p in pairs) for k in (0, 1)] for i in (0, 1)]
        result.update(paired_runs_s=pairs, paired_forward_s=f_wall, paired_jacobian_s=j_wall,
                      ratio_to_forward=j_wall / f_wall, cpu_ratio_to_forward=j_cpu / f_cpu)
    if kind.startswith("forward"):
        est = jaxcos.simulate(m, q, key, walks=walks, bounces=bounces, lobe_probs=lp, single_scattering=single)
        rel = np.asarray(est.stderr / jnp.maximum(est.f, 1e-12))
        result.update(rel_stderr_median=float(np.median(rel)), rel_stderr_p95=float(np.percentile(rel, 95)),
                      rel_stderr_max=float(rel.max()))
    out.put(result)


def main():
    import jax

    ctx = mp.get_context("spawn")
    results = []
    for product in ("dewy1", "matte2"):
        for kind in ("forward", "forward_mc_single", "jacobian"):
            queue = ctx.Queue()
            proc = ctx.Process(target=_case, args=(kind, product, queue))
            proc.start()
            results.append(queue.get())
            proc.join()
            r = results[-1]
            print(f"{product:7s} {kind:18s} compile {r['compile_s']:6.1f} s  run {r['run_s'] * 1e3:7.0f} ms  "
                  f"peak {r['peak_rss_mb']:6.0f} MB", flush=True)
    for j in results:
        if j["kind"] == "jacobian":
            print(f"{j['product']}: Jacobian / forward = {j['ratio_to_forward']:.1f} (wall), "
                  f"{j['cpu_ratio_to_forward']:.1f} (CPU), from alternating runs "
                  f"({j['paired_jacobian_s']:.2f} s / {1e3 * j['paired_forward_s']:.0f} ms)")
    machine = dict(platform=platform.platform(), processor=platform.processor(), cpus=os.cpu_count(),
                   python=sys.version.split()[0], jax=jax.__version__, backend=jax.default_backend(),
                   load_average=os.getloadavg())
    os.makedirs(os.path.join(HERE, "results"), exist_ok=True)
    with open(os.path.join(HERE, "results", "forward.json"), "w") as fh:
        json.dump(dict(machine=machine, results=results), fh, indent=2)


if __name__ == "__main__":
    main()
