"""``jaxcos fit``: fit a one-layer material to a measurement CSV, and write its params.json, report and figure."""

import os

from .._errors import InputError, refuse_overwrite
from ..inference import FIT_BOUNCES, FIT_JACOBIAN_WALKS, FIT_WALKS, fit
from ..io import load_measurements, load_params
from ..model import check_variant, resolve_budget
from ..report import FIT_FILES, write_fit
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


def _cmd(args):
    check_variant(args.variant)
    walks, bounces = resolve_budget(args.budget, walks=args.walks, bounces=args.bounces,
                                    default=(FIT_WALKS, FIT_BOUNCES))
    if args.jacobian_walks < 1:
        raise InputError(f"--jacobian-walks must be a positive integer, not {args.jacobian_walks}.")
    refuse_overwrite([os.path.join(args.out, name) for name in FIT_FILES], args.force)
    noise = parse_noise(args.noise) if args.noise is not None else None
    meas = load_measurements(args.measurements)
    if noise is not None:
        meas = meas.with_noise(*noise)
    start = load_params(args.start) if args.start else None
    result = fit(meas, variant=args.variant, method=args.method, seed=args.seed, walks=walks, bounces=bounces,
                 jacobian_walks=args.jacobian_walks, starts=args.starts, fit_t=args.fit_t, fit_phi=args.fit_phi,
                 start=start, t=args.t, interface=args.interface or None, progress=progress("fit"))
    write_fit(result, meas, args.out, force=args.force)
    print(_summary(result.record, args.out))


def add_command(sub):
    """Add ``jaxcos fit`` to the subparsers ``sub``."""
    p = sub.add_parser("fit", help="fit a layered material to a measurement CSV",
                       description="Fit a one-layer cosmetic material to MEASUREMENTS.csv by Levenberg-Marquardt "
                       "(or the Powell baseline) from a multi-start; writes DIR/params.json, DIR/report.md, DIR/fit.png.")
    p.add_argument("measurements", metavar="MEASUREMENTS.csv")
    p.add_argument("--out", required=True, metavar="DIR")
    p.add_argument("--variant", default="two_lobe",
                   help="two_lobe (default), single_lobe, diffusers_only or platelets_only")
    p.add_argument("--method", choices=("lm", "powell"), default="lm")
    p.add_argument("--seed", type=int, default=0, help="seeds the Monte Carlo key and the random starts")
    p.add_argument("--walks", type=int, default=None, help=f"walks per incidence direction (default {FIT_WALKS})")
    p.add_argument("--bounces", type=int, default=None, help=f"bounces per walk (default {FIT_BOUNCES})")
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
    p.add_argument("--force", action="store_true", help="overwrite an existing result in DIR")
    p.set_defaults(func=_cmd)
