"""The ``jaxcos`` command line: thin layers over the public API.

Every command exits non-zero with one line on stderr (no traceback) on bad
input, writes only under its ``--out``, and refuses to overwrite an existing
result without ``--force``.
"""

import argparse
import os
import sys

from .._errors import InputError, refuse_overwrite


# --- eval ------------------------------------------------------------------------


def _cmd_eval(args):
    from ._eval import run_eval
    from ..model import resolve_budget

    args.walks, args.bounces = resolve_budget(args.budget, walks=args.walks, bounces=args.bounces)
    run_eval(args)


def add_budget(p, default):
    """Add ``--budget NAME`` (a named Monte Carlo budget; ``default``: the name the help gives) to the parser ``p``."""
    from ..model import BUDGETS

    named = ", ".join(f"{name} ({w} walks x {b} bounces)" for name, (w, b) in BUDGETS.items())
    p.add_argument("--budget", metavar="NAME", default=None,
                   help=f"a named Monte Carlo budget: {named}; --walks and --bounces override it (default: {default})")


def _add_eval(sub):
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
    p.set_defaults(func=_cmd_eval)


# --- import ----------------------------------------------------------------------


def _cmd_import(args):
    from ..io import import_raw, save_measurements

    refuse_overwrite([args.out], args.force)
    meas = import_raw(args.raw)
    save_measurements(meas, args.out, overwrite=True)
    print(f"wrote {args.out}: {meas.n_points} points, linear sRGB reflectance factors (D65).")


def _add_import(sub):
    p = sub.add_parser("import", help="convert a raw spectral instrument file to a measurement CSV",
                       description="Read a raw tab-separated gonioreflectometer file (theta_i, theta_o and 81 "
                       "reflectance factors at 380, 385, ..., 780 nm per row), convert the spectra to linear sRGB "
                       "(CIE 1931 2 degree observer, D65) and write the measurement CSV of docs/formats.md.")
    p.add_argument("raw", metavar="RAW.txt", help="raw tab-separated instrument file")
    p.add_argument("--out", required=True, metavar="FILE.csv")
    p.add_argument("--force", action="store_true", help="overwrite FILE.csv if it exists")
    p.set_defaults(func=_cmd_import)


# --- plot ------------------------------------------------------------------------


def _cmd_plot(args):
    from ..io import load_measurements
    from ..io import plot_measurements

    refuse_overwrite([args.out], args.force)
    plot_measurements(load_measurements(args.measurements), args.out, exposure=args.exposure, overwrite=True)
    print(f"wrote {args.out}.")


def _add_plot(sub):
    p = sub.add_parser("plot", help="draw measurements as a reflectance table (PNG)",
                       description="Draw the in-plane points of MEASUREMENTS.csv as a table like Figure 4 of "
                       "Lanza et al. 2024: theta_o across, theta_i down, each cell the reflectance factor in sRGB "
                       "at a stated exposure, black where there is no data.")
    p.add_argument("measurements", metavar="MEASUREMENTS.csv", help="measurement CSV (docs/formats.md)")
    p.add_argument("--out", required=True, metavar="FIG.png")
    p.add_argument("--exposure", type=float, default=None,
                   help="factor applied to the reflectance factor before sRGB encoding "
                   "(default: the 95th percentile maps to 0.8)")
    p.add_argument("--force", action="store_true", help="overwrite FIG.png if it exists")
    p.set_defaults(func=_cmd_plot)


# --- shared by the commands ------------------------------------------------------


def progress(command):
    """A ``progress(message)`` callable printing ``jaxcos COMMAND [elapsed s]: message`` to stderr."""
    import time

    start = time.perf_counter()

    def say(message):
        print(f"jaxcos {command} [{time.perf_counter() - start:6.1f} s]: {message}", file=sys.stderr, flush=True)

    return say


# --- registry ----------------------------------------------------------------------

def _from(module):
    """The ``add_command(subparsers)`` of a private module, imported when the parser is built."""

    def add(sub):
        import importlib

        importlib.import_module(module, __package__).add_command(sub)

    return add


# One entry per command, in the order of ``jaxcos --help``.
_COMMANDS = [
    _add_eval,
    _from("._fit"),
    _add_import,
    _add_plot,
    _from("._posterior"),
    _from("._bench"),
    _from("._ablate"),
    _from("._render"),
]


def _parser():
    parser = argparse.ArgumentParser(
        prog="jaxcos",
        description="Differentiable appearance of cosmetics: simulate, fit and compare layered BSDFs.",
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for add in _COMMANDS:
        add(sub)
    return parser


def _compilation_cache():
    """Keep compiled programs between runs in ``$JAXCOS_CACHE`` (default ``~/.cache/jaxcos/xla``; empty: off).

    A second fit of a file of the same shape then skips most of its compile time.
    """
    path = os.environ.get("JAXCOS_CACHE")
    if path is None:
        root = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
        path = os.path.join(root, "jaxcos", "xla")
    if path:
        import jax

        jax.config.update("jax_compilation_cache_dir", path)
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)


def main(argv=None):
    """Entry point of the ``jaxcos`` console script; returns the exit status."""
    args = _parser().parse_args(argv)
    _compilation_cache()
    try:
        status = args.func(args)
    except InputError as err:
        print(f"jaxcos {args.command}: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"jaxcos {args.command}: interrupted.", file=sys.stderr)
        return 130
    return int(status or 0)


if __name__ == "__main__":
    sys.exit(main())
