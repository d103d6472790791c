"""What a Monte Carlo budget buys: error, unfinished energy, forward and Jacobian time, and fits, against the budget.

A thin wrapper of ``jaxcos bench accuracy`` (``jaxcos/inference/_bench.py``,
where the settings and the method are documented; ``jaxcos/report/_bench.py``
for the files) writing into ``benchmarks/results/``:
``accuracy.json`` (every number, machine record, load average with every
timing), ``accuracy.md`` (tables), ``accuracy.png`` and ``accuracy_fit.png``.

    python benchmarks/bench_accuracy.py --force        # 11 min on a quiet two-core machine
    python benchmarks/bench_accuracy.py --quick --out /tmp/acc   # a smoke test
"""

import os
import sys

from jaxcos.cli import main

HERE = os.path.dirname(os.path.abspath(__file__))

if __name__ == "__main__":
    argv = sys.argv[1:]
    if "--out" not in argv:
        argv += ["--out", os.path.join(HERE, "results")]
    sys.exit(main(["bench", "accuracy", *argv]))
