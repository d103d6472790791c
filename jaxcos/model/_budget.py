"""Monte Carlo budgets: walks per incidence direction and bounces per walk.

The one table of them: the named presets of ``--budget NAME``
(:data:`PRESETS`) and the default budget of each job (the estimator, the
fit, the ablation, the render, the posterior's linearisation). What a budget
buys is measured by ``jaxcos bench accuracy`` (``benchmarks/results/accuracy.md``,
docs/method.md, "Monte Carlo budget"): the error falls as 1/sqrt(walks) at
a cost linear in walks, and 128 bounces leave a truncation bias under 0.1%
(dewy1; 64 bounces: 1%), so bounces beyond 128 buy nothing.

Example::

    from jaxcos.model import FIT_BUDGET, PRESETS, resolve_budget
    walks, bounces = FIT_BUDGET                 # 1024, 128
    resolve_budget("fast", walks=32)            # (32, 64): explicit values win
"""

import dataclasses

from .._errors import InputError


@dataclasses.dataclass(frozen=True)
class Budget:
    """A Monte Carlo budget: ``walks`` per incidence direction, ``bounces`` (scattering events) per walk.

    It unpacks as a pair: ``walks, bounces = budget``.
    """

    walks: int
    bounces: int

    def __iter__(self):
        return iter((self.walks, self.bounces))

    @property
    def pair(self):
        """``(walks, bounces)``."""
        return (self.walks, self.bounces)


PRESETS = {
    "fast": Budget(64, 64),
    "standard": Budget(256, 128),
    "accurate": Budget(1024, 128),
    "paper": Budget(128, 512),
}
"""Named Monte Carlo budgets for ``--budget NAME`` of ``jaxcos fit`` and ``jaxcos eval``.
``accurate`` is the fit's default (:data:`FIT_BUDGET`), ``paper`` the estimator's
(:data:`ESTIMATOR_BUDGET`). ``fast`` is for exploring (Monte Carlo error about twice
the 2% noise of the bundled sets); ``accurate`` costs about 4x ``standard`` in a forward
evaluation for half its Monte Carlo error."""

ESTIMATOR_BUDGET = PRESETS["paper"]
"""The estimator's default (:func:`~jaxcos.simulate`, :func:`~jaxcos.inplane_bsdf`,
``jaxcos eval``): the paper's 128 walks per incidence x 512 bounces per walk, so that
published results reproduce."""

FIT_BUDGET = PRESETS["accurate"]
"""The budget of the objective's value in a fit: 1024 walks x 128 bounces. Under one fixed
key a fit follows the Monte Carlo error of its estimate, which is correlated across the
outgoing angles of an incidence and looks like a change of the parameters; the fit puts the
remaining error into the likelihood and reports it (docs/method.md, "The fit's objective").
Every fit reports the energy its walks left unfinished at 128 bounces (docs/method.md,
"Monte Carlo budget")."""

FIT_JACOBIAN_WALKS = 128
"""Walks of the fit's Jacobian: the first 128 of the objective's own walks (same key; in the later
steps, made by fewer walks, the first of those).
Levenberg-Marquardt needs a good descent direction, not an exact slope; its steps are
accepted on the value (docs/method.md)."""

ABLATION_BUDGET = Budget(128, FIT_BUDGET.bounces)
"""The budget of an ablation's Monte Carlo fits: fewer walks than the fit's default, as an
ablation makes many fits (the fits weight the larger Monte Carlo error into their objective,
as :func:`jaxcos.fit` does), and the fit's bounces (unfinished energy below 0.4% for the
bundled products)."""

RENDER_BUDGET = Budget(256, 64)
"""The budget per grid incidence of a preview (``jaxcos render``). The table shares its walks
over the whole grid, so their error is mostly a common offset of the whole picture: for Dewy 2
at ``t = 1`` over skin, the standard deviation of the BSDF is about 10% at 64 walks and 6% at
256 (of the directional albedo, which only the environment term uses, 12-22% and 6-12%). Over
a skin-coloured base less than 1e-10 of the energy is left after 64 bounces for the four
published products (1e-4 after 32)."""

POSTERIOR_BUDGET = Budget(8192, FIT_BUDGET.bounces)
"""The budget of the posterior's linearisation (``jaxcos uncertainty``): 8192 walks per
incidence for the value ``M_hi(v0)`` and the slopes ``J_hi(v0)`` at the anchor. Its bounces
are the fitted result's own (those of its record), which are the fit's by default."""

JOBS = {
    "estimator": ESTIMATOR_BUDGET,
    "fit": FIT_BUDGET,
    "ablation": ABLATION_BUDGET,
    "render": RENDER_BUDGET,
    "posterior": POSTERIOR_BUDGET,
}
"""The default budget of each job, by name (the entries above)."""

DEFAULT_WALKS = ESTIMATOR_BUDGET.walks
"""Walks per incidence direction of the estimator's default (the paper's budget)."""
DEFAULT_BOUNCES = ESTIMATOR_BUDGET.bounces
"""Scattering events per walk of the estimator's default (the paper's budget)."""
BUDGETS = {name: budget.pair for name, budget in PRESETS.items()}
"""The presets of :data:`PRESETS` as ``(walks, bounces)`` pairs."""


def resolve_budget(name=None, *, walks=None, bounces=None, default=ESTIMATOR_BUDGET):
    """``(walks, bounces)`` of the preset ``name`` of :data:`PRESETS` (``None``: ``default``); explicit values win.

    ``default`` is a :class:`Budget` or a ``(walks, bounces)`` pair.

    Raises:
        InputError: an unknown preset or a budget that is not a positive integer.
    """
    if name is None:
        base = default
    elif name in PRESETS:
        base = PRESETS[name]
    else:
        raise InputError(f"unknown budget {name!r}; choose one of {', '.join(PRESETS)}.")
    base_walks, base_bounces = base
    walks, bounces = (base_walks if walks is None else walks), (base_bounces if bounces is None else bounces)
    for flag, value in (("--walks", walks), ("--bounces", bounces)):
        if int(value) != value or value < 1:
            raise InputError(f"{flag} must be a positive integer, not {value}.")
    return int(walks), int(bounces)
