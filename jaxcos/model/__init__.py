"""The physics: phase functions, materials, their parameter ranges, the random walk and its budgets (``docs/model.md``).

The lowest layer: it imports nothing else of jaxcos but its errors. Also the Kubelka-Munk
baseline of Huang et al. 2013 (section 6).
"""

from ._interface import Interface
from ._interface import reflection as interface_reflection
from ._material import FIXED, PRODUCTS, VARIANTS, Layer, Material, check_variant, published, with_variant
from ._budget import (
    ABLATION_BUDGET,
    BUDGETS,
    DEFAULT_BOUNCES,
    DEFAULT_WALKS,
    ESTIMATOR_BUDGET,
    FIT_BUDGET,
    FIT_JACOBIAN_WALKS,
    JOBS,
    POSTERIOR_BUDGET,
    PRESETS,
    RENDER_BUDGET,
    Budget,
    resolve_budget,
)
from ._ranges import BASE_ALBEDO_RANGE, INTERFACE_RANGES, LAYER_RANGES, PHI_RANGE, RANGES, Range
from ._walk import (
    THIN_AFTER,
    Estimate,
    Query,
    boundary_probability,
    inplane_bsdf,
    lobe_probabilities,
    make_query,
    simulate,
    single_scattering,
    stack_medium,
)
from ._kubelka_munk import (
    KubelkaMunk,
    beckmann,
    directions,
    kelemen_specular,
    km_combine,
    km_invert,
    km_layer,
    km_over_background,
    km_r_inf,
    km_remission,
    schlick,
)
