"""Files in and out: measurements, angle lists, ``params.json`` and the pictures of reflectance tables.

Above :mod:`jaxcos.model`, below inference: it knows the formats of
``docs/formats.md`` and nothing of fitting.
"""

from ._measurements import (
    QUANTITIES,
    Measurements,
    import_raw,
    load_angles,
    load_measurements,
    save_measurements,
    spectral_to_srgb,
    write_evaluation,
    write_text_atomic,
)
from ._params import load_params, material_from_dict, material_to_dict, save_params
from ._plot import cell_edges, default_exposure, draw_reflectance, encode_srgb, plot_measurements
