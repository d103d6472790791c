"""Measurement files: reading, writing, validation, import of raw data, plotting, and the CLI."""

import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from jaxcos.cli import main
from jaxcos._errors import InputError
from jaxcos.io._measurements import (
    Measurements,
    import_raw,
    load_measurements,
    save_measurements,
    spectral_to_srgb,
)
from jaxcos.io._plot import default_exposure, draw_reflectance, encode_srgb, plot_measurements

SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
WAVELENGTHS = np.arange(380, 781, 10)
SPECTRAL_HEADER = "theta_i,theta_o," + ",".join(f"nm_{w}" for w in WAVELENGTHS)


def write(tmp_path, text, name="m.csv"):
    path = tmp_path / name
    path.write_bytes(text if isinstance(text, bytes) else text.encode("utf-8"))
    return str(path)


def spectral_row(theta_i, theta_o, level):
    return f"{theta_i},{theta_o}," + ",".join([str(level)] * len(WAVELENGTHS))


def raw_row(theta_i, theta_o, level=0.5):
    return "\t".join([str(theta_i), str(theta_o)] + [str(level)] * 81)


# --- reading and writing --------------------------------------------------------------


def test_round_trip_is_exact(tmp_path):
    rng = np.random.default_rng(1)
    meas = Measurements(
        theta_i=np.array([0.0, 20.0, 20.0, 45.5]),
        theta_o=np.array([-60.0, 10.0, 10.0, 89.9]),
        phi_o=np.array([0.0, 0.0, 30.0, 0.0]),
        values=rng.uniform(0, 3, (4, 3)),
        std=rng.uniform(0.001, 0.1, (4, 3)),
        quantity="brdf",
        metadata={"sample": "test: one", "seed": "1"},
    )
    path = str(tmp_path / "m.csv")
    save_measurements(meas, path)
    back = load_measurements(path)
    for name in ("theta_i", "theta_o", "phi_o", "values", "std"):
        np.testing.assert_array_equal(getattr(back, name), getattr(meas, name))
    assert back.quantity == "brdf"
    assert back.metadata == {"quantity": "brdf", "sample": "test: one", "seed": "1"}
    assert back.path == path and back.n_points == 4
    assert Path(path).read_text().startswith("# quantity: brdf\n# sample: test: one\n")


def test_round_trip_without_std_or_phi(tmp_path):
    path = write(tmp_path, "theta_i,theta_o,r,g,b\n20,10,0.5,0.25,0.125\n")
    meas = load_measurements(path)
    assert meas.std is None and meas.quantity == "reflectance_factor"
    np.testing.assert_array_equal(meas.phi_o, [0.0])
    out = str(tmp_path / "out.csv")
    save_measurements(meas, out)
    assert Path(out).read_text() == "# quantity: reflectance_factor\ntheta_i,theta_o,r,g,b\n20,10,0.5,0.25,0.125\n"


def test_save_refuses_to_overwrite(tmp_path):
    path = write(tmp_path, "keep me")
    meas = load_measurements(write(tmp_path, "theta_i,theta_o,r,g,b\n20,10,1,1,1\n", "in.csv"))
    with pytest.raises(InputError, match="already exists"):
        save_measurements(meas, path)
    assert Path(path).read_text() == "keep me"
    save_measurements(meas, path, overwrite=True)
    assert load_measurements(path).n_points == 1
    assert sorted(os.listdir(tmp_path)) == ["in.csv", "m.csv"]  # no temporary file left


def test_quantities():
    meas = Measurements(theta_i=[10.0], theta_o=[20.0], phi_o=[0.0], values=[[math.pi, 0.0, 1.0]],
                        std=[[0.1, 0.1, 0.1]])
    np.testing.assert_allclose(meas.brdf, [[1.0, 0.0, 1 / math.pi]])
    np.testing.assert_allclose(meas.brdf_std, [[0.1 / math.pi] * 3])
    brdf = meas.to_quantity("brdf")
    assert brdf.quantity == "brdf" and brdf.metadata["quantity"] == "brdf"
    np.testing.assert_allclose(brdf.brdf, meas.brdf)
    np.testing.assert_allclose(brdf.to_quantity("reflectance_factor").values, meas.values)
    with pytest.raises(ValueError):
        meas.to_quantity("radiance")
    with pytest.raises(ValueError):
        meas.values[0, 0] = 1.0  # read-only


def test_metadata_comments_blank_lines_crlf_and_bom(tmp_path):
    text = ("\ufeff# quantity: brdf\r\n# a comment without colon\r\n\r\n# illuminant: D50\r\n"
            "theta_i, theta_o, phi_o, r, g, b\r\n# a comment in the data\r\n0,0,5,1,2,3\r\n\r\n")
    meas = load_measurements(write(tmp_path, text))
    assert meas.metadata == {"quantity": "brdf", "illuminant": "D50"}
    np.testing.assert_array_equal(meas.values, [[1, 2, 3]])
    np.testing.assert_array_equal(meas.phi_o, [5.0])


def test_row_with_an_empty_value_cell_is_dropped(tmp_path):
    meas = load_measurements(write(tmp_path, "theta_i,theta_o,r,g,b,r_std,g_std,b_std\n"
                                             "20,10,1,,1,,,\n20,20,1,1,1,0.1,0.1,0.1\n"))
    np.testing.assert_array_equal(meas.theta_o, [20.0])


def test_small_negative_values_within_noise_are_kept(tmp_path):
    meas = load_measurements(write(tmp_path, "theta_i,theta_o,r,g,b,r_std,g_std,b_std\n"
                                             "20,10,-0.02,0.5,0.5,0.01,0.01,0.01\n20,20,-0.005,0,0,1,1,1\n"))
    assert meas.values[0, 0] == -0.02
    assert load_measurements(write(tmp_path, "theta_i,theta_o,r,g,b\n20,10,-0.009,0,0\n", "b.csv")).n_points == 1


# --- the spectral path ------------------------------------------------------------------


def test_flat_spectrum_is_white(tmp_path):
    text = "\n".join([SPECTRAL_HEADER, spectral_row(20, 10, 1), spectral_row(20, 20, 0.5)]) + "\n"
    meas = load_measurements(write(tmp_path, text))
    np.testing.assert_allclose(meas.values, [[1, 1, 1], [0.5, 0.5, 0.5]], atol=1e-12)
    d50 = load_measurements(write(tmp_path, "# illuminant: D50\n" + text, "d50.csv"))
    np.testing.assert_allclose(d50.values, meas.values, atol=1e-12)


def test_spectral_conversion_is_linear_and_coloured():
    ramp = np.linspace(0.1, 0.9, WAVELENGTHS.size)  # more red than blue
    rgb = spectral_to_srgb(WAVELENGTHS, ramp)
    assert rgb[0] > rgb[1] > rgb[2] > 0
    matrix = spectral_to_srgb(WAVELENGTHS, np.eye(WAVELENGTHS.size))
    np.testing.assert_allclose(ramp @ matrix, rgb, atol=1e-12)
    with pytest.raises(ValueError, match="evenly spaced"):
        spectral_to_srgb([400, 405, 420], [1, 1, 1])
    with pytest.raises(ValueError, match="illuminant"):
        spectral_to_srgb(WAVELENGTHS, ramp, illuminant="D66")


def test_spectral_file_with_rgb_std(tmp_path):
    text = SPECTRAL_HEADER + ",r_std,g_std,b_std\n" + spectral_row(30, 40, 0.2) + ",0.01,0.01,0.01\n"
    meas = load_measurements(write(tmp_path, text))
    np.testing.assert_allclose(meas.values, [[0.2, 0.2, 0.2]], atol=1e-12)
    np.testing.assert_array_equal(meas.std, [[0.01, 0.01, 0.01]])


# --- bad input ----------------------------------------------------------------------------

HEADER = "theta_i,theta_o,r,g,b\n"
BAD_CSV = {
    # name: (content, line named in the message or None, words of the problem)
    "missing column": ("theta_i,r,g,b\n20,1,1,1\n", 1, "the column 'theta_o' is missing"),
    "misspelt column": ("theta_i,theta_0,r,g,b\n20,10,1,1,1\n", 1, "unknown column 'theta_0' (did you mean 'theta_o'?)"),
    "misspelt std": (HEADER[:-1] + ",r_sd,g_std,b_std\n", 1, "did you mean 'r_std'?"),
    "misspelt wavelength": ("theta_i,theta_o,380nm,nm_390\n", 1, "did you mean 'nm_380'?"),
    "incomplete rgb": ("theta_i,theta_o,r,g\n20,10,1,1\n", 1, "the column 'b' is missing"),
    "incomplete std": (HEADER[:-1] + ",r_std\n", 1, "the header has 'r_std' but not 'g_std' and 'b_std'; give all three"),
    "rgb and spectral": ("theta_i,theta_o,r,g,b,nm_380\n", 1, "both r,g,b and spectral"),
    "no value columns": ("theta_i,theta_o\n20,10\n", 1, "no value columns"),
    "repeated column": ("theta_i,theta_o,r,g,b,r\n", 1, "appears twice"),
    "per-wavelength std": (SPECTRAL_HEADER + ",nm_380_std\n", 1, "per-wavelength std columns"),
    "text in a cell": ("# sample: x\n" + HEADER + "20,10,abc,1,1\n", 3, "'abc' in column 'r' is not a number"),
    "nan": (HEADER + "20,10,1,1,1\n20,20,1,NaN,1\n", 3, "column 'g' holds NaN; only finite numbers"),
    "inf": (HEADER + "20,10,1,1,-inf\n", 2, "column 'b' holds -inf"),
    "theta_i too large": (HEADER + "20,10,1,1,1\n90,10,1,1,1\n", 3, "theta_i = 90 is outside [0, 90)"),
    "theta_i negative": (HEADER + "-5,10,1,1,1\n", 2, "theta_i = -5 is outside [0, 90)"),
    "theta_o too small": (HEADER + "20,-90,1,1,1\n", 2, "theta_o = -90 is outside (-90, 90)"),
    "empty angle": (HEADER + "20,,1,1,1\n", 2, "column 'theta_o' is empty"),
    "negative": (HEADER + "20,10,1,1,1\n20,20,0.5,-0.05,0.5\n", 3, "g = -0.05 is negative beyond noise (below -0.01, the limit for files without std"),
    "negative beyond std": (HEADER[:-1] + ",r_std,g_std,b_std\n20,10,-0.05,1,1,0.01,0.01,0.01\n", 2,
                            "r = -0.05 is negative beyond noise (below -3 * r_std = -0.03)"),
    "negative brdf": ("# quantity: brdf\n" + HEADER + "20,10,-0.004,1,1\n", 3, "below -0.00318"),
    "zero std": (HEADER[:-1] + ",r_std,g_std,b_std\n20,10,1,1,1,0,0.1,0.1\n", 2, "r_std = 0 must be positive"),
    "std missing next to a value": (HEADER[:-1] + ",r_std,g_std,b_std\n20,10,1,1,1,0.1,,0.1\n", 2,
                                    "column 'g_std' is empty although the row has values"),
    "duplicate": (HEADER + "20,10,1,1,1\n30,10,1,1,1\n20,10,2,2,2\n", None, "lines 2 and 4: the same point "
                  "(theta_i = 20, theta_o = 10) is measured twice"),
    "duplicate with a missing row": (HEADER + "20,10,,,\n20,10,2,2,2\n", None, "lines 2 and 3"),
    "field count": (HEADER + "20,10,1,1\n", 2, "4 fields where the header (line 1) has 5 columns"),
    "spectral grid not increasing": ("theta_i,theta_o,nm_380,nm_400,nm_390\n", 1,
                                     "the spectral grid is not increasing: nm_390 follows nm_400"),
    "spectral grid uneven": ("theta_i,theta_o,nm_380,nm_390,nm_395\n", 1, "evenly spaced at 1, 5, 10 or 20 nm"),
    "spectral grid too short": ("theta_i,theta_o," + ",".join(f"nm_{w}" for w in range(500, 560, 10)) + "\n", 1,
                                "must cover 400-700 nm"),
    "unknown illuminant": ("# illuminant: D66\n" + SPECTRAL_HEADER + "\n" + spectral_row(20, 10, 1) + "\n", 1,
                           "unknown illuminant 'D66' (did you mean 'D65'?)"),
    "unknown quantity": ("# sample: s\n# quantity: brfd\n" + HEADER + "20,10,1,1,1\n", 2,
                         "unknown quantity 'brfd' (did you mean 'brdf'?)"),
    "repeated metadata": ("# sample: a\n# sample: b\n" + HEADER, 2, "the metadata key 'sample' repeats line 1"),
    "header only": ("# quantity: brdf\n" + HEADER + "\n", 2, "the header is not followed by any data row"),
    "no complete row": (HEADER + "20,10,,,\n", None, "no complete measurement"),
    "no header": ("20,10,1,1,1\n", 1, "no header row"),
    "tab-separated header": ("theta_i\ttheta_o\tr\tg\tb\n", 1, "columns must be comma-separated"),
    "metadata only": ("# quantity: brdf\n", None, "no header row, only metadata lines"),
    "empty file": ("", None, "the file is empty"),
    "blank file": ("\n \n", None, "the file is empty"),
    "binary file": (b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR", None, "not a UTF-8 text file (is it binary?)"),
    "latin-1 file": ("# sample: cr\xe8me\n".encode("latin-1") + HEADER.encode(), None, "not a UTF-8 text file"),
}


def check_message(message, path, line, problem):
    assert "\n" not in message and message.endswith(".")
    assert message.startswith(f"{path}, line {line}:" if line else f"{path}")
    assert problem in message


@pytest.mark.parametrize("case", list(BAD_CSV))
def test_bad_csv_is_rejected_with_file_line_and_problem(tmp_path, case):
    content, line, problem = BAD_CSV[case]
    path = write(tmp_path, content)
    with pytest.raises(InputError) as err:
        load_measurements(path)
    check_message(str(err.value), path, line, problem)


@pytest.mark.parametrize("case", ["no file", "directory"])
def test_missing_file_and_directory(tmp_path, case):
    path = str(tmp_path / "nope.csv") if case == "no file" else str(tmp_path)
    for read in (load_measurements, import_raw):
        with pytest.raises(InputError) as err:
            read(path)
        check_message(str(err.value), path, None, "no such file" if case == "no file" else "is a directory")


BAD_RAW = {
    "field count": (raw_row(20, 10) + "\n" + raw_row(20, 20)[:-4] + "\n", 2, "82 values where a raw row has 83"),
    "text": (raw_row(20, 10).replace("0.5", "x", 1) + "\n", 1, "'x' in column '380 nm' is not a number"),
    "nan": (raw_row(20, 10).replace("0.5", "nan") + "\n", 1, "column '380 nm' holds nan"),
    "angle": (raw_row(20, 10) + "\n" + raw_row(20, 95) + "\n", 2, "theta_o = 95 is outside (-90, 90)"),
    "duplicate": ("\n".join([raw_row(20, 10), raw_row(30, 10), raw_row(20, 10, 0.4)]) + "\n", None,
                  "lines 1 and 3: the same point"),
    "negative": (raw_row(20, 10, -0.05) + "\n", 1, "r (converted from the spectrum) = -0.05 is negative beyond noise"),
    "a CSV": (HEADER + "20,10,1,1,1\n", 1, "a measurement CSV needs no import"),
    "empty": ("", None, "the file is empty"),
    "binary": (bytes(range(256)), None, "not a UTF-8 text file"),
}


@pytest.mark.parametrize("case", list(BAD_RAW))
def test_bad_raw_file_is_rejected(tmp_path, case):
    content, line, problem = BAD_RAW[case]
    path = write(tmp_path, content, "raw.txt")
    with pytest.raises(InputError) as err:
        import_raw(path)
    check_message(str(err.value), path, line, problem)


def test_import_raw_reads_a_synthetic_file(tmp_path):
    path = write(tmp_path, "\n".join([raw_row(20, 10, 1.0), raw_row(70, -40, 0.25)]) + "\n", "raw.txt")
    meas = import_raw(path)
    np.testing.assert_allclose(meas.values, [[1, 1, 1], [0.25, 0.25, 0.25]], atol=1e-12)
    np.testing.assert_array_equal(meas.theta_o, [10, -40])
    assert meas.metadata["source"] == "raw.txt" and meas.metadata["illuminant"] == "D65"


# --- the CLI --------------------------------------------------------------------------------


def run_cli(capsys, argv):
    status = main(argv)
    captured = capsys.readouterr()
    return status, captured.out, captured.err


@pytest.mark.parametrize("case", ["text in a cell", "nan", "duplicate", "negative", "misspelt column",
                                  "empty file", "binary file", "spectral grid not increasing"])
def test_cli_plot_reports_bad_csv_and_writes_nothing(tmp_path, capsys, case):
    content, line, problem = BAD_CSV[case]
    path = write(tmp_path, content)
    before = sorted(os.listdir(tmp_path))
    status, out, err = run_cli(capsys, ["plot", path, "--out", str(tmp_path / "fig.png")])
    assert status == 2 and out == ""
    assert err.startswith("jaxcos plot: ") and err.count("\n") == 1
    check_message(err[len("jaxcos plot: "):].rstrip("\n"), path, line, problem)
    assert sorted(os.listdir(tmp_path)) == before


@pytest.mark.parametrize("case", list(BAD_RAW))
def test_cli_import_reports_bad_raw_and_writes_nothing(tmp_path, capsys, case):
    content, line, problem = BAD_RAW[case]
    path = write(tmp_path, content, "raw.txt")
    status, out, err = run_cli(capsys, ["import", path, "--out", str(tmp_path / "out.csv")])
    assert status == 2 and out == "" and err.count("\n") == 1
    check_message(err[len("jaxcos import: "):].rstrip("\n"), path, line, problem)
    assert os.listdir(tmp_path) == ["raw.txt"]


def test_cli_import_then_plot(tmp_path, capsys):
    raw = write(tmp_path, "\n".join(raw_row(ti, to, 0.1 + ti / 100) for ti in (20, 40) for to in (-10, 10, 40)), "r.txt")
    csv, png = str(tmp_path / "m.csv"), str(tmp_path / "m.png")
    assert run_cli(capsys, ["import", raw, "--out", csv])[0] == 0
    assert load_measurements(csv).n_points == 6
    assert run_cli(capsys, ["plot", csv, "--out", png, "--exposure", "2"])[0] == 0
    assert Path(png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    for argv in (["import", raw, "--out", csv], ["plot", csv, "--out", png]):
        mtime = os.path.getmtime(argv[3])
        status, _, err = run_cli(capsys, argv)
        assert status == 2 and "already exists; pass --force" in err
        assert os.path.getmtime(argv[3]) == mtime
        assert run_cli(capsys, argv + ["--force"])[0] == 0
    status, _, err = run_cli(capsys, ["plot", csv, "--out", str(tmp_path / "x.png"), "--exposure", "0"])
    assert status == 2 and "exposure must be a positive number" in err and not (tmp_path / "x.png").exists()


def test_cli_subprocess_gives_one_line_and_no_traceback(tmp_path):
    path = write(tmp_path, BAD_CSV["nan"][0])
    out = tmp_path / "fig.png"
    proc = subprocess.run([sys.executable, "-m", "jaxcos", "plot", path, "--out", str(out)],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and proc.stdout == ""
    assert proc.stderr == f"jaxcos plot: {path}, line 3: column 'g' holds NaN; only finite numbers are allowed.\n"
    assert not out.exists()


# --- random garbage ----------------------------------------------------------------------------

CSV_PIECES = st.sampled_from([
    "theta_i", "theta_o", "phi_o", "r", "g", "b", "r_std", "g_std", "b_std", "nm_380", "nm_390", "nm_", ",", ",",
    "\n", "\n", "\r", "#", ":", " quantity: brdf", " illuminant: D50", "0", "1", "20", "-5", "90", ".5", "1e3",
    "nan", "inf", "-", "abc", " ", "\t", "\x00", "\ufeff", "é",
])


@pytest.fixture(scope="module")
def garbage_dir(tmp_path_factory):
    return tmp_path_factory.mktemp("garbage")


def loads_or_input_error(read, path):
    try:
        read(path)
    except InputError as err:
        assert "\n" not in str(err) and str(err).startswith(path)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.one_of(st.binary(max_size=300), st.text(max_size=300).map(str.encode),
                      st.lists(CSV_PIECES, max_size=80).map(lambda p: "".join(p).encode("utf-8")),
                      st.lists(CSV_PIECES, max_size=60).map(lambda p: (HEADER + "".join(p)).encode("utf-8"))))
def test_garbage_loads_or_raises_input_error(garbage_dir, data):
    path = str(garbage_dir / "g.csv")
    Path(path).write_bytes(data)
    loads_or_input_error(load_measurements, path)
    loads_or_input_error(import_raw, path)


# --- plotting --------------------------------------------------------------------------------------


def test_draw_reflectance_colours_cells_and_leaves_gaps_black():
    from matplotlib.figure import Figure

    ax = Figure().subplots()
    rgb = np.array([[0.18, 0.18, 0.18], [1.0, 0.0, 0.0], [0.09, 0.09, 0.09]])
    mesh = draw_reflectance(ax, [0, 0, 10], [0, 10, 0], rgb, exposure=2.0, title="t")
    colours = mesh.get_facecolors()[:, :3]
    np.testing.assert_allclose(colours[0], encode_srgb([0.36] * 3, 1.0), atol=1e-6)
    np.testing.assert_allclose(colours[0], [1.055 * 0.36 ** (1 / 2.4) - 0.055] * 3, atol=1e-6)  # sRGB curve
    np.testing.assert_allclose(colours[1], [1, 0, 0])  # 2.0 clipped to 1
    np.testing.assert_allclose(colours[2], [1.055 * 0.18 ** (1 / 2.4) - 0.055] * 3, atol=1e-6)
    boxes = [path.get_extents() for path in mesh.get_paths()]
    assert not any(b.contains(10, 10) for b in boxes)  # (theta_i=10, theta_o=10) was not measured: black
    assert any(b.contains(0, 10) for b in boxes)
    assert ax.get_facecolor()[:3] == (0, 0, 0)
    assert "exposure x2" in ax.get_title() and ax.get_title().startswith("t")
    assert ax.get_ylim()[0] > ax.get_ylim()[1]  # theta_i increases downward
    with pytest.raises(ValueError, match="twice"):
        draw_reflectance(ax, [0, 0], [5, 5], rgb[:2], exposure=1.0)


def test_default_exposure():
    values = np.arange(1.0, 101.0)  # 95th percentile 95.05
    assert default_exposure(values) == pytest.approx(0.8 / 95.05)
    assert default_exposure(np.concatenate([values, [0.0, -5.0, np.nan]])) == pytest.approx(0.8 / 95.05)
    assert default_exposure(np.zeros(3)) == 1.0


def test_plot_measurements_writes_png(tmp_path):
    meas = Measurements(theta_i=[0.0, 30.0, 30.0], theta_o=[0.0, 30.0, 20.0], phi_o=[0.0, 0.0, 15.0],
                        values=np.full((3, 3), 0.5), std=None, quantity="brdf")
    out = tmp_path / "fig.png"
    plot_measurements(meas, out, exposure=1.0)
    assert out.read_bytes()[:4] == b"\x89PNG"
    with pytest.raises(InputError, match="already exists"):
        plot_measurements(meas, out)


# --- real data -----------------------------------------------------------------------------------

REAL = [("Clarins_105_Nude_coll_norm.txt", "clarins_105.csv"),
        ("Clarinsfoundation108_5W_norm_thick_layer_tab.txt", "clarins_108.csv")]


@pytest.mark.parametrize("raw, reference", REAL)
def test_import_of_real_data_matches_reference_conversion(tmp_path, capsys, raw, reference):
    folder = SHARED_DATA / "clarins"
    if not (folder / raw).exists():
        pytest.skip(f"{folder} is absent (the real data are not part of the project)")
    out = str(tmp_path / "imported.csv")
    assert main(["import", str(folder / raw), "--out", out]) == 0
    mine, ref = load_measurements(out), load_measurements(folder / reference)
    np.testing.assert_array_equal(mine.theta_i, ref.theta_i)
    np.testing.assert_array_equal(mine.theta_o, ref.theta_o)
    np.testing.assert_allclose(mine.values, ref.values, rtol=1e-6, atol=1e-6)
    assert mine.quantity == ref.quantity == "reflectance_factor"


# --- the synthetic data sets in measurements/ ------------------------------------------------------

MEASUREMENTS = Path(__file__).resolve().parents[1] / "measurements"
DATA_SETS = {"dewy1": 105, "dewy2": 112, "matte1": 103, "matte2": 108}


@pytest.mark.parametrize("name", list(DATA_SETS))
def test_synthetic_data_sets_load_and_say_what_they_are(name):
    meas = load_measurements(MEASUREMENTS / f"{name}.csv")
    assert meas.quantity == "reflectance_factor" and meas.std is not None
    for key in ("synthetic", "parameters", "noise", "seed", "monte_carlo", "generator"):
        assert meas.metadata.get(key), key
    expected = np.sqrt((0.02 * meas.values) ** 2 + 0.002 ** 2)
    assert np.median(np.abs(meas.std / expected - 1)) < 0.05  # std columns follow the stated noise model
    grid = SHARED_DATA / "grid.csv"
    if grid.exists():
        rows = np.loadtxt(grid, delimiter=",", skiprows=1)
        rows = rows[rows[:, 0] == DATA_SETS[name]]
        np.testing.assert_array_equal(meas.theta_i, rows[:, 1])
        np.testing.assert_array_equal(meas.theta_o, rows[:, 2])


def test_spectral_data_set_converts_back_to_rgb():
    spectral = load_measurements(MEASUREMENTS / "dewy1_spectral.csv")
    rgb = load_measurements(MEASUREMENTS / "dewy1.csv")
    assert spectral.metadata["illuminant"] == "D65"
    np.testing.assert_array_equal(spectral.theta_o, rgb.theta_o)
    np.testing.assert_allclose(spectral.values, rgb.values, rtol=0, atol=1e-8)
    np.testing.assert_array_equal(spectral.std, rgb.std)
