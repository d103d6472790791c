"""``jaxcos bench accuracy``: the accuracy benchmark, run and written.

    jaxcos bench accuracy --out benchmarks/results [--quick] [--force]
    python benchmarks/bench_accuracy.py                      # the same, into benchmarks/results

Runs :func:`jaxcos.inference.accuracy_benchmark` (the method and its
settings) and writes its files with :func:`jaxcos.report.write_accuracy`
(``accuracy.json``, ``accuracy.md``, ``accuracy.png``, ``accuracy_fit.png``
under ``--out``). Existing results are refused before anything runs, unless
``--force``.
"""

import os

from .._errors import refuse_overwrite
from ._common import progress


def _cmd_accuracy(args):
    from ..inference import accuracy_benchmark
    from ..report import ACCURACY_FILES, write_accuracy

    say = progress("bench accuracy")
    refuse_overwrite([os.path.join(args.out, name) for name in ACCURACY_FILES], args.force)
    data = accuracy_benchmark(quick=args.quick, progress=say)
    targets = write_accuracy(data, args.out, force=args.force)
    say(f"wrote {', '.join(targets)} in {data['total_s']:.0f} s")


def add_command(sub):
    """Register ``jaxcos bench accuracy``."""
    from ..report import ACCURACY_FILES

    p = sub.add_parser("bench", help="benchmarks of the estimator (accuracy against time)",
                       description="Benchmarks of jaxcos itself.")
    bench = p.add_subparsers(dest="benchmark", required=True, metavar="BENCHMARK")
    a = bench.add_parser("accuracy", help="error, unfinished energy, forward and Jacobian time against the budget",
                         description="Sweep walks per incidence and bounces, with exact and Monte Carlo single "
                         "scattering, for dewy1 and matte2 on the standard grid against a high-budget reference, "
                         "and fit a synthetic set at several budgets; writes " + ", ".join(ACCURACY_FILES) + " under DIR. "
                         "The full run took 11 minutes on a quiet two-core machine, the fits 3.5 of them.")
    a.add_argument("--out", required=True, metavar="DIR")
    a.add_argument("--quick", action="store_true", help="tiny budgets, one product, one fit (a smoke test of about a minute): the numbers mean nothing")
    a.add_argument("--force", action="store_true", help="overwrite existing results in DIR")
    a.set_defaults(func=_cmd_accuracy)
