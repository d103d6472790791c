"""jaxcos: differentiable appearance of cosmetics.

Layered media of Henyey-Greenstein diffusers and SGGX specular platelets
(Lanza et al. 2024), simulated by position-free Monte Carlo random walks in
JAX, differentiable with respect to every material parameter, and fitted to
gonioreflectometer measurements.

The package is layered, each layer importing only those below it:
:mod:`jaxcos.model` (physics), :mod:`jaxcos.io` (files),
:mod:`jaxcos.render` (previews), :mod:`jaxcos.inference` (fits, posteriors,
ablation), :mod:`jaxcos.report` (reports and figures) and :mod:`jaxcos.cli`.

Example::

    import jax, jaxcos
    m = jaxcos.published("dewy1")
    f = jaxcos.inplane_bsdf(m, [30.0, 30.0], [-20.0, 34.0], jax.random.key(0))
    f.shape  # (2, 3): the BSDF in 1/sr, linear sRGB
"""

__version__ = "0.1.0"

from ._errors import InputError
from .model import (
    BUDGETS,
    DEFAULT_BOUNCES,
    DEFAULT_WALKS,
    PRODUCTS,
    VARIANTS,
    Estimate,
    Interface,
    Layer,
    Material,
    Query,
    inplane_bsdf,
    lobe_probabilities,
    make_query,
    published,
    simulate,
    with_variant,
)
from .io import Measurements, import_raw, load_angles, load_measurements, load_params, save_measurements, save_params
from .render import render
from .model import KubelkaMunk, km_combine, km_invert, km_layer, km_over_background, km_r_inf
from .inference import (
    ABLATION_VARIANTS,
    AblationResult,
    FitRecord,
    FitResult,
    NoiseModel,
    Posterior,
    PosteriorRecord,
    ablate,
    fit,
    fit_kubelka_munk,
    uncertainty,
)
from .report import write_ablation, write_fit, write_uncertainty
