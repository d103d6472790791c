"""What an ablation leaves behind: ``ablation.csv``, ``report.md``, ``ablation.png`` and ``fits.json``.

The table has one row per file and variant with the columns of
:data:`jaxcos.inference.CSV_COLUMNS` (docs/formats.md); the report explains the
statistics of :func:`jaxcos.ablate` (``L2``, chi-square, AIC, BIC, CIEDE2000);
the figure is a grid like Figure 6 of Lanza et al. 2024 (rows: files;
columns: measured, then each variant); ``fits.json`` holds every fitted
model with its fit record.

Example::

    import jaxcos
    result = jaxcos.ablate(["measurements/matte2.csv"], variants=["two_lobe", "kubelka_munk"])
    jaxcos.write_ablation(result, "out/ablation")
"""

import csv
import io
import json
import math
import os

import numpy as np
from matplotlib.figure import Figure

from .._errors import staged_outputs
from ..inference import CSV_COLUMNS
from ..inference._ablate import INTERFACE_SUFFIX
from ..io import default_exposure, draw_reflectance, material_to_dict
from ._fit import surface_gloss
from ..model import Material

ABLATION_FILES = ("ablation.csv", "report.md", "ablation.png", "fits.json")
"""What :func:`write_ablation` writes under its folder."""
POOR_FIT = 5.0
"""A file whose best reduced chi-square exceeds this gets a warning in the report."""


def _csv_text(rows):
    out = io.StringIO()
    writer = csv.DictWriter(out, fieldnames=CSV_COLUMNS, lineterminator="\n")
    writer.writeheader()
    for row in rows:
        writer.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in row.items()})
    return out.getvalue()


def _fmt(v, digits=4):
    return "—" if isinstance(v, float) and math.isnan(v) else f"{v:.{digits}g}"


def ablation_report(result):
    """The human-readable ``report.md`` of a :class:`jaxcos.AblationResult`."""
    s = result.settings
    lines = [
        "# Ablation",
        "",
        f"{len(result.names)} file(s), variants {', '.join(f'`{v}`' for v in result.variants)}. "
        f"Monte Carlo variants: {s['walks']} walks per incidence, {s['bounces']} bounces, seed {s['seed']}; "
        f"multi-starts of 1 default + {s['starts']} other starts, one of broad tilted platelets (two_lobe refines the {s['refine']} best screened "
        f"and the default start unscreened, each reduced variant its {s['reduced_refine']} best and the default, "
        "then the start from the two-lobe fit, keeping the "
        "better by chi-square; a variant beaten by a variant nested in it is refitted from that fit"
        + ("" if s["finer"] else "; no fit's last refinement at four times the walks (`--no-finer`)")
        + "). "
        f"Kubelka-Munk: every start refined. Total time {s['total_time_s']:.0f} s"
        + (f" (1-minute load average {s['load_average'][0]} at the start, {s['load_average'][1]} at the end, "
           f"{os.cpu_count()} CPUs)." if None not in s.get("load_average", (None,)) else "."),
        "",
        "Columns: `L2` the paper's metric (sum of squared differences in the file's quantity); `chi2` with the "
        "file's std; `AIC = -2 ln L + 2k`, `BIC = -2 ln L + k ln n` from the Gaussian likelihood "
        "(`-2 ln L = chi2 + sum ln(2 pi std^2)`, `n` = points x 3; without std the variance is estimated and "
        "counted as a parameter); `ΔBIC` from the file's best. The Monte Carlo models' own error counts as misfit. "
        f"`ΔE00`: mean CIEDE2000 colour difference of linear sRGB reflectance factors at exposure "
        f"{s['exposure']:g} (a white diffuser is L* = 100), sRGB primaries, D65 white (CIE 1931 2°). "
        "Time: wall time of the variant's fits on that file, including compilation the first time a variant "
        "meets a shape.",
        "",
    ]
    interface = any(v.endswith(INTERFACE_SUFFIX) for v in result.variants)  # not for Kubelka-Munk alone
    if interface:
        lines += [
            "`V+interface`: the variant `V` under a rough dielectric top interface (docs/model.md section 3a), "
            "with its index `eta` and GGX roughness `alpha_s` fitted besides (2 more parameters). An interface "
            "with `eta` near 1 is a different model from none, so each is fitted from its own multi-start and "
            "from `V`'s index-matched fit with the default interface (`eta` 1.5, `alpha_s` 0.1), the better "
            "kept; AIC and BIC weigh the two extra parameters as any others.",
            "",
        ]
    best_rows = []
    for name, meas in zip(result.names, result.measurements):
        rows = [r for r in result.rows if r["file"] == name]
        best = min(rows, key=lambda r: r["bic"])
        best_rows.append((name, best))
        lines += [f"## {name}", "",
                  "| variant | k | L2 | RMSE | reduced chi2 | ΔE00 | AIC | BIC | ΔBIC | start kept | time |",
                  "|---|---|---|---|---|---|---|---|---|---|---|"]
        for r in rows:
            mark = " **(best BIC)**" if r is best else ""
            lines.append(f"| `{r['variant']}`{mark} | {r['n_params']} | {_fmt(r['l2'])} | {_fmt(r['rmse'])} | "
                         f"{_fmt(r['reduced_chi2'], 3)} | {_fmt(r['delta_e2000'], 3)} | {r['aic']:.1f} | "
                         f"{r['bic']:.1f} | {r['bic'] - best['bic']:.1f} | {r['start']} | {r['time_s']:.1f} s |")
        lowest = min(r["reduced_chi2"] for r in rows)
        if lowest > POOR_FIT:
            lines += ["", f"**No variant fits this file within its noise** (smallest reduced chi-square {lowest:.3g}): "
                      "the ranking says which misfit is least bad, not which model is right. A narrow highlight "
                      "that no start of the multi-start reached is the usual cause; compare the panels of "
                      "`ablation.png`."]
        gloss = None if interface else surface_gloss(meas)
        if gloss is not None:
            lines += ["", f"**{gloss}** Run the ablation again with `--interface` to fit each variant under a top "
                      "interface too."]
        lines.append("")
    lines += ["## Preferred by BIC", "", "| file | variant | next best (ΔBIC) |", "|---|---|---|"]
    for name, best in best_rows:
        others = sorted((r for r in result.rows if r["file"] == name and r is not best), key=lambda r: r["bic"])
        nxt = f"`{others[0]['variant']}` (+{others[0]['bic'] - best['bic']:.1f})" if others else "—"
        lines.append(f"| {name} | `{best['variant']}` | {nxt} |")
    if interface:
        lines += ["", "## With and without the interface", "",
                  "Differences `V+interface` minus `V` (negative: the interface is preferred); the fitted interface.",
                  "", "| file | variant | ΔAIC | ΔBIC | preferred by BIC | eta | alpha_s |",
                  "|---|---|---|---|---|---|---|"]
        for i, name in enumerate(result.names):
            for r in result.rows:
                if r["file"] != name or not r["variant"].endswith(INTERFACE_SUFFIX):
                    continue
                plain = r["variant"][:-len(INTERFACE_SUFFIX)]
                q = next(row for row in result.rows if row["file"] == name and row["variant"] == plain)
                top = result.fits[(i, r["variant"])].material.interface
                lines.append(f"| {name} | `{plain}` | {r['aic'] - q['aic']:+.1f} | {r['bic'] - q['bic']:+.1f} | "
                             f"{'with' if r['bic'] < q['bic'] else 'without'} | {float(top.eta):.3g} | "
                             f"{float(top.alpha_s):.3g} |")
    if s.get("padded_shape"):
        i, j, n = s["padded_shape"]
        lines += ["", f"Files with std columns were padded to {i} incidences x {j} outgoing directions ({n} points) "
                  "with zero-weight dummy points, so each Monte Carlo variant compiled once."]
    lines += ["", "![measured and fitted, one row per file](ablation.png)", ""]
    return "\n".join(lines)


def ablation_figure(result, path):
    """Save the grid of measured and fitted tables (rows: files; columns: measured, then each variant)."""
    n_rows, n_cols = len(result.names), 1 + len(result.variants)
    fig = Figure(figsize=(3.1 * n_cols, 2.7 * n_rows), layout="constrained")
    axes = np.atleast_2d(fig.subplots(n_rows, n_cols, squeeze=False))
    for i, (meas, name) in enumerate(zip(result.measurements, result.names)):
        to_rf = math.pi if meas.quantity == "brdf" else 1.0
        k = default_exposure(meas.values * to_rf)
        draw_reflectance(axes[i, 0], meas.theta_i, meas.theta_o, meas.values * to_rf, exposure=k,
                         title=f"{os.path.basename(name)}: measured")
        for j, variant in enumerate(result.variants, start=1):
            row = next(r for r in result.rows if r["file"] == name and r["variant"] == variant)
            draw_reflectance(axes[i, j], meas.theta_i, meas.theta_o, result.fits[(i, variant)].model * to_rf,
                             exposure=k, title=f"{variant}\nL2 {row['l2']:.3g}")
        for j in range(n_cols):
            if i < n_rows - 1:
                axes[i, j].set_xlabel("")
            if j > 0:
                axes[i, j].set_ylabel("")
    fig.savefig(path, dpi=100)


def _fits_json(result):
    """Per file and variant, the fitted model (``params.json``'s layout for a :class:`jaxcos.Material`, the
    fit record's ``parameters`` for a Kubelka-Munk model) and its ``fit`` record."""
    out = {}
    for (i, variant), r in result.fits.items():
        entry = out.setdefault(result.names[i], {})
        if isinstance(r.material, Material):
            entry[variant] = {**material_to_dict(r.material), "fit": r.record.to_json()}
        else:
            entry[variant] = {"parameters": r.record.parameters, "fit": r.record.to_json()}
    return json.dumps(out, indent=1, default=float) + "\n"


def write_ablation(result, out_dir, *, force=False):
    """Write ``ablation.csv``, ``report.md``, ``ablation.png`` and ``fits.json`` (every fitted model) under ``out_dir``.

    ``result`` is a :class:`jaxcos.AblationResult`.

    Everything is written into a temporary folder first and moved in at the
    end, so a failure leaves nothing half-written. Existing files are kept
    unless ``force``.
    """
    with staged_outputs(out_dir, ABLATION_FILES, force) as tmp:
        with open(os.path.join(tmp, "ablation.csv"), "w", encoding="utf-8") as fh:
            fh.write(_csv_text(result.rows))
        with open(os.path.join(tmp, "report.md"), "w", encoding="utf-8") as fh:
            fh.write(ablation_report(result))
        ablation_figure(result, os.path.join(tmp, "ablation.png"))
        with open(os.path.join(tmp, "fits.json"), "w", encoding="utf-8") as fh:
            fh.write(_fits_json(result))
    return [os.path.join(os.fspath(out_dir), name) for name in ABLATION_FILES]
