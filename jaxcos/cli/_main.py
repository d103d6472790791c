"""The ``jaxcos`` command line: thin layers over the public API.

Every command exits non-zero with one line on stderr (no traceback) on bad
input, writes only under its ``--out``, and refuses to overwrite an existing
result without ``--force``.
"""

import argparse
import sys

from .._errors import InputError, refuse_overwrite
from . import _ablate, _bench, _eval, _fit, _posterior, _render
from ._catalogue import compilation_cache_dir, enable_compilation_cache


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


# --- registry ----------------------------------------------------------------------

# One entry per command, in the order of ``jaxcos --help``.
_COMMANDS = [
    _eval.add_command,
    _fit.add_command,
    _add_import,
    _add_plot,
    _posterior.add_command,
    _bench.add_command,
    _ablate.add_command,
    _render.add_command,
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
    # The same folder for the workers of a catalogue (_catalogue.run_task enables it there).
    enable_compilation_cache(compilation_cache_dir())


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
