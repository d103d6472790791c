"""``jaxcos eval``: the BSDF of a material at the angles of a file, with Monte Carlo errors.

Example::

    import jax, jaxcos
    from jaxcos._eval import load_angles, evaluate
    ti, to, po = load_angles("angles.csv")
    f, f_std = evaluate(jaxcos.published("dewy1"), ti, to, po, jax.random.key(0))
"""

import os

import jax
import numpy as np

from ._errors import InputError, refuse_overwrite
from ._measurements import _check_angles, _check_duplicates, _parse_number, _read_lines, _split_header, _where
from ._walk import DEFAULT_BOUNCES, DEFAULT_WALKS, make_query, simulate

_ANGLE_COLUMNS = ("theta_i", "theta_o", "phi_o")


def load_angles(path):
    """Read ``theta_i,theta_o[,phi_o]`` rows (degrees; other columns are ignored).

    Returns:
        ``(theta_i, theta_o, phi_o)`` as float arrays.

    Raises:
        InputError: one sentence naming the file, the line and the problem.
    """
    path = os.fspath(path)
    what = "an angles CSV with columns theta_i,theta_o[,phi_o]"
    lines = _read_lines(path, what)
    _, _, header_line, header = _split_header(path, lines)
    for name in _ANGLE_COLUMNS[:2]:
        if name not in header:
            raise InputError(f"{_where(path, header_line)}: the column '{name}' is missing; {what} is expected.")
    index = {name: header.index(name) for name in _ANGLE_COLUMNS if name in header}
    rows = []
    for line, text in lines:
        if line <= header_line or not text.strip() or text.lstrip().startswith("#"):
            continue
        cells = [c.strip() for c in text.split(",")]
        if len(cells) != len(header):
            raise InputError(f"{_where(path, line)}: {len(cells)} cells for {len(header)} columns.")
        values = {}
        for name, i in index.items():
            value = _parse_number(path, line, name, cells[i])
            if value is None and name != "phi_o":
                raise InputError(f"{_where(path, line)}: the cell of column '{name}' is empty.")
            values[name] = 0.0 if value is None else value
        rows.append((line, values["theta_i"], values["theta_o"], values.get("phi_o", 0.0)))
    if not rows:
        raise InputError(f"{path}: the header has no rows under it; {what} is expected.")
    _check_angles(path, rows)
    _check_duplicates(path, rows)
    _, ti, to, po = (np.array(c, dtype=float) for c in zip(*rows))
    return ti, to, po


def evaluate(material, theta_i, theta_o, phi_o, key, *, walks=DEFAULT_WALKS, bounces=DEFAULT_BOUNCES):
    """The BSDF (1/sr) and its standard error, ``(N, 3)`` each, at the given angles (degrees)."""
    est = simulate(material, make_query(theta_i, theta_o, phi_o), key, walks=walks, bounces=bounces)
    return np.asarray(est.f, dtype=float), np.asarray(est.stderr, dtype=float)


def write_evaluation(path, theta_i, theta_o, phi_o, values, std, *, quantity, overwrite=False):
    """Write the rows of ``jaxcos eval`` (FORMATS.md) atomically; an existing file is kept unless ``overwrite``."""
    path = os.fspath(path)
    refuse_overwrite([path], overwrite)
    with_phi = bool(np.any(phi_o != 0))
    header = "theta_i,theta_o," + ("phi_o," if with_phi else "") + "r,g,b,r_std,g_std,b_std"
    lines = [f"# quantity: {quantity}", header]
    for k in range(len(theta_i)):
        angles = [theta_i[k], theta_o[k]] + ([phi_o[k]] if with_phi else [])
        lines.append(",".join(f"{a:g}" for a in angles) + "," + ",".join(f"{v:.7g}" for v in (*values[k], *std[k])))
    tmp = path + ".tmp"
    with open(tmp, "w", encoding="utf-8") as fh:
        fh.write("\n".join(lines) + "\n")
    os.replace(tmp, path)


def run_eval(args):
    """The ``jaxcos eval`` command (see ``jaxcos eval --help``)."""
    from ._material import load_params

    refuse_overwrite([args.out], args.force)
    for name, value in (("--walks", args.walks), ("--bounces", args.bounces)):
        if value is not None and value < 1:
            raise InputError(f"{name} must be a positive integer, not {value}.")
    material = load_params(args.params)
    ti, to, po = load_angles(args.angles)
    f, f_std = evaluate(material, ti, to, po, jax.random.key(args.seed),
                        walks=args.walks or DEFAULT_WALKS, bounces=args.bounces or DEFAULT_BOUNCES)
    scale = np.pi if args.quantity == "reflectance_factor" else 1.0
    write_evaluation(args.out, ti, to, po, scale * f, scale * f_std, quantity=args.quantity, overwrite=True)
    print(f"wrote {args.out}: {len(ti)} rows of {args.quantity} with Monte Carlo standard errors.")
