"""The ablation: what each part of the model buys, and how it compares with Kubelka-Munk.

Fits every variant on every measurement file, as the ablation of Lanza et al.
2024 (their Figure 6) does, plus the Kubelka-Munk baseline of Huang et al.
2013 (docs/model.md section 6, :func:`jaxcos.fit_kubelka_munk`):

==================  ==========================================================  ==========
variant             what it keeps                                               parameters
==================  ==========================================================  ==========
``diffusers_only``  two Henyey-Greenstein lobes, no platelets (``c_d = 1``)      6
``platelets_only``  SGGX platelets, no diffusers (``c_d = 0``)                   5
``single_lobe``     diffusers with one lobe (``w_g = 1``) and platelets          10
``two_lobe``        the full model                                              12
``kubelka_munk``    KM layer on the substrate + Kelemen/Beckmann/Schlick lobe    8
``V+interface``     ``V`` under a rough top interface (``eta``, ``alpha_s``)      ``V``'s + 2
==================  ==========================================================  ==========

Protocol, per file:

* ``two_lobe`` by :func:`jaxcos.fit` with its default multi-start (the default
  start and ``starts`` others, one of broad tilted platelets and the rest
  random, screened by a short LM at a small budget,
  the ``refine`` best refined besides the default start as it is, the best
  under an independent key kept).
* Each reduced Monte Carlo variant twice: from the two-lobe fit (as in the
  paper; for ``single_lobe`` the lobe asymmetry starts at the two-lobe mean
  cosine ``w_g g1 + (1 - w_g) g2``), and from its own default multi-start
  (screened the same way, its ``reduced_refine`` best refined). The better of
  the two by the chi-square below is kept. Without ``two_lobe`` among the
  variants, only the multi-start is run.
* Nested models: ``single_lobe``, ``diffusers_only`` and ``platelets_only`` are
  special cases of ``two_lobe``, and ``platelets_only`` of ``single_lobe``.
  When a nested variant ends with a lower chi-square than the variant that
  contains it, the larger one is not at its optimum (LM stopped at its step
  limit, or in a worse basin): it is refitted from the nested fit
  (:func:`embed`) and the better result kept.
* ``kubelka_munk`` by :func:`jaxcos.fit_kubelka_munk` (every start refined).

With ``interface=True`` (``jaxcos ablate --interface``) every Monte Carlo
variant ``V`` also has its counterpart with a rough dielectric top interface
(docs/model.md section 3a), ``V+interface``: the same layer and ``eta``,
``alpha_s`` (2 more parameters), listed right after ``V``. An interface with
``eta`` near 1 is a different model from no interface, not a value of it, so
the counterpart is not started at ``eta = 1``: after every index-matched
variant is fitted, each ``V+interface`` is fitted from its own multi-start
(:func:`jaxcos.fit` with ``interface=True``) and from the index-matched fit of
``V`` with the default interface start (``eta = 1.5``, ``alpha_s = 0.1``),
and, for a reduced ``V``, from the ``two_lobe+interface`` fit as above; the
better by the chi-square is kept, and the nesting rule applies among the
interface variants as among the others. The Kubelka-Munk baseline has no
counterpart. AIC and BIC compare all of them alike.

Both fits return results with the same attributes, which is all the
ablation reads: ``material``, ``model`` and ``model_std`` (``None`` for the
deterministic Kubelka-Munk model) and a typed ``record``
(:class:`~jaxcos.inference.FitRecord` or
:class:`~jaxcos.inference.KMFitRecord`) whose loss statistics have the same
attribute names (``loss``, ``l2``, ``rmse``, ``n_params``, ``time_s``).

All Monte Carlo variants use the same budget (``walks``, ``bounces``) and seed,
so the comparison is like for like. Fits of one variant on files of one shape
share compiled code: files with std columns are padded to a common shape (see
:func:`pad_measurements`).

Statistics, per file and variant (``n`` = points x 3 residuals, ``k`` = fitted parameters):

* ``l2``: the paper's metric, sum of squared differences in the file's quantity; ``rmse``.
* ``chi2 = sum ((model - measured) / std)^2`` with the file's std; the Gaussian
  log-likelihood ``-2 ln L = chi2 + sum ln(2 pi std^2)``, ``aic = -2 ln L + 2 k``,
  ``bic = -2 ln L + k ln n``. The model's own Monte Carlo error counts as misfit.
  Without std columns the variance is estimated by maximum likelihood:
  ``-2 ln L = n (ln(2 pi RSS / n) + 1)`` and ``k + 1`` parameters.
* ``delta_e2000``: the mean CIEDE2000 difference between measured and fitted
  colours: linear sRGB reflectance factors times ``exposure`` (default 1, so a
  perfect white diffuser has ``Y = 1``, ``L* = 100``) to CIE XYZ (sRGB primaries,
  D65), to CIELAB with the D65 white point (CIE 1931 2 degree observer).

Example::

    import jaxcos
    result = jaxcos.ablate(["measurements/matte2.csv"], variants=["single_lobe", "two_lobe", "kubelka_munk"])
    jaxcos.write_ablation(result, "out/ablation")
"""

import dataclasses
import math
import os
import time

import equinox as eqx
import numpy as np

from .._errors import InputError
from ..io import Measurements, load_measurements
from ..model import ABLATION_BUDGET, with_variant
from ._fit import check_determined, fit, fit_statistics, parameterization
from ._kubelka_munk import KM_N_PARAMS, fit_kubelka_munk

ABLATION_VARIANTS = ("diffusers_only", "platelets_only", "single_lobe", "two_lobe", "kubelka_munk")
"""The variants of an ablation, in the order of its table and figure."""
REDUCED = ("diffusers_only", "platelets_only", "single_lobe")
"""Monte Carlo variants that also start from the two-lobe fit."""
INTERFACE_SUFFIX = "+interface"
"""Appended to a Monte Carlo variant's name for its counterpart with a top interface (``two_lobe+interface``)."""

ABLATION_WALKS = ABLATION_BUDGET.walks
"""Walks per incidence in an ablation's Monte Carlo fits (:data:`jaxcos.model.ABLATION_BUDGET`)."""
ABLATION_BOUNCES = ABLATION_BUDGET.bounces
"""Bounces per walk in an ablation's Monte Carlo fits (:data:`jaxcos.model.ABLATION_BUDGET`)."""
CSV_COLUMNS = ("file", "variant", "l2", "rmse", "delta_e2000", "n_params", "aic", "bic", "time_s", "chi2",
               "reduced_chi2", "n_points", "loss", "start", "walks", "bounces", "seed")
"""Keys of each row of an ablation, the columns of ``ablation.csv`` (docs/formats.md requires the first nine)."""


# --- variants ---------------------------------------------------------------------------


def check_variants(variants):
    """The variants as a tuple in the order of :data:`ABLATION_VARIANTS`; a string may list them with commas.

    Raises:
        InputError: an unknown or repeated variant, or none at all.
    """
    if isinstance(variants, str):
        variants = [v for part in variants.replace(",", " ").split() for v in [part.strip()] if v]
    variants = list(variants)
    if not variants:
        raise InputError(f"no variant given; choose from {', '.join(ABLATION_VARIANTS)}.")
    for v in variants:
        if v.endswith(INTERFACE_SUFFIX) and v[:-len(INTERFACE_SUFFIX)] in ABLATION_VARIANTS:
            raise InputError(f"variant {v!r}: ask for the interface with --interface (interface=True), which adds "
                             "the counterpart with a top interface of every Monte Carlo variant.")
        if v not in ABLATION_VARIANTS:
            raise InputError(f"unknown variant {v!r}; choose from {', '.join(ABLATION_VARIANTS)}.")
        if variants.count(v) > 1:
            raise InputError(f"variant {v!r} is given twice.")
    return tuple(v for v in ABLATION_VARIANTS if v in variants)


def with_interface_variants(variants):
    """``variants`` with each Monte Carlo variant followed by its counterpart with a top interface.

    ``("single_lobe", "two_lobe", "kubelka_munk")`` becomes ``("single_lobe",
    "single_lobe+interface", "two_lobe", "two_lobe+interface", "kubelka_munk")``.
    """
    return tuple(name for v in variants
                 for name in ((v,) if v == "kubelka_munk" else (v, v + INTERFACE_SUFFIX)))


def split_variant(name):
    """``(variant, interface)`` of an ablation variant's name: ``"two_lobe+interface"`` gives ``("two_lobe", True)``."""
    if name.endswith(INTERFACE_SUFFIX):
        return name[:-len(INTERFACE_SUFFIX)], True
    return name, False


NESTED = {"two_lobe": ("single_lobe", "diffusers_only", "platelets_only"), "single_lobe": ("platelets_only",)}
"""Variants whose models are special cases of another's (``w_g = 1``, ``c_d = 1``, ``c_d = 0``).

The same holds among the interface counterparts (``single_lobe+interface`` in
``two_lobe+interface``, ...); and each ``V+interface`` is started from ``V``'s fit
with the default interface (module docstring)."""


def embed(material, variant, reference):
    """A start for ``variant`` that reproduces the nested fit ``material``; other parts come from ``reference``.

    From ``single_lobe`` to ``two_lobe``: both lobes get ``g1`` and ``w_g = 1/2``
    (the same phase function, with ``w_g`` away from its saturated end). From
    ``diffusers_only`` (``platelets_only``): ``c_d = 0.97`` (``0.03``) and the
    platelet (diffuser) parameters of ``reference``, a fit of ``variant``.
    """
    sub, ref = material.layers[0], reference.layers[0]
    if material.variant == "single_lobe":
        layer = eqx.tree_at(lambda l: (l.g2, l.w_g), sub, (sub.g1, sub.w_g * 0 + 0.5))
    elif material.variant == "diffusers_only":
        layer = eqx.tree_at(lambda l: (l.c_d, l.albedo_p, l.alpha_p, l.theta_p, l.phi_p), sub,
                            (sub.c_d * 0 + 0.97, ref.albedo_p, ref.alpha_p, ref.theta_p, ref.phi_p))
    elif material.variant == "platelets_only":
        layer = eqx.tree_at(lambda l: (l.c_d, l.albedo_d, l.g1, l.g2, l.w_g), sub,
                            (sub.c_d * 0 + 0.03, ref.albedo_d, ref.g1, ref.g2, ref.w_g))
    else:
        raise ValueError(f"{material.variant} is not nested in another variant")
    return with_variant(dataclasses.replace(material, layers=(layer,), variant=variant), variant)


def _score(meas, result):
    """What "better" means when two fits of one variant compete: chi-square with the file's std, else L2."""
    chi2 = information_criteria(meas, result.model, result.record.n_params)[0]
    return result.record.l2 if math.isnan(chi2) else chi2


def n_params(variant):
    """Number of fitted parameters of an ablation variant (``V+interface``: ``V``'s and ``eta``, ``alpha_s``)."""
    variant, interface = split_variant(variant)
    if variant == "kubelka_munk" and not interface:
        return KM_N_PARAMS
    return parameterization(variant, interface=interface).size


def start_from_two_lobe(material, variant):
    """The start of a reduced ``variant`` taken from a two-lobe fit ``material`` (the paper's protocol).

    The parts the variant keeps take the two-lobe values; ``single_lobe``
    takes the mean cosine ``w_g g1 + (1 - w_g) g2`` of the two lobes as its ``g1``.
    """
    layer = material.layers[0]
    if variant == "single_lobe":
        g = layer.w_g * layer.g1 + (1.0 - layer.w_g) * layer.g2
        material = dataclasses.replace(material, layers=(eqx.tree_at(lambda l: l.g1, layer, g),))
    return with_variant(material, variant)


# --- padding to a common shape -----------------------------------------------------------


def _rows(meas):
    values, counts = np.unique(meas.theta_i, return_counts=True)
    return values, counts


def _common_shape(group):
    """``(incidences, widest row, points)`` that every file of ``group`` can be padded to."""
    shapes = [(len(c), int(c.max()), m.n_points) for m in group for _, c in [_rows(m)]]
    n_inc = max(s[0] for s in shapes)
    width = max(s[1] for s in shapes)
    points = max(n + (width - w) + (n_inc - i) for i, w, n in shapes)
    return n_inc, width, points


def pad_measurements(meas, shape):
    """``meas`` with dummy points appended so that its walks and arrays have ``shape``.

    ``shape = (incidences, widest row, points)``. The fit groups points by
    incidence and pads every row to the widest; two files give the same
    array shapes, and so share compiled code, when these three numbers agree.
    Dummy points carry value 0 and an infinite std: their residuals and
    Jacobian rows are exactly 0, so the objective and its minimum are those of
    the real points. New incidences are placed at angles the file lacks,
    counting down from 85 degrees. The real points keep their order and come
    first. Only files with std columns can be padded.
    """
    n_inc, width, points = shape
    angles, counts = _rows(meas)
    if meas.std is None:
        raise ValueError("only a file with std columns can be padded")
    if len(angles) > n_inc or counts.max() > width or meas.n_points > points:
        raise ValueError(f"{meas.path} does not fit in the shape {shape}")
    new = [a for a in np.arange(85.0, -1.0, -1.0) if a not in angles][: n_inc - len(angles)]
    fill = {float(a): int(c) for a, c in zip(angles, counts)}
    fill.update({float(a): 0 for a in new})
    extra = []

    def add(angle, k):
        extra.extend([angle] * k)
        fill[angle] += k

    for a in new:
        add(float(a), 1)
    widest = max(fill, key=lambda a: fill[a])
    add(widest, width - fill[widest])
    left = points - meas.n_points - len(extra)
    for a in fill:
        k = min(left, width - fill[a])
        add(a, k)
        left -= k
    if left:
        raise ValueError(f"{meas.path} does not fit in the shape {shape}")
    k = len(extra)
    return dataclasses.replace(
        meas,
        theta_i=np.concatenate([meas.theta_i, extra]),
        theta_o=np.concatenate([meas.theta_o, np.zeros(k)]),
        phi_o=np.concatenate([meas.phi_o, np.zeros(k)]),
        values=np.concatenate([meas.values, np.zeros((k, 3))]),
        std=np.concatenate([meas.std, np.full((k, 3), np.inf)]),
    )


# --- statistics --------------------------------------------------------------------------


def information_criteria(meas, model, k):
    """``(chi2, aic, bic)`` of a fitted ``model`` (``(N, 3)``, file's quantity) with ``k`` parameters (module docstring)."""
    resid = np.asarray(model, float) - meas.values
    n = resid.size
    if meas.std is not None:
        chi2 = float(np.sum((resid / meas.std) ** 2))
        m2ll = chi2 + float(np.sum(np.log(2 * np.pi * meas.std ** 2)))
    else:
        rss = float(np.sum(resid ** 2))
        chi2 = float("nan")
        m2ll = n * (math.log(2 * math.pi * max(rss, 1e-300) / n) + 1.0)
        k = k + 1
    return chi2, m2ll + 2 * k, m2ll + k * math.log(n)


def mean_delta_e2000(measured, model, quantity="reflectance_factor", exposure=1.0):
    """Mean CIEDE2000 difference between two ``(N, 3)`` linear sRGB tables (module docstring).

    Values in ``quantity`` are first turned into reflectance factors, then
    multiplied by ``exposure``.
    """
    import colour

    to_rf = math.pi if quantity == "brdf" else 1.0
    space = colour.RGB_COLOURSPACES["sRGB"]
    lab = [colour.XYZ_to_Lab(colour.RGB_to_XYZ(np.asarray(v, float) * to_rf * exposure, space), space.whitepoint)
           for v in (measured, model)]
    return float(np.mean(colour.delta_E(lab[0], lab[1], method="CIE 2000")))


# --- the ablation -----------------------------------------------------------------------


@dataclasses.dataclass
class AblationResult:
    """The outcome of :func:`ablate`.

    Attributes:
        rows: one dict per file and variant with the columns of :data:`CSV_COLUMNS`.
        fits: ``{(file index, variant): FitResult or KMFitResult}``, the kept fits (the same attributes).
        measurements: the measurement tables, in order.
        names: the file names used in the table.
        variants: the variants fitted, in table order (with ``interface``, each Monte
            Carlo variant followed by its ``+interface`` counterpart).
        settings: budget, seed, starts, exposure, interface, finer, padding and total time.
    """

    rows: list
    fits: dict
    measurements: list
    names: list
    variants: tuple
    settings: dict


def _load(item):
    """``(measurements, name)`` of a measurement table or of the path of its file."""
    if isinstance(item, Measurements):
        return item, item.path or "measurements"
    if isinstance(item, (str, os.PathLike)):
        return load_measurements(item), os.fspath(item)
    raise InputError(f"expected a measurement file or Measurements, not {type(item).__name__}.")


def _load_average():
    """The 1-minute load average of the machine (``None`` where the system does not say)."""
    try:
        return round(os.getloadavg()[0], 2)
    except (AttributeError, OSError):
        return None


def _real(result, meas):
    """A fit of a padded file cut back to the file's real points (they come first), its statistics redone."""
    n = meas.n_points
    if result.model.shape[0] == n:
        return result
    stats = fit_statistics(meas, result.model[:n], result.record.loss, result.record.n_params)
    cut = dict(model=result.model[:n])
    if result.model_std is not None:
        cut["model_std"] = result.model_std[:n]
        stats["mc_error_median"] = float(np.median(cut["model_std"] / (meas.std if meas.std is not None else 1.0)))
    return dataclasses.replace(result, record=dataclasses.replace(result.record, **stats), **cut)


def ablate(measurements_list, variants=ABLATION_VARIANTS, *, seed=0, walks=ABLATION_WALKS, bounces=ABLATION_BOUNCES,
           starts=15, refine=1, reduced_refine=1, exposure=1.0, interface=False, finer=True, share_compiled=True,
           progress=None):
    """Fit every variant on every file and compare them (module docstring).

    Args:
        measurements_list: paths of measurement CSVs, or :class:`~jaxcos.Measurements`.
        variants: a subset of :data:`ABLATION_VARIANTS` (or a comma-separated string).
        seed: seeds every fit's Monte Carlo key and random starts.
        walks, bounces: the Monte Carlo budget of every Monte Carlo variant.
        starts: starts screened besides the default one, per multi-start (one of broad tilted
            platelets, the rest random: :func:`jaxcos.fit`).
        refine: screened starts refined for ``two_lobe``.
        reduced_refine: screened starts refined for each reduced variant's own
            multi-start (the start from the two-lobe fit is refined besides).
        exposure: scale of the reflectance factors before the CIEDE2000 colours.
        interface: also fit each Monte Carlo variant with a rough dielectric top
            interface (``V+interface``, 2 more parameters; module docstring).
        finer: each fit's last refinement at four times the walks, where its
            objective is rough (:func:`jaxcos.fit`); ``False`` skips it.
        share_compiled: pad files with std columns to a common shape so that
            their fits share compiled code.
        progress: a callable ``progress(message)`` (default: none).

    Returns:
        An :class:`AblationResult`.

    Raises:
        InputError: bad files, variants or settings (one sentence naming the problem).
    """
    variants = check_variants(variants)
    for flag, value in (("walks", walks), ("bounces", bounces), ("refine", refine), ("reduced_refine", reduced_refine)):
        if isinstance(value, bool) or int(value) != value or value < 1:
            raise InputError(f"{flag} must be a positive integer, not {value}.")
    if isinstance(starts, bool) or int(starts) != starts or starts < 0:
        raise InputError(f"starts must be a non-negative integer, not {starts}.")
    if not (isinstance(exposure, (int, float)) and math.isfinite(exposure) and exposure > 0):
        raise InputError(f"exposure must be a positive number, not {exposure}.")
    if not isinstance(interface, (bool, np.bool_)):
        raise InputError(f"interface must be True or False, not {interface!r}.")
    interface = bool(interface)
    table = with_interface_variants(variants) if interface else variants
    items = list(measurements_list) if not isinstance(measurements_list, (str, os.PathLike)) else [measurements_list]
    if not items:
        raise InputError("no measurement file given.")
    loaded = [_load(item) for item in items]
    names = [name for _, name in loaded]
    for name in names:
        if names.count(name) > 1:
            raise InputError(f"{name}: the file is given twice.")
    measurements = [m for m, _ in loaded]
    for meas in measurements:  # before any fit: each variant needs more values than parameters
        for entry in table:
            check_determined(meas, n_params(entry), entry, "--variants")
    say = progress or (lambda msg: None)
    t_start = time.perf_counter()
    load_start = _load_average()

    padded = list(measurements)
    shape = None
    with_std = [m for m in measurements if m.std is not None]
    if share_compiled and len(with_std) > 1:
        shape = _common_shape(with_std)
        padded = [pad_measurements(m, shape) if m.std is not None else m for m in measurements]
        say(f"padding {len(with_std)} files to {shape[0]} incidences x {shape[1]} outgoing directions "
            f"({shape[2]} points) so that each variant compiles once")

    rows, fits = [], {}
    budget = dict(seed=seed, walks=int(walks), bounces=int(bounces))
    for index, (meas, name) in enumerate(zip(measurements, names)):
        base = os.path.basename(name)
        kept, times = {}, {}  # variant -> (score, start label, result); variant -> seconds

        def attempt(entry, label, **options):
            tell = lambda msg: say(f"{base} {entry}: {msg}")
            tell(f"fitting from the {label}")
            t0 = time.perf_counter()
            variant, top = split_variant(entry)
            r = _real(fit(padded[index], variant=variant, interface=top, finer=finer, progress=tell, **budget,
                             **options), meas)
            times[entry] = times.get(entry, 0.0) + time.perf_counter() - t0
            score = _score(meas, r)
            if entry not in kept or score < kept[entry][0]:
                kept[entry] = (score, label, r)

        # the index-matched variants, then (interface=True) their counterparts with a top interface
        for suffix in ("", INTERFACE_SUFFIX) if interface else ("",):
            for variant in [v for v in ("two_lobe",) + REDUCED if v in variants]:
                multi = dict(starts=starts, refine=refine if variant == "two_lobe" else reduced_refine)
                attempt(variant + suffix, "multi-start", **multi)
                if suffix:  # the index-matched fit with the default interface (fit's start for a missing one)
                    attempt(variant + suffix, "index-matched fit", start=kept[variant][2].material)
                if variant in REDUCED and "two_lobe" + suffix in kept:
                    attempt(variant + suffix, "two-lobe fit",
                            start=start_from_two_lobe(kept["two_lobe" + suffix][2].material, variant))
            for outer in ("single_lobe", "two_lobe"):
                for inner in NESTED.get(outer, ()):
                    o, i = outer + suffix, inner + suffix
                    if o in kept and i in kept and kept[i][0] < kept[o][0]:
                        say(f"{base} {o}: the nested {i} fits better; refitting {o} from it")
                        attempt(o, f"{i} fit", start=embed(kept[i][2].material, outer, kept[o][2].material))
        if "kubelka_munk" in variants:
            t0 = time.perf_counter()
            r = _real(fit_kubelka_munk(padded[index], seed=seed, starts=starts,
                                       progress=lambda msg: say(f"{base} kubelka_munk: {msg}")), meas)
            times["kubelka_munk"] = time.perf_counter() - t0
            kept["kubelka_munk"] = (_score(meas, r), "multi-start", r)
        for variant in table:
            _, label, result = kept[variant]
            record = result.record
            chi2, aic, bic = information_criteria(meas, result.model, record.n_params)
            dof = max(meas.values.size - record.n_params, 1)
            rows.append(dict(
                file=name, variant=variant, l2=record.l2, rmse=record.rmse,
                delta_e2000=mean_delta_e2000(meas.values, result.model, meas.quantity, exposure),
                n_params=record.n_params, aic=aic, bic=bic, time_s=round(times[variant], 2), chi2=chi2,
                reduced_chi2=chi2 / dof, n_points=meas.n_points, loss=record.loss, start=label,
                walks=budget["walks"] if variant != "kubelka_munk" else "",
                bounces=budget["bounces"] if variant != "kubelka_munk" else "", seed=seed,
            ))
            fits[(index, variant)] = result
            say(f"{base} {variant}: L2 {record.l2:.4g}, BIC {bic:.1f} ({times[variant]:.1f} s, kept the {label})")
    settings = dict(seed=int(seed), walks=int(walks), bounces=int(bounces), starts=int(starts), refine=int(refine),
                    reduced_refine=int(reduced_refine), exposure=float(exposure), interface=interface, finer=bool(finer),
                    padded_shape=shape, total_time_s=round(time.perf_counter() - t_start, 1),
                    load_average=(load_start, _load_average()))
    return AblationResult(rows=rows, fits=fits, measurements=measurements, names=names, variants=table,
                          settings=settings)
