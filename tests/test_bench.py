"""``jaxcos bench accuracy --quick`` writes its files; ``--budget`` presets resolve, and unknown ones are refused.

The benchmark's numbers are not checked (a tiny budget on a shared machine):
only that the whole path runs and leaves what it promises. The package data
it reads (``jaxcos/data/``) are checked against the top-level files they copy.
"""

import csv
import importlib.resources
import json
import os
from pathlib import Path

import pytest

import jaxcos.cli._eval
import jaxcos.cli._fit
from jaxcos.report import ACCURACY_FILES as FILES
from jaxcos.cli import main
from jaxcos._errors import InputError
from jaxcos.io import load_measurements
from jaxcos.inference import FIT_BOUNCES, FIT_WALKS
from jaxcos.model._budget import BUDGETS, DEFAULT_BOUNCES, DEFAULT_WALKS, resolve_budget

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
MATTE2 = os.path.join(ROOT, "measurements", "matte2.csv")
DATA = importlib.resources.files("jaxcos") / "data"
GRID_PRODUCTS = {"dewy1": 105, "dewy2": 112, "matte1": 103, "matte2": 108}  # docs/model.md section 5


def test_bundled_synthetic_set_equals_the_top_level_file():
    assert (DATA / "matte2.csv").read_bytes() == Path(MATTE2).read_bytes()


def test_the_instrument_grid_holds_angles_only_and_the_positions_of_the_bundled_sets():
    with (DATA / "grid.csv").open(newline="") as fh:
        reader = csv.DictReader(fh)
        rows = list(reader)
    assert reader.fieldnames == ["product", "theta_i", "theta_o"]
    for name, product in GRID_PRODUCTS.items():
        meas = load_measurements(os.path.join(ROOT, "measurements", f"{name}.csv"))
        positions = [(float(r["theta_i"]), float(r["theta_o"])) for r in rows if int(r["product"]) == product]
        assert positions == list(zip(meas.theta_i.tolist(), meas.theta_o.tolist())), name


@pytest.mark.slow
def test_bench_accuracy_quick_writes_its_files(tmp_path, capsys):
    out = tmp_path / "acc"
    assert main(["bench", "accuracy", "--out", str(out), "--quick"]) == 0
    for name in FILES:
        assert (out / name).stat().st_size > 0, name
    data = json.loads((out / "accuracy.json").read_text())
    assert data["quick"] and data["machine"]["cpus"] >= 1 and len(data["machine"]["load_average"]) == 3
    assert {r["strategy"] for r in data["sweep"]} == {"exact", "mc"}
    assert all("forward_load" in r and r["forward_s"] > 0 for r in data["sweep"])
    assert any("jacobian_s" in r for r in data["sweep"]) and len(data["fits"]) >= 1
    assert "| exact |" in (out / "accuracy.md").read_text()
    capsys.readouterr()
    # An existing result is kept without --force: one line, exit status 2.
    assert main(["bench", "accuracy", "--out", str(out), "--quick"]) == 2
    err = capsys.readouterr().err.strip()
    assert "--force" in err and "\n" not in err


def test_budget_presets_resolve():
    assert BUDGETS["accurate"] == (FIT_WALKS, FIT_BOUNCES)
    assert BUDGETS["paper"] == (DEFAULT_WALKS, DEFAULT_BOUNCES)
    for name, budget in BUDGETS.items():
        assert resolve_budget(name) == budget
    assert resolve_budget() == (DEFAULT_WALKS, DEFAULT_BOUNCES)
    assert resolve_budget(default=(7, 9)) == (7, 9)
    w, b = BUDGETS["fast"]
    assert resolve_budget("fast", walks=3) == (3, b)  # explicit values win
    assert resolve_budget("fast", bounces=5) == (w, 5)


@pytest.mark.parametrize("kwargs", [dict(name="quick"), dict(name="fast", walks=0)])
def test_budget_refuses_bad_input(kwargs):
    with pytest.raises(InputError) as err:
        resolve_budget(kwargs.pop("name"), **kwargs)
    message = str(err.value)
    assert message.count(". ") == 0 and message.endswith(".")
    if "quick" in message:
        assert all(name in message for name in BUDGETS)


def _raise():
    raise InputError("stopped by the test.")


def test_cli_budget_reaches_fit_and_eval(tmp_path, monkeypatch, capsys):
    seen = {}
    monkeypatch.setattr(jaxcos.cli._fit, "fit", lambda meas, **kw: (seen.update(kw), _raise()))
    assert main(["fit", MATTE2, "--out", str(tmp_path / "f"), "--budget", "fast"]) == 2
    assert (seen["walks"], seen["bounces"]) == BUDGETS["fast"]
    assert main(["fit", MATTE2, "--out", str(tmp_path / "f"), "--budget", "accurate", "--walks", "32"]) == 2
    assert (seen["walks"], seen["bounces"]) == (32, BUDGETS["accurate"][1])
    assert main(["fit", MATTE2, "--out", str(tmp_path / "f")]) == 2
    assert (seen["walks"], seen["bounces"]) == (FIT_WALKS, FIT_BOUNCES)

    monkeypatch.setattr(jaxcos.cli._eval, "run_eval", lambda args: (seen.update(walks=args.walks, bounces=args.bounces),
                                                                 _raise()))
    params = os.path.join(ROOT, "fits", "matte2", "params.json")
    angles = os.path.join(ROOT, "measurements", "standard_angles.csv")
    assert main(["eval", params, "--angles", angles, "--out", str(tmp_path / "e.csv"), "--budget", "fast"]) == 2
    assert (seen["walks"], seen["bounces"]) == BUDGETS["fast"]
    assert main(["eval", params, "--angles", angles, "--out", str(tmp_path / "e.csv")]) == 2
    assert (seen["walks"], seen["bounces"]) == (DEFAULT_WALKS, DEFAULT_BOUNCES)
    capsys.readouterr()

    # An unknown preset: one sentence naming the choices, exit status 2, nothing run.
    seen.clear()
    for argv in (["fit", MATTE2, "--out", str(tmp_path / "f")], ["eval", params, "--angles", angles, "--out",
                                                                  str(tmp_path / "e.csv")]):
        assert main(argv + ["--budget", "turbo"]) == 2
        err = capsys.readouterr().err.strip()
        assert "unknown budget 'turbo'" in err and "standard" in err and "\n" not in err
    assert not seen
