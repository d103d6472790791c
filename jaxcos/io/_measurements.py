"""Measurements: the CSV of docs/formats.md, the raw instrument format, spectral to sRGB.

A :class:`Measurements` holds in-plane (or out-of-plane) gonioreflectometer
points in the angle convention of docs/model.md section 1 (degrees; ``theta_o < 0``
on the light's side) with linear sRGB values in the file's quantity.

Example::

    import jaxcos
    meas = jaxcos.load_measurements("measurements/dewy1.csv")
    meas.n_points, meas.quantity      # (147, 'reflectance_factor')
    meas.brdf                         # f in 1/sr, shape (N, 3)

Reading rules (beyond docs/formats.md):

- ``#`` lines before the header are metadata ``key: value`` pairs, kept in
  order; a ``#`` line without a colon, and any ``#`` line after the header, is
  a comment. Blank lines are skipped.
- Columns: ``theta_i``, ``theta_o``, optional ``phi_o`` (degrees), then either
  ``r,g,b`` or spectral columns ``nm_<wavelength>``, and optionally
  ``r_std,g_std,b_std`` (all three or none). In a spectral file the std
  columns are the standard deviations of the *converted* linear sRGB values;
  per-wavelength deviations are not accepted. Unknown columns are errors.
- A row with an empty value cell (any of ``r,g,b`` or any spectral cell) is a
  missing measurement and is dropped whole; empty angle cells, and an empty
  std cell next to a present value, are errors.
- "Negative beyond noise": a value below ``-3 * std`` when the file has std
  columns, otherwise below ``-0.01`` in reflectance factor (``-0.01 / pi`` for
  ``brdf``), about the noise floor of a spectralon-calibrated instrument.
  Smaller negative values are kept as they are (clipping would bias a fit).
  For spectral files the test applies to the converted sRGB values.
- Duplicate points (same ``theta_i``, ``theta_o``, ``phi_o``) are errors, also
  when one of the two rows is a missing measurement.
"""

import dataclasses
import difflib
import functools
import math
import os
import re
import warnings

import numpy as np

from .._errors import InputError, refuse_overwrite

QUANTITIES = ("reflectance_factor", "brdf")
"""Quantities a file may hold: ``pi * f`` (1 for a white diffuser) or ``f`` (1/sr)."""

NEGATIVE_TOLERANCE = 0.01
"""Without std columns, values below ``-NEGATIVE_TOLERANCE`` (in reflectance
factor; divided by pi for ``brdf``) are rejected as negative beyond noise."""

RAW_WAVELENGTHS = np.arange(380.0, 781.0, 5.0)
"""Wavelengths (nm) of the 81 spectral values of a raw instrument row."""

SPECTRAL_STEPS = (1, 5, 10, 20)
"""Spectral column spacings (nm) accepted: those of ASTM E308 weighting."""

_RGB = ("r", "g", "b")
_STD = ("r_std", "g_std", "b_std")
_KNOWN = ("theta_i", "theta_o", "phi_o") + _RGB + _STD
_NUMBER = re.compile(r"[+-]?(\d+\.?\d*|\.\d+)([eE][+-]?\d+)?")
_NONFINITE = re.compile(r"[+-]?(nan|inf|infinity)", re.IGNORECASE)
_WAVELENGTH = re.compile(r"nm_(\d+(\.\d*)?)")
_WAVELENGTH_LIKE = re.compile(r"(?:nm)?[ _-]?(\d{3}(?:\.\d*)?)[ _-]?(?:nm)?")


@dataclasses.dataclass(frozen=True, eq=False)
class Measurements:
    """A measurement table: angles, linear sRGB values, optional std, metadata.

    Attributes:
        theta_i: incidence polar angles, degrees, shape ``(N,)``, in ``[0, 90)``.
        theta_o: signed viewing angles in the plane of incidence, degrees,
            shape ``(N,)``, in ``(-90, 90)``; ``theta_o < 0`` is the light's side.
        phi_o: azimuth of the viewing direction out of that plane, degrees,
            shape ``(N,)`` (0 for in-plane points).
        values: linear sRGB in ``quantity``, shape ``(N, 3)``.
        std: per-point standard deviations of ``values``, shape ``(N, 3)``, or
            ``None``.
        quantity: ``"reflectance_factor"`` (``pi * f``) or ``"brdf"`` (``f``, 1/sr).
        metadata: the file's ``# key: value`` lines, in order (values as text).
        path: the file the table came from (``""`` if built in memory).
        noise: ``(relative, absolute)``, the levels of the noise model that
            gave ``std`` (:meth:`with_noise`; ``absolute`` in ``quantity``), or
            ``None`` where ``std`` is the file's or there is none. A file's own
            ``# noise:`` line is metadata, never read as this.

    The arrays are read-only.
    """

    theta_i: np.ndarray
    theta_o: np.ndarray
    phi_o: np.ndarray
    values: np.ndarray
    std: np.ndarray | None
    quantity: str = "reflectance_factor"
    metadata: dict = dataclasses.field(default_factory=dict)
    path: str = ""
    noise: tuple | None = None

    def __post_init__(self):
        if self.quantity not in QUANTITIES:
            raise ValueError(f"unknown quantity {self.quantity!r}; expected one of {', '.join(QUANTITIES)}")
        n = np.shape(self.theta_i)[0] if np.ndim(self.theta_i) == 1 else -1
        for name in ("theta_i", "theta_o", "phi_o", "values", "std"):
            value = getattr(self, name)
            if value is None and name == "std":
                continue
            array = np.array(value, dtype=float)
            expected = (n,) if name in ("theta_i", "theta_o", "phi_o") else (n, 3)
            if array.shape != expected:
                raise ValueError(f"{name} has shape {array.shape}, expected {expected}")
            array.setflags(write=False)
            object.__setattr__(self, name, array)

    @property
    def n_points(self):
        """Number of measured points ``N``."""
        return self.theta_i.shape[0]

    def to_quantity(self, quantity):
        """The same table in ``quantity`` (values and std scaled by ``pi`` or ``1 / pi``)."""
        if quantity not in QUANTITIES:
            raise ValueError(f"unknown quantity {quantity!r}; expected one of {', '.join(QUANTITIES)}")
        scale = _to_brdf(self.quantity) / _to_brdf(quantity)
        return dataclasses.replace(
            self,
            values=self.values * scale,
            std=None if self.std is None else self.std * scale,
            quantity=quantity,
            metadata={**self.metadata, "quantity": quantity},
            noise=None if self.noise is None else (self.noise[0], self.noise[1] * scale),
        )

    @property
    def scale(self):
        """The factor turning a BSDF ``f`` (1/sr) into this table's quantity: ``pi`` for a reflectance factor, else 1."""
        return 1.0 / _to_brdf(self.quantity)

    def with_noise(self, relative, absolute=0.0):
        """The same table with the noise model ``std = relative * |value| + absolute`` (per point and channel).

        For a file without std columns: the fit then weighs every point by its
        size instead of minimising the plain L2. ``relative`` and ``absolute``
        are in the table's quantity (absolute) or dimensionless (relative);
        at least one must be positive, neither negative. The returned table
        holds them as :attr:`noise`; its metadata are the file's.

        Raises:
            InputError: if the table has std columns already or the levels are invalid.
        """
        name = self.path or "the measurements"
        if self.std is not None:
            raise InputError(f"{name}: the file has std columns; a noise model is only for files without them.")
        if not (math.isfinite(relative) and math.isfinite(absolute)) or relative < 0 or absolute < 0 \
                or relative + absolute <= 0:
            raise InputError(f"noise levels must be non-negative and not both zero, not {relative:g},{absolute:g}.")
        std = relative * np.abs(self.values) + absolute
        if np.any(std <= 0):
            raise InputError(f"{name}: the noise model {relative:g},{absolute:g} gives a zero std where a value is 0; "
                             "add an absolute level.")
        return dataclasses.replace(self, std=std, noise=(float(relative), float(absolute)))

    @property
    def brdf(self):
        """The BSDF ``f`` in 1/sr, shape ``(N, 3)`` (``values / pi`` for a reflectance factor)."""
        return self.to_quantity("brdf").values

    @property
    def brdf_std(self):
        """Standard deviations of :attr:`brdf` in 1/sr, shape ``(N, 3)``, or ``None``."""
        return self.to_quantity("brdf").std


def _to_brdf(quantity):
    """Factor turning a value of ``quantity`` into ``f`` (1/sr)."""
    return 1.0 / math.pi if quantity == "reflectance_factor" else 1.0


# --- spectral to linear sRGB ---------------------------------------------------------


def _known_illuminant(name):
    import colour

    return name in colour.SDS_ILLUMINANTS


@functools.lru_cache(maxsize=16)
def _spectral_matrix(wavelengths, illuminant):
    """``(n, 3)`` matrix mapping ``n`` spectral samples to linear sRGB (cached)."""
    import colour
    from colour.utilities import ColourRuntimeWarning, ColourWarning

    cmfs = colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"]
    basis = colour.MultiSpectralDistributions(np.eye(len(wavelengths)), np.array(wavelengths))
    with warnings.catch_warnings():
        # colour reports that it aligns the shapes of the data, illuminant and CMFs: expected here.
        warnings.simplefilter("ignore", ColourWarning)
        warnings.simplefilter("ignore", ColourRuntimeWarning)
        xyz = colour.msds_to_XYZ(basis, cmfs, colour.SDS_ILLUMINANTS[illuminant], method="ASTM E308")
    rgb = np.asarray(xyz) @ colour.RGB_COLOURSPACES["sRGB"].matrix_XYZ_to_RGB.T
    return rgb / rgb.sum(axis=0)


def spectral_to_srgb(wavelengths, spectra, illuminant="D65"):
    """Linear sRGB of reflectance spectra, normalised so a flat spectrum of 1 gives ``r = g = b = 1``.

    The spectra are integrated against the CIE 1931 2 degree observer under
    ``illuminant`` (a name of ``colour.SDS_ILLUMINANTS``) with colour-science's
    ASTM E308 method (which extends a spectrum by its end values to the
    360-780 nm practice range), converted with the plain XYZ to sRGB matrix
    (no chromatic adaptation), and each channel divided by its value for a
    flat spectrum of 1. The map is linear: ``spectral_to_srgb(wl, np.eye(n))``
    is its ``(n, 3)`` matrix.

    Args:
        wavelengths: ``(n,)`` wavelengths in nm, evenly spaced at 1, 5, 10 or
            20 nm, the first a multiple of 5 nm, covering 400-700 nm, within
            360-830 nm.
        spectra: ``(..., n)`` reflectance factors (or BRDF values) per wavelength.
        illuminant: illuminant name, default ``"D65"``.

    Returns:
        ``(..., 3)`` linear sRGB in the quantity of ``spectra``.

    Raises:
        ValueError: for a wavelength grid outside the rules above or an
            unknown illuminant.
    """
    wavelengths = np.asarray(wavelengths, dtype=float)
    problem = _grid_problem(wavelengths)
    if problem:
        raise ValueError(f"spectral grid: {problem}")
    if not _known_illuminant(illuminant):
        raise ValueError(f"unknown illuminant {illuminant!r}")
    return np.asarray(spectra, dtype=float) @ _spectral_matrix(tuple(wavelengths.tolist()), illuminant)


def _grid_problem(wavelengths):
    """Why ``wavelengths`` (nm, increasing) cannot be converted, or ``None``."""
    steps = np.diff(wavelengths)
    step = steps[0] if steps.size else 0.0
    if steps.size == 0 or step not in SPECTRAL_STEPS or np.any(steps != step):
        return "the wavelengths must be evenly spaced at 1, 5, 10 or 20 nm"
    if wavelengths[0] % 5:
        return f"the first wavelength ({wavelengths[0]:g} nm) must be a multiple of 5 nm"
    if wavelengths[0] > 400 or wavelengths[-1] < 700 or wavelengths[0] < 360 or wavelengths[-1] > 830:
        return (f"the wavelengths must cover 400-700 nm and stay within 360-830 nm, "
                f"not {wavelengths[0]:g}-{wavelengths[-1]:g} nm")
    return None


# --- reading text ----------------------------------------------------------------------


def _read_lines(path, what):
    """The lines of a text file as ``(line_number, text)``; InputError if it cannot be read."""
    try:
        with open(path, "rb") as fh:
            data = fh.read()
    except FileNotFoundError:
        raise InputError(f"{path}: no such file.") from None
    except IsADirectoryError:
        raise InputError(f"{path}: is a directory, not {what}.") from None
    except OSError as err:
        raise InputError(f"{path}: cannot be read ({err.strerror}).") from None
    try:
        if b"\0" in data:
            raise UnicodeDecodeError("utf-8", data, 0, 1, "NUL byte")
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError:
        raise InputError(f"{path}: not a UTF-8 text file (is it binary?); expected {what}.") from None
    lines = text.replace("\r\n", "\n").replace("\r", "\n").split("\n")
    if not any(line.strip() for line in lines):
        raise InputError(f"{path}: the file is empty; expected {what}.")
    return [(i + 1, line) for i, line in enumerate(lines)]


def _where(path, line):
    return f"{path}, line {line}"


def _parse_number(path, line, column, cell):
    """``cell`` as a finite float, or ``None`` when empty."""
    cell = cell.strip()
    if not cell:
        return None
    if _NUMBER.fullmatch(cell):
        return float(cell)
    if _NONFINITE.fullmatch(cell):
        raise InputError(f"{_where(path, line)}: column '{column}' holds {cell}; only finite numbers are allowed.")
    raise InputError(f"{_where(path, line)}: {_show(cell)} in column '{column}' is not a number.")


def _show(text, limit=24):
    """``text`` quoted for a one-line message: shortened, control characters escaped."""
    text = text if len(text) <= limit else text[:limit - 3] + "..."
    return f"'{text}'" if text.isprintable() else ascii(text)


def _suggestion(name):
    """`` (did you mean 'x'?)`` for a misspelt column name, or ``""``."""
    like = _WAVELENGTH_LIKE.fullmatch(name.strip().lower())
    if like:
        return f" (did you mean 'nm_{like.group(1)}'?)"
    if name.lower().startswith("nm"):
        return " (spectral columns are named nm_<wavelength in nm>, e.g. nm_380)"
    close = difflib.get_close_matches(name.strip().lower(), _KNOWN, n=1, cutoff=0.6)
    return f" (did you mean '{close[0]}'?)" if close else ""


# --- the CSV of docs/formats.md ---------------------------------------------------------------


def load_measurements(path):
    """Read a measurement CSV (docs/formats.md) into :class:`Measurements`.

    Spectral columns are converted with :func:`spectral_to_srgb` under the
    ``# illuminant:`` of the metadata (default D65). The values stay in the
    file's ``# quantity:`` (default ``reflectance_factor``). See the module
    docstring for missing cells, comments and the noise threshold.

    Raises:
        InputError: one sentence naming the file, the line and the problem.
    """
    path = os.fspath(path)
    what = "a measurement CSV (docs/formats.md)"
    lines = _read_lines(path, what)
    metadata, meta_lines, header_line, header = _split_header(path, lines)
    columns = _check_columns(path, header_line, header)
    quantity = metadata.get("quantity", "reflectance_factor")
    if quantity not in QUANTITIES:
        close = difflib.get_close_matches(quantity, QUANTITIES, n=1)
        hint = f" (did you mean '{close[0]}'?)" if close else ""
        raise InputError(f"{_where(path, meta_lines['quantity'])}: unknown quantity {_show(quantity)}{hint}; "
                         f"expected reflectance_factor or brdf.")
    wavelengths = columns["wavelengths"]
    matrix = None
    if wavelengths is not None:
        illuminant = metadata.get("illuminant", "D65")
        if not _known_illuminant(illuminant):
            import colour

            close = difflib.get_close_matches(illuminant, list(colour.SDS_ILLUMINANTS), n=1)
            hint = f" (did you mean '{close[0]}'?)" if close else ""
            raise InputError(f"{_where(path, meta_lines['illuminant'])}: unknown illuminant {_show(illuminant)}{hint}; "
                             f"use a name of colour.SDS_ILLUMINANTS such as D65 or D50.")
        matrix = spectral_to_srgb(wavelengths, np.eye(len(wavelengths)), illuminant)

    rows = []  # (line, theta_i, theta_o, phi_o, values or None, std or None)
    index = {name: i for i, name in enumerate(header)}
    value_names = columns["values"]
    for line, text in lines[header_line:]:
        if not text.strip() or text.lstrip().startswith("#"):
            continue
        cells = text.split(",")
        if len(cells) != len(header):
            raise InputError(f"{_where(path, line)}: {len(cells)} fields where the header (line {header_line}) "
                             f"has {len(header)} columns.")
        get = {name: _parse_number(path, line, name, cells[i]) for name, i in index.items()}
        for name in ("theta_i", "theta_o") + (("phi_o",) if "phi_o" in index else ()):
            if get[name] is None:
                raise InputError(f"{_where(path, line)}: the cell in column '{name}' is empty.")
        values = [get[name] for name in value_names]
        if any(v is None for v in values):
            values = std = None
        else:
            std = None
            if columns["std"]:
                for name in _STD:
                    if get[name] is None:
                        raise InputError(f"{_where(path, line)}: the cell in column '{name}' is empty "
                                         f"although the row has values.")
                    if get[name] <= 0:
                        raise InputError(f"{_where(path, line)}: {name} = {get[name]:g} must be positive.")
                std = [get[name] for name in _STD]
        rows.append((line, get["theta_i"], get["theta_o"], get.get("phi_o") or 0.0, values, std))
    if not rows:
        raise InputError(f"{_where(path, header_line)}: the header is not followed by any data row.")

    _check_angles(path, rows)
    _check_duplicates(path, rows)
    kept = [row for row in rows if row[4] is not None]
    if not kept:
        raise InputError(f"{path}: no complete measurement; every row has an empty value cell.")
    values = np.array([row[4] for row in kept], dtype=float)
    if matrix is not None:
        values = values @ matrix
    std = np.array([row[5] for row in kept], dtype=float) if columns["std"] else None
    labels = _RGB if matrix is None else tuple(f"{c} (converted from the spectrum)" for c in _RGB)
    _check_negative(path, [row[0] for row in kept], values, std, quantity, labels)
    return Measurements(
        theta_i=np.array([row[1] for row in kept]),
        theta_o=np.array([row[2] for row in kept]),
        phi_o=np.array([row[3] for row in kept]),
        values=values, std=std, quantity=quantity, metadata=metadata, path=path,
    )


def _split_header(path, lines):
    """Metadata (and the line of each key), the header's line number and its column names."""
    metadata, meta_lines = {}, {}
    for line, text in lines:
        stripped = text.strip()
        if not stripped:
            continue
        if stripped.startswith("#"):
            key, colon, value = stripped[1:].partition(":")
            key = key.strip()
            if colon and key:
                if key in metadata:
                    raise InputError(f"{_where(path, line)}: the metadata key '{key}' repeats line {meta_lines[key]}.")
                metadata[key], meta_lines[key] = value.strip(), line
            continue
        fields = [f.strip() for f in stripped.split(",")]
        if all(_NUMBER.fullmatch(f) for f in re.split(r"[\s,;]+", stripped)):
            raise InputError(f"{_where(path, line)}: no header row; the first row must name the columns, "
                             f"e.g. theta_i,theta_o,r,g,b (convert a raw tab-separated instrument file with 'jaxcos import').")
        if len(fields) == 1 and re.search(r"[\t;]", stripped):
            raise InputError(f"{_where(path, line)}: the header has no commas; columns must be comma-separated, "
                             f"e.g. theta_i,theta_o,r,g,b.")
        return metadata, meta_lines, line, fields
    raise InputError(f"{path}: no header row, only metadata lines; expected a measurement CSV (docs/formats.md).")


def _check_columns(path, line, header):
    """Validate the header; returns the value column names, the wavelengths and whether std is given."""
    where = _where(path, line)
    seen = set()
    wavelengths = []
    for name in header:
        if not name:
            raise InputError(f"{where}: the header has an empty column name.")
        if name in seen:
            raise InputError(f"{where}: the column {_show(name)} appears twice.")
        seen.add(name)
        match = _WAVELENGTH.fullmatch(name)
        if match:
            wavelengths.append(float(match.group(1)))
        elif name.startswith("nm_") and name.endswith("_std"):
            raise InputError(f"{where}: per-wavelength std columns like {_show(name)} are not supported; "
                             f"give r_std,g_std,b_std of the converted linear sRGB instead.")
        elif name not in _KNOWN:
            raise InputError(f"{where}: unknown column {_show(name)}{_suggestion(name)}; expected theta_i, theta_o, "
                             f"optional phi_o, r,g,b or nm_<wavelength> columns, and optional r_std,g_std,b_std.")
    for name in ("theta_i", "theta_o"):
        if name not in seen:
            raise InputError(f"{where}: the column '{name}' is missing.")
    rgb = [c for c in _RGB if c in seen]
    if rgb and wavelengths:
        raise InputError(f"{where}: the header has both r,g,b and spectral nm_ columns; keep one of them.")
    if not rgb and not wavelengths:
        raise InputError(f"{where}: no value columns; expected r,g,b or spectral columns nm_380,nm_390,...")
    if rgb and len(rgb) < 3:
        missing = ", ".join(f"'{c}'" for c in _RGB if c not in seen)
        raise InputError(f"{where}: the column{'s' if len(rgb) == 1 else ''} {missing} "
                         f"{'are' if len(rgb) == 1 else 'is'} missing; r,g,b go together.")
    std = [c for c in _STD if c in seen]
    if std and len(std) < 3:
        missing = " and ".join(f"'{c}'" for c in _STD if c not in seen)
        raise InputError(f"{where}: the header has {' and '.join(repr(c) for c in std)} but not {missing}; "
                         f"give all three std columns or none.")
    if wavelengths:
        for a, b in zip(wavelengths, wavelengths[1:]):
            if b <= a:
                raise InputError(f"{where}: the spectral grid is not increasing: nm_{b:g} follows nm_{a:g}.")
        problem = _grid_problem(np.array(wavelengths))
        if problem:
            raise InputError(f"{where}: unsupported spectral grid; {problem}.")
    values = [name for name in header if _WAVELENGTH.fullmatch(name)] if wavelengths else list(_RGB)
    return {"values": values, "wavelengths": wavelengths or None, "std": bool(std)}


# --- checks shared by both readers ---------------------------------------------------------


def _check_angles(path, rows):
    for line, theta_i, theta_o, phi_o, *_ in rows:
        if not 0.0 <= theta_i < 90.0:
            raise InputError(f"{_where(path, line)}: theta_i = {theta_i:g} is outside [0, 90) degrees.")
        if not -90.0 < theta_o < 90.0:
            raise InputError(f"{_where(path, line)}: theta_o = {theta_o:g} is outside (-90, 90) degrees.")
        if not -180.0 <= phi_o <= 180.0:
            raise InputError(f"{_where(path, line)}: phi_o = {phi_o:g} is outside [-180, 180] degrees.")


def _check_duplicates(path, rows):
    first = {}
    for line, theta_i, theta_o, phi_o, *_ in rows:
        key = (theta_i, theta_o, phi_o)
        if key in first:
            at = f"theta_i = {theta_i:g}, theta_o = {theta_o:g}" + (f", phi_o = {phi_o:g}" if phi_o else "")
            raise InputError(f"{path}, lines {first[key]} and {line}: the same point ({at}) is measured twice.")
        first[key] = line


def _check_negative(path, lines, values, std, quantity, labels):
    if std is not None:
        floor = -3.0 * std
    else:
        floor = np.full_like(values, -NEGATIVE_TOLERANCE * _to_brdf("reflectance_factor") / _to_brdf(quantity))
    bad = np.argwhere(values < floor)
    if bad.size:
        i, c = bad[0]
        rule = (f"-3 * {_STD[c]} = {floor[i, c]:.3g}" if std is not None
                else f"{floor[i, c]:.3g}, the limit for files without std columns")
        raise InputError(f"{_where(path, lines[i])}: {labels[c]} = {values[i, c]:.4g} is negative beyond noise "
                         f"(below {rule}).")


# --- the raw instrument format ---------------------------------------------------------------


def import_raw(path):
    """Read a raw tab-separated instrument file (``shared/data/README.md``) into :class:`Measurements`.

    Each row is ``theta_i theta_o`` (degrees) and 81 reflectance factors at
    380, 385, ..., 780 nm; they are converted to linear sRGB with
    :func:`spectral_to_srgb` under D65. The result has no std, quantity
    ``reflectance_factor`` and metadata naming the source file and the
    conversion. The same checks as :func:`load_measurements` apply.

    Raises:
        InputError: one sentence naming the file, the line and the problem.
    """
    path = os.fspath(path)
    what = "a raw instrument file (theta_i, theta_o and 81 spectral values per row)"
    rows, spectra = [], []
    n = 2 + len(RAW_WAVELENGTHS)
    names = ["theta_i", "theta_o"] + [f"{w:g} nm" for w in RAW_WAVELENGTHS]
    for line, text in _read_lines(path, what):
        cells = text.split()
        if not cells:
            continue
        if "," in text or text.lstrip().startswith("#"):
            raise InputError(f"{_where(path, line)}: a raw file holds only whitespace-separated numbers, "
                             f"but this line has a comma or '#' (a measurement CSV needs no import).")
        if len(cells) != n:
            raise InputError(f"{_where(path, line)}: {len(cells)} values where a raw row has {n} "
                             f"(theta_i, theta_o and 81 spectral values at 380, 385, ..., 780 nm).")
        numbers = [_parse_number(path, line, name, cell) for name, cell in zip(names, cells)]
        rows.append((line, numbers[0], numbers[1], 0.0))
        spectra.append(numbers[2:])
    _check_angles(path, rows)
    _check_duplicates(path, rows)
    values = spectral_to_srgb(RAW_WAVELENGTHS, np.array(spectra))
    labels = tuple(f"{c} (converted from the spectrum)" for c in _RGB)
    _check_negative(path, [row[0] for row in rows], values, None, "reflectance_factor", labels)
    metadata = {
        "quantity": "reflectance_factor",
        "source": os.path.basename(path),
        "illuminant": "D65",
        "conversion": "spectra 380-780 nm, CIE 1931 2 degree observer, D65, colour-science ASTM E308, "
                      "sRGB matrix without chromatic adaptation, flat spectrum 1 -> r = g = b = 1",
    }
    return Measurements(
        theta_i=np.array([row[1] for row in rows]),
        theta_o=np.array([row[2] for row in rows]),
        phi_o=np.zeros(len(rows)),
        values=values, std=None, quantity="reflectance_factor", metadata=metadata, path=path,
    )


# --- writing -----------------------------------------------------------------------------------


def _format(x):
    """Shortest text that reads back as the same float (``20`` rather than ``20.0``)."""
    text = repr(float(x))
    return text[:-2] if text.endswith(".0") else text


def save_measurements(meas, path, *, overwrite=False):
    """Write ``meas`` as the CSV of docs/formats.md (linear sRGB, in ``meas.quantity``).

    The metadata come first, ``# quantity:`` leading; ``phi_o`` is written only
    when a point is out of the plane, the std columns only when ``meas.std``
    is set. Numbers are written exactly (shortest round-trip form). The file
    is written under a temporary name and renamed, so a failure leaves
    nothing half-written.

    Raises:
        InputError: if ``path`` exists and ``overwrite`` is off, or cannot be written.
    """
    path = os.fspath(path)
    if os.path.exists(path) and not overwrite:
        raise InputError(f"{path}: already exists; pass overwrite=True (or --force) to replace it.")
    metadata = {"quantity": meas.quantity, **{k: v for k, v in meas.metadata.items() if k != "quantity"}}
    header = ["theta_i", "theta_o"]
    columns = [meas.theta_i, meas.theta_o]
    if np.any(meas.phi_o != 0):
        header.append("phi_o")
        columns.append(meas.phi_o)
    header += list(_RGB)
    columns += list(meas.values.T)
    if meas.std is not None:
        header += list(_STD)
        columns += list(meas.std.T)
    lines = [f"# {key}: {' '.join(str(value).splitlines())}" for key, value in metadata.items()]
    lines.append(",".join(header))
    lines += [",".join(_format(x) for x in row) for row in zip(*columns)]
    write_text_atomic(path, "\n".join(lines) + "\n")


def write_text_atomic(path, text):
    """Write ``text`` to ``path`` through a temporary file and a rename (complete or absent); returns ``path``.

    Raises:
        InputError: ``path`` cannot be written.
    """
    tmp = f"{path}.tmp"
    try:
        with open(tmp, "w", encoding="utf-8") as fh:
            fh.write(text)
        os.replace(tmp, path)
    except OSError as err:
        if os.path.exists(tmp):
            os.remove(tmp)
        raise InputError(f"{path}: cannot be written ({err.strerror}).") from None
    return path


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


def write_evaluation(path, theta_i, theta_o, phi_o, values, std, *, quantity, overwrite=False):
    """Write the rows of ``jaxcos eval`` (docs/formats.md) atomically; an existing file is kept unless ``overwrite``."""
    path = os.fspath(path)
    refuse_overwrite([path], overwrite)
    with_phi = bool(np.any(phi_o != 0))
    header = "theta_i,theta_o," + ("phi_o," if with_phi else "") + "r,g,b,r_std,g_std,b_std"
    lines = [f"# quantity: {quantity}", header]
    for k in range(len(theta_i)):
        angles = [theta_i[k], theta_o[k]] + ([phi_o[k]] if with_phi else [])
        lines.append(",".join(f"{a:g}" for a in angles) + "," + ",".join(f"{v:.7g}" for v in (*values[k], *std[k])))
    write_text_atomic(path, "\n".join(lines) + "\n")
