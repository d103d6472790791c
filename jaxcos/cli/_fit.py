"""``jaxcos fit``: fit a one-layer material to a measurement CSV, and write its params.json, report and figure."""

import os

from .._errors import InputError, refuse_overwrite
from ..inference import FitBudget, fit
from ..io import load_measurements, load_params
from ..model import FIT_BUDGET, FIT_JACOBIAN_WALKS, check_variant, resolve_budget
from ..report import FIT_FILES, body_hint, gloss_hint, write_fit
from ._catalogue import (Job, add_catalogue_options, check_catalogue_options, draw_curves, is_catalogue,
                         run_catalogue)
from ._common import add_budget, progress


def _summary(record, out):
    """The command's closing line: what was fitted, how well, and what was written."""
    chi2 = (f", reduced chi-square {record.reduced_chi2:.2f}" if record.reduced_chi2 is not None
            else " (unweighted: the file has no std; report.md says which points carry the loss)")
    if record.check.reduced_chi2 is not None:
        chi2 += f" ({record.check.reduced_chi2:.2f} +- {record.check.reduced_chi2_se:.2f} under independent keys)"
    return (f"fitted {record.variant} to {record.n_points} points in {record.time_s:.1f} s: L2 {record.l2:.4g}, "
            f"RMSE {record.rmse:.4g}{chi2}; {record.starts_at_optimum} of {record.starts_refined} refined starts "
            f"agree. Wrote {', '.join(os.path.join(out, n) for n in FIT_FILES)}.")


def parse_noise(text):
    """``REL[,ABS]`` of ``--noise`` as two floats; one sentence on a malformed value."""
    parts = text.split(",")
    try:
        if len(parts) not in (1, 2):
            raise ValueError
        levels = [float(part) for part in parts] + [0.0] * (2 - len(parts))
    except ValueError:
        raise InputError(f"--noise takes REL or REL,ABS (for example 0.05,0.005), not {text!r}.") from None
    return levels[0], levels[1]


def fit_options(args):
    """The fit's settings from the parsed arguments, checked: what :func:`fit_into` takes as ``options``.

    The Jacobian's walks are those of :meth:`~jaxcos.inference.FitBudget.of` (at most the walks), so that a
    catalogue's settings line states the budget its fits ran with."""
    check_variant(args.variant)
    walks, bounces = resolve_budget(args.budget, walks=args.walks, bounces=args.bounces,
                                    default=FIT_BUDGET)
    if args.jacobian_walks < 1:
        raise InputError(f"--jacobian-walks must be a positive integer, not {args.jacobian_walks}.")
    noise = parse_noise(args.noise) if args.noise is not None else None
    budget = FitBudget.of(walks, bounces, args.jacobian_walks)
    return dict(variant=args.variant, method=args.method, seed=args.seed, walks=walks, bounces=bounces,
                jacobian_walks=budget.jacobian_walks, starts=args.starts, fit_t=args.fit_t, fit_phi=args.fit_phi,
                start=args.start, t=args.t, interface=args.interface, noise=noise, finer=not args.no_finer)


def fit_file(path, out, options, *, force=False, progress=None):
    """Fit the measurement file ``path`` with ``options`` (:func:`fit_options`) and write its result folder ``out``.

    What ``jaxcos fit FILE --out DIR`` runs, and what a catalogue runs for each of its files;
    returns the :class:`~jaxcos.FitResult` and the measurements it was fitted to.
    """
    meas = load_measurements(path)
    if options["noise"] is not None:
        meas = meas.with_noise(*options["noise"])
    start = load_params(options["start"]) if options["start"] else None
    result = fit(meas, variant=options["variant"], method=options["method"], seed=options["seed"],
                 walks=options["walks"], bounces=options["bounces"], jacobian_walks=options["jacobian_walks"],
                 starts=options["starts"], fit_t=options["fit_t"], fit_phi=options["fit_phi"], start=start,
                 t=options["t"], interface=options["interface"] or None, finer=options["finer"], progress=progress)
    write_fit(result, meas, out, force=force)
    return result, meas


def fit_into(path, folder, options):
    """:func:`fit_file` into a new folder, silently: a catalogue's task for one file."""
    fit_file(path, folder, options)


_PARAM_COLUMNS = ("t", "c_d", "albedo_d_r", "albedo_d_g", "albedo_d_b", "g1", "g2", "w_g", "albedo_p_r", "albedo_p_g",
                  "albedo_p_b", "alpha_p", "theta_p_deg", "phi_p_deg", "eta", "alpha_s")
_RECORD_COLUMNS = ("n_points", "l2", "rmse", "reduced_chi2", "check_material_chi2", "check_material_chi2_se",
                   "check_reduced_chi2", "check_reduced_chi2_se", "walks", "bounces", "seed", "time_s")
CATALOGUE_COLUMNS = ("variant",) + _PARAM_COLUMNS + _RECORD_COLUMNS
"""The columns of a fit catalogue between ``file, result, status`` and ``wall_s, error`` (docs/formats.md)."""


def _read_params(folder):
    import json

    with open(os.path.join(folder, "params.json"), encoding="utf-8") as fh:
        return json.load(fh)


def fit_row(folder):
    """The catalogue columns of the fit in ``folder``: its parameters and its record's statistics."""
    doc = _read_params(folder)
    layer, record = doc["layers"][0], doc.get("fit", {})
    row = dict(variant=doc.get("variant", "two_lobe"), phi_p_deg=layer.get("phi_p_deg", 0.0),
               **(doc.get("interface") or {}))
    for name in ("t", "c_d", "g1", "g2", "w_g", "alpha_p", "theta_p_deg"):
        row[name] = layer[name]
    for name in ("albedo_d", "albedo_p"):
        value = layer[name]
        value = value if isinstance(value, list) else [value] * 3
        row.update({f"{name}_{c}": v for c, v in zip("rgb", value)})
    row.update({k: record.get(k) for k in ("n_points", "l2", "rmse", "reduced_chi2", "walks", "bounces", "seed",
                                           "time_s")})
    check = record.get("check") or {}
    row.update({f"check_{k}": check.get(k) for k in ("material_chi2", "material_chi2_se", "reduced_chi2",
                                                       "reduced_chi2_se")})
    return row


def _settings_differ(folder, options):
    """How the fit in ``folder`` was made with other settings than ``options``, or ``None``."""
    params = _read_params(folder)
    record = params.get("fit", {})
    for key in ("variant", "method", "seed", "walks", "bounces", "jacobian_walks"):
        if key in record and record[key] != options[key]:
            return f"holds a fit with {key} {record[key]}, not {options[key]}"
    if options["interface"] and "interface" not in params:
        return "holds a fit without a top interface, not one with --interface"
    if "finer" in record and options["method"] == "lm" and (record["finer"] is not None) != options["finer"]:
        made, asked = ("with", "without") if record["finer"] is not None else ("without", "with")
        return f"holds a fit made {made} the finer refinement, not {asked} it"
    return None


def _picture(rows, path):
    named = [(os.path.basename(r["file"]), load_params(os.path.join(r["result"], "params.json"))) for r in rows]
    return draw_curves(named, path)


FIT_JOB = Job(command="fit", files=FIT_FILES, run=fit_into, row=fit_row, columns=CATALOGUE_COLUMNS,
              settings_differ=_settings_differ, picture=_picture)
"""``jaxcos fit`` over a catalogue (:func:`~jaxcos.cli._catalogue.run_catalogue`)."""


def _cmd(args):
    catalogue = is_catalogue(args.measurements)
    check_catalogue_options(args, catalogue)
    options = fit_options(args)
    if catalogue:
        if options["start"]:
            load_params(options["start"])  # one message here rather than one per file
            options["start"] = os.path.abspath(options["start"])
        return run_catalogue(FIT_JOB, args.measurements, args.out, options, force=args.force,
                             scheduler=args.scheduler, workers=args.workers, tries=args.tries, say=progress("fit"))
    refuse_overwrite([os.path.join(args.out, name) for name in FIT_FILES], args.force)
    result, meas = fit_file(args.measurements[0], args.out, options, force=args.force, progress=progress("fit"))
    print(_summary(result.record, args.out))
    for hint in (gloss_hint(meas, result.material), body_hint(meas, result.model)):
        if hint is not None:
            print(hint)


def add_command(sub):
    """Add ``jaxcos fit`` to the subparsers ``sub``."""
    p = sub.add_parser("fit", help="fit a layered material to a measurement CSV",
                       description="Fit a one-layer cosmetic material to MEASUREMENTS.csv by Levenberg-Marquardt "
                       "(or the Powell baseline) from a multi-start; writes DIR/params.json, DIR/report.md, DIR/fit.png. "
                       "Several files, a folder or a glob pattern make a catalogue: one Dask task per file, "
                       "DIR/STEM/ per file (the same three files), DIR/catalogue.csv, DIR/catalogue.md and "
                       "DIR/catalogue.png; a rerun skips the files already done.")
    p.add_argument("measurements", nargs="+", metavar="MEASUREMENTS.csv",
                   help="a measurement file; or several, folders (their *.csv) or glob patterns: a catalogue")
    p.add_argument("--out", required=True, metavar="DIR")
    p.add_argument("--variant", default="two_lobe",
                   help="two_lobe (default), single_lobe, diffusers_only or platelets_only")
    p.add_argument("--method", choices=("lm", "powell"), default="lm")
    p.add_argument("--seed", type=int, default=0, help="seeds the Monte Carlo key and the random starts")
    p.add_argument("--walks", type=int, default=None, help=f"walks per incidence direction (default {FIT_BUDGET.walks})")
    p.add_argument("--bounces", type=int, default=None, help=f"bounces per walk (default {FIT_BUDGET.bounces})")
    p.add_argument("--jacobian-walks", type=int, default=FIT_JACOBIAN_WALKS, metavar="N",
                   help=f"walks of the Jacobian, the first of the objective's walks (default {FIT_JACOBIAN_WALKS})")
    add_budget(p, "accurate")
    p.add_argument("--starts", type=int, default=15,
                   help="starts screened besides the default one: one of broad tilted platelets, the rest random "
                        "(default 15)")
    p.add_argument("--start", metavar="PARAMS", help="start from this params.json instead of the multi-start")
    p.add_argument("--t", type=float, default=16.0, help="optical thickness when it is not fitted (default 16)")
    p.add_argument("--fit-t", action="store_true", help="also fit the optical thickness t")
    p.add_argument("--fit-phi", action="store_true", help="also fit the tilt azimuth phi_p (default: held at 0)")
    p.add_argument("--interface", action="store_true",
                   help="give the material a rough dielectric top interface and fit its eta (1.01-2.5) and "
                        "alpha_s (0.005-1) with the rest (docs/model.md section 3a; the default with a --start "
                        "that has one)")
    p.add_argument("--noise", metavar="REL[,ABS]", default=None,
                   help="for a file without std columns: weigh each point by the noise model "
                        "std = REL * value + ABS (for example 0.05,0.005) instead of minimising the plain L2")
    p.add_argument("--no-finer", action="store_true",
                   help="skip the last refinement at four times the walks: a faster fit that may stop short of "
                        "the optimum where the fit's own walks cannot resolve it (docs/method.md)")
    p.add_argument("--force", action="store_true", help="overwrite an existing result in DIR")
    add_catalogue_options(p)
    p.set_defaults(func=_cmd)
