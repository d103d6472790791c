"""The estimator: position-free Monte Carlo random walks in a layered slab.

One walk starts along ``-wi`` at the top of the stack and makes ``bounces``
steps of a fixed-length :func:`jax.lax.scan`; each step is a free flight and a
scattering event. At every event the walk connects to *all* outgoing
directions of its incidence at once (next-event estimation, docs/model.md
section 4), so one batch of walks per incidence serves every ``wo``.

Derivatives (``jax.grad``, ``jax.jvp``, ``jax.jacfwd``) are unbiased because
no random decision has a probability that depends on a parameter:

* **Free flights are conditioned** to end inside the stack. The depth is drawn
  from the exponential law truncated at the boundary ahead (inverse CDF, a
  smooth function of the parameters: reparameterization), and the walk's
  throughput is multiplied by the probability of not leaving,
  ``1 - exp(-tau)``. There is no "escaped" or "absorbed by the base" branch
  whose threshold moves with the parameters; that energy is tallied in
  expectation instead. In a stack, the layer in which the flight ends is
  chosen uniformly among the layers ahead and weighted by its probability; a
  Lambertian base is reached with probability 1/2 (when flying down) and
  weighted by the transmittance.
* **Lobe selection uses fixed probabilities** (:func:`lobe_probabilities`
  of a reference material, held fixed) and one-sample MIS: the throughput is multiplied by
  ``W(w -> w') / pdf_mix(w')``, where ``pdf_mix`` is the mixture of the lobe
  densities with those same fixed probabilities. Only the direction within a
  lobe is a continuous sample: by reparameterization (attached), or drawn
  from the lobes of a fixed reference material (``simulate(sampling=...)``,
  detached), with ``pdf_mix`` that material's.

With a fixed key, every estimate is then a continuous function of every
parameter (common random numbers), and smooth with detached directions; the
derivative of the estimate is an unbiased estimate of the derivative. See
``docs/derivatives.md`` for the argument and the evidence.

An optional rough top interface (``Material(interface=...)``, docs/model.md
section 3a) is structure: without one the program is exactly the
index-matched walk; with one (:func:`_walk_rough`, ``docs/interface.md``) the
walks enter, connect and reflect through it by reparameterized visible-normal
draws, and the choice between the top (or a Lambertian base) and the stack
is made with a fixed probability (:func:`boundary_probability`).

Cost: every step evaluates the phase functions of all the lobes present (a
vectorised walk samples every lobe and selects), and ``walks x J`` NEE
connections; the structure of the :class:`~jaxcos.Material` (variant, layer
count, base) is static, so a variant's program contains only its own lobes.
With ``simulate(connection="mis")`` every step also makes one backward
connection per walk (:func:`_backward_connection`), about half as costly as
the rest of the step. The later steps are made by fewer walks, which stand
for the others (:func:`stages`): under a third of the steps at 128 bounces.
"""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from . import _interface as I
from . import _phase as P
from ._budget import DEFAULT_BOUNCES, DEFAULT_WALKS

_BASE_PROB = 0.5  # probability of choosing a Lambertian base when flying down
_MIN_MU = 1e-6


# --- the query -------------------------------------------------------------------


class Query(eqx.Module):
    """Directions of one BSDF evaluation, grouped by incidence.

    Attributes:
        wi: ``(I, 3)`` unique directions towards the light.
        wo: ``(I, J, 3)`` outgoing directions per incidence (rows padded by
            repetition to a common ``J``).
        pair_i, pair_j: ``(N,)`` indices mapping each requested pair to its
            ``(incidence, outgoing)`` slot.
    """

    wi: jnp.ndarray
    wo: jnp.ndarray
    pair_i: jnp.ndarray
    pair_j: jnp.ndarray


@jax.jit
def _direction_in(theta_deg):
    th = jnp.deg2rad(theta_deg)
    return jnp.stack([-jnp.sin(th), jnp.zeros_like(th), jnp.cos(th)], axis=-1)


@jax.jit
def _direction_out(theta_deg, phi_deg):
    th, ph = jnp.deg2rad(theta_deg), jnp.deg2rad(phi_deg)
    return jnp.stack([jnp.sin(th) * jnp.cos(ph), jnp.sin(th) * jnp.sin(ph), jnp.cos(th)], axis=-1)


def make_query(theta_i_deg, theta_o_deg, phi_o_deg=None):
    """Group angle pairs (degrees, docs/model.md section 1 convention) by incidence.

    With concrete angles, pairs sharing a ``theta_i`` share one batch of walks.
    With traced angles (inside ``jit``) grouping is impossible and each pair
    gets its own walks: correct, but slower.
    """
    if phi_o_deg is None:
        phi_o_deg = jnp.zeros_like(jnp.asarray(theta_o_deg, dtype=float))
    if any(isinstance(a, jax.core.Tracer) for a in (theta_i_deg, theta_o_deg, phi_o_deg)):
        ti = jnp.atleast_1d(jnp.asarray(theta_i_deg, dtype=float))
        to = jnp.broadcast_to(jnp.asarray(theta_o_deg, dtype=float), ti.shape)
        po = jnp.broadcast_to(jnp.asarray(phi_o_deg, dtype=float), ti.shape)
        n = ti.shape[0]
        return Query(_direction_in(ti), _direction_out(to, po)[:, None, :], jnp.arange(n), jnp.zeros(n, int))
    ti = np.atleast_1d(np.asarray(theta_i_deg, dtype=float))
    to = np.broadcast_to(np.asarray(theta_o_deg, dtype=float), ti.shape)
    po = np.broadcast_to(np.asarray(phi_o_deg, dtype=float), ti.shape)
    unique, pair_i = np.unique(ti, return_inverse=True)
    rows = [np.flatnonzero(pair_i == i) for i in range(len(unique))]
    width = max(len(r) for r in rows)
    pair_j = np.zeros(len(ti), dtype=int)
    slots = np.zeros((len(unique), width), dtype=int)
    for i, r in enumerate(rows):
        pair_j[r] = np.arange(len(r))
        slots[i] = np.concatenate([r, np.full(width - len(r), r[-1])])
    dtype = jnp.result_type(float)
    wo = _direction_out(jnp.asarray(to[slots], dtype), jnp.asarray(po[slots], dtype))
    return Query(_direction_in(jnp.asarray(unique, dtype)), wo, jnp.asarray(pair_i), jnp.asarray(pair_j))


# --- the medium ------------------------------------------------------------------


class _Medium(eqx.Module):
    """A material's layers stacked along a leading axis, with the variant applied."""

    t: jnp.ndarray  # (L,)
    top: jnp.ndarray  # (L,) depth of each layer's top
    c_d: jnp.ndarray
    albedo_d: jnp.ndarray  # (L, 3)
    g1: jnp.ndarray
    g2: jnp.ndarray
    w_g: jnp.ndarray
    albedo_p: jnp.ndarray  # (L, 3)
    alpha_p: jnp.ndarray
    m: jnp.ndarray  # (L, 3)
    diffusers: bool = eqx.field(static=True)
    platelets: bool = eqx.field(static=True)
    two_lobes: bool = eqx.field(static=True)

    @property
    def n_layers(self):
        return self.t.shape[0]

    def take(self, k):
        """Per-walk parameters of layer ``k`` (``(W,)`` ints); a no-op gather for one layer."""
        if self.n_layers == 1:
            return jax.tree.map(lambda a: a[0], self)
        return jax.tree.map(lambda a: a[k], self)

    def sigma_t(self, w, sig_s=None):
        """Extinction ``c_d + (1 - c_d) sigma_S(w)`` (achromatic); ``sig_s`` if already known."""
        if not self.platelets:
            return jnp.ones(w.shape[:-1], w.dtype)
        if sig_s is None:
            sig_s = P.sggx_sigma(w, self.m, self.alpha_p)
        if not self.diffusers:
            return sig_s
        return self.c_d + (1.0 - self.c_d) * sig_s

    def lobes(self, w, w_out):
        """Lobe values ``(f_d, sigma_S(w) f_p)`` of ``w -> w'`` (1/sr); ``None`` for an absent part.

        ``f_d`` is the diffuser mixture ``w_g f_HG(g1) + (1 - w_g) f_HG(g2)``,
        ``sigma_S(w) f_p = D(h) / 4`` the platelets' specular reflection.
        """
        f_d = f_p = None
        if self.diffusers:
            f_d = P.hg(w, w_out, self.g1)
            if self.two_lobes:
                f_d = self.w_g * f_d + (1.0 - self.w_g) * P.hg(w, w_out, self.g2)
        if self.platelets:
            f_p = P.flake_reflection(w, w_out, self.m, self.alpha_p)
        return f_d, f_p

    def prefactors(self, sig_t):
        """RGB factors ``(k_d, k_p)`` with ``W(w -> w') = k_d f_d + k_p sigma_S(w) f_p`` (docs/model.md eq. 8).

        ``k_d = albedo_d c_d / sigma_t(w)``, ``k_p = albedo_p (1 - c_d) / sigma_t(w)``;
        ``sig_t``: the extinction along ``w``.
        """
        inv = 1.0 / sig_t
        k_d = (self.c_d * inv)[..., None] * self.albedo_d if self.diffusers else None
        if self.platelets:
            c_p = 1.0 - self.c_d if self.diffusers else 1.0
            k_p = (c_p * inv)[..., None] * self.albedo_p
        else:
            k_p = None
        return k_d, k_p

    def scatter(self, w, w_out, sig_t):
        """Per-collision weight ``W(w -> w')`` (RGB, 1/sr): scattering over extinction.

        ``sig_t``: the extinction along ``w``. Leading axes of ``w``/``w_out``
        broadcast against the parameters' shape.
        """
        return _combine(self.lobes(w, w_out), self.prefactors(sig_t))

    def depth_optical(self, sig_layers, z):
        """``sum_l sigma_l clip(z - top_l, 0, t_l)``: optical depth from the top to depth ``z`` per unit ``|mu|``.

        ``sig_layers``: ``(..., L)`` extinctions of each layer along a direction.
        """
        return jnp.sum(sig_layers * jnp.clip(z[..., None] - self.top, 0.0, self.t), axis=-1)


def _combine(lobes, factors):
    """``k_d f_d + k_p f_p`` over the parts present (RGB on the last axis)."""
    return sum(f[..., None] * k for f, k in zip(lobes, factors) if f is not None)


def stack_medium(material):
    layers = material.layers
    stack = lambda name: jnp.stack([jnp.asarray(getattr(l, name)) for l in layers])
    t = stack("t")
    c_d = stack("c_d")
    if material.variant == "diffusers_only":
        c_d = jnp.ones_like(c_d)
    elif material.variant == "platelets_only":
        c_d = jnp.zeros_like(c_d)
    w_g = stack("w_g") if material.two_lobes else jnp.ones_like(t)
    return _Medium(
        t=t,
        top=jnp.concatenate([jnp.zeros(1, t.dtype), jnp.cumsum(t)[:-1]]),
        c_d=c_d,
        albedo_d=stack("albedo_d"),
        g1=stack("g1"),
        g2=stack("g2"),
        w_g=w_g,
        albedo_p=stack("albedo_p"),
        alpha_p=stack("alpha_p"),
        m=P.mean_normal(stack("theta_p"), stack("phi_p")),
        diffusers=material.has_diffusers,
        platelets=material.has_platelets,
        two_lobes=material.two_lobes,
    )


def _sigma_layers(med, w):
    """Extinction of every layer along ``w``: ``(..., L)``."""
    return jnp.broadcast_to(med.sigma_t(w[..., None, :]), w.shape[:-1] + (med.n_layers,))


# --- random numbers ---------------------------------------------------------------


def _mix(x):
    """The 'lowbias32' integer hash (C. Wellons): a bijection of uint32 with good avalanche."""
    x = x ^ (x >> 16)
    x = x * jnp.uint32(0x7FEB352D)
    x = x ^ (x >> 15)
    x = x * jnp.uint32(0x846CA68B)
    return x ^ (x >> 16)


def _uniforms(seed, step, walks, n, dtype, first=0):
    """``(walks, n)`` uniform numbers in ``[0, 1)`` for one step, from a counter-based hash.

    ``seed``: two uint32 drawn from the caller's PRNG key, so the same key
    gives the same numbers. jax.random's generators cost about 25 ns per
    number on this project's 2-core CPU, a quarter of a whole walk; hashing the
    counter ``(walk, stream, step)`` fuses into the step and costs ~1 ns.
    24 random bits per number. A walk's numbers do not depend on ``walks``:
    the first ``w`` walks of a larger batch are the batch of ``w`` walks (the
    fit takes its Jacobian from them). ``first``: the index of the first
    walk (a chunk of walks ``first .. first + walks - 1``).
    """
    walk = jnp.arange(walks, dtype=jnp.uint32)
    if not (isinstance(first, int) and first == 0):
        walk = walk + jnp.asarray(first).astype(jnp.uint32)
    counter = walk[:, None] * jnp.uint32(n) + jnp.arange(n, dtype=jnp.uint32)
    x = _mix(_mix(counter ^ seed[0]) + _mix(step.astype(jnp.uint32) ^ seed[1]))
    return (x >> 8).astype(dtype) * (1.0 / 16777216.0)


# --- fewer walks for the later steps ----------------------------------------------------

THIN_AFTER = 16
"""Steps that every walk makes; after them the walk count halves, and halves again each time
the step count doubles (:func:`stages`). From step 16 rather than 32, the default 128 x 512
evaluation of the standard grid was 1.2-1.7 times as efficient (dewy1 1.24, dewy2 1.38, matte2
1.56, the renderer's slab 1.71; benchmarks/RESULTS.md, "Estimator efficiency"); from step 8
the dewy sets' error grew faster than the time fell."""
THIN_HALVINGS = 4
"""At most this many halvings: the later steps are made by at least a sixteenth of the walks."""
THIN_CHUNK = 8
"""The fewest walks of a stage: thinning stops above it (and where the walks do not halve evenly)."""


def stages(walks, bounces, thin_after=THIN_AFTER):
    """The walks of each step: static ``((start, stop, n), ...)``, steps ``[start, stop)`` made by the first ``n`` walks.

    Walks of one incidence are independent and identically distributed, so the
    contribution of steps ``[start, stop)`` can be estimated from any fixed
    subset of them: the first ``n``, their throughput multiplied by the
    previous stage's count over this one's at each boundary. The estimate stays
    unbiased, no decision is random (so its derivatives are too), and a walk
    draws the same numbers as before. Light of high orders is little and varies
    little between walks (dewy1 keeps 20% of its energy after 32 steps and 5%
    after 64), so those steps are cheap to estimate from fewer walks. The count
    halves after ``thin_after`` steps and each time the step count doubles,
    at most :data:`THIN_HALVINGS` times, while it halves evenly and stays at
    least :data:`THIN_CHUNK`: at 1024 x 128 walks 1024, 512, 256, 128 from
    steps 0, 16, 32, 64 (40 steps a walk instead of 128; at 128 x 512, 64
    instead of 512).
    ``thin_after=None``: every walk makes every step.
    """
    if thin_after is None:
        return ((0, bounces, walks),)
    halvings = 0
    while (halvings < THIN_HALVINGS and thin_after << halvings < bounces and walks % (2 << halvings) == 0
           and walks >> (halvings + 1) >= THIN_CHUNK):
        halvings += 1
    bounds = [0] + [thin_after << k for k in range(halvings)] + [bounces]
    return tuple((bounds[k], bounds[k + 1], walks >> k) for k in range(halvings + 1))


def _chunk(a, first, n):
    """Rows ``first .. first + n - 1`` of ``a`` (all of it for a plain scan: ``first`` the int 0, ``n`` its length)."""
    if isinstance(first, int) and first == 0 and a.shape[0] == n:
        return a
    return jax.lax.dynamic_slice_in_dim(a, first, n)


def _staged_scan(step, state, plan, accumulators):
    """``jax.lax.scan`` of ``step(s, i, first)`` over the steps of a :func:`stages` plan, with one compiled body.

    The walks go through the plan in chunks of the last stage's count ``c`` and
    blocks of ``L`` steps (the greatest common divisor of the stages'
    lengths): an outer scan over the (chunk, block) pairs slices the chunk's
    state out of the state of all walks, runs the inner scan of ``L`` steps of
    ``step`` (``s``: the state of walks ``first .. first + c - 1``; ``i``: the
    step) and writes it back. At the first step of a stage the chunk's
    throughput ``beta`` is multiplied by the ratio of the counts. A walk left
    out at a boundary keeps its ``accumulators`` and its ``beta`` becomes 0
    (its energy is carried by the walks kept). Returns the final state of all
    walks, the outputs ``(iterations, c, ...)`` and the static step and first
    walk of each iteration (``None`` for one stage: a plain scan over the
    steps, outputs ``(bounces, W, ...)``).
    """
    if len(plan) == 1:
        state, out = jax.lax.scan(lambda s, i: step(s, i, 0), state, jnp.arange(plan[0][1]))
        return state, out, None, None
    c = plan[-1][2]
    block = math.gcd(*[stop - start for start, stop, _ in plan])
    firsts, starts, scales, prev = [], [], [], plan[0][2]
    for start, stop, n in plan:
        for first in range(0, n, c):
            for i in range(start, stop, block):
                firsts.append(first)
                starts.append(i)
                scales.append(prev / n if i == start else 1.0)
        prev = n

    def segment(full, xs):
        first, i0, scale = xs
        s = {key: jax.lax.dynamic_slice_in_dim(value, first, c) for key, value in full.items()}
        s["beta"] = s["beta"] * scale.astype(s["beta"].dtype)
        s, out = jax.lax.scan(lambda s, j: step(s, i0 + j, first), s, jnp.arange(block))
        return {key: jax.lax.dynamic_update_slice_in_dim(full[key], s[key], first, 0) for key in full}, out

    xs = (jnp.asarray(firsts, jnp.int32), jnp.asarray(starts, jnp.int32), jnp.asarray(scales))
    state, out = jax.lax.scan(segment, state, xs)
    out = jax.tree.map(lambda a: a.reshape((-1,) + a.shape[2:]), out)
    state = {key: value for key, value in state.items() if key in accumulators or key == "beta"}
    state["beta"] = state["beta"].at[c:].set(0.0)
    steps = (np.asarray(starts)[:, None] + np.arange(block)).ravel()
    return state, out, steps, np.repeat(firsts, block)


def stage_stderr(acc, plan):
    """Standard error of ``mean(acc, axis=1)`` for the per-walk values ``acc`` ``(..., W, ...)`` of a :func:`stages` plan.

    Walks that made the same steps are identically distributed: the variance
    of the mean is ``sum_g n_g s_g^2 / W^2`` over those groups (``s_g^2``:
    the group's sample variance; :func:`stages` makes groups of at least
    :data:`THIN_CHUNK` walks).
    """
    walks = plan[0][2]
    if len(plan) == 1:
        return jnp.std(acc, axis=1, ddof=1) / jnp.sqrt(walks)
    bounds = sorted({n for _, _, n in plan} | {0})
    var = sum((hi - lo) * jnp.var(acc[:, lo:hi], axis=1, ddof=1) for lo, hi in zip(bounds[:-1], bounds[1:]))
    return jnp.sqrt(var) / walks


# --- one step of a walk ------------------------------------------------------------


def _flight(med, lambertian, z, k, w, beta, u_sel, u_fl, top_prob=None, base_prob=_BASE_PROB):
    """A conditioned free flight from depth ``z`` in layer ``k`` along ``w``.

    Returns the new depth and layer, the throughput multiplied by the
    probability of the chosen outcome over its selection probability, whether
    the walk reached the (Lambertian) base, and the energy that left through
    the top or into the (black) base, in expectation.

    ``base_prob``: the probability of choosing a Lambertian base when flying
    down. Under a top interface, ``top_prob`` (not ``None``) is the probability
    that a flight up reaches the top (weighted by its transmittance over that
    probability; depth 0, layer 0) instead of colliding: nothing is tallied as
    escaped here, the interface decides what leaves. A seventh value then says
    whether the walk reached the top. Both are fixed numbers (never
    differentiated).
    """
    n = med.n_layers
    mu = w[..., 2]
    up = mu > 0
    amu = jnp.maximum(jnp.abs(mu), _MIN_MU)
    sig = _sigma_layers(med, w)  # (W, L)
    layer = jnp.arange(n)
    bottom = med.top + med.t
    here = layer == k[..., None]
    ahead = jnp.where(up[..., None], layer < k[..., None], layer > k[..., None])
    seg = jnp.where(here, jnp.where(up, z - med.top[k] if n > 1 else z, (bottom[k] if n > 1 else med.t[0]) - z)[..., None],
                    jnp.where(ahead, med.t, 0.0))
    seg = jnp.maximum(seg, 0.0)
    tau = sig * seg / amu[..., None]  # (W, L)
    tau_total = jnp.sum(tau, axis=-1)
    leave = jnp.exp(-tau_total)

    if n == 1:
        choice, n_ahead, tau_before = jnp.zeros_like(k), 1.0, 0.0
        tau_k, sig_k = tau[..., 0], sig[..., 0]
        entry = z
        lo, hi = jnp.zeros_like(z), jnp.broadcast_to(med.t[0], z.shape)
    else:
        csum = jnp.cumsum(tau, axis=-1)
        before_down = csum - tau
        before_up = tau_total[..., None] - csum
        tau_before_all = jnp.where(up[..., None], before_up, before_down)
        n_ahead = jnp.where(up, k + 1, n - k)
    interface = top_prob is not None
    base = jnp.logical_and(~up, u_sel < base_prob) if lambertian else jnp.zeros_like(up)
    if interface:
        top = jnp.logical_and(up, u_sel < top_prob)
        u_up = jnp.maximum(u_sel - top_prob, 0.0) / (1.0 - top_prob)
    if lambertian:
        u_sel = jnp.where(up, u_sel, jnp.maximum(u_sel - base_prob, 0.0) / (1.0 - base_prob) if interface
                          else (u_sel - base_prob) / (1.0 - base_prob))
    if interface:
        u_sel = jnp.where(up, u_up, u_sel)
    if n > 1:
        step = jnp.minimum(jnp.floor(u_sel * n_ahead).astype(k.dtype), n_ahead - 1)
        choice = jnp.where(up, k - step, k + step)
        pick = lambda a: jnp.take_along_axis(a, choice[..., None], axis=-1)[..., 0]
        tau_k, sig_k, tau_before = pick(tau), pick(sig), pick(tau_before_all)
        lo, hi = med.top[choice], bottom[choice]
        entry = jnp.where(choice == k, z, jnp.where(up, hi, lo))
    p_collide = jnp.exp(-tau_before) * -jnp.expm1(-tau_k)
    tau_star = -jnp.log1p(u_fl * jnp.expm1(-tau_k))
    offset = tau_star * amu / sig_k
    z_new = jnp.clip(jnp.where(up, entry - offset, entry + offset), lo, hi)
    weight = p_collide * n_ahead
    if lambertian:
        weight = jnp.where(up, weight, jnp.where(base, leave, weight) / jnp.where(base, base_prob, 1.0 - base_prob))
        z_new = jnp.where(base, jnp.sum(med.t), z_new)
        choice = jnp.where(base, n - 1, choice)
    if interface:
        weight = jnp.where(up, jnp.where(top, leave, weight) / jnp.where(top, top_prob, 1.0 - top_prob), weight)
        z_new = jnp.where(top, 0.0, z_new)
        choice = jnp.where(top, 0, choice)
        escaped = jnp.zeros_like(beta)
    else:
        escaped = jnp.where(up, leave, 0.0)[..., None] * beta
    into_base = jnp.zeros_like(escaped) if lambertian else jnp.where(up, 0.0, leave)[..., None] * beta
    if interface:
        return z_new, choice, beta * weight[..., None], base, escaped, into_base, top
    return z_new, choice, beta * weight[..., None], base, escaped, into_base


@eqx.filter_jit
def lobe_probabilities(material):
    """Lobe-selection probabilities ``(L, 3)`` (Henyey-Greenstein 1, 2, platelets) for walks in ``material``.

    Proportional to each lobe's share of scattering, ``c_d w_g mean(albedo_d)``,
    ``c_d (1 - w_g) mean(albedo_d)`` and ``(1 - c_d) mean(albedo_p) (1 + alpha_p) / 2``
    (the last factor is roughly the mean projected area), with a floor of 0.05
    for every lobe the variant contains, so a lobe can never be missed. They are
    fixed numbers, not parameters: :func:`simulate` does not differentiate
    them, and the estimate is unbiased for any of them. Holding them fixed while
    the material changes (as a fit does) keeps the estimate under a fixed key a
    smooth function of the parameters; recomputing them from each material
    gives lower variance but small jumps.
    """
    med = stack_medium(jax.lax.stop_gradient(material))
    lam_d = med.c_d * jnp.mean(med.albedo_d, axis=-1)
    lam = jnp.stack([
        lam_d * med.w_g if med.diffusers else jnp.zeros_like(lam_d),
        lam_d * (1.0 - med.w_g) if med.diffusers and med.two_lobes else jnp.zeros_like(lam_d),
        (1.0 - med.c_d) * jnp.mean(med.albedo_p, axis=-1) * 0.5 * (1.0 + med.alpha_p)
        if med.platelets else jnp.zeros_like(lam_d),
    ], axis=-1)
    present = jnp.array([med.diffusers, med.diffusers and med.two_lobes, med.platelets], lam.dtype)
    total = jnp.sum(lam, axis=-1, keepdims=True)
    q = jnp.where(total > 1e-6, lam / jnp.where(total > 1e-6, total, 1.0), present / jnp.sum(present))
    q = jnp.maximum(q, 0.05) * present
    return q / jnp.sum(q, axis=-1, keepdims=True)


def _scatter(med, q, w, u_lobe, u1, s, ref=None):
    """A new direction from the lobe mixture with probabilities ``q``, ``W / pdf_mix`` (RGB) and ``pdf_mix``.

    ``q``: ``(..., 3)`` probabilities of (HG ``g1``, HG ``g2``, platelets),
    zero for the lobes the variant lacks. ``ref``: the layer whose lobes draw
    the direction and make up ``pdf_mix`` (held fixed: detached sampling);
    by default ``med``'s own (reparameterized: attached sampling).
    """
    q1, q2 = q[..., 0], q[..., 1]
    smp = med if ref is None else ref
    candidates = []
    if med.diffusers:
        g = jnp.where(u_lobe < q1, smp.g1, smp.g2) if med.two_lobes else smp.g1
        candidates.append(P.hg_sample(w, g, u1, s))
    if med.platelets:
        candidates.append(P.sggx_sample(w, smp.m, smp.alpha_p, s))
    if len(candidates) == 1:
        w_new = candidates[0]
    else:
        w_new = jnp.where((u_lobe >= q1 + q2)[..., None], candidates[1], candidates[0])
    value, pdf = _mixture(med, q, w, w_new, ref)
    return w_new, value / pdf[..., None], pdf


def _mixture(med, q, w, w_new, ref=None):
    """``W(w -> w')`` (RGB, 1/sr) and the lobe mixture's density ``pdf_mix(w')`` (1/sr, floored at 1e-30).

    ``q`` and ``ref`` as in :func:`_scatter`: the density is that of the
    lobes of ``ref`` (detached) or of ``med`` (attached).
    """
    q1, q2, qp = q[..., 0], q[..., 1], q[..., 2]
    pdf = 0.0
    f_1 = f_2 = None
    if med.diffusers:
        f_1 = P.hg(w, w_new, med.g1)
        pdf = pdf + q1 * (f_1 if ref is None else P.hg(w, w_new, ref.g1))
        if med.two_lobes:
            f_2 = P.hg(w, w_new, med.g2)
            pdf = pdf + q2 * (f_2 if ref is None else P.hg(w, w_new, ref.g2))
    sig_s = f_p = None
    if med.platelets:
        sig_s = P.sggx_sigma(w, med.m, med.alpha_p)
        f_p = P.flake_reflection(w, w_new, med.m, med.alpha_p)  # sigma_S(w) f_p
        if ref is None:
            pdf = pdf + qp * f_p / sig_s
        else:
            pdf = pdf + qp * P.flake_reflection(w, w_new, ref.m, ref.alpha_p) / P.sggx_sigma(w, ref.m, ref.alpha_p)
    f_d = f_1 if f_2 is None else med.w_g * f_1 + (1.0 - med.w_g) * f_2
    return _combine((f_d, f_p), med.prefactors(med.sigma_t(w, sig_s))), jnp.maximum(pdf, 1e-30)


def _backward_pdf(smp, w, wo):
    """Density (1/sr) of ``w`` drawn backwards through the platelet lobe from ``wo``: ``f_p(-wo -> -w)``.

    ``= D(h) / (4 sigma_S(wo))`` with the half vector ``h`` of ``w -> wo``;
    ``smp``: the layer whose platelet lobe draws ``w``.
    """
    return P.flake_reflection(w, wo, smp.m, smp.alpha_p) / P.sggx_sigma(wo, smp.m, smp.alpha_p)


def _backward_connection(med, lambertian, lay, smp, q, z, k, w, beta, wo, u, n_out, rate_o, inv_mu_o, sig_o, ref):
    """The second connection strategy: a flight drawn towards ``wo`` through the platelet lobe; RGB ``(W, 3)``.

    From a medium vertex at depth ``z`` (layer ``k``, incoming ``w``,
    throughput ``beta``), draw ``w'`` by :func:`_backward_pdf` (the platelet
    lobe of ``smp`` reversed from ``wo``), fly along it to a vertex ``z'``
    and connect that vertex's platelet reflection to ``wo``. The value is the
    path's contribution over ``pdf_mix(w') + pdf_b(w') / n_out``: the balance
    heuristic against next-event estimation at ``z'`` (which drew ``w'``
    from the mixture), with ``wo`` one of ``n_out`` directions chosen
    uniformly. ``wo``: ``(W, 3)``, and ``rate_o``, ``inv_mu_o``, ``sig_o``
    its per-walk terms. ``u``: ``(W, 4)`` uniforms.
    """
    w_b = -P.sggx_sample(-wo, smp.m, smp.alpha_p, P.uniform_sphere(u[:, 0], u[:, 1]))
    value, pdf = _mixture(lay, q, w, w_b, ref)
    pdf = pdf + _backward_pdf(smp, w_b, wo) / n_out
    z2, k2, beta2, base2, _, _ = _flight(med, lambertian, z, k, w_b, beta * value, u[:, 2], u[:, 3])
    far = med.take(k2)
    k_p = far.prefactors(far.sigma_t(w_b))[1]
    tau = _tau_to_exit(med, z2, rate_o, inv_mu_o, sig_o)
    out = P.flake_reflection(w_b, wo, far.m, far.alpha_p) * jnp.exp(-tau) * inv_mu_o / pdf
    out = beta2 * k_p * out[:, None]
    return jnp.where(base2[:, None], 0.0, out) if lambertian else out


def _tau_to_exit(med, z, rate_o, inv_mu_o, sig_o):
    """``tau(z, wo)``: the optical depth from a vertex at depth ``z`` to the top along ``wo``.

    ``rate_o``: ``sigma_t(wo) / mu_o`` of a single layer; ``sig_o``: ``(..., L)``
    extinctions along ``wo`` (stacks); all broadcast against ``z``.
    """
    if med.n_layers == 1:
        return z * rate_o
    return med.depth_optical(sig_o, z) * inv_mu_o


def _per_pair(lay):
    """Per-walk layer parameters ``(W,)`` given the axis of ``wo``: ``(W, 1)``."""
    return jax.tree.map(lambda a: a[:, None], lay)


def _nee(med, lay, z, w, beta, wo, rate_o, inv_mu_o, sig_o, mis=None):
    """Connection of medium vertices to every outgoing direction, times throughput: ``(W, J, 3)``.

    ``beta * W(w -> wo) * exp(-tau(z, wo)) / mu_o``, the platelet part of
    ``W`` multiplied by ``mis(D(h) / 4)`` ``(W, J)`` when given. ``lay``: the vertex
    layer's parameters (per walk); ``rate_o``: ``sigma_t(wo) / mu_o`` of a
    single layer, ``(J,)``; ``sig_o``: ``(J, L)`` extinctions along ``wo``
    (stacks). The RGB factors are formed per walk, the lobes per pair.
    """
    atten = jnp.exp(-_tau_to_exit(med, z[:, None], rate_o, inv_mu_o, sig_o)) * inv_mu_o  # (W, J)
    factors = [None if k is None else beta * k for k in lay.prefactors(lay.sigma_t(w))]
    if med.n_layers > 1:  # per-walk parameters gain the axis of wo
        lay = _per_pair(lay)
    f_d, f_p = lay.lobes(w[:, None, :], wo[None, :, :])
    if mis is not None:
        f_p = f_p * mis(f_p)
    return _combine([None if f is None else f * atten for f in (f_d, f_p)],
                    [None if k is None else k[:, None, :] for k in factors])


def _walk_one(med, base_albedo, q, wi, wo, seed, walks, bounces, skip_first, ref=None, mis=False, interface=None,
              top_prob=None, thin_after=THIN_AFTER, first_walk=0):
    """All walks of one incidence: per-walk connection sums ``(W, J, 3)`` and energy tallies ``(W, 3)``.

    Returns ``(acc, escaped, into_base, unfinished, shadowed)``. The later
    steps are made by fewer walks (:func:`stages` of ``thin_after``), whose
    values carry the weight of those left out: the per-walk values are
    independent but not identically distributed (:func:`stage_stderr`).

    With platelets and ``mis``, every medium vertex also makes one
    :func:`_backward_connection` (to one ``wo`` per step, cycling through them
    from a random offset), and next-event estimation's platelet part at a
    vertex whose incoming direction the mixture drew is weighted against it.

    With a top ``interface`` (:class:`~jaxcos.Interface`; docs/interface.md)
    the walk is :func:`_walk_rough`'s, with ``top_prob`` (:func:`boundary_probability`);
    ``mis`` is then ignored. ``first_walk``: the index of the first walk
    (these are walks ``first_walk .. first_walk + walks - 1`` of ``seed``'s).
    """
    if interface is not None:
        return _walk_rough(med, base_albedo, q, wi, wo, seed, walks, bounces, skip_first, ref, interface,
                           boundary_probability(med) if top_prob is None else top_prob, thin_after, first_walk)
    dtype = wi.dtype
    n_out = wo.shape[0]
    mu_o = jnp.maximum(wo[:, 2], _MIN_MU)
    inv_mu_o = 1.0 / mu_o
    sig_o = _sigma_layers(med, wo)  # (J, L)
    rate_o = sig_o[:, 0] * inv_mu_o
    total_t = jnp.sum(med.t)
    lambertian = base_albedo is not None
    mis = mis and med.platelets
    if lambertian:
        base_nee = (base_albedo / jnp.pi)[None, :] * jnp.exp(-med.depth_optical(sig_o, total_t) / mu_o)[:, None]
    state = dict(
        z=jnp.zeros(walks, dtype),
        k=jnp.zeros(walks, jnp.int32),
        w=jnp.broadcast_to(-wi, (walks, 3)),
        beta=jnp.ones((walks, 3), dtype),
        acc=jnp.zeros((walks, wo.shape[0], 3), dtype),
        escaped=jnp.zeros((walks, 3), dtype),
        into_base=jnp.zeros((walks, 3), dtype),
    )
    if mis:
        # The second strategy's numbers: a stream of its own (the hash's input as if the counters had
        # their top bit set, which the walks' never reach), so the walks are those of mis=False. The
        # offsets use a step number the walks never reach either.
        seed_b = seed ^ jnp.array([0x80000000, 0], jnp.uint32)
        offset = _uniforms(seed_b, jnp.uint32(0xFFFFFFFF), walks, 1, dtype, first_walk)[:, 0]
        offset = jnp.minimum(jnp.floor(offset * n_out).astype(jnp.int32), n_out - 1)
        # 1 / the mixture density that drew the incoming direction (0: the mixture did not draw it)
        state.update(inv_pdf=jnp.zeros(walks, dtype))
        if med.n_layers > 1:  # and the layer whose lobes drew it
            state.update(k_src=jnp.zeros(walks, jnp.int32))
    sampler = med if ref is None else ref
    if mis and med.n_layers == 1:
        inv_sig_b = 1.0 / (P.sggx_sigma(wo, sampler.m[0], sampler.alpha_p[0]) * n_out)  # (J,)

    def step(s, i, first):
        n = s["z"].shape[0]  # the walks first .. first + n - 1 of this call
        u = _uniforms(seed, i, n, 6, dtype, first + first_walk)
        sphere = P.uniform_sphere(u[:, 4], u[:, 5])
        z, k, beta, base, escaped, into_base = _flight(med, lambertian, s["z"], s["k"], s["w"], s["beta"], u[:, 0], u[:, 1])
        lay = med.take(k)
        def nee_weight(f_p):
            """The balance heuristic's weight of NEE's platelet part, given its ``D(h) / 4``."""
            if med.n_layers > 1:
                p_b = _backward_pdf(_per_pair(sampler.take(s["k_src"])), s["w"][:, None, :], wo[None]) / n_out
            elif ref is None:  # the lobe that would have drawn w backwards is this vertex's
                p_b = f_p * inv_sig_b
            else:
                p_b = P.flake_reflection(s["w"][:, None, :], wo[None], ref.m[0], ref.alpha_p[0]) * inv_sig_b
            return 1.0 / (1.0 + p_b * s["inv_pdf"][:, None])

        contrib = _nee(med, lay, z, s["w"], beta, wo, rate_o, inv_mu_o, sig_o, nee_weight if mis else None)
        if lambertian:
            contrib = jnp.where(base[:, None, None], beta[:, None, :] * base_nee[None], contrib)
        count = jnp.where(jnp.logical_and(skip_first, i == 0), 0.0, 1.0).astype(dtype)
        acc = s["acc"] + count * contrib
        q_k = q[0] if med.n_layers == 1 else q[k]
        ref_k = None if ref is None else ref.take(k)
        w_new, weight, pdf = _scatter(lay, q_k, s["w"], u[:, 2], u[:, 3], sphere, ref_k)
        new = {}
        if mis:
            # The backward strategy makes the next vertex: none from the last step, so that both
            # strategies cover the same scattering orders.
            j = (_chunk(offset, first, n) + i) % n_out  # the same slot as after the scan
            b = _backward_connection(med, lambertian, lay, lay if ref is None else ref_k, q_k, z, k, s["w"], beta,
                                     wo[j], _uniforms(seed_b, i, n, 4, dtype, first + first_walk), n_out, rate_o[j],
                                     inv_mu_o[j],
                                     sig_o[j], ref_k)
            keep = i < bounces - 1
            if lambertian:
                keep = jnp.logical_and(keep, ~base)
            b = jnp.where(keep[..., None], b, 0.0)
            new = dict(inv_pdf=jnp.where(base, 0.0, 1.0 / pdf) if lambertian else 1.0 / pdf)
            if med.n_layers > 1:
                new.update(k_src=k)
        if lambertian:
            up = P.cosine_sample(jnp.array([0.0, 0.0, 1.0], dtype), sphere)
            w_new = jnp.where(base[:, None], up, w_new)
            weight = jnp.where(base[:, None], base_albedo, weight)
        s = dict(z=z, k=k, w=w_new, beta=beta * weight, acc=acc,
                 escaped=s["escaped"] + escaped, into_base=s["into_base"] + into_base, **new)
        return s, (b if mis else None)

    state, out, steps, firsts = _staged_scan(step, state, stages(walks, bounces, thin_after),
                                             ("acc", "escaped", "into_base"))
    acc = state["acc"]
    if mis:
        if steps is None:
            backward = out
        else:  # (bounces, W, 3): each iteration's chunk in its place, zero for the walks left out
            rows = firsts[:, None] + np.arange(out.shape[1])
            backward = jnp.zeros((bounces, walks, 3), dtype).at[steps[:, None], rows].set(out)
        # Each step's backward connection (W, 3) joins its wo after the walk: step i's goes to
        # slot (offset + i) % J. Summed by the phase i % J, then rotated by each walk's offset.
        cycles = -(-bounces // n_out)
        backward = jnp.pad(backward, ((0, cycles * n_out - bounces), (0, 0), (0, 0)))
        by_phase = jnp.moveaxis(backward.reshape(cycles, n_out, walks, 3).sum(0), 0, 1)  # (W, J, 3)
        phase = (jnp.arange(n_out)[None, :] - offset[:, None]) % n_out  # (W, J): the phase of slot j
        acc = acc + jnp.take_along_axis(by_phase, phase[..., None], axis=1)
    return acc, state["escaped"], state["into_base"], state["beta"], jnp.zeros_like(state["beta"])


def _nee_inside(med, lay, z, w, beta, v, inv_vz, sig_v, scale):
    """Connection of medium vertices to per-walk directions ``v`` ``(W, J, 3)`` inside, times throughput: ``(W, J, 3)``.

    ``beta * W(w -> v) * exp(-tau(z, v)) * scale`` (:func:`_nee` with ``wo``
    replaced by a direction per walk and pair): ``scale`` ``(W, J)`` is
    ``1 / v_z`` times the interface's bracket. ``inv_vz``: ``1 / v_z``;
    ``sig_v``: ``(W, J, L)`` extinctions along ``v``.
    """
    if med.n_layers == 1:
        tau = z[:, None] * sig_v[..., 0] * inv_vz
    else:
        tau = med.depth_optical(sig_v, z[:, None]) * inv_vz
    atten = jnp.exp(-tau) * scale  # (W, J)
    factors = [None if k is None else beta * k for k in lay.prefactors(lay.sigma_t(w))]
    if med.n_layers > 1:
        lay = _per_pair(lay)
    f_d, f_p = lay.lobes(w[:, None, :], v)
    return _combine([None if f is None else f * atten for f in (f_d, f_p)],
                    [None if k is None else k[:, None, :] for k in factors])


def _walk_rough(med, base_albedo, q, wi, wo, seed, walks, bounces, skip_first, ref, interface, top_prob,
                thin_after=THIN_AFTER, first_walk=0):
    """:func:`_walk_one` under a rough dielectric top interface (docs/model.md section 3a, docs/interface.md).

    * The walk starts along ``u``, the refraction of ``wi`` through a visible
      normal, with throughput ``(1 - F) G2(wi, u) / G1(wi)``; the reflection
      through the same normal is tallied as escaped, the shadowing loss as
      ``shadowed``.
    * Next-event estimation goes through the interface: for every ``wo``, a
      direction ``v`` inside is drawn from the interface as seen from ``wo``
      (:func:`~jaxcos.model._interface.leave`), and every vertex connects to
      ``v`` (the medium's :func:`_nee_inside`, or the base's
      ``rho / pi exp(-tau(T, v))``) times the bracket ``f_t(wo <- v) |v_z| / p(v)``.
      One ``v`` per walk and ``wo`` serves all the walk's vertices: each
      connection is still unbiased (``v`` is independent of the walk), and
      on dewy1's angles (``alpha_s`` 0.1 and 0.3) fresh draws at every vertex
      gave the same standard errors for 5 to 7 times the cost (docs/interface.md).
    * A flight up reaches the top with probability ``top_prob`` (fixed;
      :func:`boundary_probability`), and a flight down a Lambertian base with
      the same probability (:func:`_flight`). At the top the walk reflects
      through a visible normal with weight ``F G2 / G1`` (total internal
      reflection included). The refracted part is tallied as escaped
      (next-event estimation has counted its light), the shadowing loss as
      ``shadowed``; such a vertex makes no connection.
    * ``skip_first``: the first vertex's connection is replaced by the first
      order integrated over depth in closed form (:func:`single_scattering`
      along the walk's ``u`` and a fresh ``v`` per ``wo``), exact given those
      directions; the directions remain Monte Carlo.

    The interface's draws use a random stream of their own; they are always
    reparameterized (``ref`` draws only the lobes' directions).
    """
    dtype = wi.dtype
    n_out = wo.shape[0]
    eta, alpha = interface.eta, interface.alpha_s
    total_t = jnp.sum(med.t)
    lambertian = base_albedo is not None
    seed_x = seed ^ jnp.array([0x40000000, 0], jnp.uint32)  # the interface's stream
    u_e = _uniforms(seed_x, jnp.uint32(0xFFFFFFFF), walks, 2, dtype, first_walk)
    u_in, w_t, w_r, lost = I.enter(wi, eta, alpha, u_e[:, 0], u_e[:, 1])

    def exits(step):
        """Directions ``v`` ``(W, J, 3)`` inside towards every ``wo``, their brackets, ``1 / v_z`` and extinctions."""
        ux = _uniforms(seed_x, step, walks, 2 * n_out, dtype, first_walk)
        v, bracket = I.leave(wo[None], eta, alpha, ux[:, :n_out], ux[:, n_out:])
        return v, bracket, 1.0 / jnp.maximum(v[..., 2], _MIN_MU), _sigma_layers(med, v)

    acc = jnp.zeros((walks, n_out, 3), dtype)
    if skip_first:
        v1, bracket1, _, _ = exits(jnp.uint32(0xFFFFFFFE))
        # the flight's floor of |mu| (_MIN_MU) also for the closed form's mu_i
        wi_first = jnp.stack([-u_in[:, 0], -u_in[:, 1], jnp.maximum(-u_in[:, 2], _MIN_MU)], axis=-1)
        acc = single_scattering(med, base_albedo, wi_first, v1) * (bracket1 * w_t[:, None])[..., None]
    # one exit direction per walk and wo, shared by all its vertices (see the docstring)
    v, bracket, inv_vz, sig_v = exits(jnp.uint32(0xFFFFFFFD))
    scale = bracket * inv_vz
    if lambertian:  # the base's connection, rho / pi exp(-tau(T, v)) times the bracket: (W, J, 3)
        base_nee = (base_albedo / jnp.pi) * (bracket * jnp.exp(-med.depth_optical(sig_v, total_t) * inv_vz))[..., None]
    state = dict(
        z=jnp.zeros(walks, dtype),
        k=jnp.zeros(walks, jnp.int32),
        w=u_in,
        beta=jnp.broadcast_to(w_t[:, None], (walks, 3)),
        acc=acc,
        escaped=jnp.broadcast_to(w_r[:, None], (walks, 3)),
        into_base=jnp.zeros((walks, 3), dtype),
        shadowed=jnp.broadcast_to(lost[:, None], (walks, 3)),
    )

    def step(s, i, first):
        n = s["z"].shape[0]  # the walks first .. first + n - 1
        chunk = lambda a: _chunk(a, first, n)
        u = _uniforms(seed, i, n, 6, dtype, first + first_walk)
        sphere = P.uniform_sphere(u[:, 4], u[:, 5])
        z, k, beta, base, _, into_base, top = _flight(med, lambertian, s["z"], s["k"], s["w"], s["beta"], u[:, 0],
                                                      u[:, 1], top_prob, top_prob)
        lay = med.take(k)
        contrib = _nee_inside(med, lay, z, s["w"], beta, chunk(v), chunk(inv_vz), chunk(sig_v), chunk(scale))
        if lambertian:
            contrib = jnp.where(base[:, None, None], beta[:, None, :] * chunk(base_nee), contrib)
        contrib = jnp.where(top[:, None, None], 0.0, contrib)
        count = jnp.where(jnp.logical_and(skip_first, i == 0), 0.0, 1.0).astype(dtype)
        acc = s["acc"] + count * contrib
        q_k = q[0] if med.n_layers == 1 else q[k]
        ref_k = None if ref is None else ref.take(k)
        w_new, weight, _ = _scatter(lay, q_k, s["w"], u[:, 2], u[:, 3], sphere, ref_k)
        if lambertian:
            up = P.cosine_sample(jnp.array([0.0, 0.0, 1.0], dtype), sphere)
            w_new = jnp.where(base[:, None], up, w_new)
            weight = jnp.where(base[:, None], base_albedo, weight)
        # at the top: the reflection (the numbers of the base's cosine draw, unused there)
        r, w_rr, w_tt, lost_t = I.reflect_inside(s["w"], eta, alpha, u[:, 4], u[:, 5])
        w_new = jnp.where(top[:, None], r, w_new)
        weight = jnp.where(top[:, None], w_rr[:, None], weight)
        escaped = s["escaped"] + jnp.where(top, w_tt, 0.0)[:, None] * beta
        shadowed = s["shadowed"] + jnp.where(top, lost_t, 0.0)[:, None] * beta
        s = dict(z=z, k=k, w=w_new, beta=beta * weight, acc=acc, escaped=escaped,
                 into_base=s["into_base"] + into_base, shadowed=shadowed)
        return s, None

    state, _, _, _ = _staged_scan(step, state, stages(walks, bounces, thin_after),
                                  ("acc", "escaped", "into_base", "shadowed"))
    return state["acc"], state["escaped"], state["into_base"], state["beta"], state["shadowed"]


def boundary_probability(material):
    """The fixed probability that a flight under a top interface ends on a boundary it flies towards.

    ``material``: a :class:`~jaxcos.Material` (or its stacked medium).

    Under an interface a flight up either collides in the stack or reaches
    the top (and reflects there), and the walk picks one with a fixed
    probability ``p``, weighting by the outcome's probability over ``p``: no
    decision whose probability moves with the parameters. Each such choice
    multiplies the second moment of the throughput by ``L^2 / p + (1 - L)^2 / (1 - p)``
    (``L``: the probability of reaching the boundary): ``1 / p`` where the
    boundary is sure to be reached, ``1 / (1 - p)`` where it is out of reach
    (deep in a thick layer), so ``p = 1/2`` (the index-matched
    walk's choice of a Lambertian base) makes the variance of a thick layer's
    walks grow twofold per flight up (median relative standard error 6.5% at
    512 walks x 128 bounces on dewy1's angles, against 2% without an interface). The
    best fixed ``p`` is ``sqrt(E L^2) / (sqrt(E L^2) + sqrt(E (1 - L)^2))``; for
    vertices spread over a total optical depth ``T``, ``E L^2 ~ 1 / (3 T)``, and
    ``p = 1 / (1 + sqrt(6 T))`` (clipped to ``[0.05, 0.95]``) was within the
    measured optimum for ``T`` = 1, 4 and 16 (median relative standard error
    2.2% on dewy1). The same ``p`` serves a Lambertian base.

    It depends on ``t`` only (never differentiated): estimates under a fixed
    key are a smooth function of every parameter but ``t``; pass
    ``simulate(boundary_prob=...)`` to hold it fixed when ``t`` varies.
    """
    t = material.t if isinstance(material, _Medium) else jnp.stack([jnp.asarray(l.t) for l in material.layers])
    total = jax.lax.stop_gradient(jnp.sum(t))
    return jnp.clip(1.0 / (1.0 + jnp.sqrt(6.0 * total)), 0.05, 0.95)


# --- the exact single-scattering term ------------------------------------------------


def single_scattering(med, base_albedo, wi, wo):
    """First-order BSDF ``(I, J, 3)`` in closed form (docs/model.md section 4), all layers.

    The light of order one: scattered once in some layer, attenuated on the
    way in and out, plus, over a Lambertian base, the base seen through the
    whole stack (``rho / pi`` for a zero-thickness stack).
    """
    w = -wi  # (I, 3) propagation direction in
    mu_i = wi[:, 2][:, None]  # (I, 1)
    mu_o = jnp.maximum(wo[..., 2], _MIN_MU)  # (I, J)
    sig_i = _sigma_layers(med, w)  # (I, L)
    sig_o = _sigma_layers(med, wo)  # (I, J, L)
    rate = sig_i[:, None, :] / mu_i[..., None] + sig_o / mu_o[..., None]  # (I, J, L) per unit depth
    above = jnp.cumsum(rate * med.t, axis=-1) - rate * med.t
    f = med.scatter(w[:, None, None, :], wo[:, :, None, :], sig_i[:, None, :])  # (I, J, L, 3): sigma_s f / sigma_t(-wi)
    per_layer = sig_i[:, None, :] * -jnp.expm1(-rate * med.t) * jnp.exp(-above) / (
        sig_i[:, None, :] * mu_o[..., None] + sig_o * mu_i[..., None])
    total = jnp.sum(f * per_layer[..., None], axis=-2)
    if base_albedo is not None:
        through = jnp.exp(-jnp.sum(rate * med.t, axis=-1))  # (I, J)
        total = total + through[..., None] * base_albedo / jnp.pi
    return total


_first_order = single_scattering  # simulate's argument of that name shadows the function there


# --- the public estimator ----------------------------------------------------------------


class Estimate(eqx.Module):
    """A BSDF estimate and its bookkeeping.

    Attributes:
        f: ``(N, 3)`` BSDF in 1/sr (linear RGB) at the query's pairs.
        stderr: ``(N, 3)`` standard error of ``f`` over walks (the Monte Carlo
            part; the exact single-scattering term has none).
        reflected: ``(I, 3)`` energy leaving through the top per incidence
            (directional-hemispherical reflectance, an independent estimate;
            with a top interface it includes the interface's own reflection).
        absorbed_base: ``(I, 3)`` energy absorbed by a black base.
        unfinished: ``(I, 3)`` energy still carried by walks after the last bounce.
        shadowed: ``(I, 3)`` energy removed by Smith shadowing at a top
            interface (docs/model.md section 3a: the microfacet model is not
            energy conserving); zero without one.
    """

    f: jnp.ndarray
    stderr: jnp.ndarray
    reflected: jnp.ndarray
    absorbed_base: jnp.ndarray
    unfinished: jnp.ndarray
    shadowed: jnp.ndarray


@eqx.filter_jit
def simulate(material, query, key, *, walks=DEFAULT_WALKS, bounces=DEFAULT_BOUNCES, single_scattering="exact",
             lobe_probs=None, incidence_batch=None, sampling=None, connection="nee", boundary_prob=None,
             thin_after=THIN_AFTER, first=0):
    """Estimate the BSDF of ``material`` for a :class:`Query`.

    Args:
        material: a :class:`~jaxcos.Material`.
        query: from :func:`make_query`.
        key: a JAX PRNG key; the same key gives the same numbers.
        walks: walks per incidence direction.
        bounces: scattering events per walk (the scan length).
        single_scattering: ``"exact"`` adds the closed-form first order and
            lets the walks estimate orders two and up; ``"mc"`` estimates every
            order by the walks (a check of the walk against the closed form).
        lobe_probs: fixed lobe-selection probabilities ``(L, 3)``; by default
            :func:`lobe_probabilities` of ``material``. Pass those of a fixed
            reference material to make estimates under one key a smooth
            function of the parameters (common random numbers).
        incidence_batch: how many incidence directions are walked together
            (vectorised); the others follow in sequence. By default all at
            once, the fastest for one evaluation; derivatives through many
            tangents at once (``jax.jacfwd``) run faster with 1.
            The numbers are the same either way, up to float rounding.
        sampling: a fixed material whose lobes draw the scattering directions
            (detached sampling: its parameters are not differentiated, and
            the weights ``W / pdf`` carry the values and derivatives of
            ``material``). By default ``material``'s own lobes draw them, by
            reparameterization (attached sampling). Both are unbiased; with
            ``lobe_probs`` and ``sampling`` both taken from one fixed material,
            estimates under one key are a smooth function of every parameter,
            while attached sampling leaves steep (continuous) features along
            ``g1``, ``g2``, ``alpha_p``, ``theta_p`` and ``phi_p``
            (``docs/derivatives.md``). Same variant and layer count as
            ``material``.
        connection: how scattering vertices connect to the viewer. ``"nee"``
            (the default, the paper's estimator): next-event estimation
            alone. Near-mirror platelets (``alpha_p`` ~ 0.002) give it rare
            spikes of about ``1 / alpha_p^2`` wherever a diffuse bounce lands
            in the platelets' mirror lobe. ``"mis"`` adds, where the material
            has platelets, a second strategy for the platelets' part: from
            every vertex a flight drawn backwards through the platelet lobe
            from one ``wo`` (:func:`_backward_connection`), the two weighted by
            multiple importance sampling (the balance heuristic). On dewy2 it
            takes the largest relative standard error over the measured
            points from 0.28 to 0.07 (1024 walks) for about 1.5 times the
            cost of an evaluation. Both are unbiased and draw the same walks.
            With a top interface, ``"mis"`` is ``"nee"`` (the backward strategy
            does not go through the interface).
        boundary_prob: under a top interface, the fixed probability that a
            flight towards the top (or a Lambertian base) ends there
            (:func:`boundary_probability`, from the material's thickness by
            default). Unbiased for any value in ``(0, 1)``; like ``lobe_probs``,
            hold it fixed to keep estimates under one key a smooth function
            of ``t``. Ignored without an interface.
        thin_after: the steps that every walk makes; the later steps are
            made by fewer walks, whose throughput is scaled up to stand for
            the others (:func:`stages`: the count halves after ``thin_after``
            steps and each time the step count doubles). Unbiased, and the
            same walks draw the same numbers. ``None``: every walk makes
            every step (the estimator before 2026-12-02, kept as the
            reference of ``jaxcos bench accuracy``).
        first: the index of the first walk: the estimate is that of walks
            ``first .. first + walks - 1`` of each incidence under ``key``
            (a walk's random numbers depend on its index, not on how many
            walks there are), so that a large budget can be evaluated in
            chunks by one compiled program (an integer array is not static:
            every chunk shares the program). Chunks of thinned walks thin
            within the chunk.

    A ``material`` with a top :class:`~jaxcos.Interface` (docs/model.md section
    3a, docs/interface.md) adds the interface's reflection ``f_s`` exactly
    (no standard error), and its walks enter, leave and reflect through the
    interface; ``single_scattering="exact"`` then integrates the first order
    over depth in closed form along each walk's sampled entry and exit
    directions (no longer variance-free: the directions are drawn).
    Without one (``interface=None``) the program is exactly the index-matched one.

    Returns:
        An :class:`Estimate`.
    """
    if single_scattering not in ("exact", "mc"):
        raise ValueError(f"single_scattering must be 'exact' or 'mc', not {single_scattering!r}")
    if connection not in ("mis", "nee"):
        raise ValueError(f"connection must be 'mis' or 'nee', not {connection!r}")
    med = stack_medium(material)
    q = lobe_probabilities(material) if lobe_probs is None else jax.lax.stop_gradient(jnp.asarray(lobe_probs))
    exact = single_scattering == "exact"
    seeds = jax.random.bits(key, (query.wi.shape[0], 2), jnp.uint32)
    ref = None if sampling is None else stack_medium(jax.lax.stop_gradient(sampling))
    if ref is not None and (ref.diffusers, ref.platelets, ref.two_lobes, ref.n_layers) != (
            med.diffusers, med.platelets, med.two_lobes, med.n_layers):
        raise ValueError("sampling must have the variant and the number of layers of material.")
    interface = material.interface
    top_prob = None
    if interface is not None:
        top_prob = (boundary_probability(med) if boundary_prob is None
                    else jax.lax.stop_gradient(jnp.asarray(boundary_prob, med.t.dtype)))
    walk = lambda wi, wo, k: _walk_one(med, material.base_albedo, q, wi, wo, k, walks, bounces, exact, ref,
                                       connection == "mis", interface, top_prob, thin_after, first)
    if incidence_batch is None or incidence_batch >= query.wi.shape[0]:
        acc, escaped, into_base, unfinished, shadowed = jax.vmap(walk)(query.wi, query.wo, seeds)
    else:
        acc, escaped, into_base, unfinished, shadowed = jax.lax.map(lambda a: walk(*a), (query.wi, query.wo, seeds),
                                                                    batch_size=incidence_batch)
    f = jnp.mean(acc, axis=1)
    stderr = stage_stderr(acc, stages(walks, bounces, thin_after)) if walks > 1 else jnp.full_like(f, jnp.inf)
    if interface is not None:
        f = f + I.reflection(query.wi[:, None, :], query.wo, interface.eta, interface.alpha_s, _MIN_MU)[..., None]
    elif exact:
        f = f + _first_order(med, material.base_albedo, query.wi, query.wo)
    pick = lambda a: a[query.pair_i, query.pair_j]
    return Estimate(
        f=pick(f),
        stderr=pick(stderr),
        reflected=jnp.mean(escaped, axis=1),
        absorbed_base=jnp.mean(into_base, axis=1),
        unfinished=jnp.mean(unfinished, axis=1),
        shadowed=jnp.mean(shadowed, axis=1),
    )


def inplane_bsdf(material, theta_i_deg, theta_o_deg, key, *, walks=DEFAULT_WALKS, bounces=DEFAULT_BOUNCES,
                 phi_o_deg=None, single_scattering="exact", connection="nee"):
    """The BSDF ``f(wi, wo)`` in 1/sr, linear RGB, shape ``(N, 3)``, at ``N`` angle pairs.

    Angles in degrees, gonioreflectometer convention (docs/model.md section 1):
    ``wi = (-sin ti, 0, cos ti)``, ``wo = (sin to cos po, sin to sin po, cos to)``;
    ``to = ti`` is the mirror direction. Jittable, and differentiable with
    respect to every array leaf of ``material``.

    Example::

        >>> import jax, jaxcos
        >>> f = jaxcos.inplane_bsdf(jaxcos.published("matte2"), [30.0], [30.0], jax.random.key(0), walks=16)
        >>> f.shape
        (1, 3)
    """
    query = make_query(theta_i_deg, theta_o_deg, phi_o_deg)
    return simulate(material, query, key, walks=walks, bounces=bounces, single_scattering=single_scattering,
                    connection=connection).f
