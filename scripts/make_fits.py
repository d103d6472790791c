"""Refit the bundled data sets into ``fits/``: ``python scripts/make_fits.py [dewy1 ...]``.

Runs ``jaxcos fit measurements/NAME.csv --out fits/NAME --force`` with the
defaults (Levenberg-Marquardt, multi-start, seed 0) for each named product
(default: all four). ``fits/published/`` holds the paper's published
parameters (docs/model.md section 5) as ``params.json`` files, for comparison.
"""

import os
import sys

from jaxcos.cli import main

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PRODUCTS = ("dewy1", "dewy2", "matte1", "matte2")

if __name__ == "__main__":
    for name in sys.argv[1:] or PRODUCTS:
        status = main(["fit", os.path.join(ROOT, "measurements", f"{name}.csv"),
                       "--out", os.path.join(ROOT, "fits", name), "--force"])
        if status:
            sys.exit(status)
