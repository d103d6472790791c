"""What a fit leaves behind: ``params.json``, ``report.md`` and ``fit.png``.

Example::

    import jaxcos
    meas = jaxcos.load_measurements("measurements/dewy1.csv")
    jaxcos.write_fit(jaxcos.fit(meas), meas, "out/dewy1")
"""

import os
from typing import NamedTuple

import numpy as np
from matplotlib.figure import Figure

from .._errors import staged_outputs
from ..inference import gloss_growth
from ..io import material_to_dict, save_params
from ..io import default_exposure, draw_reflectance

FIT_FILES = ("params.json", "report.md", "fit.png")
DIFFERENCE_GAIN = 4.0
"""The difference panel of ``fit.png`` shows ``|fitted - measured|`` at this many times the exposure."""


def fit_figure(meas, model, path, *, exposure=None):
    """Save measured, fitted and ``|difference|`` tables side by side (Figure-4 style) to ``path``."""
    k = default_exposure(meas.values) if exposure is None else exposure
    fig = Figure(figsize=(15, 4.2), constrained_layout=True)
    axes = fig.subplots(1, 3)
    unit = "reflectance factor" if meas.quantity == "reflectance_factor" else "BRDF (1/sr)"
    panels = [(meas.values, f"measured ({unit})", 1.0), (model, "fitted", 1.0),
              (np.abs(model - meas.values), "|fitted - measured|", DIFFERENCE_GAIN)]
    for ax, (values, title, gain) in zip(axes, panels):
        draw_reflectance(ax, meas.theta_i, meas.theta_o, values, exposure=gain * k, title=title)
    fig.savefig(path, dpi=110)


def _fmt(v):
    if isinstance(v, (list, tuple, np.ndarray)):
        return "(" + ", ".join(f"{float(x):.4g}" for x in np.ravel(v)) + ")"
    return f"{float(v):.4g}"


def _starts_legend(record):
    """What the starts table's labels mean: the screen's fixed starts by index (``record.fixed_starts``)."""
    fixed = record.fixed_starts
    if not fixed:
        return "the given start"
    return ", ".join(f"{i} = {name}" for i, name in enumerate(fixed)) + "; screened unless said"


def _budget_name(record):
    from ..model import BUDGETS

    names = [n for n, budget in BUDGETS.items() if budget == (record.budget.walks, record.budget.bounces)]
    return f" (budget `{names[0]}`)" if names else ""


def _check_section(r):
    """The report's account of the fit's check (``record.check``): the fit under a key it was not tuned to."""
    c = r.check
    weighted = c.reduced_chi2 is not None
    what = "weighted by the measurement std" if weighted else "unweighted: the file has no std"
    lines = [
        "",
        "## Check under independent keys",
        "",
        f"Under its fixed key a fit can follow that key's Monte Carlo error. Each refined start was therefore "
        f"evaluated again in {c.batches} batches of {c.walks // c.batches} walks under independent keys. "
        f"Per point, the product of two batches' residuals estimates the squared residual of the exact model, "
        f"free of Monte Carlo variance; summed over points and channels ({what}) and averaged over batch pairs, it "
        "is the column \"material chi-square\" above (the raw chi-square would also rank materials by how noisy "
        "they are to simulate). Its standard error is the jackknife's, leaving out one batch at a time. The fit is the start "
        "for which the material chi-square plus twice its standard error is lowest.",
    ] + _finer_lines(r) + _final_step_lines(r)
    if weighted:
        dof = r.n_points * 3 - r.n_params
        lines += [
            "",
            f"The pooled estimate scores a chi-square of {c.chi2:.6g}, of which {c.chi2_mc:.6g} is the check's "
            f"own Monte Carlo error. The material's own chi-square, reduced over {dof} degrees of freedom: "
            f"**{c.reduced_chi2:.3f} +- {c.reduced_chi2_se:.3f}** (about 1 for a material that explains the "
            f"data to their noise). Under the fit's key, by measurement noise alone, it was "
            f"{r.reduced_chi2_noise_only:.3f}.",
        ]
        if c.reduced_chi2_se > 0.5 * max(abs(c.reduced_chi2), 1.0):
            lines += ["", "**The check cannot pin down this material's chi-square**: a few rare walks dominate its "
                      "Monte Carlo estimate (typical of a near-mirror platelet lobe, narrow `alpha_p`). Compare "
                      "results by L2, or evaluate them with many more walks (`jaxcos eval --walks`)."]
        elif c.reduced_chi2 > 2.0 * max(r.reduced_chi2_noise_only, 1.0):
            lines += ["", "**The fit does not hold under another key**: it has followed its own key's Monte Carlo "
                      "error. Refit with more walks (`--walks`)."]
        elif c.reduced_chi2 > 3.0:
            lines += ["", "**The fitted material does not explain the data to their noise.** The search may have "
                      "missed the optimum (try more `--starts`, another `--seed`, or `--start` from a guess), or "
                      "the variant lacks an effect the data show (`jaxcos ablate`)."]
    return lines


def _finer_lines(r):
    """The report's account of the fit's finer refinement (:func:`jaxcos.inference._fit.refine_finer`; LM fits)."""
    finer = r.finer
    if finer is None:
        return []
    share = (f"Of the selected start's objective, a share of {finer.share:.2g} was its own Monte Carlo error "
             f"(the check's, scaled to the fit's {r.budget.walks} walks, over the material chi-square)")
    if finer.ran:
        return ["", f"{share}, at least {finer.threshold}: that start was refined once more at "
                f"{finer.factor} times the walks and checked like the others (the row ending \"x walks\")."]
    return ["", f"{share}, below {finer.threshold}: {finer.factor} times the walks would change it little, and it "
            "was not refined again."]


def _final_step_lines(r):
    """The report's account of the fit's last steps (the polish stage of :func:`jaxcos.fit`; LM fits)."""
    step = r.final_step
    if step is None:
        return []
    before = step.check_before
    lines = ["", "Then that start was checked again under fresh keys (the check that selected it leans towards the "
             "data by its own luck), and damped Gauss-Newton steps were taken from it, each on the residuals of the "
             f"last check's pooled estimate ({before.walks} walks, {before.walks // r.budget.walks} times the fit's, "
             "so that much less Monte Carlo variance) along a Jacobian of the fit's objective from "
             f"{step.jacobian_walks} walks: under its one key the fit also follows that key's Monte Carlo error, "
             "and the steps undo part of it. Each step is checked under fresh keys and kept where it scores better; "
             "the first one not kept ends the steps along that Jacobian, and where they kept one, a new Jacobian is "
             f"taken where they ended ({step.jacobians} Jacobian{'s' * (step.jacobians > 1)} taken)."]
    after = step.check_after
    if after is None:
        return lines + ["The first step was not finite and was not taken."]
    reduced = before.reduced_chi2 is not None  # per degree of freedom where the file has std columns
    what = "reduced chi-square" if reduced else "chi-square"
    (a, a_se), (b, b_se) = [(c.reduced_chi2, c.reduced_chi2_se) if reduced else (c.material_chi2, c.material_chi2_se)
                            for c in (after, before)]
    if not step.kept:
        return lines + [f"Checked under fresh keys, the first stepped material's {what} is {a:.3f} +- {a_se:.3f}, "
                        f"against {b:.3f} +- {b_se:.3f} before it. It was not kept."]
    kept = "one step was" if step.steps == 1 else f"{step.steps} steps were"
    return lines + [f"Checked under fresh keys, {kept} kept: the fitted material's {what} is {a:.3f} +- {a_se:.3f}, "
                    f"against {b:.3f} +- {b_se:.3f} before the steps."]


BRIGHT_FRACTION = 0.1
"""An unweighted fit's report says how much of L2 its brightest points (this fraction of them) carry."""
RELATIVE_MISS = 0.10
"""An unweighted fit's report and command warn when its other points' median relative difference exceeds this
while its brightest points carry most of L2 (:func:`favours_bright`): beyond a tenth the body renders as another
colour (issue 30's bound on a dewy product's body)."""


class LossSplit(NamedTuple):
    """Where a model's L2 lies: the brightest points (:data:`BRIGHT_FRACTION`) against the rest, the body.

    Attributes:
        bright: boolean mask ``(N,)`` of the brightest points by mean value.
        share: their share of L2.
        body_miss: the median relative difference between model and
            measurement over the other points and channels (0 if there are none).
    """

    bright: np.ndarray
    share: float
    body_miss: float


def loss_split(meas, model):
    """The :class:`LossSplit` of ``model`` ``(N, 3)``, in the file's quantity, against ``meas``."""
    brightness = meas.values.mean(axis=1)
    n_bright = max(1, int(round(BRIGHT_FRACTION * brightness.size)))
    bright = np.zeros(brightness.size, bool)
    bright[np.argsort(brightness, kind="stable")[-n_bright:]] = True
    resid2 = ((model - meas.values) ** 2).sum(axis=1)
    share = resid2[bright].sum() / max(resid2.sum(), 1e-300)
    miss = float(np.median(np.abs(model[~bright] - meas.values[~bright])
                           / np.maximum(np.abs(meas.values[~bright]), 1e-30))) if n_bright < bright.size else 0.0
    return LossSplit(bright, float(share), miss)


def favours_bright(split):
    """Whether a plain-L2 fit's :class:`LossSplit` shows the fit trading its body for its highlight: the brightest
    points carry more than half of L2 and the others are missed by more than :data:`RELATIVE_MISS` in the median.
    Where the body carries most of L2 a weighting would not move it."""
    return split.share > 0.5 and split.body_miss > RELATIVE_MISS


def _unweighted_lines(meas, model):
    """Where an unweighted fit's L2 comes from: its brightest points against the rest.

    Without std columns every point counts by its absolute difference, so a
    few bright highlight points can outweigh the whole diffuse body; these
    lines say how much, and what to do if the rest matters.
    """
    split = loss_split(meas, model)
    bright, share, miss = split
    n_bright = int(bright.sum())
    brightness = meas.values.mean(axis=1)
    text = (f"The file has no std, so the fit minimises the plain L2: every point counts by its absolute difference, "
            f"and the brightest weigh most. The brightest {n_bright} of {bright.size} points (mean value at least "
            f"{brightness[bright].min():.3g}) carry {100 * share:.0f}% of L2; on the other points the fitted values "
            f"differ from the measured by {100 * miss:.0f}% in the median.")
    if favours_bright(split):
        text += (" **The fit favours the bright points over the rest of the table.** If the rest matters, weigh "
                 f"each point by its size: fit with {_NOISE_OPTION}, or give the file std columns.")
    return ["", "## Where the loss comes from", "", text]


_NOISE_OPTION = ("--noise REL,ABS (a standard deviation of REL times each value plus ABS; for example "
                 "--noise 0.05,0.005)")
"""The advice of :func:`_unweighted_lines` and :func:`body_hint`."""


def body_hint(meas, model):
    """For a fit to ``meas`` without std whose model ``(N, 3)`` trades the body for the highlight
    (:func:`favours_bright`), what to do: one sentence naming ``--noise``; else ``None``."""
    if meas.std is not None:
        return None
    split = loss_split(meas, model)
    if not favours_bright(split):
        return None
    return (f"The plain L2 favours the brightest points (a tenth of them carry {100 * split.share:.0f}% of it): the "
            f"fit misses the others by {100 * split.body_miss:.0f}% in the median. To weigh each point by its "
            f"size, fit with {_NOISE_OPTION}.")


def surface_gloss(meas):
    """What makes the gloss of ``meas``, where it grows like a surface's (:func:`~jaxcos.inference.gloss_growth`):
    one sentence, else ``None``."""
    gloss = gloss_growth(meas)
    if gloss is None or not gloss.surface_like:
        return None
    lo, hi = gloss.theta_i
    return (f"The measured gloss grows {gloss.growth:.1f}-fold from theta_i {lo:g} to {hi:g} degrees, like a "
            f"reflection at the surface ({gloss.surface:.1f}-fold before Fresnel), not like light scattered in "
            f"the layer ({gloss.volume:.1f}-fold): without a top interface only a mirror-like medium of "
            "platelets makes it.")


def gloss_hint(meas, material):
    """For a fit without a top interface to data whose gloss grows like a surface's (:func:`surface_gloss`), what
    to do instead: one sentence naming ``--interface``; else ``None``. Such a gloss needs a top interface, or the
    fit makes the medium a mirror."""
    text = None if material.interface is not None else surface_gloss(meas)
    return None if text is None else f"{text} Fit with --interface."


def _gloss_lines(meas, material):
    """The report's section on a gloss that needs a top interface (:func:`gloss_hint`), or nothing."""
    hint = gloss_hint(meas, material)
    if hint is None:
        return []
    return ["", "## The gloss", "", f"**{hint}**", "",
            "`jaxcos fit FILE --interface` gives the material a rough dielectric top surface (docs/model.md "
            "section 3a) whose reflection grows that way; `jaxcos ablate FILE --interface` compares the two "
            "models by AIC and BIC."]


_CHANNELS = {"[0]": " (red)", "[1]": " (green)", "[2]": " (blue)"}
_AT_BOUND = {
    ("albedo_d", "high"): "a diffuser albedo at 1 says the body wants more light than a non-absorbing medium over "
                          "the black base returns",
    ("albedo_p", "high"): "a platelet albedo at 1 says the platelets reflect all they receive and the data would "
                          "take more",
    ("c_d", "high"): "`c_d` at 1 leaves no platelets",
    ("c_d", "low"): "`c_d` at 0 leaves no diffusers",
    ("w_g", "high"): "`w_g` at 1 is one diffuser lobe",
    ("eta", "low"): "`eta` at 1.01 asks for a surface closer to index-matched than the range allows (`jaxcos ablate "
                    "--interface` compares the two models)",
}


def _bound_lines(result):
    """The parameters that ended at a bound of their fit range (:meth:`Parameterization.at_bounds`), or nothing."""
    at = result.param.at_bounds(result.x)
    if not at:
        return []
    low = dict(zip(result.param.labels(), result.param.bounds()[0]))
    named, meanings = [], []
    for label, bound in at:
        channel = next((c for k, c in _CHANNELS.items() if label.endswith(k)), "")
        named.append(f"`{label}`{channel} at {bound:g}")
        meaning = _AT_BOUND.get((label.split("[")[0], "low" if bound == low[label] else "high"))
        if meaning is not None and meaning not in meanings:
            meanings.append(meaning)
    text = (f"**At a bound of the fit's range: {', '.join(named)}.** There the value is the bound, not an estimate: "
            "the data ask for at least (or at most) that much")
    return ["", text + ("; " + "; ".join(meanings) if meanings else "") + "."]


def _weighting(meas):
    """One sentence: how the points were weighed (std columns, a ``--noise`` model, or none: plain L2)."""
    if meas.std is None:
        return "Weights: none (the file has no std columns): the fit minimises the plain L2."
    if meas.noise is not None:
        relative, absolute = meas.noise
        return (f"Weights: the noise model std = {relative:g} * value + {absolute:g} (`--noise`; the file has no "
                "std columns).")
    return "Weights: the file's std columns."


def fit_report(result, meas):
    """The human-readable ``report.md`` of a :class:`~jaxcos.FitResult`."""
    r = result.record
    layer = material_to_dict(result.material)["layers"][0]
    lines = [
        f"# Fit of {os.path.basename(meas.path) or 'measurements'}",
        "",
        f"Variant `{r.variant}`, method `{r.method}`, {r.n_points} points x 3 channels, "
        f"{r.n_params} fitted parameters ({', '.join(r.fitted)}), seed {r.seed}.",
        "",
        _weighting(meas),
        "",
        "## Quality",
        "",
        "| quantity | value |",
        "|---|---|",
        f"| loss (the objective, under the fit's key, at the fitted material) | {r.loss:.6g} |",
        f"| L2 (paper's metric: sum of squared differences, file's quantity) | {r.l2:.6g} |",
        f"| RMSE | {r.rmse:.4g} |",
    ]
    if r.reduced_chi2 is not None:
        lines += [f"| reduced chi-square (noise and Monte Carlo error) | {r.reduced_chi2:.3f} |",
                  f"| reduced chi-square (measurement noise only) | {r.reduced_chi2_noise_only:.3f} |"]
    c = r.check
    lines.append(f"| L2 under independent keys, {c.walks} walks (see Check) | {c.l2:.6g} |")
    if c.reduced_chi2 is not None:
        lines.append(f"| reduced chi-square of the material (independent keys, see Check) | {c.reduced_chi2:.3f} "
                     f"+- {c.reduced_chi2_se:.3f} |")
    lines += [
        f"| iterations (best start) | {r.iterations} |",
        f"| forward evaluations at the objective's walks (a Jacobian counts as parameters + 1 forwards at its "
        f"walks) | {r.n_evaluations} |",
        f"| time | {r.time_s:.1f} s |",
        "",
        "## Parameters",
        "",
        "| parameter | value |",
        "|---|---|",
    ]
    for key, value in layer.items():
        mark = "" if key.replace("_deg", "") in r.fitted else " (fixed)"
        lines.append(f"| `{key}` | {_fmt(value)}{mark} |")
    if "phi_p_deg" not in layer:
        lines.append(f"| `phi_p_deg` | 0{'' if 'phi_p' in r.fitted else ' (fixed: tilt in the plane of incidence)'} |")
    top = result.material.interface
    if top is None:
        lines.append("| top interface | none: index-matched (docs/model.md section 3) |")
    else:
        lines += [f"| `interface.eta` (top interface, docs/model.md section 3a) | {_fmt(float(top.eta))} |",
                  f"| `interface.alpha_s` | {_fmt(float(top.alpha_s))} |"]
    lines += _bound_lines(result)
    lines += _gloss_lines(meas, result.material)
    lines += [
        "",
        "## Starts",
        "",
        f"{r.starts_at_optimum} of {r.starts_refined} refined starts reached the best optimum (their loss "
        "within 1% of the best's on the best start's objective: final losses are not comparable across starts, "
        "whose weights and lobe probabilities are set where each pass begins):",
        "",
        f"| start ({_starts_legend(r)}) | final loss "
        "| material chi-square under independent keys (see Check) |",
        "|---|---|---|",
    ] + [f"| {i} | {loss:.6g} | {chi2:.6g} +- {se:.2g} |" for i, loss, chi2, se in result.starts]
    lines += _check_section(r) + [
        "",
        "## Monte Carlo budget",
        "",
        f"{r.budget.walks} walks per incidence direction, {r.budget.bounces} bounces per walk{_budget_name(r)}, "
        f"one fixed key (common random numbers); the Jacobian from the first {r.budget.jacobian_walks} of those "
        "walks. Energy left in unfinished walks: at most "
        f"{r.unfinished_energy:.2g} of the incident energy.",
    ]
    if r.connection == "mis":
        lines.append("The measured highlight is narrower than the angular sampling (near-mirror platelets): each "
                     "scattering vertex connects to the viewer both by next-event estimation and by a flight drawn "
                     "back through the platelet lobe, weighted by multiple importance sampling "
                     "(`simulate(connection=\"mis\")`), which keeps rare walks from dominating the estimate.")
    if meas.std is not None:
        lines.append(f"Median Monte Carlo standard error of the model relative to the measurement std: "
                     f"{r.mc_error_median:.2f}; the fit weights each residual by the two combined.")
        lines.append(f"Relative to the values (medians over points and channels): Monte Carlo error "
                     f"{100 * np.median(result.model_std / np.maximum(np.abs(result.model), 1e-30)):.1f}%, "
                     f"measurement noise {100 * np.median(meas.std / np.maximum(np.abs(meas.values), 1e-30)):.1f}%. "
                     "A larger budget (`--budget`, `--walks`) shrinks the first as 1/sqrt(walks).")
    else:
        lines.append(f"Median Monte Carlo standard error of the model: {r.mc_error_median:.3g} (the file has no std).")
        lines += _unweighted_lines(meas, result.model)
    lines += ["", "![measured, fitted and difference](fit.png)", ""]
    return "\n".join(lines)


def write_fit(result, meas, out_dir, *, force=False):
    """Write ``params.json`` (with its ``"fit"`` record), ``report.md`` and ``fit.png`` under ``out_dir``.

    Everything is written into a temporary folder first and moved in at the
    end, so a failure leaves nothing half-written. Existing files are kept
    unless ``force``.
    """
    with staged_outputs(out_dir, FIT_FILES, force) as tmp:
        save_params(result.material, os.path.join(tmp, "params.json"), extra={"fit": result.record.to_json()})
        with open(os.path.join(tmp, "report.md"), "w", encoding="utf-8") as fh:
            fh.write(fit_report(result, meas))
        fit_figure(meas, result.model, os.path.join(tmp, "fit.png"))
    return [os.path.join(out_dir, name) for name in FIT_FILES]
