"""``jaxcos eval``: the BSDF of a material at the angles of a file, with Monte Carlo errors.

Example::

    import jax, jaxcos
    from jaxcos.io import load_angles
    from jaxcos.cli._eval import evaluate
    ti, to, po = load_angles("angles.csv")
    f, f_std = evaluate(jaxcos.published("dewy1"), ti, to, po, jax.random.key(0))
"""


import jax
import numpy as np

from .._errors import InputError, refuse_overwrite
from ..io import load_angles, write_evaluation
from ..model import ESTIMATOR_BUDGET, make_query, resolve_budget, simulate
from ._common import add_budget


def evaluate(material, theta_i, theta_o, phi_o, key, *, walks=ESTIMATOR_BUDGET.walks,
             bounces=ESTIMATOR_BUDGET.bounces):
    """The BSDF (1/sr) and its standard error, ``(N, 3)`` each, at the given angles (degrees)."""
    est = simulate(material, make_query(theta_i, theta_o, phi_o), key, walks=walks, bounces=bounces)
    return np.asarray(est.f, dtype=float), np.asarray(est.stderr, dtype=float)


def run_eval(args):
    """The ``jaxcos eval`` command (see ``jaxcos eval --help``)."""
    from ..io import load_params

    refuse_overwrite([args.out], args.force)
    for name, value in (("--walks", args.walks), ("--bounces", args.bounces)):
        if value is not None and value < 1:
            raise InputError(f"{name} must be a positive integer, not {value}.")
    material = load_params(args.params)
    ti, to, po = load_angles(args.angles)
    f, f_std = evaluate(material, ti, to, po, jax.random.key(args.seed),
                        walks=args.walks or ESTIMATOR_BUDGET.walks, bounces=args.bounces or ESTIMATOR_BUDGET.bounces)
    scale = np.pi if args.quantity == "reflectance_factor" else 1.0
    write_evaluation(args.out, ti, to, po, scale * f, scale * f_std, quantity=args.quantity, overwrite=True)
    print(f"wrote {args.out}: {len(ti)} rows of {args.quantity} with Monte Carlo standard errors.")


def _cmd(args):
    args.walks, args.bounces = resolve_budget(args.budget, walks=args.walks, bounces=args.bounces)
    run_eval(args)


def add_command(sub):
    """Add ``jaxcos eval`` to the subparsers ``sub``."""
    p = sub.add_parser("eval", help="evaluate the BSDF of a params.json at given angles",
                       description="Evaluate the BSDF of PARAMS at the theta_i,theta_o[,phi_o] rows of ANGLES.csv; "
                       "writes OUT.csv with r,g,b and their Monte Carlo standard errors r_std,g_std,b_std.")
    p.add_argument("params", metavar="PARAMS", help="params.json (docs/formats.md)")
    p.add_argument("--angles", required=True, metavar="ANGLES.csv", help="CSV with columns theta_i,theta_o[,phi_o] in degrees")
    p.add_argument("--out", required=True, metavar="OUT.csv")
    p.add_argument("--walks", type=int, default=None, help="walks per incidence direction (default: the library default)")
    p.add_argument("--bounces", type=int, default=None, help="bounces per walk (default: the library default)")
    add_budget(p, "paper")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--quantity", choices=("brdf", "reflectance_factor"), default="brdf",
                   help="write f (1/sr) or the reflectance factor pi*f")
    p.add_argument("--force", action="store_true", help="overwrite OUT.csv if it exists")
    p.set_defaults(func=_cmd)
