"""Make the synthetic Clarins-style data sets in ``measurements/``.

    python scripts/make_measurements.py [--grid PATH] [--out DIR] [--force]

writes ``dewy1.csv``, ``dewy2.csv``, ``matte1.csv``, ``matte2.csv`` and
``dewy1_spectral.csv`` (the CSV of docs/formats.md). They are *synthetic*: the
BSDF of the paper's published fits (``jaxcos.published(name)``, Lanza et al.
2024 Table 2: one layer, ``t = 16``, black base, ``phi_p = 0``) simulated by
jaxcos, plus Gaussian noise. Nothing of the real measurements goes into them
except the measurement *positions*.

Angles: the ``(theta_i, theta_o)`` positions the real instrument measured,
read from the package's ``jaxcos/data/grid.csv`` (angles only, no measured
values; ``--grid`` to read another file of the same columns), so the data
have the instrument's coverage and gaps. Its ``product`` column holds the
Clarins product numbers, mapped as in docs/model.md section 5: 105 Skin Illusion 105 Nude =
Dewy 1, 112 Skin Illusion 112 Nude = Dewy 2, 103 Skin Illusion Velvet 103 Nude
= Matte 1, 108 Skin Illusion Velvet 108 = Matte 2.

Model values: the reflectance factor ``v = pi * f`` from
:func:`jaxcos.simulate` with the exact single-scattering term, ``BOUNCES``
bounces and ``WALKS[name]`` walks per incidence, run in batches of ``BATCH``
walks (key ``fold_in(fold_in(key(SEED), product), batch)``) and averaged. The
budgets are chosen so that the Monte Carlo standard error is small next to
the noise; each file states the ratio it reached.

Noise (per point and channel, independent): ``value = v + N(0, s^2)`` with
``s = sqrt((0.02 v)^2 + 0.002^2)``: 2 % multiplicative plus 0.002 additive
(in reflectance factor). ``r_std, g_std, b_std`` hold ``s`` (computed from the
noise-free ``v``). Draws come from ``numpy.random.default_rng([SEED, product])``.
Values and std are written with 6 significant digits.

The spectral file ``dewy1_spectral.csv`` holds the noisy values of
``dewy1.csv`` as spectra at 380, 390, ..., 780 nm: per point, the quadratic
polynomial in wavelength whose linear sRGB under D65
(:func:`jaxcos.io.spectral_to_srgb`) is exactly that point's
``r, g, b`` (a flat spectrum for a grey). Reading it gives back ``dewy1.csv``
to about 1e-9.

Reproducibility: the same seed, jaxcos estimator and jax version give the
same files on CPU (the generating versions are in each file's metadata); any
change to the estimator's arithmetic moves the last digits, so rerun this
script after changing ``jaxcos/model/_walk.py`` or ``jaxcos/model/_phase.py``. Regenerate
into another folder and compare with ``--out``. It needs about 6 minutes of
CPU time (Dewy 2, the sharpest highlight, takes most of it): 6 to 11 minutes
on two cores.
"""

import argparse
import csv
import importlib.resources
import json
import sys
import time
from pathlib import Path

import jax
import numpy as np

import jaxcos
from jaxcos.io import Measurements, load_measurements, material_to_dict, save_measurements, spectral_to_srgb

SEED = 20240601
BOUNCES = 256
BATCH = 8192
WALKS = {"dewy1": 65536, "dewy2": 524288, "matte1": 32768, "matte2": 65536}
"""Walks per incidence: the sharper the highlight, the more walks it needs."""
NOISE_RELATIVE = 0.02
NOISE_ABSOLUTE = 0.002
DIGITS = 6
PRODUCTS = {  # jaxcos name: (grid.csv product number, label)
    "dewy1": (105, "Dewy 1 (Clarins Skin Illusion 105 Nude style)"),
    "dewy2": (112, "Dewy 2 (Clarins Skin Illusion 112 Nude style)"),
    "matte1": (103, "Matte 1 (Clarins Skin Illusion Velvet 103 Nude style)"),
    "matte2": (108, "Matte 2 (Clarins Skin Illusion Velvet 108 style)"),
}
SPECTRAL_WAVELENGTHS = np.arange(380.0, 781.0, 10.0)
DEFAULT_GRID = importlib.resources.files("jaxcos") / "data" / "grid.csv"
"""The instrument's measurement positions, shipped with the package."""
OUT = Path(__file__).resolve().parents[1] / "measurements"


def read_grid(path, product):
    """``(theta_i, theta_o)`` in degrees of one product of ``grid.csv``, in file order.

    ``path``: a :class:`~pathlib.Path` or a package resource (:data:`DEFAULT_GRID`).
    """
    with path.open(newline="") as fh:
        rows = [r for r in csv.DictReader(fh) if int(r["product"]) == product]
    if not rows:
        sys.exit(f"{path}: no positions for product {product}.")
    return np.array([float(r["theta_i"]) for r in rows]), np.array([float(r["theta_o"]) for r in rows])


def simulate_reflectance(material, theta_i, theta_o, product, walks):
    """Reflectance factor ``pi * f`` and its Monte Carlo standard error, ``(N, 3)`` each."""
    query = jaxcos.make_query(theta_i, theta_o)
    run = jax.jit(lambda key: jaxcos.simulate(material, query, key, walks=BATCH, bounces=BOUNCES))
    base = jax.random.fold_in(jax.random.key(SEED), product)
    means, errors = [], []
    for batch in range(walks // BATCH):
        est = run(jax.random.fold_in(base, batch))
        means.append(np.asarray(est.f, dtype=float))
        errors.append(np.asarray(est.stderr, dtype=float))
    k = len(means)
    return np.pi * np.mean(means, axis=0), np.pi * np.sqrt(np.sum(np.square(errors), axis=0)) / k


def rounded(data):
    """``data`` (parsed JSON) with floats shown to 7 significant digits (the float32 parameters as published)."""
    if isinstance(data, dict):
        return {k: rounded(v) for k, v in data.items()}
    if isinstance(data, list):
        return [rounded(v) for v in data]
    return float(f"{data:.7g}") if isinstance(data, float) else data


def significant(x):
    """``x`` rounded to :data:`DIGITS` significant digits."""
    return np.vectorize(lambda v: float(f"{v:.{DIGITS}g}"))(x)


def grid_label(grid):
    """How the metadata name the grid file: ``jaxcos/data/grid.csv`` for the package's own."""
    return "jaxcos/data/grid.csv" if grid == DEFAULT_GRID else str(grid)


def make_product(name, grid, out, force):
    product, label = PRODUCTS[name]
    theta_i, theta_o = read_grid(grid, product)
    material = jaxcos.published(name)
    start = time.time()
    truth, mc_error = simulate_reflectance(material, theta_i, theta_o, product, WALKS[name])
    noise_std = np.sqrt((NOISE_RELATIVE * truth) ** 2 + NOISE_ABSOLUTE ** 2)
    values = truth + np.random.default_rng([SEED, product]).normal(size=truth.shape) * noise_std
    ratio = mc_error / noise_std
    metadata = {
        "quantity": "reflectance_factor",
        "sample": f"{label}, synthetic",
        "synthetic": "yes: simulated by jaxcos from published parameters plus noise, not measured",
        "parameters": f"jaxcos.published('{name}'), Lanza et al. 2024 Table 2 (t = 16, black base, phi_p = 0): "
                      + json.dumps(rounded(material_to_dict(material))),
        "angles": f"positions measured for product {product} in {grid_label(grid)} (real instrument pattern)",
        "noise": f"value = v + N(0, s^2), s = sqrt(({NOISE_RELATIVE} v)^2 + {NOISE_ABSOLUTE}^2), v = noise-free "
                 f"reflectance factor, independent per point and channel; r_std,g_std,b_std hold s",
        "seed": str(SEED),
        "monte_carlo": f"walks = {WALKS[name]} per incidence, bounces = {BOUNCES}, exact single scattering; "
                       f"MC standard error / noise std: median {np.median(ratio):.2f}, "
                       f"95th percentile {np.percentile(ratio, 95):.2f}, max {ratio.max():.2f}",
        "generator": f"scripts/make_measurements.py (jaxcos {jaxcos.__version__}, jax {jax.__version__}, "
                     f"{jax.default_backend()}, {jax.numpy.result_type(float)})",
    }
    meas = Measurements(theta_i=theta_i, theta_o=theta_o, phi_o=np.zeros_like(theta_i),
                        values=significant(values), std=significant(noise_std), metadata=metadata)
    save_measurements(meas, out / f"{name}.csv", overwrite=force)
    print(f"{name}: {meas.n_points} points, {time.time() - start:.0f} s, {metadata['monte_carlo']}", flush=True)
    return meas


def write_spectral(meas, path):
    """Write ``meas`` as spectra (quadratic in wavelength) whose linear sRGB are its values."""
    x = (SPECTRAL_WAVELENGTHS - 580.0) / 200.0
    basis = np.stack([np.ones_like(x), x, x ** 2], axis=1)  # (n, 3): 1, x, x^2
    to_rgb = spectral_to_srgb(SPECTRAL_WAVELENGTHS, basis.T)  # (3, 3): sRGB of each basis spectrum
    spectra = np.linalg.solve(to_rgb.T, meas.values.T).T @ basis.T  # (N, n)
    metadata = {**meas.metadata, "illuminant": "D65",
                "spectral": "per point, the quadratic polynomial in wavelength whose linear sRGB (D65) is the "
                            "r,g,b of dewy1.csv; r_std,g_std,b_std are the std of that linear sRGB"}
    metadata["sample"] = metadata["sample"] + ", spectral form"
    lines = [f"# {k}: {v}" for k, v in metadata.items()]
    lines.append(",".join(["theta_i", "theta_o"] + [f"nm_{w:g}" for w in SPECTRAL_WAVELENGTHS]
                          + ["r_std", "g_std", "b_std"]))
    for ti, to, spectrum, std in zip(meas.theta_i, meas.theta_o, spectra, meas.std):
        lines.append(",".join([f"{ti:g}", f"{to:g}"] + [f"{v:.10g}" for v in spectrum] + [f"{v:g}" for v in std]))
    path.write_text("\n".join(lines) + "\n")
    back = load_measurements(path)
    error = np.abs(back.values - meas.values).max()
    if error > 1e-8 or spectra.min() < 0:
        sys.exit(f"{path}: the spectra reproduce dewy1 only to {error:.2g} (min {spectra.min():.3g}).")
    print(f"{path.name}: spectra give back dewy1 to {error:.1g}", flush=True)


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--grid", type=Path, default=DEFAULT_GRID,
                        help="CSV of measurement positions, columns product,theta_i,theta_o "
                        "(default: the package's jaxcos/data/grid.csv)")
    parser.add_argument("--out", type=Path, default=OUT, help="output folder (default: measurements/)")
    parser.add_argument("--force", action="store_true", help="overwrite existing files")
    args = parser.parse_args()
    if not args.grid.is_file():
        sys.exit(f"{args.grid}: no such file; pass --grid with the path of a grid.csv.")
    names = [f"{name}.csv" for name in PRODUCTS] + ["dewy1_spectral.csv"]
    existing = [n for n in names if (args.out / n).exists()]
    if existing and not args.force:
        sys.exit(f"{args.out / existing[0]}: already exists; pass --force to replace the data sets.")
    args.out.mkdir(parents=True, exist_ok=True)
    made = {name: make_product(name, args.grid, args.out, args.force) for name in PRODUCTS}
    write_spectral(made["dewy1"], args.out / "dewy1_spectral.csv")


if __name__ == "__main__":
    main()
