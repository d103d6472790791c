"""Fitting, posteriors, ablation and the accuracy benchmark: the model against measurements."""

from ._fit import FIT_BOUNCES, FIT_JACOBIAN_WALKS, FIT_WALKS, FitResult, fit, make_problem, parameterization
from ._posterior import Posterior, uncertainty
from ._ablate import ABLATION_VARIANTS, AblationResult, ablate
from ._kubelka_munk import KubelkaMunk, fit_kubelka_munk, km_combine, km_invert, km_layer, km_over_background, km_r_inf
