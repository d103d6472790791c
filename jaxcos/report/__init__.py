"""Reports and figures of fits, posteriors, ablations and benchmarks (Markdown, PNG, CSV, JSON)."""

from ._fit import FIT_FILES, LossSplit, body_hint, gloss_hint, loss_split, write_fit
from ._posterior import UNCERTAINTY_FILES, uncertainty_report, write_uncertainty
from ._bench import ACCURACY_FILES, write_accuracy
from ._ablate import ABLATION_FILES, write_ablation
