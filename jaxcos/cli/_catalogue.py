"""Many measurement files in one command: one Dask task per file, one result folder per file, and a catalogue.

The engine behind ``jaxcos fit FILE... --out DIR`` (docs/formats.md, "Catalogues"). A
command describes its per-file work as a :class:`Job`; :func:`run_catalogue`
expands the inputs (files, folders, globs), skips files whose result folder is
complete, sends each other file to a Dask cluster as one task (by default an
in-process ``LocalCluster`` of one single-threaded worker process per core;
``--scheduler`` names an existing one), and writes ``DIR/catalogue.csv``,
``DIR/catalogue.md`` and ``DIR/catalogue.png``.

A task writes its result into a hidden temporary sibling folder
(``DIR/.STEM.partial-XXXX``) with the same function a single-file run uses, and
renames it into place at the end: a result folder is complete or absent. A file
that fails (bad input, a failed fit) becomes a ``failed`` row with its one-line
error; a worker that dies in the middle of a file loses nothing else, and the
scheduler reruns the file elsewhere, up to ``--tries`` times in all (Dask's
``distributed.scheduler.allowed-failures`` + 1).

This module imports the library only through the commands' own functions; the
library never imports it.
"""

import csv
import dataclasses
import glob
import io
import os
import shutil
import sys
import time
import uuid

from .._errors import InputError
from ..io import write_text_atomic

CATALOGUE_FILES = ("catalogue.csv", "catalogue.md", "catalogue.png")
"""What a catalogue run writes at the top of ``--out`` (rewritten by every run, from the result folders)."""

DEFAULT_TRIES = 3
"""Tries of a file whose worker dies under it, on the in-process cluster (``--tries``)."""

_PARTIAL = ".partial-"
_OLD = ".old-"
_GLOB_CHARS = "*?["


# --- the compiled-program cache, shared by the command and its workers ---------------


def compilation_cache_dir():
    """``$JAXCOS_CACHE`` (default ``$XDG_CACHE_HOME/jaxcos/xla`` or ``~/.cache/jaxcos/xla``); ``""``: off."""
    path = os.environ.get("JAXCOS_CACHE")
    if path is None:
        root = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
        path = os.path.join(root, "jaxcos", "xla")
    return path


def enable_compilation_cache(path):
    """Keep JAX's compiled programs in the folder ``path`` (nothing when it is empty)."""
    if path:
        import jax

        jax.config.update("jax_compilation_cache_dir", path)
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)


# --- inputs ---------------------------------------------------------------------------


def is_catalogue(items):
    """Whether the command-line inputs ask for a catalogue: several of them, a folder or a glob pattern."""
    return len(items) > 1 or any(os.path.isdir(item) or _is_glob(item) for item in items)


def _is_glob(item):
    return any(c in item for c in _GLOB_CHARS) and not os.path.exists(item)


def expand_inputs(items):
    """The measurement files named by ``items`` (files, folders: their ``*.csv``, glob patterns), in order, once each.

    Raises :class:`InputError` for an item that names nothing, and for two files
    with the same name (their result folders would collide).
    """
    files = []
    for item in items:
        if os.path.isdir(item):
            found = sorted(p for p in glob.glob(os.path.join(glob.escape(item), "*.csv")) if os.path.isfile(p))
            if not found:
                raise InputError(f"{item}: a folder without *.csv files.")
        elif _is_glob(item):
            found = sorted(p for p in glob.glob(item) if os.path.isfile(p))
            if not found:
                raise InputError(f"{item}: no file matches this pattern.")
        elif os.path.isfile(item):
            found = [item]
        else:
            raise InputError(f"{item}: no such file or folder.")
        files.extend(found)
    unique, seen = [], {}
    for path in files:
        real = os.path.realpath(path)
        if real in seen:
            continue
        stem = result_name(path)
        for other in seen.values():
            if result_name(other) == stem:
                raise InputError(f"{path} and {other} would share the result folder {stem}/: rename one of them.")
        seen[real] = path
        unique.append(path)
    return unique


def result_name(path):
    """The result folder of a measurement file under ``--out``: its name without the extension."""
    return os.path.splitext(os.path.basename(path))[0]


# --- what a command contributes -----------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Job:
    """A command's per-file work, as the catalogue engine runs it.

    Attributes:
        command: the command's name (``"fit"``).
        files: the files that make a result folder complete.
        run: ``run(path, folder, options)``, a module-level function (workers import it by
            name): writes the result of the measurement file ``path`` into ``folder``,
            exactly as the single-file command does; raises on failure.
        row: ``row(folder)``: the catalogue columns of a complete result folder, as a dict.
        columns: the catalogue columns ``row`` gives, in order.
        settings_differ: ``settings_differ(folder, options)``: a sentence saying how a
            complete result was made with other settings than ``options``, or ``None``.
        picture: ``picture(rows, path)``: draws ``catalogue.png`` from the rows of the
            complete results (each with its ``result`` folder); returns a caption, or ``None``
            when there is nothing to draw.
        status: ``status(table)``: the exit status when no file failed (default 0).
        summary: the columns of ``catalogue.md``'s table besides file, status and error:
            ``(header, column, format)``.

    Columns that ``row`` gives beyond ``columns`` (a posterior's parameters, say) follow them,
    in the order they first appear.
    """

    command: str
    files: tuple
    run: object
    row: object
    columns: tuple
    settings_differ: object = None
    picture: object = None
    status: object = None
    summary: tuple = (("L2", "l2", ".4g"), ("RMSE", "rmse", ".4g"), ("reduced chi-square", "reduced_chi2", ".2f"),
                      ("check: reduced chi-square", "check_reduced_chi2", ".2f"), ("time (s)", "time_s", ".1f"))


def is_complete(folder, files):
    """Whether ``folder`` holds every one of ``files``."""
    return os.path.isdir(folder) and all(os.path.isfile(os.path.join(folder, name)) for name in files)


# --- the task: one file, on a worker ------------------------------------------------------------


def one_line(err):
    """An exception as one line: its message (with its type unless it is an :class:`InputError`)."""
    text = " ".join(str(err).split()) or type(err).__name__
    return text if isinstance(err, InputError) else f"{type(err).__name__}: {text}"


def run_task(run, path, folder, options, force, cache, files=()):
    """Run ``run(path, tmp, options)`` into a temporary sibling of ``folder``, then rename it to ``folder``.

    ``cache``: the compiled-program cache to use (:func:`enable_compilation_cache`; ``None``:
    the worker's own :func:`compilation_cache_dir`). Without ``force``, a complete ``folder``
    (holding ``files``) is an earlier try of this very task (the catalogue runs only files whose
    folder was absent), whose worker died after writing it but before it said so: it is kept,
    not redone.

    What a Dask worker executes for one file. Returns a dict: ``status`` (``"done"`` or
    ``"failed"``), ``error`` (one line), ``wall_s`` and the worker's ``pid``. A worker that
    dies leaves at most a ``.STEM.partial-XXXX`` folder, which the next run removes.
    """
    start = time.perf_counter()
    if not force and files and is_complete(folder, files):
        return dict(status="done", error="", wall_s=time.perf_counter() - start, pid=os.getpid())
    enable_compilation_cache(compilation_cache_dir() if cache is None else cache)
    parent, name = os.path.split(folder)
    tmp = os.path.join(parent, f".{name}{_PARTIAL}{uuid.uuid4().hex[:12]}")
    try:
        run(path, tmp, options)
        if not force and files and is_complete(folder, files):  # an earlier try finished meanwhile
            shutil.rmtree(tmp, ignore_errors=True)
        else:
            _install(tmp, folder, force)
    except Exception as err:  # noqa: BLE001 - any failure of one file becomes its catalogue row
        shutil.rmtree(tmp, ignore_errors=True)
        return dict(status="failed", error=one_line(err), wall_s=time.perf_counter() - start, pid=os.getpid())
    return dict(status="done", error="", wall_s=time.perf_counter() - start, pid=os.getpid())


def _install(tmp, folder, force):
    """Move the finished result ``tmp`` to ``folder`` by renames; an existing ``folder`` only with ``force``."""
    if not os.path.lexists(folder):
        os.replace(tmp, folder)
        return
    if not force:
        raise InputError(f"{folder}: already exists; pass --force to overwrite it.")
    parent, name = os.path.split(folder)
    old = os.path.join(parent, f".{name}{_OLD}{uuid.uuid4().hex[:12]}")
    os.replace(folder, old)
    os.replace(tmp, folder)
    shutil.rmtree(old, ignore_errors=True)


def _remove_leftovers(out):
    """Remove the temporary folders a killed task or run left in ``out``; returns how many."""
    gone = 0
    for entry in os.scandir(out):
        if entry.name.startswith(".") and (_PARTIAL in entry.name or _OLD in entry.name) and entry.is_dir():
            shutil.rmtree(entry.path, ignore_errors=True)
            gone += 1
    return gone


# --- the cluster ------------------------------------------------------------------------------------


def default_workers():
    """One worker per core this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


class _Cluster:
    """A Dask client: to the cluster at ``scheduler``, or to a new in-process ``LocalCluster``.

    The ``LocalCluster`` has ``workers`` worker processes of one thread each, and lets a
    task's worker die ``tries - 1`` times before the task fails.
    """

    def __init__(self, scheduler, workers, tries):
        self.scheduler, self.workers, self.tries = scheduler, workers, tries
        self.cluster = self.client = None

    def __enter__(self):
        import logging

        import dask
        from distributed import Client, LocalCluster

        if self.scheduler:
            try:
                self.client = Client(self.scheduler, timeout="20s")
            except OSError as err:
                raise InputError(f"--scheduler {self.scheduler}: cannot reach it ({one_line(err)}).") from None
            try:
                self.tries = int(self.client.run_on_scheduler(_allowed_failures)) + 1
            except Exception:  # noqa: BLE001 - a scheduler without jaxcos: its setting is unknown here
                self.tries = None
        else:
            with dask.config.set({"distributed.scheduler.allowed-failures": self.tries - 1}):
                self.cluster = LocalCluster(n_workers=self.workers, threads_per_worker=1, processes=True,
                                            dashboard_address=":0", silence_logs=logging.ERROR)
            self.client = Client(self.cluster)
        return self

    def threads(self):
        """Worker threads now in the cluster (at least 1)."""
        return max(1, sum(self.client.nthreads().values()))

    def __exit__(self, *exc):
        self.client.close()
        if self.cluster is not None:
            self.cluster.close()


def _allowed_failures(dask_scheduler=None):
    return dask_scheduler.allowed_failures


# --- the command ------------------------------------------------------------------------------------------


def add_catalogue_options(p):
    """Add ``--scheduler``, ``--workers`` and ``--tries`` (used with several files) to the parser ``p``."""
    p.add_argument("--scheduler", metavar="tcp://HOST:PORT", default=None,
                   help="with several files: run them on this Dask cluster (started with `dask scheduler` and "
                   "`dask worker`) instead of an in-process one; its workers must see the same paths")
    p.add_argument("--workers", type=int, default=None, metavar="N",
                   help=f"with several files: worker processes of the in-process cluster (default: one per core, "
                   f"{default_workers()} here)")
    p.add_argument("--tries", type=int, default=DEFAULT_TRIES, metavar="N",
                   help=f"with several files: runs of a file whose worker dies under it before it is reported "
                   f"failed (default {DEFAULT_TRIES}; with --scheduler, the cluster's own setting)")


def check_catalogue_options(args, catalogue, needs="several files, a folder or a pattern"):
    """Refuse the catalogue options where they do not apply (``needs``: what they need) or are out of range."""
    given = [flag for flag, value, default in (("--scheduler", args.scheduler, None), ("--workers", args.workers, None),
                                               ("--tries", args.tries, DEFAULT_TRIES)) if value != default]
    if not catalogue and given:
        raise InputError(f"{given[0]} applies to {needs}, not to one file." if needs.startswith("several")
                         else f"{given[0]} needs {needs}.")
    if args.workers is not None and args.workers < 1:
        raise InputError(f"--workers must be a positive integer, not {args.workers}.")
    if args.tries < 1:
        raise InputError(f"--tries must be a positive integer, not {args.tries}.")
    if args.scheduler and (args.workers is not None or args.tries != DEFAULT_TRIES):
        raise InputError("--workers and --tries belong to the in-process cluster; a --scheduler cluster has its own.")


def run_catalogue(job, items, out, options, *, force=False, scheduler=None, workers=None, tries=DEFAULT_TRIES,
                  say=None):
    """Run ``job`` on every measurement file of ``items`` into ``out/STEM/``, then write the catalogue.

    Returns the exit status: 0 when every file has a complete result, 1 when any failed.
    """
    say = say or (lambda message: None)
    out = os.path.abspath(out)
    inside = os.path.join(os.path.realpath(out), "")
    # what a catalogue wrote (catalogue.csv, say) is not one of its inputs on a rerun
    files = [os.path.abspath(p) for p in expand_inputs(items) if not os.path.realpath(p).startswith(inside)]
    if not files:
        raise InputError(f"{', '.join(items)}: no measurement file outside --out {out}.")
    if os.path.exists(out) and not os.path.isdir(out):
        raise InputError(f"{out}: exists and is not a folder.")
    os.makedirs(out, exist_ok=True)
    if _remove_leftovers(out):
        say("removed the temporary folders an interrupted run left")
    rows, todo = {}, []
    for path in files:
        folder = os.path.join(out, result_name(path))
        base = dict(file=path, result=folder)
        if os.path.lexists(folder) and not force:
            if not is_complete(folder, job.files):
                rows[path] = dict(base, status="failed", error=f"{folder}: exists but is not a complete result; "
                                  "remove it or pass --force.")
                continue
            try:
                differ = job.settings_differ(folder, options) if job.settings_differ else None
            except Exception as err:  # noqa: BLE001 - a damaged result is reported, not fatal
                differ = f"holds an unreadable result ({one_line(err)})"
            if differ:
                rows[path] = dict(base, status="failed", error=f"{folder}: {differ}; pass --force to redo it.")
                continue
            rows[path] = dict(base, status="existing")
        else:
            todo.append(path)
    earlier = sum(r["status"] == "existing" for r in rows.values())
    say(f"{len(files)} files: {earlier} complete from an earlier run (skipped), "
        f"{sum(r['status'] == 'failed' for r in rows.values())} in the way, {len(todo)} to run")
    start = time.perf_counter()
    if todo:
        _run_all(job, todo, out, options, rows, force=force, scheduler=scheduler, workers=workers, tries=tries,
                 say=say)
    _remove_leftovers(out)
    table = []
    for path in files:
        row = rows[path]
        if row["status"] in ("done", "existing"):
            try:
                row = {**job.row(row["result"]), **row}
            except Exception as err:  # noqa: BLE001 - an unreadable result is reported, not fatal
                row = dict(row, status="failed", error=f"{row['result']}: unreadable result ({one_line(err)})")
        table.append(row)
    written = write_catalogue(job, table, out, elapsed=time.perf_counter() - start, options=options)
    counts = {s: sum(r["status"] == s for r in table) for s in ("done", "existing", "failed")}
    print(f"{job.command} catalogue of {len(table)} files in {time.perf_counter() - start:.1f} s: {counts['done']} "
          f"done, {counts['existing']} already complete (skipped), {counts['failed']} failed. Wrote "
          f"{', '.join(written)} and one folder per file.")
    for row in table:
        if row["status"] == "failed":
            print(f"failed: {os.path.basename(row['file'])}: {row['error']}", file=sys.stderr)
    if counts["failed"]:
        return 1
    return job.status(table) if job.status else 0


def _run_all(job, todo, out, options, rows, *, force, scheduler, workers, tries, say):
    """Submit one task per file of ``todo`` and collect each into ``rows`` as it finishes."""
    from distributed import as_completed

    cache = os.environ.get("JAXCOS_CACHE")  # None: each worker's own default (its own home on another machine)
    with _Cluster(scheduler, workers or default_workers(), tries) as cluster:
        client = cluster.client
        say(f"running {len(todo)} files on {cluster.threads()} workers "
            f"({'cluster ' + scheduler if scheduler else 'in-process cluster'}; a file whose worker dies is "
            + (f"tried {cluster.tries} times in all)" if cluster.tries else "retried as the cluster allows)"))
        token = uuid.uuid4().hex[:8]
        futures = {}
        for path in todo:
            folder = os.path.join(out, result_name(path))
            fut = client.submit(run_task, job.run, path, folder, options, force, cache, job.files, pure=False,
                                key=f"jaxcos-{job.command}-{result_name(path)}-{token}")
            futures[fut] = path
        start, finished, failed = time.perf_counter(), 0, 0
        for fut in as_completed(futures):
            path = futures[fut]
            folder = os.path.join(out, result_name(path))
            try:
                outcome = fut.result()
            except Exception as err:  # noqa: BLE001 - KilledWorker, a lost cluster: the file failed
                name = type(err).__name__
                error = (f"its worker died {cluster.tries or 'too many'} times while running it (KilledWorker)"
                         if name == "KilledWorker" else one_line(err))
                outcome = dict(status="failed", error=error, wall_s=None)
            rows[path] = dict(file=path, result=folder, status=outcome["status"], error=outcome["error"],
                              wall_s=outcome["wall_s"])
            finished += 1
            failed += outcome["status"] == "failed"
            left = len(todo) - finished
            threads = cluster.threads()
            eta = (time.perf_counter() - start) / finished * left
            what = (f"done in {outcome['wall_s']:.1f} s" if outcome["status"] == "done"
                    else f"FAILED: {outcome['error']}")
            say(f"{os.path.basename(path)} {what}; {finished - failed} done, {min(threads, left)} running, "
                f"{failed} failed, {left} left" + (f", about {_duration(eta)} to go" if left else ""))


def _duration(seconds):
    return f"{seconds:.0f} s" if seconds < 120 else f"{seconds / 60:.0f} min"


# --- the catalogue files ------------------------------------------------------------------------------------


BASE_COLUMNS = ("file", "result", "status")
TAIL_COLUMNS = ("wall_s", "error")


def write_catalogue(job, table, out, *, elapsed, options):
    """Write ``catalogue.csv``, ``catalogue.md`` and ``catalogue.png`` under ``out``; returns their paths."""
    columns = BASE_COLUMNS + tuple(job.columns)
    extra = [k for row in table for k in row if k not in columns and k not in TAIL_COLUMNS]
    columns += tuple(dict.fromkeys(extra)) + TAIL_COLUMNS
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=columns, extrasaction="ignore", lineterminator="\n")
    writer.writeheader()
    for row in table:
        writer.writerow({k: _cell(row.get(k)) for k in columns})
    written = [write_text_atomic(os.path.join(out, "catalogue.csv"), buf.getvalue())]
    complete = [r for r in table if r["status"] in ("done", "existing")]
    png = os.path.join(out, "catalogue.png")
    caption = None
    if complete and job.picture is not None:
        tmp = os.path.join(out, f".catalogue{_PARTIAL}{uuid.uuid4().hex[:8]}.png")
        try:
            caption = job.picture(complete, tmp)
            os.replace(tmp, png)
        except Exception as err:  # noqa: BLE001 - the picture is a convenience
            caption = None
            print(f"jaxcos {job.command}: no catalogue.png ({one_line(err)}).", file=sys.stderr)
        finally:
            if os.path.exists(tmp):
                os.remove(tmp)
    if caption is None and os.path.exists(png):
        os.remove(png)
    written.append(write_text_atomic(os.path.join(out, "catalogue.md"),
                                 _markdown(job, table, out, caption=caption, elapsed=elapsed, options=options)))
    if caption is not None:
        written.insert(1, png)
    return written


def _cell(value):
    if value is None:
        return ""
    if isinstance(value, float):
        return f"{value:.6g}"
    return value


def _fmt(value, spec):
    return "" if value is None or value == "" else format(value, spec)


def _markdown(job, table, out, *, caption, elapsed, options):
    counts = {s: sum(r["status"] == s for r in table) for s in ("done", "existing", "failed")}
    settings = ", ".join(f"{k} {v}" for k, v in options.items()
                         if v is not None and v is not False and not callable(v) and k != "command")
    lines = [f"# Catalogue: jaxcos {job.command} of {len(table)} files", "",
             f"{counts['done']} done in this run ({elapsed:.0f} s), {counts['existing']} complete from an earlier run, "
             f"{counts['failed']} failed. Settings: {settings}. Each file's result is in its own folder; "
             "`catalogue.csv` has every column.", ""]
    if caption:
        lines += [f"![{caption}](catalogue.png)", "", caption, ""]
    lines += ["| file | status | " + " | ".join(h for h, _, _ in job.summary) + " | error |",
              "|---|---|" + "---|" * len(job.summary) + "---|"]
    for r in table:
        name = os.path.basename(r["file"])
        link = f"[{name}]({os.path.relpath(r['result'], out)}/)" if r["status"] != "failed" else name
        cells = " | ".join(_fmt(r.get(key), spec) for _, key, spec in job.summary)
        lines.append(f"| {link} | {r['status']} | {cells} | {(r.get('error') or '').replace('|', '/')} |")
    return "\n".join(lines) + "\n"


# --- the picture: the products' fitted in-plane curves ------------------------------------------------


CURVE_INCIDENCE = 30.0
"""The incidence (degrees) of the catalogue's picture."""

CURVE_BUDGET = (256, 64)
"""Walks x bounces of the picture's curves (one key for every product, so they differ by the material alone)."""


def draw_curves(named_materials, path):
    """Draw the in-plane reflectance factor (luminance) of each ``(name, Material)`` at one incidence into ``path``.

    Returns the figure's caption.
    """
    import jax
    import matplotlib
    import numpy as np
    from matplotlib.figure import Figure

    from ..model import inplane_bsdf

    theta_o = np.arange(-80.0, 80.1, 5.0)
    theta_i = np.full_like(theta_o, CURVE_INCIDENCE)
    walks, bounces = CURVE_BUDGET
    fig = Figure(figsize=(7.5, 4.5), dpi=110)
    ax = fig.add_subplot()
    cmap = matplotlib.colormaps["tab10" if len(named_materials) <= 10 else "tab20"]
    for i, (name, material) in enumerate(named_materials):
        f = np.asarray(inplane_bsdf(material, theta_i, theta_o, jax.random.key(0), walks=walks, bounces=bounces))
        y = np.pi * (f @ np.array([0.2126, 0.7152, 0.0722]))
        ax.plot(theta_o, y, color=cmap(i % cmap.N), lw=1.4, label=name)
    ax.axvline(CURVE_INCIDENCE, color="0.7", lw=0.8, ls=":")
    ax.set_xlabel("viewing angle theta_o (degrees; mirror direction dotted)")
    ax.set_ylabel("reflectance factor, luminance Y")
    ax.set_yscale("log")
    ax.set_title(f"Fitted in-plane curves at {CURVE_INCIDENCE:g} degree incidence")
    if len(named_materials) <= 20:
        ax.legend(fontsize=7, ncol=2 if len(named_materials) > 8 else 1)
    fig.tight_layout()
    fig.savefig(path, format="png")
    return (f"Fitted in-plane reflectance factor (luminance Y, log scale) of each product at {CURVE_INCIDENCE:g} degree "
            f"incidence, one colour per product ({walks} walks x {bounces} bounces, one key for all).")


# --- other commands over a catalogue: their own single-file command function, on each file ------------------

_NOT_OPTIONS = ("measurements", "out", "force", "scheduler", "workers", "tries", "catalogue")


def command_options(args):
    """The parsed arguments of a command that apply to each file alike (``func``, the command's function, included)."""
    return {k: v for k, v in vars(args).items() if k not in _NOT_OPTIONS}


def run_command(path, folder, options):
    """Run the command's own function (``options["func"]``) on the one file ``path`` into ``folder``, quietly.

    Exactly what ``jaxcos COMMAND path --out folder OPTIONS`` runs; raises on a failure.
    Returns the command's exit status (``jaxcos uncertainty``: 3 for a short chain).
    """
    import argparse
    import contextlib

    args = argparse.Namespace(**options, measurements=[path], out=folder, force=False, scheduler=None,
                              workers=None, tries=DEFAULT_TRIES, catalogue=False)
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        return args.func(args)


def uncertainty_into(path, folder, options):
    """``jaxcos uncertainty`` of one file; ``--params DIR`` of a catalogue names ``DIR/NAME/params.json``."""
    if options.get("params") and os.path.isdir(options["params"]):
        options = dict(options, params=os.path.join(options["params"], result_name(path), "params.json"))
    run_command(path, folder, options)


def _read_json(folder, name):
    import json

    with open(os.path.join(folder, name), encoding="utf-8") as fh:
        return json.load(fh)


def uncertainty_row(folder):
    """A posterior's catalogue columns: the fit's statistics, the chain's, and the median and 68% of each parameter
    and each derived quantity (``g_mean`` of a two-lobe fit)."""
    doc = _read_json(folder, "posterior.json")
    fit, record = doc.get("fit", {}), doc.get("record", {})
    row = dict(variant=record.get("variant"), n_points=record.get("n_points"), l2=fit.get("l2"), rmse=fit.get("rmse"),
               reduced_chi2=fit.get("reduced_chi2"), converged=record.get("converged"),
               chain_in_tau=record.get("chain_in_tau"), walkers=record.get("walkers"), steps=record.get("steps"),
               seed=record.get("seed"), time_s=record.get("time_s"))
    for label, summary in {**doc.get("parameters", {}), **doc.get("derived", {})}.items():
        row.update({f"{label}_{q}": summary.get(q) for q in ("median", "p16", "p84")})
    return row


def _uncertainty_differ(folder, options):
    seed = _read_json(folder, "posterior.json").get("record", {}).get("seed")
    return None if seed in (None, options["seed"]) else f"holds a posterior with seed {seed}, not {options['seed']}"


def _uncertainty_status(table):
    return 3 if any(r.get("converged") is False for r in table) else 0


def _uncertainty_picture(rows, path):
    """Each parameter's median and 68% interval, one colour per product."""
    import matplotlib
    from matplotlib.figure import Figure

    labels = list(dict.fromkeys(k[:-len("_median")] for r in rows for k in r if k.endswith("_median")))
    if not labels:
        return None
    cols = min(4, len(labels))
    nrows = -(-len(labels) // cols)
    fig = Figure(figsize=(3.0 * cols, 0.35 * len(rows) * nrows + 1.2 * nrows), dpi=100)
    cmap = matplotlib.colormaps["tab10" if len(rows) <= 10 else "tab20"]
    for j, label in enumerate(labels):
        ax = fig.add_subplot(nrows, cols, j + 1)
        for i, r in enumerate(rows):
            med = r.get(f"{label}_median")
            if med is None:
                continue
            ax.errorbar([med], [i], xerr=[[med - r[f"{label}_p16"]], [r[f"{label}_p84"] - med]], fmt="o",
                        color=cmap(i % cmap.N), ms=4)
        ax.set_title(label, fontsize=9)
        ax.set_yticks(range(len(rows)))
        ax.set_yticklabels([os.path.basename(r["file"]) for r in rows] if j % cols == 0 else [], fontsize=7)
        ax.set_ylim(len(rows) - 0.5, -0.5)
        ax.tick_params(axis="x", labelsize=7)
    fig.tight_layout()
    fig.savefig(path, format="png")
    return "Posterior median and 68% interval of each parameter, one row (and colour) per product."


def uncertainty_job():
    """``jaxcos uncertainty`` over a catalogue."""
    from ..report import UNCERTAINTY_FILES

    return Job(command="uncertainty", files=tuple(UNCERTAINTY_FILES), run=uncertainty_into, row=uncertainty_row,
               columns=("variant", "n_points", "l2", "rmse", "reduced_chi2", "converged", "chain_in_tau", "walkers",
                        "steps", "seed", "time_s"),
               settings_differ=_uncertainty_differ, picture=_uncertainty_picture, status=_uncertainty_status,
               summary=(("L2", "l2", ".4g"), ("reduced chi-square", "reduced_chi2", ".2f"),
                        ("converged", "converged", ""), ("chain / tau", "chain_in_tau", ".1f"),
                        ("time (s)", "time_s", ".0f")))


def ablation_row(folder):
    """An ablation's catalogue columns: the best variant by BIC, and each variant's L2, BIC and CIEDE2000."""
    with open(os.path.join(folder, "ablation.csv"), encoding="utf-8") as fh:
        rows = [r for r in csv.DictReader(line for line in fh if not line.startswith("#"))]
    num = lambda v: float(v) if v not in (None, "") else None  # noqa: E731
    best = min(rows, key=lambda r: num(r["bic"]))
    row = dict(best_variant=best["variant"], best_l2=num(best["l2"]), best_bic=num(best["bic"]),
               n_points=best.get("n_points"), seed=best.get("seed"),
               time_s=sum(num(r["time_s"]) or 0.0 for r in rows))
    for r in rows:
        row.update({f"{r['variant']}_{k}": num(r[k]) for k in ("l2", "delta_e2000", "bic")})
    return row


def _ablation_differ(folder, options):
    with open(os.path.join(folder, "ablation.csv"), encoding="utf-8") as fh:
        rows = list(csv.DictReader(line for line in fh if not line.startswith("#")))
    for key in ("seed", "walks", "bounces"):
        for r in rows:
            if r.get(key) not in (None, "") and r["variant"] != "kubelka_munk" and int(float(r[key])) != options[key]:
                return f"holds an ablation with {key} {r[key]}, not {options[key]}"
    return None


def ablation_job():
    """``jaxcos ablate --catalogue``: one ablation per file."""
    from ..report import ABLATION_FILES

    return Job(command="ablate", files=tuple(ABLATION_FILES), run=run_command, row=ablation_row,
               columns=("best_variant", "best_l2", "best_bic", "n_points", "seed", "time_s"),
               settings_differ=_ablation_differ,
               summary=(("best by BIC", "best_variant", ""), ("its L2", "best_l2", ".4g"),
                        ("time (s)", "time_s", ".0f")))


def uncertainty_catalogue(args):
    """``jaxcos uncertainty FILE... --out DIR``: one posterior per file (``--params DIR``: a fit catalogue's folders)."""
    from ._common import progress

    if (args.walkers is not None and args.walkers < 4) or args.steps < 1:
        raise InputError("--walkers must be at least 4 and --steps at least 1.")
    options = command_options(args)
    if args.params:
        if not os.path.isdir(args.params):
            raise InputError(f"--params {args.params}: with several files, name the folder of a fit catalogue "
                             "(its NAME/params.json starts the file NAME.csv).")
        options["params"] = os.path.abspath(args.params)
    return run_catalogue(uncertainty_job(), args.measurements, args.out, options, force=args.force,
                         scheduler=args.scheduler, workers=args.workers, tries=args.tries,
                         say=progress("uncertainty"))


def ablation_catalogue(args):
    """``jaxcos ablate --catalogue FILE... --out DIR``: one ablation per file, in ``DIR/NAME/``."""
    from ..inference import check_variants
    from ._common import progress

    check_variants(args.variants)
    return run_catalogue(ablation_job(), args.measurements, args.out, command_options(args), force=args.force,
                         scheduler=args.scheduler, workers=args.workers, tries=args.tries, say=progress("ablate"))
