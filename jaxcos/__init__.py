"""jaxcos: differentiable appearance of cosmetics.

Layered media of Henyey-Greenstein diffusers and SGGX specular platelets
(Lanza et al. 2024), simulated by position-free Monte Carlo random walks in
JAX, differentiable with respect to every material parameter, and fitted to
gonioreflectometer measurements.

Example::

    import jax, jaxcos
    m = jaxcos.published("dewy1")
    f = jaxcos.inplane_bsdf(m, [30.0, 30.0], [-20.0, 34.0], jax.random.key(0))
    f.shape  # (2, 3): the BSDF in 1/sr, linear sRGB
"""

from ._errors import InputError
from ._material import (
    PRODUCTS,
    VARIANTS,
    Layer,
    Material,
    load_params,
    published,
    save_params,
    with_variant,
)

__version__ = "0.1.0"
from ._walk import DEFAULT_BOUNCES, DEFAULT_WALKS, Estimate, Query, inplane_bsdf, lobe_probabilities, make_query, simulate
from ._fit import FitResult, fit
from ._measurements import Measurements, import_raw, load_measurements, save_measurements
from ._report import write_fit
from ._posterior import Posterior, uncertainty, write_uncertainty
from ._ablate import ABLATION_VARIANTS, AblationResult, KubelkaMunk, ablate, fit_kubelka_munk, km_combine, km_invert, km_layer, km_over_background, km_r_inf, write_ablation
from ._render import render
