"""params.json: round trips, validation with one clear sentence, variants; and the eval command."""

import json
import re
import warnings

import numpy as np
import pytest

import jaxcos
from jaxcos.cli import main

LAYER = {"t": 16.0, "c_d": 0.9, "albedo_d": [0.99, 0.98, 0.95], "g1": 0.55, "g2": 0.09, "w_g": 1.0,
         "albedo_p": [0.75, 0.85, 0.99], "alpha_p": 0.13, "theta_p_deg": 1.47}


def _write(tmp_path, data, name="params.json"):
    path = tmp_path / name
    path.write_text(json.dumps(data) if not isinstance(data, str) else data)
    return path


def test_round_trip(tmp_path):
    m = jaxcos.Material(layers=(jaxcos.Layer(**{**{k: v for k, v in LAYER.items() if k != "theta_p_deg"},
                                                 "theta_p": 1.47, "phi_p": 30.0}),
                                jaxcos.published("matte2").layers[0]),
                        base_albedo=(0.6, 0.4, 0.3))
    path = tmp_path / "p.json"
    jaxcos.save_params(m, path)
    back = jaxcos.load_params(path)
    assert back.variant == "two_lobe" and back.base == "lambertian" and len(back.layers) == 2
    for a, b in zip(back.layers, m.layers):
        for name in ("t", "c_d", "albedo_d", "g1", "g2", "w_g", "albedo_p", "alpha_p", "theta_p", "phi_p"):
            np.testing.assert_allclose(getattr(a, name), getattr(b, name), rtol=1e-6)
    np.testing.assert_allclose(back.base_albedo, [0.6, 0.4, 0.3], rtol=1e-6)


def test_save_does_not_overwrite(tmp_path):
    path = tmp_path / "p.json"
    path.write_text("keep")
    with pytest.raises(jaxcos.InputError, match="already exists"):
        jaxcos.save_params(jaxcos.published("dewy1"), path)
    assert path.read_text() == "keep"


@pytest.mark.parametrize("data, message", [
    ({"layers": [LAYER]}, "the key 'base' is missing"),
    ({"layers": [], "base": {"type": "black"}}, "'layers' must be a non-empty list"),
    ({"layers": [{k: v for k, v in LAYER.items() if k != "g2"}], "base": {"type": "black"}},
     "layer 0 is missing the key 'g2'"),
    ({"layers": [{**LAYER, "c_d": 1.5}], "base": {"type": "black"}}, "'c_d' = 1.5 is outside its range [0, 1]"),
    ({"layers": [{**LAYER, "g1": 1.0}], "base": {"type": "black"}}, "'g1' = 1.0 is outside its range (-1, 1)"),
    ({"layers": [{**LAYER, "alpha_p": 0.0}], "base": {"type": "black"}}, "'alpha_p' = 0.0 is outside its range (0, 1]"),
    ({"layers": [{**LAYER, "albedo_d": [0.5, 0.5]}], "base": {"type": "black"}}, "list of three numbers"),
    ({"layers": [{**LAYER, "t": "thick"}], "base": {"type": "black"}}, "'t' must be a number, not \"thick\""),
    ({"layers": [{**LAYER, "theta_p": 3.0}], "base": {"type": "black"}}, "unknown key 'theta_p'"),
    ({"layers": [LAYER], "base": {"type": "skin"}}, "'base' must be"),
    ({"layers": [LAYER], "base": {"type": "lambertian"}}, "needs an 'albedo'"),
    ({"layers": [LAYER], "base": {"type": "black"}, "variant": "three_lobe"}, "unknown variant 'three_lobe'"),
    ("[1, 2", "line 1: not valid JSON"),
])
def test_invalid_params_name_file_and_problem(tmp_path, data, message):
    path = _write(tmp_path, data)
    with pytest.raises(jaxcos.InputError) as err:
        jaxcos.load_params(path)
    text = str(err.value)
    assert str(path) in text and message in text and "\n" not in text


def test_missing_file(tmp_path):
    with pytest.raises(jaxcos.InputError, match="no such file"):
        jaxcos.load_params(tmp_path / "nope.json")


def test_variant_fixes_switched_off_values_with_a_warning(tmp_path):
    path = _write(tmp_path, {"layers": [LAYER], "base": {"type": "black"}, "variant": "diffusers_only"})
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        m = jaxcos.load_params(path)
    assert float(m.layers[0].c_d) == 1.0 and m.variant == "diffusers_only"
    assert any("'c_d' = 0.9 is ignored" in str(w.message) for w in caught)


def test_eval_writes_values_and_standard_errors(tmp_path):
    params = tmp_path / "p.json"
    jaxcos.save_params(jaxcos.published("matte2"), params)
    angles = tmp_path / "angles.csv"
    angles.write_text("theta_i,theta_o\n30,-20\n30,30\n60,10\n")
    out = tmp_path / "out.csv"
    assert main(["eval", str(params), "--angles", str(angles), "--out", str(out), "--walks", "32",
                 "--bounces", "16", "--quantity", "reflectance_factor"]) == 0
    lines = out.read_text().splitlines()
    assert lines[0] == "# quantity: reflectance_factor"
    assert lines[1] == "theta_i,theta_o,r,g,b,r_std,g_std,b_std"
    rows = np.array([[float(x) for x in line.split(",")] for line in lines[2:]])
    assert rows.shape == (3, 8) and np.all(rows[:, 2:5] > 0) and np.all(rows[:, 5:] > 0)
    np.testing.assert_array_equal(rows[:, :2], [[30, -20], [30, 30], [60, 10]])


def test_eval_refuses_bad_angles_and_writes_nothing(tmp_path, capsys):
    params = tmp_path / "p.json"
    jaxcos.save_params(jaxcos.published("dewy1"), params)
    angles = tmp_path / "angles.csv"
    angles.write_text("theta_i,theta_o\n30,-20\n95,30\n")
    out = tmp_path / "out.csv"
    assert main(["eval", str(params), "--angles", str(angles), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert str(angles) in err and "line 3" in err and "theta_i = 95" in err and len(err.splitlines()) == 1
    assert not out.exists()


def test_params_json_ranges_come_from_the_model_table(tmp_path):
    """io validates params.json against jaxcos.model's one table of ranges: the ends it states, open or closed."""
    from jaxcos.model import INTERFACE_RANGES, LAYER_RANGES

    assert LAYER_RANGES["theta_p"].key == "theta_p_deg" and LAYER_RANGES["albedo_d"].size == 3
    for field, r in LAYER_RANGES.items():
        if r.kind == "rgb" or r.high == float("inf"):
            continue
        for end, is_open in ((r.low, r.low_open), (r.high, r.high_open)):
            path = _write(tmp_path, {"layers": [{**LAYER, r.key: end}], "base": {"type": "black"}})
            if is_open:
                with pytest.raises(jaxcos.InputError, match=r"outside its range " + re.escape(r.interval())):
                    jaxcos.load_params(path)
            else:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    jaxcos.load_params(path)
    for key, r in INTERFACE_RANGES.items():
        data = {"layers": [LAYER], "base": {"type": "black"}, "interface": {"eta": 1.5, "alpha_s": 0.1, key: r.low}}
        with pytest.raises(jaxcos.InputError, match=re.escape(r.interval())):
            jaxcos.load_params(_write(tmp_path, data))


def test_budget_table():
    """One table: the presets, each job's default, and the old names as its aliases."""
    from jaxcos import model
    from jaxcos.inference import ABLATION_BOUNCES, ABLATION_WALKS, FIT_BOUNCES, FIT_JACOBIAN_WALKS, FIT_WALKS
    from jaxcos.inference._posterior import HI_WALKS
    from jaxcos.render import RENDER_BOUNCES, RENDER_WALKS

    assert model.FIT_BUDGET is model.PRESETS["accurate"] and model.ESTIMATOR_BUDGET is model.PRESETS["paper"]
    assert model.BUDGETS == {name: (b.walks, b.bounces) for name, b in model.PRESETS.items()}
    assert (model.DEFAULT_WALKS, model.DEFAULT_BOUNCES) == tuple(model.ESTIMATOR_BUDGET) == (128, 512)
    assert (FIT_WALKS, FIT_BOUNCES, FIT_JACOBIAN_WALKS) == (1024, 128, 128) == (*model.FIT_BUDGET,
                                                                                model.FIT_JACOBIAN_WALKS)
    assert (ABLATION_WALKS, ABLATION_BOUNCES) == tuple(model.ABLATION_BUDGET) == (128, 128)
    assert (RENDER_WALKS, RENDER_BOUNCES) == tuple(model.RENDER_BUDGET) == (256, 64)
    assert HI_WALKS == model.POSTERIOR_BUDGET.walks == 8192
    assert set(model.JOBS) == {"estimator", "fit", "ablation", "render", "posterior"}
    assert model.resolve_budget(default=model.FIT_BUDGET) == (1024, 128)
