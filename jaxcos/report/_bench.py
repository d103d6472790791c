"""The accuracy benchmark's outputs: ``accuracy.json``, ``accuracy.md``, ``accuracy.png``, ``accuracy_fit.png``.

:func:`write_accuracy` writes them for the dict of
:func:`jaxcos.inference.accuracy_benchmark` (or for one read back from an
``accuracy.json``, to redraw them):

* ``accuracy.json``: every number, with the machine record and the load
  average around each timing;
* ``accuracy.md``: the tables, one per product (error, truncation bias,
  unfinished energy, forward and Jacobian time per budget) and one of the
  end-to-end fits;
* ``accuracy.png``: RMS relative error of the BSDF against forward CPU time
  (log-log), per product, one curve per single-scattering strategy and sweep,
  the paper's and the fit's default budgets marked; below, the unfinished
  energy and truncation bias against bounces, and the cost against walks x
  bounces;
* ``accuracy_fit.png``: the fits' checked reduced chi-square and BSDF error
  to the truth against fit CPU time.

The figures use CPU time (all threads of the process), which contention
disturbs far less than wall time; the tables give both.
"""

import json
import os

from .._errors import staged_outputs
from ..inference import FIT_BOUNCES, FIT_WALKS

ACCURACY_FILES = ("accuracy.json", "accuracy.md", "accuracy.png", "accuracy_fit.png")
"""The files :func:`write_accuracy` writes, in order."""
PAPER_BUDGET = (128, 512)
"""The paper's budget (Lanza et al. 2024): 128 samples per direction, 512 bounces."""
FIT_BUDGET = (FIT_WALKS, FIT_BOUNCES)
"""The fit's default budget, marked in the figure."""

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
    if data.get("efficiency"):
        lines += [
            "## Efficiency: the estimator against its reference, side by side",
            "",
            "Efficiency = 1 / (RMS relative error^2 x CPU seconds) of one forward evaluation (exact single "
            f"scattering, {s['efficiency_seeds']} keys, the same for both). *Reference*: every walk makes every "
            "step (`simulate(thin_after=None)`, the estimator before 2026-12-02); *estimator*: the default, whose "
            "later steps are made by fewer walks. The error includes the reference BSDF's own (the floor).",
            "",
            "| product | walks | bounces | floor | error ref. / est. | mean error ref. / est. | CPU ref. / est. | "
            "efficiency ref. / est. | ratio |",
            "|---|---|---|---|---|---|---|---|---|",
        ]
        for r in data["efficiency"]:
            a, b = r["reference"], r["estimator"]
            lines.append(f"| {r['product']} | {r['walks']} | {r['bounces']} | {100 * r['reference_floor']:.2f}% | "
                         f"{100 * a['rms_rel_error']:.2f}% / {100 * b['rms_rel_error']:.2f}% | "
                         f"{100 * a['mean_rel_error']:+.2f}% / {100 * b['mean_rel_error']:+.2f}% | "
                         f"{1e3 * a['forward_cpu_s']:.0f} / {1e3 * b['forward_cpu_s']:.0f} ms | "
                         f"{a['efficiency']:.0f} / {b['efficiency']:.0f} | {r['ratio']:.2f} |")
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


def write_accuracy(data, out_dir, *, force=False):
    """Write :data:`ACCURACY_FILES` under ``out_dir`` for the ``data`` of :func:`jaxcos.inference.accuracy_benchmark`.

    Everything is written to a temporary folder and moved in at the end;
    existing files are kept unless ``force``. Returns the paths written.

    Raises:
        InputError: if a file exists and not ``force``.
    """
    with staged_outputs(out_dir, ACCURACY_FILES, force) as tmp:
        with open(os.path.join(tmp, ACCURACY_FILES[0]), "w", encoding="utf-8") as fh:
            json.dump(data, fh, indent=1)
        with open(os.path.join(tmp, ACCURACY_FILES[1]), "w", encoding="utf-8") as fh:
            fh.write(accuracy_table(data))
        accuracy_figure(data, os.path.join(tmp, ACCURACY_FILES[2]))
        fit_figure(data, os.path.join(tmp, ACCURACY_FILES[3]))
    return [os.path.join(out_dir, name) for name in ACCURACY_FILES]
