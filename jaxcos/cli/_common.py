"""What every command shares: the progress printer and the ``--budget`` option."""

import sys
import time

from ..model import PRESETS


def progress(command):
    """A ``progress(message)`` callable printing ``jaxcos COMMAND [elapsed s]: message`` to stderr."""
    start = time.perf_counter()

    def say(message):
        print(f"jaxcos {command} [{time.perf_counter() - start:6.1f} s]: {message}", file=sys.stderr, flush=True)

    return say


def add_budget(p, default):
    """Add ``--budget NAME`` (a named Monte Carlo budget; ``default``: the name the help gives) to the parser ``p``."""
    named = ", ".join(f"{name} ({w} walks x {b} bounces)" for name, (w, b) in PRESETS.items())
    p.add_argument("--budget", metavar="NAME", default=None,
                   help=f"a named Monte Carlo budget: {named}; --walks and --bounces override it (default: {default})")
