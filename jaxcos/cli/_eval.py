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
from ..model import DEFAULT_BOUNCES, DEFAULT_WALKS, make_query, simulate

def evaluate(material, theta_i, theta_o, phi_o, key, *, walks=DEFAULT_WALKS, bounces=DEFAULT_BOUNCES):
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
                        walks=args.walks or DEFAULT_WALKS, bounces=args.bounces or DEFAULT_BOUNCES)
    scale = np.pi if args.quantity == "reflectance_factor" else 1.0
    write_evaluation(args.out, ti, to, po, scale * f, scale * f_std, quantity=args.quantity, overwrite=True)
    print(f"wrote {args.out}: {len(ti)} rows of {args.quantity} with Monte Carlo standard errors.")
