"""Fitting, posteriors, ablation and the accuracy benchmark: the model against measurements."""

from ._fit import (
    FIT_BOUNCES,
    FIT_JACOBIAN_WALKS,
    FIT_WALKS,
    Budget,
    CheckResult,
    FinalStep,
    FinerStage,
    FitBudget,
    FitRecord,
    FitResult,
    FitSummary,
    GlossGrowth,
    WeightedLeastSquares,
    fit,
    gloss_growth,
    make_problem,
    parameterization,
)
from ._posterior import (
    CHAIN_TAUS,
    MAX_STEPS,
    WALKERS,
    NoiseModel,
    Posterior,
    PosteriorRecord,
    estimate_noise,
    uncertainty,
)
from ._ablate import ABLATION_BOUNCES, ABLATION_VARIANTS, ABLATION_WALKS, CSV_COLUMNS, AblationResult, ablate, check_variants
from ._kubelka_munk import KM_N_PARAMS, KMFitRecord, KMFitResult, fit_kubelka_munk
from ._bench import accuracy_benchmark, bsdf_problem
