"""Tests of the derivative estimator (docs/derivatives.md).

1. Every array leaf has a finite, non-zero derivative through ``jax.grad``,
   ``jax.jvp`` and ``jax.jacfwd`` of :func:`jaxcos.inplane_bsdf`, and the three
   agree under one key.
2. Unbiasedness: the mean over keys of the AD derivative of a scalar functional
   agrees with a central finite difference (common random numbers, lobe
   probabilities fixed) within 3 combined standard errors, for dewy1, matte2
   and a Lambertian base.
3. Common random numbers: along 1-D scans under one key the estimate has no
   jump. For the parameters that enter only weights and flight lengths, every
   step of an 81-point scan is predicted by the AD derivative to within 0.25
   standard errors; a negative control (lobe probabilities recomputed at every
   point) shows that this check catches jumps. For the parameters that move
   sampled directions (g1, g2, alpha_p, theta_p, phi_p) the scans have steep
   continuous features narrower than their step; refining the worst interval
   10^6-fold shows it continuous (no step above 0.25 SE).
4. Finite everywhere: no NaN or inf in any value or Jacobian over the hard
   cases, all four variants, black and Lambertian bases.

Every tolerance is derived from float32 rounding or from standard errors
estimated from the same data, never tuned; the keys are fixed. Results
(z-scores, jump fractions) are printed: run with ``-s`` to see them.

Budgets are small (walks 8-16, bounces 16-64): statistical power comes from
many keys in one vectorised call. Compilation dominates (about 10 s per
vmapped JVP program and 40 s for reverse mode on two cores), so each program
is compiled once (``functools.lru_cache``) and fed batches of one fixed size.
"""

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.flatten_util import ravel_pytree

import jaxcos

# --- a flat parameter vector for one-layer materials ----------------------------------

NAMES = ("t", "c_d", "albedo_d0", "albedo_d1", "albedo_d2", "g1", "g2", "w_g", "albedo_p0", "albedo_p1",
         "albedo_p2", "alpha_p", "theta_p", "phi_p", "base0", "base1", "base2")
IDX = {n: i for i, n in enumerate(NAMES)}
DTYPE = np.float32


def _vec(material):
    """The 17 parameters of a one-layer material (zeros for a black base's albedo)."""
    l = material.layers[0]
    base = np.zeros(3) if material.base_albedo is None else np.asarray(material.base_albedo)
    return np.concatenate([[l.t, l.c_d], l.albedo_d, [l.g1, l.g2, l.w_g], l.albedo_p,
                           [l.alpha_p, l.theta_p, l.phi_p], base]).astype(DTYPE)


def _material(v, lambertian, variant="two_lobe"):
    layer = jaxcos.Layer(t=v[0], c_d=v[1], albedo_d=v[2:5], g1=v[5], g2=v[6], w_g=v[7], albedo_p=v[8:11],
                         alpha_p=v[11], theta_p=v[12], phi_p=v[13])
    return jaxcos.Material(layers=(layer,), base_albedo=v[14:17] if lambertian else None, variant=variant)


def _with(material, **changes):
    layer = eqx.tree_at(lambda l: [getattr(l, k) for k in changes], material.layers[0],
                        [jnp.asarray(v, jnp.result_type(float)) for v in changes.values()])
    return eqx.tree_at(lambda m: m.layers, material, (layer,))


# --- the batched estimator of tests 2 and 3 ---------------------------------------------

# Six pairs: two incidences, the mirror-ish direction of dewy1's tilted platelets
# (17 and 47 degrees), back scattering and a grazing exit.
TI = [15.0, 15.0, 15.0, 45.0, 45.0, 45.0]
TO = [-40.0, 17.0, 35.0, -10.0, 47.0, 65.0]
QUERY = jaxcos.make_query(TI, TO)
WALKS = 16  # small on purpose: power comes from many keys; see test 3 for why 16
BOUNCES = 64
THIN_AFTER = 4  # the later steps by fewer walks: steps 0-3 all 16 walks, then the first 8 (two chunks, then one)
CHUNK = 512  # every call gets this batch size, so each program compiles once


@functools.lru_cache(maxsize=None)
def _batched(lambertian, detached, connection="nee"):
    """``jit(vmap)`` of (f, stderr, df) at parameters ``v``, tangent ``dv``, lobe probabilities, key and
    (``detached``) the parameters ``ref`` of the material whose lobes draw the directions."""

    def one(v, dv, lp, key, ref):
        def est(v):
            e = jaxcos.simulate(_material(v, lambertian), QUERY, key, walks=WALKS, bounces=BOUNCES, lobe_probs=lp,
                                sampling=_material(ref, lambertian) if detached else None, connection=connection,
                                thin_after=THIN_AFTER)
            return e.f, e.stderr

        (f, se), (df, _) = jax.jvp(est, (v,), (dv,))
        return f, se, df

    return jax.jit(jax.vmap(one))


def _run(lambertian, v, dv, lp, keys, ref=None, connection="nee"):
    """Evaluate a batch of any size in padded chunks of ``CHUNK``: (f, stderr, df), each ``(n, 6, 3)``.

    ``ref``: per row, the parameters of a fixed material whose lobes draw the directions (detached
    sampling); by default each row's own lobes draw them (attached).
    """
    n = len(v)
    detached = ref is not None
    v, dv, lp, ref = (np.asarray(a, DTYPE) for a in (v, dv, lp, v if ref is None else ref))
    out = []
    for a in range(0, n, CHUNK):
        idx = np.minimum(np.arange(a, a + CHUNK), n - 1)
        res = _batched(lambertian, detached, connection)(v[idx], dv[idx], lp[idx], keys[jnp.asarray(idx)], ref[idx])
        out.append([np.asarray(r)[: min(CHUNK, n - a)] for r in res])
    return tuple(np.concatenate([o[i] for o in out]) for i in range(3))


def _lobe_probs(v, lambertian):
    return np.asarray(jaxcos.lobe_probabilities(_material(jnp.asarray(v), lambertian)))


# --- 1. grad, jvp and jacfwd agree ---------------------------------------------------------

# A query with the hard angles of test 4 (normal incidence, the mirror direction
# and its opposite, grazing 89.9 degrees), shared with test 4 so that the
# jacfwd program compiles once.
HARD_TI = [0.0, 30.0, 30.0, 60.0, 89.9, 89.9]
HARD_TO = [0.0, 30.0, -30.0, 89.9, 89.9, -89.9]
HARD_WALKS, HARD_BOUNCES = 8, 16
WEIGHTS = jnp.asarray(np.random.default_rng(0).uniform(0.5, 1.5, (len(HARD_TI), 3)), jnp.result_type(float))


def _bsdf(m, key, connection="nee"):
    return jaxcos.inplane_bsdf(m, HARD_TI, HARD_TO, key, walks=HARD_WALKS, bounces=HARD_BOUNCES, connection=connection)


@functools.lru_cache(maxsize=None)
def _value_and_jacobian(variant, lambertian, connection="nee"):
    """Compiled ``(f, jax.jacfwd(f))`` for one structure; variant, base and connection decide the program."""
    del variant, lambertian  # the cache key: one compiled program per structure
    bsdf = lambda m, key: _bsdf(m, key, connection)
    return eqx.filter_jit(lambda m, key: (bsdf(m, key), jax.jacfwd(bsdf)(m, key)))


def _generic():
    """A material where every leaf matters: two lobes, platelets tilted out of the plane, thin, Lambertian base."""
    layer = jaxcos.Layer(t=2.0, c_d=0.6, albedo_d=(0.9, 0.8, 0.7), g1=0.5, g2=-0.3, w_g=0.6,
                         albedo_p=(0.85, 0.8, 0.75), alpha_p=0.2, theta_p=10.0, phi_p=20.0)
    return jaxcos.Material(layers=(layer,), base_albedo=(0.6, 0.5, 0.4))


@pytest.mark.slow
def test_grad_jvp_jacfwd_agree():
    m, key = _generic(), jax.random.key(11)
    scalar = lambda m, key: jnp.sum(WEIGHTS * _bsdf(m, key))
    grad = eqx.filter_jit(jax.grad(scalar))(m, key)
    f, jac = _value_and_jacobian("two_lobe", True, "nee")(m, key)
    from_jac = jax.tree.map(lambda j: jnp.tensordot(WEIGHTS, j, axes=2), jac)
    flat, unravel = ravel_pytree(m)
    jvp = eqx.filter_jit(lambda m, tangent, key: jax.jvp(lambda mm: scalar(mm, key), (m,), (tangent,))[1])
    by_jvp = np.array([jvp(m, unravel(jnp.zeros_like(flat).at[i].set(1.0)), key) for i in range(flat.size)])
    g, j = np.asarray(ravel_pytree(grad)[0]), np.asarray(ravel_pytree(from_jac)[0])
    assert g.size == 17 and np.all(np.isfinite(f))
    assert np.all(np.isfinite(g)) and np.all(np.isfinite(j)) and np.all(np.isfinite(by_jvp))
    # Exists: with a thin layer, a Lambertian base, two lobes and a tilted flake, no leaf is idle.
    assert np.all(g != 0.0), f"zero derivative for leaves {np.flatnonzero(g == 0)} of {flat.size}"
    # Agreement: the three programs evaluate the same derivative in different orders (reverse
    # accumulation, vectorised tangents, one tangent at a time), so they differ only by float32
    # rounding of sums of ~walks x bounces x pairs terms: relative error ~sqrt(n) eps ~ 1e-5 of the
    # largest term. The bound below, 1e-4 of the largest derivative, is ten times that.
    scale = np.max(np.abs(g))
    print(f"\n[grad/jvp/jacfwd] max |grad - jacfwd| = {np.max(np.abs(g - j)) / scale:.2e}, "
          f"max |grad - jvp| = {np.max(np.abs(g - by_jvp)) / scale:.2e} (relative to max |grad| = {scale:.3g})")
    np.testing.assert_allclose(j, g, rtol=1e-4, atol=1e-4 * scale)
    np.testing.assert_allclose(by_jvp, g, rtol=1e-4, atol=1e-4 * scale)


# --- 2. unbiasedness: AD against finite differences -------------------------------------------

K_AD = 64  # keys for the AD mean (64 x 16 walks)
K_FD = 128  # keys for the finite differences: twice the samples of the AD side

# Finite-difference steps. With common random numbers and fixed lobe probabilities the
# per-key difference quotient is that of a smooth function, so the step is limited by float32
# rounding from below and by the O(h^2) truncation from above. A scan of h on dewy1 (h = 1e-3
# ... 3e-2 of each parameter's scale) gave the per-key |FD - AD| (median over keys) smallest for
# h = 3e-3 ... 1e-2 (for c_d: 2.2e-4, 1.7e-4, 3.1e-4, 2.9e-3 at h = 1e-3, 3e-3, 1e-2, 3e-2):
# rounding (~1e-6 of f over 2h) dominates below, truncation above. Of that range the larger step
# is taken, because for the direction parameters it averages over more of the narrow features
# of test 3 (a smaller FD variance). So h is 1% of the parameter's scale: 1 for c_d, albedos, g and
# w_g; its own value for t and alpha_p; 30 degrees for the angles (h = 0.3 degrees). The test
# also computes 2h and requires the implied truncation error of the step-h
# estimate, |FD(2h) - FD(h)| / 3 (FD(h) = d + c h^2 + ...), to be below half a combined standard
# error (it then moves z by less than 0.5) up to 3 standard errors of that estimate: it is itself
# noisy, because for the direction parameters a few keys have features narrower than h (test 3),
# which FD(h) and FD(2h) weigh differently. So the check fails only on significant evidence of a
# truncation above 0.5 SE.
#
# The keys of the two sides are independent, so the combined SE is sqrt(SE_AD^2 + SE_FD^2).
# Printed as a diagnostic, not asserted: AD on the first K_AD FD keys minus the FD, key by key,
# in combined SEs and as a z-score of its own. A discontinuity that AD misses would show there
# as a mean difference far outside its (for smooth parameters tiny) SE.
H_REL = 0.01


def _step(name, v0):
    if name in ("t", "alpha_p"):
        return H_REL * float(v0[IDX[name]])
    if name in ("theta_p", "phi_p"):
        return H_REL * 30.0
    return H_REL


UNBIASED_CASES = {
    # thin (t = 2) so that d/dt matters; w_g = 1, so E[d/dg2] = 0 and, at phi_p = 0 in the plane,
    # E[d/dphi_p] = 0 by symmetry: both check that the gradient is unbiased for zero too.
    "dewy1": (jaxcos.published("dewy1", t=2.0),
              ["t", "c_d", "albedo_d0", "g1", "g2", "w_g", "albedo_p2", "alpha_p", "theta_p", "phi_p"]),
    # published thickness 16; phi_p = 30 so that the azimuth's derivative is not zero by symmetry
    "matte2": (_with(jaxcos.published("matte2"), phi_p=30.0),
               ["t", "c_d", "albedo_d1", "g1", "g2", "w_g", "albedo_p0", "alpha_p", "theta_p", "phi_p"]),
    "lambertian": (eqx.tree_at(lambda m: m.base_albedo, jaxcos.published("dewy1", t=2.0),
                               jnp.asarray([0.5, 0.4, 0.3]), is_leaf=lambda x: x is None),
                   ["t", "c_d", "base0"]),
}


@pytest.mark.slow
@pytest.mark.parametrize("case, detached, connection", [(c, False, "nee") for c in UNBIASED_CASES]
                         + [("dewy1", True, "nee"), ("matte2", True, "nee"), ("dewy1", False, "mis"),
                            ("matte2", True, "mis")])
def test_gradient_unbiased(case, detached, connection):
    """Mean AD derivative over many keys against a central difference; ``detached``: directions drawn
    from the unperturbed material's lobes on both sides (``simulate(sampling=...)``), as in a fit;
    ``connection``: the estimator's (``"mis"``: its second strategy and weights are differentiated too)."""
    material, params = UNBIASED_CASES[case]
    lambertian = material.base_albedo is not None
    v0 = _vec(material)
    ref = lambda n: np.repeat(v0[None], n, 0) if detached else None
    lp = np.asarray(jaxcos.lobe_probabilities(material))
    eye = np.eye(len(NAMES), dtype=DTYPE)
    keys_ad = jax.random.split(jax.random.key(101), K_AD)
    keys_fd = jax.random.split(jax.random.key(202), K_FD)  # independent of the AD keys

    # AD: the functional S = sum of f over the six pairs and three channels; one tangent per parameter.
    # Computed on the AD keys (the test) and, as a diagnostic, on the FD keys (paired with the FD).
    p = len(params)

    def ad_at(keys):
        k = len(keys)
        dv = np.concatenate([np.repeat(eye[IDX[n]][None], k, 0) for n in params])
        _, _, df = _run(lambertian, np.repeat(v0[None], p * k, 0), dv, np.repeat(lp[None], p * k, 0),
                        jnp.concatenate([keys] * p), ref(p * k), connection)
        return df.sum(axis=(1, 2)).reshape(p, k)

    ad, ad_paired = ad_at(keys_ad), ad_at(keys_fd[:K_AD])

    # FD: S at v0 +- h (K_FD keys) and v0 +- 2h (the first K_AD of them, for the truncation check),
    # the same key on both sides (common random numbers).
    def fd_at(mult, keys):
        v = []
        for n in params:
            h = mult * _step(n, v0)
            v += [np.repeat((v0 + sign * h * eye[IDX[n]])[None], len(keys), 0) for sign in (1, -1)]
        v = np.concatenate(v)
        f, _, _ = _run(lambertian, v, np.zeros_like(v), np.repeat(lp[None], len(v), 0),
                       jnp.concatenate([keys] * (2 * p)), ref(len(v)), connection)
        s_ = f.sum(axis=(1, 2)).reshape(p, 2, len(keys))
        return (s_[:, 0] - s_[:, 1]) / (2 * mult * np.array([_step(n, v0) for n in params]))[:, None]

    fd_h, fd_2h = fd_at(1, keys_fd), fd_at(2, keys_fd[:K_AD])

    sem = lambda x: np.std(x, ddof=1) / np.sqrt(len(x))
    rows, failures = [], []
    for i, n in enumerate(params):
        h, fd1 = _step(n, v0), fd_h[i]
        se = np.hypot(sem(ad[i]), sem(fd1))
        if se == 0:  # exactly constant on both sides (detached g2 at w_g = 1): agree if equal
            se = np.inf if ad[i].mean() == fd1.mean() else 0.0
        z = (ad[i].mean() - fd1.mean()) / se
        # Richardson: FD(2h) - FD(h) = 3 c h^2, so the truncation of FD(h) is estimated by a third
        # of that, with a standard error of its own (a third of the SE of the per-key difference).
        trunc, trunc_se = abs(np.mean(fd_2h[i] - fd1[:K_AD])) / 3.0, sem(fd_2h[i] - fd1[:K_AD]) / 3.0
        paired = ad_paired[i] - fd1[:K_AD]
        rows.append(f"  {case:10s} {n:10s} h={h:<8.3g} AD {ad[i].mean():+11.5f} +- {sem(ad[i]):.5f}   "
                    f"FD {fd1.mean():+11.5f} +- {sem(fd1):.5f}   z = {z:+5.2f}   "
                    f"truncation/SE = {trunc / se:.3f} +- {trunc_se / se:.3f}   "
                    f"paired AD - FD = {paired.mean() / se:+.4f} SE (z {paired.mean() / max(sem(paired), 1e-30):+.2f})")
        if not abs(z) < 3.0:
            failures.append(f"{n}: z = {z:+.2f}")
        if not trunc < 0.5 * se + 3.0 * trunc_se:
            failures.append(f"{n}: FD truncation {trunc:.3g} not negligible against SE {se:.3g}")
    print(f"\n[unbiased] {case}{' (detached directions)' * detached}, {connection}: mean AD gradient vs central FD "
          f"(K_AD={K_AD}, K_FD={K_FD}, walks={WALKS})")
    print("\n".join(rows))
    # 3 SE per comparison (the requirement); with the 43 comparisons of the five cases a Sidak
    # correction at a 5 % family-wise rate would ask for |z| < 3.24, so 3 is a stricter test.
    assert not failures, "; ".join(failures) + "\n" + "\n".join(rows)


# --- 3. common random numbers: no jump along 1-D scans ----------------------------------------

N_SCAN = 81
SCAN_KEY = jax.random.key(7)
# name: (low, high, log-spaced)
SCAN_RANGES = {
    "t": (0.5, 20.0, True), "c_d": (0.05, 0.95, False), "albedo_d0": (0.0, 1.0, False),
    "w_g": (0.0, 1.0, False), "albedo_p1": (0.0, 1.0, False),
    "g1": (-0.9, 0.9, False), "g2": (-0.9, 0.9, False), "alpha_p": (0.01, 1.0, True),
    "theta_p": (0.0, 60.0, False), "phi_p": (-90.0, 90.0, False),
    "base0": (0.0, 1.0, False),
}
# Parameters that enter only weights and flight lengths: the directions sampled by a walk do not
# move with them.
WEIGHT_PARAMS = ("t", "c_d", "albedo_d0", "w_g", "albedo_p1")
# Parameters that move sampled directions (HG polar angle, SGGX visible normal) and the NDF.
DIRECTION_PARAMS = ("g1", "g2", "alpha_p", "theta_p", "phi_p")
# Why 0.25 of the standard error. Between neighbouring points s_k, s_k+1 the jump is the
# trapezoid residual  r = f(s_k+1) - f(s_k) - (f'(s_k) + f'(s_k+1)) ds / 2,  with f' the AD
# derivative (w.r.t. s, i.e. x f'(x) on log-spaced scans). For a smooth f, r = -ds^3 f''' / 12:
# it falls 8-fold when the grid is refined 2-fold (measured from 41 to 81 points: 0.016 -> 0.002 SE
# for t on dewy1, 0.246 -> 0.031 SE for albedo_d0 over a Lambertian base, whose f, a polynomial of
# degree ~64 in the albedo, curves strongly near 1; hence 81 points).
# A jump is invisible to AD and shows in full in r. The smallest jump worth catching is one walk
# taking another path: its contribution changes by ~ sqrt(2) sigma_walk, so f by
# sqrt(2) sigma_walk / W = sqrt(2 / W) SE = 0.35 SE at W = 16 walks (SE = sigma_walk / sqrt(W)).
# A threshold of 0.25 SE sits below that and, on the weight-only parameters, well above the
# smooth residual. (That is also why the scans use only 16 walks: with more, a one-walk jump is a
# smaller fraction of the SE.)
JUMP_FRACTION = 0.25


def _scan_points(name):
    lo, hi, log = SCAN_RANGES[name]
    s = np.linspace(np.log(lo), np.log(hi), N_SCAN) if log else np.linspace(lo, hi, N_SCAN)
    return s, (np.exp(s) if log else s), log


def _scan(material, names, recompute=False, points=None, detached=False):
    """Values, SEs and derivatives d f / d s along the scans of ``names`` (each ``(len(names), n, 18)``).

    ``detached``: the directions are drawn from ``material``'s lobes at every point of the scan.
    """
    lambertian = material.base_albedo is not None
    v0, lp0 = _vec(material), np.asarray(jaxcos.lobe_probabilities(material))
    vs, dvs, lps = [], [], []
    for name in names:
        s, x, log = _scan_points(name) if points is None else points[name]
        for xi in x:
            v = v0.copy()
            v[IDX[name]] = xi
            dv = np.zeros_like(v)
            dv[IDX[name]] = xi if log else 1.0  # d x / d s
            vs.append(v), dvs.append(dv), lps.append(_lobe_probs(v, lambertian) if recompute else lp0)
    f, se, df = _run(lambertian, np.array(vs), np.array(dvs), np.array(lps), jnp.stack([SCAN_KEY] * len(vs)),
                     np.repeat(v0[None], len(vs), 0) if detached else None)
    shape = (len(names), -1, f.shape[1] * f.shape[2])
    return f.reshape(shape), se.reshape(shape), df.reshape(shape)


def _jump_fraction(s, f, se, df):
    """Per interval and component, |trapezoid residual| / (smaller SE of its two ends): ``(n - 1, 18)``."""
    ds = np.diff(s)[:, None]
    r = f[1:] - f[:-1] - 0.5 * (df[1:] + df[:-1]) * ds
    return np.abs(r) / np.minimum(se[1:], se[:-1])


SCAN_MATERIALS = {
    "dewy1": jaxcos.published("dewy1"),
    "matte2": jaxcos.published("matte2"),
    "lambertian": UNBIASED_CASES["lambertian"][0],
}


@functools.lru_cache(maxsize=None)
def _weight_scans(product):
    names = WEIGHT_PARAMS + (("base0",) if product == "lambertian" else ())
    material = SCAN_MATERIALS[product]
    fixed = _scan(material, names)
    recomputed = _scan(material, ("c_d", "w_g"), recompute=True) if product != "lambertian" else None
    return names, fixed, recomputed


def _worst_jumps(product, label, names, f, se, df):
    """``{name: largest jump / SE}`` along each scan, printed."""
    worst = {name: float(_jump_fraction(_scan_points(name)[0], f[i], se[i], df[i]).max())
             for i, name in enumerate(names)}
    print(f"\n[scan] {product}: max jump / SE {label}: " + ", ".join(f"{k} {v:.3f}" for k, v in worst.items()))
    return worst


@pytest.mark.parametrize("product", list(SCAN_MATERIALS))
def test_crn_scans_have_no_jump(product):
    """Weight-only parameters: every step of an 81-point scan is predicted by the AD derivative."""
    names, (f, se, df), _ = _weight_scans(product)
    worst = _worst_jumps(product, "with fixed lobe probabilities", names, f, se, df)
    bad = {k: v for k, v in worst.items() if not v < JUMP_FRACTION}
    assert not bad, f"jumps above {JUMP_FRACTION} SE: {bad}"


@pytest.mark.parametrize("product", ["dewy1", "matte2"])
def test_crn_scan_check_catches_recomputed_lobe_probabilities(product):
    """Negative control: with lobe probabilities recomputed at every point, walks switch lobes and jump."""
    _, _, (f, se, df) = _weight_scans(product)
    worst = _worst_jumps(product, "with lobe probabilities recomputed", ("c_d", "w_g"), f, se, df)
    for name, value in worst.items():
        assert value > JUMP_FRACTION, f"{name}: the check did not see the jumps of recomputed lobe probabilities"


@pytest.mark.parametrize("product", ["dewy1", "matte2"])
def test_crn_scans_with_detached_directions_have_no_jump(product):
    """Every parameter, directions drawn from the scan's centre material: no step is unpredicted.

    With the lobe probabilities and the lobes that draw the directions both held at one material,
    a walk's path does not move with any parameter: only its weights and flight lengths do.
    """
    names = WEIGHT_PARAMS + DIRECTION_PARAMS
    f, se, df = _scan(SCAN_MATERIALS[product], names, detached=True)
    worst = _worst_jumps(product, "with detached directions", names, f, se, df)
    bad = {k: v for k, v in worst.items() if not v < JUMP_FRACTION}
    assert not bad, f"jumps above {JUMP_FRACTION} SE: {bad}"


ZOOM_LEVELS, ZOOM_POINTS = 3, 101


@pytest.mark.slow
@pytest.mark.parametrize("product", ["dewy1", "matte2"])
def test_crn_scans_of_direction_parameters_are_continuous(product):
    """Direction parameters, attached sampling: the worst step of each scan is a narrow continuous
    feature, not a jump.

    Along g1, g2, alpha_p, theta_p and phi_p the 81-point scans do show steps of several SE that
    the AD derivative at the ends does not predict (printed). They are not discontinuities: walks
    whose direction grazes the surface near the top see their collision probability
    1 - exp(-sigma z / mu) switch over a parameter range ~ sigma z / |d mu / d x| (z the depth,
    arbitrarily small); the azimuth construction and narrow platelet lobes amplify direction
    changes from bounce to bounce, down to features 1e-7 wide in alpha_p (checked in float64:
    there the AD derivative matches a central difference with h = 1e-10). This test zooms into
    the worst interval of each scan, 100-fold per level, following the largest step: a jump would
    keep its size at every level; a continuous feature spreads over the finer steps. After a
    10^6-fold refinement the largest step must be below the same 0.25 SE.
    """
    material = SCAN_MATERIALS[product]
    names = DIRECTION_PARAMS
    f, se, df = _scan(material, names)
    coarse, intervals, comps = {}, {}, {}
    for i, name in enumerate(names):
        s, _, _ = _scan_points(name)
        frac = _jump_fraction(s, f[i], se[i], df[i])
        k, c = np.unravel_index(np.argmax(frac), frac.shape)
        coarse[name], intervals[name], comps[name] = float(frac.max()), (s[k], s[k + 1]), c
    history = {name: [] for name in names}
    for _ in range(ZOOM_LEVELS):
        points = {}
        for name in names:
            a, b = intervals[name]
            s = np.linspace(a, b, ZOOM_POINTS)
            log = SCAN_RANGES[name][2]
            points[name] = (s, np.exp(s) if log else s, log)
        f, se, _ = _scan(material, names, points=points)
        for i, name in enumerate(names):
            c = comps[name]
            step = np.abs(np.diff(f[i, :, c]))
            j = int(np.argmax(step))
            history[name].append(float(step[j] / min(se[i, j, c], se[i, j + 1, c])))
            intervals[name] = (points[name][0][j], points[name][0][j + 1])
    print(f"\n[scan] {product}: direction parameters, max jump / SE on the 81-point scan, then the largest "
          f"step / SE after each 100-fold refinement of the worst interval:")
    for name in names:
        print(f"  {name:8s} coarse {coarse[name]:7.3f}   refined " + " -> ".join(f"{h:.4f}" for h in history[name]))
    bad = {name: history[name][-1] for name in names if not history[name][-1] < JUMP_FRACTION}
    assert not bad, f"steps that do not shrink under refinement (discontinuities): {bad}"


# --- 4. finite values and Jacobians at the hard cases ---------------------------------------------

NOMINAL = dict(t=2.0, c_d=0.5, albedo_d=0.8, g1=0.5, g2=-0.3, w_g=0.6, albedo_p=0.8, alpha_p=0.1,
               theta_p=10.0, phi_p=20.0, base=0.5)
HARD_VALUES = (
    [{}]
    + [{"alpha_p": a} for a in (1e-4, 0.002, 1.0)]
    + [{g: x} for g in ("g1", "g2") for x in (-0.999, 0.0, 0.999)]
    + [{k: x} for k in ("c_d", "w_g", "albedo_d", "albedo_p", "base") for x in (0.0, 1.0)]
    + [{"t": x} for x in (0.0, 1e-3, 100.0)]
    + [{"theta_p": x} for x in (0.0, 90.0)]
    + [  # combinations of extremes
        dict(alpha_p=1e-4, g1=0.999, g2=-0.999, t=100.0, albedo_d=1.0, albedo_p=1.0, base=1.0),
        dict(alpha_p=1e-4, theta_p=0.0, t=1e-3, c_d=0.0, albedo_p=1.0),
        dict(alpha_p=0.002, g1=-0.999, g2=0.999, c_d=1.0, w_g=0.0, albedo_d=1.0, t=100.0),
        dict(alpha_p=1.0, g1=0.0, g2=0.0, c_d=0.0, w_g=1.0, albedo_d=0.0, albedo_p=0.0, base=0.0, t=0.0),
        dict(alpha_p=0.002, c_d=1.0, w_g=1.0, g1=0.999, albedo_d=1.0, albedo_p=0.0, t=1e-3),
    ]
)


def _hard_material(values, variant, lambertian):
    p = dict(NOMINAL, **values)
    layer = jaxcos.Layer(t=p["t"], c_d=p["c_d"], albedo_d=p["albedo_d"], g1=p["g1"], g2=p["g2"], w_g=p["w_g"],
                         albedo_p=p["albedo_p"], alpha_p=p["alpha_p"], theta_p=p["theta_p"], phi_p=p["phi_p"])
    return jaxcos.Material(layers=(layer,), base_albedo=p["base"] if lambertian else None, variant=variant)


@pytest.mark.slow
@pytest.mark.parametrize("variant, connection", [(v, "nee") for v in jaxcos.VARIANTS]
                         + [("two_lobe", "mis"), ("platelets_only", "mis")])
def test_finite_everywhere(variant, connection):
    """No NaN or inf in the BSDF or in ``jax.jacfwd`` over all leaves, at every hard case."""
    key = jax.random.key(5)
    problems = []
    for lambertian in (False, True):
        fn = _value_and_jacobian(variant, lambertian, connection)
        for values in HARD_VALUES:
            f, jac = fn(_hard_material(values, variant, lambertian), key)
            flat = np.asarray(ravel_pytree(jac)[0])
            if not np.all(np.isfinite(np.asarray(f))):
                problems.append(f"value, {'lambertian' if lambertian else 'black'}, {values}")
            if not np.all(np.isfinite(flat)):
                problems.append(f"jacobian, {'lambertian' if lambertian else 'black'}, {values}")
    assert not problems, "non-finite at: " + "; ".join(problems)


@functools.lru_cache(maxsize=None)
def _value_and_jacobian_detached(lambertian):
    """Compiled ``(f, jax.jacfwd(f))`` with the directions drawn from the lobes of a second material."""
    del lambertian  # the cache key
    query = jaxcos.make_query(HARD_TI, HARD_TO)
    bsdf = lambda m, ref, key: jaxcos.simulate(m, query, key, walks=HARD_WALKS, bounces=HARD_BOUNCES, sampling=ref).f
    return eqx.filter_jit(lambda m, ref, key: (bsdf(m, ref, key), jax.jacfwd(bsdf)(m, ref, key)))


@pytest.mark.slow
def test_finite_everywhere_with_detached_directions():
    """Detached sampling at every hard case: directions drawn from the material itself (as in a fit) and
    from the nominal material (weights ``W / pdf`` of lobes that differ: a narrow lobe sampled broadly)."""
    key = jax.random.key(5)
    problems = []
    for lambertian in (False, True):
        fn = _value_and_jacobian_detached(lambertian)
        nominal = _hard_material({}, "two_lobe", lambertian)
        for values in HARD_VALUES:
            material = _hard_material(values, "two_lobe", lambertian)
            for name, ref in (("itself", material), ("nominal", nominal)):
                f, jac = fn(material, ref, key)
                where = f"{'lambertian' if lambertian else 'black'}, sampled from {name}, {values}"
                if not np.all(np.isfinite(np.asarray(f))):
                    problems.append(f"value, {where}")
                if not np.all(np.isfinite(np.asarray(ravel_pytree(jac)[0]))):
                    problems.append(f"jacobian, {where}")
    assert not problems, "non-finite at: " + "; ".join(problems)
