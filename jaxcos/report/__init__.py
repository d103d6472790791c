"""Reports and figures of fits, posteriors, ablations and benchmarks (Markdown, PNG, CSV, JSON)."""

from ._fit import FIT_FILES, write_fit
