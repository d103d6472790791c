"""``jaxcos ablate``: fit every model variant and the Kubelka-Munk baseline to measurement files.

Thin over :func:`jaxcos.ablate` and :func:`jaxcos.write_ablation`; the protocol
and statistics are those of :mod:`jaxcos.inference` (docs/formats.md for the
files written).
"""

import os

from .._errors import refuse_overwrite
from ..inference import ABLATION_BOUNCES, ABLATION_VARIANTS, ABLATION_WALKS, ablate, check_variants
from ..report import ABLATION_FILES, write_ablation
from ._catalogue import ablation_catalogue, add_catalogue_options, check_catalogue_options
from ._common import progress


def _cmd(args):
    if args.catalogue:  # one ablation per file, on Dask (_catalogue.py)
        return ablation_catalogue(args)
    check_catalogue_options(args, False, needs="--catalogue")
    variants = check_variants(args.variants)
    targets = [os.path.join(args.out, name) for name in ABLATION_FILES]
    refuse_overwrite(targets, args.force)
    result = ablate(args.measurements, variants, seed=args.seed, walks=args.walks, bounces=args.bounces,
                    starts=args.starts, exposure=args.exposure, interface=args.interface, finer=not args.no_finer,
                    progress=progress("ablate"))
    write_ablation(result, args.out, force=args.force)
    for name in result.names:
        best = min((r for r in result.rows if r["file"] == name), key=lambda r: r["bic"])
        print(f"{name}: best by BIC {best['variant']} (L2 {best['l2']:.4g})")
    print(f"ablation of {len(result.names)} file(s) x {len(result.variants)} variant(s) in "
          f"{result.settings['total_time_s']:.0f} s. Wrote {', '.join(targets)}.")


def add_command(sub):
    """Register ``jaxcos ablate`` on an argparse subparsers object."""
    p = sub.add_parser("ablate", help="fit every model variant and the Kubelka-Munk baseline to measurement files",
                       description="Fit each variant (diffusers_only, platelets_only, single_lobe, two_lobe, "
                       "kubelka_munk) to each MEASUREMENTS.csv and compare them: writes DIR/ablation.csv (L2, RMSE, "
                       "mean CIEDE2000, parameters, AIC, BIC, time per file and variant), DIR/report.md, "
                       "DIR/ablation.png (a grid like Figure 6 of Lanza et al. 2024) and DIR/fits.json.")
    p.add_argument("measurements", nargs="+", metavar="MEASUREMENTS.csv")
    p.add_argument("--out", required=True, metavar="DIR")
    p.add_argument("--variants", default=",".join(ABLATION_VARIANTS), metavar="LIST",
                   help=f"comma-separated variants (default: all: {','.join(ABLATION_VARIANTS)})")
    p.add_argument("--seed", type=int, default=0, help="seeds every fit's Monte Carlo key and random starts")
    p.add_argument("--walks", type=int, default=ABLATION_WALKS,
                   help=f"walks per incidence of the Monte Carlo fits (default {ABLATION_WALKS})")
    p.add_argument("--bounces", type=int, default=ABLATION_BOUNCES,
                   help=f"bounces per walk (default {ABLATION_BOUNCES})")
    p.add_argument("--starts", type=int, default=15, help="random starts per multi-start besides the default one")
    p.add_argument("--exposure", type=float, default=1.0,
                   help="scale of the reflectance factors before the CIEDE2000 colours (default 1: white = L* 100)")
    p.add_argument("--interface", action="store_true",
                   help="also fit each Monte Carlo variant V with a rough dielectric top interface (V+interface: "
                   "eta and alpha_s fitted besides; docs/model.md section 3a); AIC and BIC compare them all")
    p.add_argument("--no-finer", action="store_true",
                   help="skip each fit's last refinement at four times the walks (as jaxcos fit --no-finer)")
    p.add_argument("--force", action="store_true", help="overwrite an existing result in DIR")
    p.add_argument("--catalogue", action="store_true",
                   help="one ablation per file (files, folders or glob patterns) in DIR/NAME/, as a catalogue on "
                   "Dask, instead of one comparison of all the files (docs/formats.md, Catalogues)")
    add_catalogue_options(p)
    p.set_defaults(func=_cmd)
