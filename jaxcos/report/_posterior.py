"""What :func:`~jaxcos.uncertainty` leaves behind: ``posterior.json``, ``report.md`` and three figures.

``corner.png`` (the chain's draws, thinned to about two per autocorrelation
time), ``predictive.png`` (the measured points against the 95% band of the
model at posterior draws) and ``sensitivity.png`` (what each measurement
constrains: ``dv / dy`` times the measurement's standard deviation, summed
over r, g, b).

Example::

    import jaxcos
    meas = jaxcos.load_measurements("measurements/matte2.csv")
    post = jaxcos.uncertainty(meas, jaxcos.fit(meas))
    jaxcos.write_uncertainty(post, meas, "out/matte2_posterior")
"""

import json
import os

import numpy as np

from .._errors import staged_outputs
from ..inference import CHAIN_TAUS
from ..io import cell_edges

UNCERTAINTY_FILES = ("posterior.json", "report.md", "corner.png", "predictive.png", "sensitivity.png")


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


def _held_sd(post, name):
    """The Laplace sd of ``name`` with the unresolved parameters held: ``sqrt(S_nn - S_nu S_uu^-1 S_un)`` of the
    Laplace covariance ``S``, ``u`` the unresolved. ``None`` where there are none, or where that variance is not
    positive (``name`` a function of the unresolved ones, as where the data have fewer values than parameters)."""
    if not post.record.unresolved:
        return None
    cov = np.asarray(post.laplace_cov, float)
    u = [post.labels.index(n) for n in post.record.unresolved]
    i = post.labels.index(name)
    var = cov[i, i] - cov[i, u] @ np.linalg.lstsq(cov[np.ix_(u, u)], cov[u, i], rcond=None)[0]
    return float(np.sqrt(var)) if var > 0 else None


def _laplace_notes(post):
    """One sentence per parameter where the Laplace spread and the chain's disagree, or the prior cuts the posterior."""
    notes = []
    prior = post.record.prior
    region = post.record.linear_region
    for name, s in post.summary.items():
        half = 0.5 * (s["p84_noise_only"] - s["p16_noise_only"])
        low, high = prior[name]
        span = high - low
        a, b = region[name]
        if name in post.record.unresolved:
            notes.append(f"`{name}`: its slopes at the anchor are mostly their own Monte Carlo noise, so the "
                         "linearisation resolves nothing along its direction and its interval is the region "
                         f"[{a:.4g}, {b:.4g}]; the data may constrain it more than this budget of walks can show.")
        elif (a > low and s["p2.5"] <= a + 1e-3 * span) or (b < high and s["p97.5"] >= b - 1e-3 * span):
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
            held = _held_sd(post, name)
            if held is not None and 2 / 3 <= half / held <= 3 / 2:
                names = ", ".join(f"`{n}`" for n in post.record.unresolved)
                notes.append(f"`{name}`: chain half-width {half:.3g} against Laplace sd {s['laplace_sd']:.3g}, "
                             f"and {held:.3g} with {names} held: the difference is its correlation with "
                             "parameters the linearisation does not resolve, so its interval holds for them "
                             "within their region.")
            else:
                notes.append(f"`{name}`: chain half-width {half:.3g} against Laplace sd {s['laplace_sd']:.3g}; "
                             "the posterior is not Gaussian at this scale.")
    g1, g2 = post.summary.get("g1"), post.summary.get("g2")
    if g2 is not None and g1["p2.5"] <= g2["p97.5"] and g2["p2.5"] <= g1["p97.5"]:
        notes.append(f"`w_g`: the 95% intervals of `g1` [{g1['p2.5']:.3g}, {g1['p97.5']:.3g}] and `g2` "
                     f"[{g2['p2.5']:.3g}, {g2['p97.5']:.3g}] overlap, so the data may not tell the two lobes "
                     "apart, and then any `w_g` fits alike. Each draw names its more forward lobe `g1`, so where "
                     "the lobes cross in the chain `w_g`'s interval holds the weights of both labellings. The "
                     "single-lobe variant may serve as well (`jaxcos ablate`).")
    return notes


def _noise_words(post):
    """How the likelihood's noise was set; for an estimated one, its levels and their 68% intervals."""
    model = post.noise_model
    if model is None:
        return post.record.noise

    def level(name, value, sd):
        if not np.isfinite(sd) or sd > 1.0:  # a flat likelihood: more than a decade either way
            return f"{name} {value:.3g}, not identified by the data (its log10 has a Laplace sd of {sd:.2g})"
        return f"{name} {value:.3g} (68%: [{value * 10 ** -sd:.3g}, {value * 10 ** sd:.3g}])"

    return ("the file has no std columns, so std = relative x |value| + absolute, estimated by maximum likelihood "
            f"with the material: {level('relative', model.relative, model.sd[0])}, "
            f"{level('absolute', model.absolute, model.sd[1])}; "
            f"`jaxcos fit --noise {model.relative:.3g},{model.absolute:.3g}` weighs a fit by it. The estimate "
            "holds whatever the model cannot fit as well as the instrument's noise: where it is well above what "
            "the instrument is known to reach, the model misses the data, and the intervals are those of its best "
            "approximation, not of the material")


def uncertainty_report(post, meas):
    """The human-readable ``report.md`` of a :class:`Posterior`."""
    r = post.record
    c = post.chain
    lines = [
        f"# Posterior spreads for {os.path.basename(meas.path) or 'measurements'}",
        "",
        f"Variant `{r.variant}`"
        + (" under a rough dielectric top interface (its index `eta` and roughness `alpha_s` sampled with the "
           "rest; docs/model.md section 3a)" if r.interface else "")
        + f", {r.n_points} points x 3 channels, {r.n_params} parameters, "
        f"uniform priors on their physical ranges, Gaussian likelihood ({_noise_words(post)}).",
        "",
    ]
    if not post.converged:
        lines += [f"**The chain is too short:** {c.steps} steps are {r.chain_in_tau:.1f} autocorrelation times; "
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
    if "g_mean" in post.derived:
        s = post.derived["g_mean"]
        lines += ["", f"The diffusers' mean cosine `g_mean` = `w_g g1 + (1 - w_g) g2` (fit {s['fit']:.4g}): median "
                  f"{s['median']:.4g}, 68% [{s['p16']:.4g}, {s['p84']:.4g}], 95% [{s['p2.5']:.4g}, {s['p97.5']:.4g}], "
                  "over the same draws. Mixtures of nearly the same first moments scatter nearly alike, so the "
                  "data may fix the mean cosine better than how it is split between the lobes: the intervals of "
                  "`g1`, `g2` and `w_g` describe the split around the anchor, and another split that fits as well "
                  "may lie outside them."]
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
        f"| chain length in autocorrelation times | {r.chain_in_tau:.1f} (needed: {CHAIN_TAUS}) |",
        f"| acceptance fraction | {r.acceptance_fraction:.2f} (lowest walker {r.acceptance_fraction_min:.2f}) |",
        f"| smallest effective sample size | {np.min(c.ess):.0f} |",
        f"| sampling time | {r.sampling_time_s:.0f} s (total {r.time_s:.0f} s) |",
        "", "## Monte Carlo error of the model", "",
        f"The chain evaluates the linearisation of one estimate at the anchor ({r.hi_walks} walks x "
        f"{r.bounces} bounces; slopes by central differences), within the region given in "
        "`posterior.json` (`linear_region`). "
        f"High-budget chi-square at the fit {r.chi2_high_budget_at_fit:.1f}, at the anchor "
        f"{r.chi2_high_budget_at_anchor:.1f}. "
        f"Median error of the anchor relative to the measurement noise: {r.mc_anchor_error_over_noise:.2f} (included "
        f"in the likelihood). RMS error of the sampled model at posterior draws, against independent estimates: "
        f"{r.mc_model_error_over_noise:.2f} of the noise. Its effect on the parameters, the `MC sd` column, comes "
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
    samples = post.draws[::thin]
    fig = corner.corner(samples, labels=post.labels, truths=[s["fit"] for s in post.summary.values()],
                        quantiles=[0.16, 0.5, 0.84], label_kwargs=dict(fontsize=8))
    fig.savefig(path, dpi=70)
    return fig


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
            err = post.noise[sel, ch]
            ax.errorbar(to, meas.values[sel, ch], yerr=err, fmt=".", color=colour, ms=3, lw=0.8)
        ax.set_title(f"theta_i = {ti:g} deg")
        ax.set_xlabel("theta_o (deg)")
        ax.set_ylabel(unit)
    fig.suptitle("measured (points, 1 std" + ("" if meas.std is not None else ", estimated") +
                 ") and 95% band of the posterior model")
    fig.savefig(path, dpi=90)


def _sensitivity_maps(post, meas, path):
    from matplotlib.figure import Figure

    rows, cols = np.unique(meas.theta_i), np.unique(meas.theta_o)
    std = post.noise
    n = post.sensitivity.shape[0]  # the material's parameters (not the noise levels)
    ncol = min(n, 4)
    fig = Figure(figsize=(4 * ncol, 2.8 * -(-n // ncol)), constrained_layout=True)
    axes = np.atleast_1d(fig.subplots(-(-n // ncol), ncol)).ravel()
    ri = np.searchsorted(rows, meas.theta_i)
    ci = np.searchsorted(cols, meas.theta_o)
    for ax, name, sens in zip(axes, post.labels, post.sensitivity):
        grid = np.full((rows.size, cols.size), np.nan)
        grid[ri, ci] = np.sum(sens * std, axis=1)
        scale = np.nanmax(np.abs(grid)) or 1.0
        mesh = ax.pcolormesh(cell_edges(cols), cell_edges(rows, half=2.5), grid, cmap="coolwarm", vmin=-scale, vmax=scale)
        ax.set_ylim(ax.get_ylim()[::-1])
        ax.set_facecolor("0.85")
        ax.set_title(name, fontsize=9)
        ax.set_xlabel("theta_o (deg)", fontsize=8)
        ax.set_ylabel("theta_i (deg)", fontsize=8)
        fig.colorbar(mesh, ax=ax, shrink=0.8)
    for ax in axes[n:]:
        ax.set_visible(False)
    fig.savefig(path, dpi=80)
    return fig


def write_uncertainty(post, meas, out_dir, *, force=False):
    """Write ``posterior.json``, ``report.md``, ``corner.png``, ``predictive.png`` and ``sensitivity.png``.

    Written into a temporary folder first and moved in at the end; existing
    files are kept unless ``force``.
    """
    c = post.chain
    data = dict(
        parameters=post.summary,
        derived=post.derived,
        correlation=dict(labels=post.labels, matrix=post.correlation),
        laplace=dict(labels=post.labels, covariance=post.laplace_cov),
        diagnostics=dict(tau=dict(zip(post.labels, c.tau)), ess=dict(zip(post.labels, c.ess)), steps=c.steps,
                         burn=c.burn, walkers=c.walkers, chain_in_tau=post.record.chain_in_tau,
                         acceptance_fraction=post.record.acceptance_fraction, converged=c.converged,
                         required_chain_in_tau=CHAIN_TAUS),
        record=post.record.to_json(),
        fit=post.fit.record.to_json(),
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
