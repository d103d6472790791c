"""Throughput of a fit catalogue: one process, the in-process LocalCluster, and `dask worker` processes.

    python benchmarks/bench_catalogue.py --out /tmp/bench_catalogue             # 8 files, toy budget
    python benchmarks/bench_catalogue.py --files 16 --walks 256 --bounces 64 --out /tmp/bc

The catalogue: ``--files`` measurement files on the angles of
``measurements/matte2.csv`` (the real instrument's 107 positions), its values
scaled by factors from 0.7 to 1.3 and its std alike, so that every file has the
same shape and the programs compile once. Every mode fits them all with the
same options (``--walks``, ``--bounces``, ``--starts``, single_lobe, seed 0):

1. ``one process``: :func:`jaxcos.cli._fit.fit_file` on each file in turn, in
   this process (XLA uses every core), the way a shell loop without start-up
   costs would;
2. ``LocalCluster``: ``jaxcos fit DIR --out ...`` (one single-threaded worker
   process per core, ``--workers``), the command as a user runs it;
3. ``dask worker``: ``dask scheduler`` and ``dask worker --nworkers N
   --nthreads 1`` started on the command line, then ``jaxcos fit DIR
   --scheduler tcp://127.0.0.1:PORT``.

The compiled-program cache (``JAXCOS_CACHE``, a folder of its own under
``--out``) is warmed by one fit first, so every mode loads the programs
rather than compiling them. Times are wall-clock, start-up included (the
cluster's workers, each worker's first load of the programs). Writes
``--out/catalogue_bench.json`` and prints a table; the scaling estimate for
``M`` machines of this kind is ``M`` times the ``dask worker`` throughput
(each file is an independent task; the scheduler's cost per task is
milliseconds against seconds of work), less each machine's start-up.
"""

import argparse
import json
import os
import platform
import shutil
import socket
import subprocess
import sys
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _make_files(folder, n):
    from jaxcos.io import load_measurements
    from jaxcos.io._measurements import Measurements, save_measurements

    base = load_measurements(os.path.join(ROOT, "measurements", "matte2.csv"))
    os.makedirs(folder, exist_ok=True)
    for i, scale in enumerate(np.linspace(0.7, 1.3, n)):
        meas = Measurements(theta_i=base.theta_i, theta_o=base.theta_o, phi_o=base.phi_o, values=base.values * scale,
                            std=base.std * scale, quantity=base.quantity, metadata={"sample": f"matte2 x {scale:.3f}"},
                            path=f"p{i:02d}.csv")
        save_measurements(meas, os.path.join(folder, f"p{i:02d}.csv"), overwrite=True)
    return sorted(os.path.join(folder, f) for f in os.listdir(folder))


def _free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _jaxcos(argv, env, ready=None):
    """Run the command; its wall time, and into ``ready`` (a dict) when its cluster was ready and the file lines."""
    start = time.perf_counter()
    done = subprocess.run([os.path.join(os.path.dirname(sys.executable), "jaxcos"), *argv], check=True, env=env,
                          stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    if ready is not None:
        for line in done.stderr.splitlines():
            stamp = float(line.split("[", 1)[1].split("s]", 1)[0]) if "s]:" in line else None
            if " running " in line and " files on " in line:
                ready["cluster_ready_s"] = stamp
            elif " done in " in line:
                ready.setdefault("file_done_at_s", []).append(stamp)
    return time.perf_counter() - start


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", required=True)
    ap.add_argument("--files", type=int, default=8)
    ap.add_argument("--walks", type=int, default=64)
    ap.add_argument("--bounces", type=int, default=32)
    ap.add_argument("--starts", type=int, default=2)
    ap.add_argument("--workers", type=int, default=None, help="worker processes (default: one per core)")
    ap.add_argument("--modes", default="one,local,dask", help="comma-separated: one, local, dask")
    args = ap.parse_args()

    from jaxcos.cli._catalogue import default_workers

    workers = args.workers or default_workers()
    out = os.path.abspath(args.out)
    shutil.rmtree(out, ignore_errors=True)
    files = _make_files(os.path.join(out, "in"), args.files)
    env = dict(os.environ, JAXCOS_CACHE=os.path.join(out, "xla"))
    os.environ["JAXCOS_CACHE"] = env["JAXCOS_CACHE"]
    opts = ["--variant", "single_lobe", "--walks", str(args.walks), "--bounces", str(args.bounces),
            "--jacobian-walks", str(min(args.walks, 64)), "--starts", str(args.starts)]
    warm = _jaxcos(["fit", files[0], "--out", os.path.join(out, "warm"), *opts], env)
    results = dict(files=len(files), workers=workers, options=opts, warm_up_s=warm, modes={},
                   machine=dict(platform=platform.platform(), python=platform.python_version(),
                                cpus=os.cpu_count(), cores_usable=default_workers(),
                                load_average_before=os.getloadavg()))
    modes = args.modes.split(",")

    if "one" in modes:
        from jaxcos.cli._catalogue import enable_compilation_cache
        from jaxcos.cli._fit import fit_file

        enable_compilation_cache(env["JAXCOS_CACHE"])
        start = time.perf_counter()
        ns = argparse.Namespace(variant="single_lobe", method="lm", seed=0, walks=args.walks, bounces=args.bounces,
                                budget=None, jacobian_walks=min(args.walks, 64), starts=args.starts, fit_t=False,
                                fit_phi=False, start=None, t=16.0, interface=False, noise=None)
        from jaxcos.cli._fit import fit_options

        options = fit_options(ns)
        stamps = results.setdefault("detail", {}).setdefault("one process", {"file_done_at_s": []})
        for path in files:
            fit_file(path, os.path.join(out, "one", os.path.basename(path)[:-4]), options)
            stamps["file_done_at_s"].append(time.perf_counter() - start)
        results["modes"]["one process"] = time.perf_counter() - start

    if "local" in modes:
        detail = results.setdefault("detail", {}).setdefault("LocalCluster", {})
        results["modes"][f"LocalCluster ({workers} workers)"] = _jaxcos(
            ["fit", os.path.join(out, "in"), "--out", os.path.join(out, "local"), "--workers", str(workers), *opts], env,
            detail)

    if "dask" in modes:
        port = _free_port()
        start = time.perf_counter()
        dask = os.path.join(os.path.dirname(sys.executable), "dask")
        procs = [subprocess.Popen([dask, "scheduler", "--host", "127.0.0.1", "--port", str(port),
                                   "--dashboard-address", ":0"], env=env, stdout=subprocess.DEVNULL,
                                  stderr=subprocess.DEVNULL)]
        try:
            time.sleep(3)
            procs.append(subprocess.Popen([dask, "worker", f"tcp://127.0.0.1:{port}", "--nworkers", str(workers),
                                           "--nthreads", "1", "--no-dashboard"], env=env,
                                          stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
            from distributed import Client

            with Client(f"tcp://127.0.0.1:{port}", timeout="60s") as client:
                client.wait_for_workers(workers, timeout=120)
            ready = time.perf_counter() - start
            run = _jaxcos(["fit", os.path.join(out, "in"), "--out", os.path.join(out, "dask"), "--scheduler",
                           f"tcp://127.0.0.1:{port}", *opts], env, results.setdefault("detail", {}).setdefault(
                               "dask worker", {}))
            results["modes"][f"dask worker ({workers} processes)"] = run
            results["dask_cluster_start_s"] = ready
        finally:
            for p in reversed(procs):
                p.terminate()
                p.wait(timeout=30)

    results["machine"]["load_average_after"] = os.getloadavg()
    with open(os.path.join(out, "catalogue_bench.json"), "w", encoding="utf-8") as fh:
        json.dump(results, fh, indent=2)
    print(f"| mode | {len(files)} files (s) | files per minute |\n|---|---|---|")
    for mode, seconds in results["modes"].items():
        print(f"| {mode} | {seconds:.1f} | {60 * len(files) / seconds:.1f} |")
    print(f"warm-up fit {warm:.1f} s; detail: {json.dumps(results.get('detail'))}; machine: {results['machine']}")


if __name__ == "__main__":
    main()
