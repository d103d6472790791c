"""The physics: phase functions, materials and the random walk (``docs/model.md``).

The lowest layer: it imports nothing else of jaxcos but its errors.
"""

from ._material import FIXED, PRODUCTS, VARIANTS, Layer, Material, check_variant, published, with_variant
from ._walk import (
    BUDGETS,
    DEFAULT_BOUNCES,
    DEFAULT_WALKS,
    Estimate,
    Query,
    inplane_bsdf,
    lobe_probabilities,
    make_query,
    resolve_budget,
    simulate,
    single_scattering,
    stack_medium,
)
