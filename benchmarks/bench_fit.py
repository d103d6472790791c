"""Levenberg-Marquardt against the Powell baseline, on the same objective, per bundled data set.

Both methods refine the same start, once from each of the fit's fixed starts
(``default``, the broad, tilted ``platelet`` start and, where the fit adds it
for a highlight narrower than the angular sampling, the ``near-mirror`` start
at the highlight's tilt; no screening, so the comparison is of the local
solvers), on the same residuals: the same key,
budget, lobe probabilities and weights (those of the full fit's best start).
Recorded: wall time, forward evaluations (a Jacobian counts as its measured
cost in forward evaluations at the objective's walks), final loss, the time LM
needs to reach Powell's final loss (from a second, compiled run whose accepted
losses a host callback times), the time each needs to reach the worse of the
two final losses (Powell's evaluations timed from the end of the first, which
compiles the objective), and both solutions' chi-square under an
independent key (``jaxcos.inference._fit.check``), which neither solver could tune.

    python benchmarks/bench_fit.py dewy1 matte2     # appends to benchmarks/results/fit.json
    python benchmarks/bench_fit.py --powell 1000 dewy1   # Powell's evaluation cap (default 4000)
"""

import json
import os
import platform
import sys
import time

import jax

import jaxcos
from jaxcos.inference._fit import CHECK_FACTOR, check, fixed_starts, highlight_tilt, solve_lm, solve_powell, with_mc_error

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)


def _time(fn):
    t0 = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - t0


def _lm_trace(problem, x0, max_steps=40):
    """``[(seconds, loss)]`` of LM's accepted points, run after compilation, timed by a host callback per step."""
    import equinox as eqx
    import optimistix as optx

    from jaxcos.inference._fit import LevenbergMarquardt

    trace, t0 = [], [0.0]

    def record(loss):
        trace.append((time.perf_counter() - t0[0], float(loss)))

    solver = LevenbergMarquardt(rtol=1e-4, atol=1e-5)
    solver = eqx.tree_at(lambda s: s.verbose, solver,
                         lambda **kw: jax.debug.callback(record, 2 * kw["loss_last_accepted_step"][1]))
    run = eqx.filter_jit(lambda p, x: optx.least_squares(lambda x, p: p.residuals(x), solver, x, args=p,
                                                         max_steps=max_steps, throw=False).value)
    jax.block_until_ready(run(problem, x0))
    trace.clear()
    t0[0] = time.perf_counter()
    jax.block_until_ready(run(problem, x0))
    # The callback of step k reports the last accepted loss before step k's evaluation: drop step 0's zero.
    return [(t, loss) for t, loss in trace if loss > 0]


def _starts(meas, problem):
    """The fit's fixed starts for ``meas`` (:func:`jaxcos.inference._fit.fixed_starts`): ``{key: Layer values}``."""
    tilt = highlight_tilt(meas) if "theta_p" in problem.param.names else None
    return {start.key: start.values for start in fixed_starts(2, 16.0, tilt, problem.connection)}


def bench(product, max_powell=4000):
    """One record per fixed start of the fit, all on the objective of the full fit's best start."""
    meas = jaxcos.load_measurements(os.path.join(ROOT, "measurements", f"{product}.csv"))
    full, t_full = _time(lambda: jaxcos.fit(meas))
    problem = with_mc_error(full.problem, meas, full.problem.param.from_material(full.material))
    records = []
    for name, values in _starts(meas, problem).items():
        x0 = full.param.from_material(jaxcos.Material(layers=(jaxcos.Layer(**values),)))
        r = _compare(problem, meas, x0, max_powell)
        records.append(dict(product=product, start=name, n_params=int(problem.param.size),
                            n_points=int(meas.n_points), full_fit=dict(time_s=t_full, record=full.record.to_json()), **r))
    return records


def _compare(problem, meas, x0, max_powell):
    """LM and Powell from ``x0`` on ``problem``: times, evaluations, losses, and their check."""
    solve_lm(problem, x0)  # compile
    (x_lm, loss_lm, steps, accepted), t_lm = _time(lambda: solve_lm(problem, x0))
    trace = _lm_trace(problem, x0)
    loss_fn = jax.jit(lambda x: problem.loss(x))
    loss_fn(x0).block_until_ready()
    fwd = min(_time(lambda: loss_fn(x0).block_until_ready())[1] for _ in range(5))
    jac_fn = jax.jit(jax.jacfwd(lambda x: problem.residuals(x)))
    jac_fn(x0).block_until_ready()
    jac = min(_time(lambda: jac_fn(x0).block_until_ready())[1] for _ in range(3))
    powell_trace, t1 = [], [None]

    def on_evaluation(loss):
        # Times from the end of the first evaluation, which compiles the objective.
        if t1[0] is None:
            t1[0] = time.perf_counter()
        powell_trace.append((time.perf_counter() - t1[0], loss))

    (x_pw, loss_pw, nfev), t_pw = _time(lambda: solve_powell(problem, x0, max_evaluations=max_powell,
                                                            on_evaluation=on_evaluation))
    # LM's time to Powell's final loss: the first accepted point at or below it.
    reach = [t for t, loss in trace if loss <= loss_pw]
    t_reach = reach[0] if reach else None
    # The same loss for both: the worse of the two final losses, and each solver's first time at or below it.
    same = max(loss_lm, loss_pw)
    t_lm_same = next((t for t, loss in trace if loss <= same * (1 + 1e-6)), t_lm)
    t_pw_same = next(t for t, loss in powell_trace if loss <= same * (1 + 1e-6))
    checked = {name: check(problem, meas, x, key=jax.random.key(12345), walks=CHECK_FACTOR * problem.walks).to_json()
               for name, x in (("lm", x_lm), ("powell", x_pw))}
    return dict(check=checked, forward_s=fwd, jacobian_s=jac, jacobian_in_forwards=jac / fwd,
                lm=dict(time_s=t_lm, loss=loss_lm, steps=steps, accepted=accepted,
                        forward_evaluations=steps + accepted * jac / fwd),
                powell=dict(time_s=t_pw, loss=loss_pw, forward_evaluations=nfev, max_evaluations=max_powell),
                speedup=t_pw / t_lm, lm_loss_not_worse=loss_lm <= loss_pw * (1 + 1e-3),
                lm_time_to_powell_loss_s=t_reach,
                speedup_to_same_loss=None if t_reach is None else t_pw / t_reach, lm_trace=trace,
                same_loss=dict(loss=same, lm_s=t_lm_same, powell_s=t_pw_same, speedup=t_pw_same / t_lm_same))


def main(products, max_powell=4000):
    path = os.path.join(HERE, "results", "fit.json")
    os.makedirs(os.path.dirname(path), exist_ok=True)
    data = json.load(open(path)) if os.path.exists(path) else {"runs": []}
    for product in products:
        for r in bench(product, max_powell=max_powell):
            r["machine"] = dict(platform=platform.platform(), cpus=os.cpu_count(), jax=jax.__version__,
                                load_average=os.getloadavg())
            data["runs"].append(r)
            lm, pw, same, chk = r["lm"], r["powell"], r["same_loss"], r["check"]
            print(f"{product}: full fit {r['full_fit']['time_s']:.0f} s; from the {r['start']} start "
                  f"LM {lm['time_s']:.1f} s loss {lm['loss']:.1f} ({lm['forward_evaluations']:.0f} forward evals), "
                  f"Powell {pw['time_s']:.1f} s loss {pw['loss']:.1f} ({pw['forward_evaluations']} evals); "
                  f"speed-up {r['speedup']:.1f}; LM reaches Powell's loss in {r['lm_time_to_powell_loss_s']} s; "
                  f"both reach {same['loss']:.1f} in LM {same['lm_s']:.1f} s, Powell {same['powell_s']:.1f} s; "
                  "reduced chi-square under an independent key: "
                  f"LM {chk['lm'].get('reduced_chi2')}, Powell {chk['powell'].get('reduced_chi2')}", flush=True)
            with open(path, "w") as fh:
                json.dump(data, fh, indent=2)


if __name__ == "__main__":
    args = sys.argv[1:]
    cap = 4000
    if args[:1] == ["--powell"]:
        cap, args = int(args[1]), args[2:]
    main(args or list(jaxcos.PRODUCTS), max_powell=cap)
