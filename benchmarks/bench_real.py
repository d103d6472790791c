"""Fits of the real measured foundations, with and without the top interface (issue 30's evidence).

Reads the raw instrument files of ``../shared/data/clarins/`` (not shipped:
their source grants no licence, so nothing they produce is committed but the
summary numbers), imports them, fits every product four ways (index-matched or
with the top interface; plain L2 or ``--noise 0.05,0.005``), and records per fit:
L2 at 8192 walks under a key the fit never saw, the median relative miss of
the points outside the brightest tenth (the diffuse body), the fitted
``c_d``, ``eta`` and ``alpha_s``, and the fit's time (compilation included
for the first fit of each shape). Each fit's params.json, report.md, fit.png
and a render (``render.png``) go to ``OUT/<product>_<variant>``.

    python benchmarks/bench_real.py --out /tmp/real          # all 8 fits, about 10-15 min on 2 cores
    python benchmarks/bench_real.py --out /tmp/real --only 105
"""

import argparse
import json
import os
import platform
import sys
import time

import jax
import numpy as np

import jaxcos
from jaxcos.render import write_png
from jaxcos.report import loss_split

RAW = {
    "105": "Clarins_105_Nude_coll_norm.txt",
    "108": "Clarinsfoundation108_5W_norm_thick_layer_tab.txt",
}
SCORE_WALKS = 8192
SCORE_KEY = 12345  # independent of every fit's key


def score(material, meas):
    """L2 at :data:`SCORE_WALKS` walks under an independent key, and the body's median relative miss
    (:func:`jaxcos.report.loss_split`, as a fit's report gives it)."""
    query = jaxcos.make_query(meas.theta_i, meas.theta_o, meas.phi_o)
    est = jaxcos.simulate(material, query, jax.random.key(SCORE_KEY), walks=SCORE_WALKS, bounces=128)
    model = meas.scale * np.asarray(est.f, float)
    return float(np.sum((model - meas.values) ** 2)), loss_split(meas, model).body_miss


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", default=os.path.join(os.path.dirname(__file__), "..", "..", "shared", "data", "clarins"))
    parser.add_argument("--out", required=True)
    parser.add_argument("--only", choices=tuple(RAW), default=None)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    if not os.path.isdir(args.data):
        sys.exit(f"{args.data}: no such folder; pass --data with the folder of the raw Clarins files.")
    os.makedirs(args.out, exist_ok=True)
    rows = []
    for product, raw in RAW.items():
        if args.only and product != args.only:
            continue
        plain = jaxcos.import_raw(os.path.join(args.data, raw))
        for interface in (False, True):
            for noise in (None, (0.05, 0.005)):
                meas = plain if noise is None else plain.with_noise(*noise)
                name = f"{product}_{'interface' if interface else 'matched'}_{'noise' if noise else 'plain'}"
                started = time.perf_counter()
                result = jaxcos.fit(meas, seed=args.seed, interface=interface)
                seconds = time.perf_counter() - started
                l2, miss = score(result.material, plain)
                folder = os.path.join(args.out, name)
                jaxcos.write_fit(result, meas, folder, force=True)
                image = jaxcos.render(result.material, key=jax.random.key(0))
                write_png(image, os.path.join(folder, "render.png"), overwrite=True)
                layer = result.material.layers[0]
                top = result.material.interface
                row = dict(fit=name, l2=l2, body_median_miss=miss, time_s=seconds, c_d=float(layer.c_d),
                           albedo_d=[float(v) for v in layer.albedo_d], alpha_p=float(layer.alpha_p),
                           eta=None if top is None else float(top.eta),
                           alpha_s=None if top is None else float(top.alpha_s))
                rows.append(row)
                print(json.dumps(row), flush=True)
    record = dict(machine=f"{platform.machine()} {platform.processor() or ''} {os.cpu_count()} cores".strip(),
                  jax=jax.__version__, score_walks=SCORE_WALKS, rows=rows)
    with open(os.path.join(args.out, "real.json"), "w", encoding="utf-8") as fh:
        json.dump(record, fh, indent=2)


if __name__ == "__main__":
    main()
