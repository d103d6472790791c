"""Catalogues: ``jaxcos fit`` over many files on a Dask cluster, resumable and fault-tolerant.

The fits run at a toy budget (a few seconds each once compiled): these tests
check the bookkeeping (one complete folder per file, the catalogue, resume,
failures, a killed worker), not the fits. Most of them share one
``LocalCluster`` of two single-threaded worker processes, reached with
``--scheduler`` as a user's own cluster would be; one runs the command's own
in-process cluster.
"""

import contextlib
import csv
import json
import os
import threading

import numpy as np
import pytest

import jaxcos
from jaxcos.cli import main
from jaxcos.cli._catalogue import uncertainty_row
from jaxcos.cli._fit import fit_row
from jaxcos.io._measurements import Measurements, save_measurements
from jaxcos.report import FIT_FILES

distributed = pytest.importorskip("distributed")

TOY = ["--variant", "single_lobe", "--walks", "4", "--bounces", "4", "--jacobian-walks", "4", "--starts", "0",
       "--no-finer"]
TIME_FIELDS = ("time_s",)


def _measurements(scale, path):
    """A small measurement file: two incidences by eight viewing angles of a dim matte material, scaled."""
    ti = np.repeat([30.0, 50.0], 8)
    to = np.tile([-60.0, -40.0, -20.0, 0.0, 20.0, 35.0, 50.0, 70.0], 2)
    values = scale * np.array([0.30, 0.28, 0.26]) * (1.0 + 0.3 * np.cos(np.radians(to - ti)))[:, None]
    meas = Measurements(theta_i=ti, theta_o=to, phi_o=np.zeros_like(ti), values=values, std=0.02 * values + 0.002,
                        quantity="reflectance_factor", metadata={"sample": f"toy {scale}"}, path=str(path))
    save_measurements(meas, path)
    return path


def _bad(path):
    """A measurement file with a malformed line."""
    path.write_text("theta_i,theta_o,r,g,b\n30,10,0.3,0.3,0.3\n30,twenty,0.3,0.3,0.3\n")
    return path


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    root = tmp_path_factory.mktemp("inputs")
    return [_measurements(scale, root / f"{name}.csv") for name, scale in (("a", 1.0), ("b", 1.3), ("c", 0.7))]


@contextlib.contextmanager
def _local_cluster():
    """Two single-threaded worker processes; a task may lose its worker twice (three tries)."""
    import dask

    with dask.config.set({"distributed.scheduler.allowed-failures": 2}):
        with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0") as c:
            yield c


@pytest.fixture(scope="module")
def cluster():
    """The :func:`_local_cluster` the tests of this module share."""
    with _local_cluster() as c:
        yield c


@pytest.fixture(scope="module")
def catalogue(inputs, cluster, tmp_path_factory):
    """The catalogue of the three files, run once: its folder and its exit status."""
    out = tmp_path_factory.mktemp("cat") / "out"
    status = main(["fit", *map(str, inputs), "--out", str(out), "--scheduler", cluster.scheduler_address, *TOY])
    return out, status


def _rows(out):
    with open(out / "catalogue.csv", encoding="utf-8") as fh:
        return list(csv.DictReader(fh))


def _complete(folder):
    """Every file of a fit's result, and a params.json that loads."""
    assert sorted(os.listdir(folder)) == sorted(FIT_FILES), folder
    jaxcos.load_params(folder / "params.json")
    return json.loads((folder / "params.json").read_text())


def _no_leftovers(out):
    assert not [n for n in os.listdir(out) if n.startswith(".")], os.listdir(out)


def test_catalogue_fits_and_summarises(catalogue, inputs):
    out, status = catalogue
    assert status == 0
    rows = _rows(out)
    assert [r["file"] for r in rows] == [str(p) for p in inputs]
    for row, path in zip(rows, inputs):
        assert row["status"] == "done" and row["error"] == ""
        doc = _complete(out / path.stem)
        assert float(row["l2"]) == pytest.approx(doc["fit"]["l2"], rel=1e-5)
        assert float(row["c_d"]) == pytest.approx(doc["layers"][0]["c_d"], rel=1e-5)
        assert float(row["check_reduced_chi2"]) == pytest.approx(doc["fit"]["check"]["reduced_chi2"], rel=1e-5)
        assert row["n_points"] == "16" and row["walks"] == "4"
    md = (out / "catalogue.md").read_text()
    assert "[a.csv](a/)" in md and "catalogue.png" in md
    assert (out / "catalogue.png").stat().st_size > 1000
    _no_leftovers(out)


def test_catalogue_row_equals_single_file_run(catalogue, inputs, tmp_path):
    """The catalogue's folder for a file holds what ``jaxcos fit FILE`` writes with the same seed."""
    out, _ = catalogue
    single = tmp_path / "single"
    assert main(["fit", str(inputs[0]), "--out", str(single), *TOY]) == 0
    mine, theirs = _complete(out / "a"), _complete(single)
    for doc in (mine, theirs):
        for name in TIME_FIELDS:
            doc["fit"].pop(name)
    assert mine == theirs
    row, expected = fit_row(out / "a"), fit_row(single)
    row.pop("time_s"), expected.pop("time_s")
    assert row == expected


def test_rerun_skips_completed_files(catalogue, inputs, cluster, capsys):
    out, _ = catalogue
    kept = (out / "a" / "params.json").stat().st_mtime_ns
    for name in FIT_FILES:
        (out / "b" / name).unlink()
    (out / "b").rmdir()
    capsys.readouterr()
    assert main(["fit", *map(str, inputs), "--out", str(out), "--scheduler", cluster.scheduler_address, *TOY]) == 0
    captured = capsys.readouterr()
    assert "3 files: 2 complete from an earlier run (skipped)" in captured.err
    assert "1 done, 2 already complete (skipped), 0 failed" in captured.out
    assert (out / "a" / "params.json").stat().st_mtime_ns == kept
    assert [r["status"] for r in _rows(out)] == ["existing", "done", "existing"]
    _complete(out / "b")
    # other settings are not taken for a finished result, and nothing is overwritten without --force
    other = [a if a != "4" or TOY[i - 1] != "--walks" else "5" for i, a in enumerate(TOY)]
    assert main(["fit", str(inputs[0]), str(inputs[1]), "--out", str(out), "--scheduler", cluster.scheduler_address,
                 *other]) == 1
    rows = _rows(out)
    assert all(r["status"] == "failed" and "holds a fit with" in r["error"] and "--force" in r["error"] for r in rows)
    assert (out / "a" / "params.json").stat().st_mtime_ns == kept


def test_settings_differ_names_the_finer_refinement_and_the_interface(tmp_path):
    """A finished result made with or without the finer refinement, or without an interface asked for now, is
    not taken for a rerun's; a record from before the finer stage was recorded is not questioned."""
    from jaxcos.cli._fit import _settings_differ

    options = dict(variant="single_lobe", method="lm", seed=0, walks=4, bounces=4, jacobian_walks=4, interface=False,
                   finer=True)
    fit = dict(variant="single_lobe", method="lm", seed=0, walks=4, bounces=4, jacobian_walks=4)

    def differ(params, **changed):
        (tmp_path / "params.json").write_text(json.dumps(params))
        return _settings_differ(str(tmp_path), {**options, **changed})

    ran = dict(share=0.3, threshold=0.05, factor=4, ran=True)
    assert differ(dict(fit={**fit, "finer": ran})) is None
    assert differ(dict(fit={**fit, "finer": {**ran, "ran": False}})) is None  # asked for, not needed
    assert differ(dict(fit={**fit, "finer": None})) == "holds a fit made without the finer refinement, not with it"
    assert differ(dict(fit={**fit, "finer": ran}), finer=False) == (
        "holds a fit made with the finer refinement, not without it")
    assert differ(dict(fit=fit), finer=False) is None
    assert differ(dict(fit={**fit, "finer": None}), method="powell") == "holds a fit with method lm, not powell"
    assert "without a top interface" in differ(dict(fit={**fit, "finer": ran}), interface=True)
    assert differ(dict(fit={**fit, "finer": ran}, interface=dict(eta=1.5, alpha_s=0.1)), interface=True) is None


def test_bad_file_is_reported_and_the_others_finish(inputs, cluster, tmp_path, capsys):
    bad = _bad(tmp_path / "broken.csv")
    out = tmp_path / "out"
    status = main(["fit", str(inputs[0]), str(bad), "--out", str(out), "--scheduler", cluster.scheduler_address, *TOY])
    assert status == 1
    good, failed = _rows(out)
    assert good["status"] == "done" and failed["status"] == "failed"
    assert "broken.csv" in failed["error"] and "line 3" in failed["error"] and "\n" not in failed["error"]
    _complete(out / "a")
    assert not (out / "broken").exists()
    _no_leftovers(out)
    assert "failed: broken.csv:" in capsys.readouterr().err


def _killer(marker, key_part, delay):
    """A worker plugin that kills its worker process ``delay`` s after it starts a task whose key holds ``key_part``.

    Once: the marker file records the kill (and the killed process), so the retried task runs.
    Defined in a function so that it travels to the workers by value.
    """

    class KillOnce(distributed.WorkerPlugin):
        def transition(self, key, start, finish, **kwargs):
            if finish == "executing" and key_part in str(key) and not os.path.exists(marker):
                with open(marker, "w") as fh:
                    fh.write(str(os.getpid()))
                threading.Timer(delay, os._exit, (1,)).start()

    return KillOnce()


def test_killed_worker_loses_nothing(inputs, cluster, tmp_path, capsys):
    """A worker killed in the middle of a file: the file is rerun, every result ends complete, nothing half-written."""
    marker = tmp_path / "killed"
    out = tmp_path / "out"
    with distributed.Client(cluster) as client:
        client.register_plugin(_killer(str(marker), "-fit-b-", 0.2), name="kill-once")
        try:
            status = main(["fit", *map(str, inputs), "--out", str(out), "--scheduler", cluster.scheduler_address,
                           *TOY])
        finally:
            client.unregister_worker_plugin("kill-once")
    assert marker.exists(), "the fault was not injected"
    with distributed.Client(cluster) as client:  # the worker that ran b first is gone, replaced by its nanny
        assert int(marker.read_text()) not in client.run(os.getpid).values()
    assert status == 0
    assert "tried 3 times in all" in capsys.readouterr().err
    assert [r["status"] for r in _rows(out)] == ["done"] * 3
    for path in inputs:
        _complete(out / path.stem)
    _no_leftovers(out)


def _always_killer(key_part):
    """A worker plugin that kills its worker process whenever it starts a task whose key holds ``key_part``."""

    class KillAlways(distributed.WorkerPlugin):
        def transition(self, key, start, finish, **kwargs):
            if finish == "executing" and key_part in str(key):
                os._exit(1)

    return KillAlways()


def test_file_that_kills_its_workers_fails_after_the_tries(inputs, tmp_path):
    """A file whose every run kills its worker is reported failed after the cluster's 3 tries; the others finish.

    On a cluster of its own: a nanny whose worker died three times in a few seconds may close instead of
    restarting it (seen under a loaded test run), which would leave the shared cluster one worker short."""
    out = tmp_path / "out"
    with _local_cluster() as cluster, distributed.Client(cluster) as client:
        client.register_plugin(_always_killer("-fit-c-"), name="kill-always")
        status = main(["fit", str(inputs[0]), str(inputs[2]), "--out", str(out), "--scheduler",
                       cluster.scheduler_address, *TOY])
    assert status == 1
    good, bad = _rows(out)
    assert good["status"] == "done" and bad["status"] == "failed"
    assert bad["error"] == "its worker died 3 times while running it (KilledWorker)"
    _complete(out / "a")
    assert not (out / "c").exists()
    _no_leftovers(out)


def test_in_process_cluster_and_tries(tmp_path, capsys):
    """Without --scheduler the command starts its own cluster; bad files fail there without stopping the run."""
    folder = tmp_path / "in"
    folder.mkdir()
    _bad(folder / "x.csv"), _bad(folder / "y.csv")
    out = tmp_path / "out"
    assert main(["fit", str(folder), "--out", str(out), "--workers", "2", "--tries", "2", *TOY]) == 1
    assert [r["status"] for r in _rows(out)] == ["failed", "failed"]
    err = capsys.readouterr().err
    assert "on 2 workers (in-process cluster; a file whose worker dies is tried 2 times in all)" in err
    assert not (out / "catalogue.png").exists()


def test_catalogue_options_and_inputs(tmp_path, inputs, capsys):
    """One file keeps the single-file command (its options refused); an empty pattern or a name clash is an error."""
    assert main(["fit", str(inputs[0]), "--out", str(tmp_path / "o"), "--workers", "2"]) == 2
    assert "--workers applies to several files" in capsys.readouterr().err
    assert main(["fit", str(tmp_path / "*.csv"), "--out", str(tmp_path / "o")]) == 2
    assert "no file matches" in capsys.readouterr().err
    (tmp_path / "sub").mkdir()
    _measurements(1.0, tmp_path / "sub" / "a.csv")
    assert main(["fit", str(inputs[0]), str(tmp_path / "sub" / "a.csv"), "--out", str(tmp_path / "o")]) == 2
    assert "share the result folder a/" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_ablate_catalogue_one_ablation_per_file(inputs, cluster, tmp_path):
    """``jaxcos ablate --catalogue``: each file's own ablation in its folder, summarised by its best variant."""
    out = tmp_path / "out"
    assert main(["ablate", "--catalogue", str(inputs[0]), str(inputs[1]), "--out", str(out), "--variants",
                 "kubelka_munk", "--scheduler", cluster.scheduler_address]) == 0
    rows = _rows(out)
    assert [r["status"] for r in rows] == ["done", "done"]
    for row, path in zip(rows, inputs):
        assert row["best_variant"] == "kubelka_munk" and float(row["kubelka_munk_l2"]) > 0
        assert sorted(os.listdir(out / path.stem)) == ["ablation.csv", "ablation.png", "fits.json", "report.md"]
    _no_leftovers(out)


def test_uncertainty_catalogue_options(inputs, tmp_path, capsys):
    """``jaxcos uncertainty`` over several files takes a fit catalogue's folder as --params, not one file."""
    params = tmp_path / "p.json"
    params.write_text("{}")
    assert main(["uncertainty", str(inputs[0]), str(inputs[1]), "--out", str(tmp_path / "o"), "--params",
                 str(params)]) == 2
    assert "name the folder of a fit catalogue" in capsys.readouterr().err
    assert main(["uncertainty", str(inputs[0]), "--out", str(tmp_path / "o"), "--tries", "2"]) == 2
    assert main(["ablate", str(inputs[0]), "--out", str(tmp_path / "o"), "--workers", "2"]) == 2
    assert "--workers needs --catalogue" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_uncertainty_row_has_the_derived_quantities(tmp_path):
    """A two-lobe posterior's ``derived`` quantities are columns of the catalogue like its parameters."""
    row = dict(median=0.4, p16=0.38, p84=0.42)
    doc = dict(parameters={"g1": row, "albedo_d[0]": row}, derived={"g_mean": dict(row, fit=0.41)},
               record=dict(variant="two_lobe"), fit={})
    (tmp_path / "posterior.json").write_text(json.dumps(doc))
    got = uncertainty_row(str(tmp_path))
    assert {"g1_median", "albedo_d[0]_p84", "g_mean_median", "g_mean_p16", "g_mean_p84"} <= set(got)
    assert got["g_mean_p84"] == 0.42 and "g_mean_fit" not in got
    del doc["derived"]  # a posterior written before derived quantities existed
    (tmp_path / "posterior.json").write_text(json.dumps(doc))
    assert not any(k.startswith("g_mean") for k in uncertainty_row(str(tmp_path)))
