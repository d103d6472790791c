"""``jaxcos uncertainty``: posterior spreads of a fit's parameters (emcee), written as a report."""

import json
import os
import sys

from .._errors import InputError, refuse_overwrite
from ..inference import CHAIN_TAUS, MAX_STEPS, WALKERS, fit, uncertainty
from ..io import load_measurements, load_params
from ..report import UNCERTAINTY_FILES, write_uncertainty
from ._catalogue import add_catalogue_options, check_catalogue_options, is_catalogue, uncertainty_catalogue
from ._common import progress


def start_from_params(meas, path, *, seed=0, progress=None):
    """A :class:`~jaxcos.FitResult` of ``meas`` refined by Levenberg-Marquardt from the params.json at ``path``.

    The fitted set of parameters (``t``, ``phi_p``) follows the file's
    ``"fit"`` record when it has one.
    """
    material = load_params(path)
    with open(path, encoding="utf-8") as fh:
        fitted = json.load(fh).get("fit", {}).get("fitted", [])
    return fit(meas, variant=material.variant, seed=seed, start=material, fit_t="t" in fitted,
               fit_phi="phi_p" in fitted, t=float(material.layers[0].t), progress=progress)


def _cmd(args):
    if is_catalogue(args.measurements):  # several files: one posterior each (_catalogue.py)
        return uncertainty_catalogue(args)
    check_catalogue_options(args, False)
    say = progress("uncertainty")

    if (args.walkers is not None and args.walkers < 4) or args.steps < 1:
        raise InputError("--walkers must be at least 4 and --steps at least 1.")
    refuse_overwrite([os.path.join(args.out, name) for name in UNCERTAINTY_FILES], args.force)
    meas = load_measurements(args.measurements[0])
    if args.params:
        if not os.path.isfile(args.params):
            raise InputError(f"{args.params}: no such file.")
        start = start_from_params(meas, args.params, seed=args.seed, progress=say)
    else:
        start = fit(meas, seed=args.seed, progress=say)
    post = uncertainty(meas, start, seed=args.seed, walkers=args.walkers, max_steps=args.steps, progress=say)
    paths = write_uncertainty(post, meas, args.out, force=args.force)
    worst = min(post.summary, key=lambda k: post.summary[k]["ess"])
    print(f"sampled {post.chain.walkers} walkers x {post.chain.steps} steps in {post.record.sampling_time_s:.1f} s "
          f"({post.record.time_s:.0f} s in all): "
          f"chain {post.record.chain_in_tau:.1f} autocorrelation times long, smallest effective sample size "
          f"{post.summary[worst]['ess']:.0f} ({worst}). Wrote {', '.join(paths)}.")
    if not post.converged:
        print(f"jaxcos uncertainty: the chain is shorter than {CHAIN_TAUS} autocorrelation times; its spreads are "
              "not reliable (run longer with --steps).", file=sys.stderr)
        return 3
    return 0


def add_command(sub):
    """Register ``jaxcos uncertainty``."""
    p = sub.add_parser("uncertainty", help="posterior spreads of a fit's parameters (emcee)",
                       description="Sample the posterior of the parameters of a fit to MEASUREMENTS.csv with emcee, "
                       "starting from a fit (run first unless --params gives one); writes DIR/posterior.json, "
                       "DIR/report.md, DIR/corner.png, DIR/predictive.png and DIR/sensitivity.png. Exit status 3 "
                       "means the chain was too short for its autocorrelation time.")
    p.add_argument("measurements", nargs="+", metavar="MEASUREMENTS.csv",
                   help="a measurement file; or several, folders or glob patterns: a catalogue, one posterior each "
                   "in DIR/NAME/ (docs/formats.md, Catalogues)")
    p.add_argument("--out", required=True, metavar="DIR")
    p.add_argument("--params", metavar="FIT.json", help="start from this params.json (refined by a short fit); with "
                   "several files, a fit catalogue's folder (its NAME/params.json for NAME.csv)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--walkers", type=int, default=None,
                   help=f"ensemble size, at least 2 x parameters + 2 (default {WALKERS}, or 2 x parameters + 2 "
                   "where that is more: a fit with an interface, t and phi_p has 16 parameters)")
    p.add_argument("--steps", type=int, default=MAX_STEPS,
                   help=f"longest chain in steps (default {MAX_STEPS}); it stops at {CHAIN_TAUS} autocorrelation times")
    p.add_argument("--force", action="store_true", help="overwrite an existing result in DIR")
    add_catalogue_options(p)
    p.set_defaults(func=_cmd)
