"""The physics: phase functions, materials and the random walk (``docs/model.md``).

The lowest layer: it imports nothing else of jaxcos but its errors. Also the Kubelka-Munk
baseline of Huang et al. 2013 (section 6).
"""

from ._interface import Interface
from ._interface import reflection as interface_reflection
from ._material import FIXED, PRODUCTS, VARIANTS, Layer, Material, check_variant, published, with_variant
from ._walk import (
    BUDGETS,
    DEFAULT_BOUNCES,
    DEFAULT_WALKS,
    Estimate,
    Query,
    boundary_probability,
    inplane_bsdf,
    lobe_probabilities,
    make_query,
    resolve_budget,
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
