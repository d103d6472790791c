"""1-D scans of the estimate under common random numbers: ``docs/crn_scans.png``.

    python scripts/crn_scans.py [--out docs/crn_scans.png] [--walks 64] [--points 81]

For dewy1 and matte2 (the published fits, ``t = 16``, black base) and each of
ten parameters, the BSDF at one angle pair (45, 47 degrees, green) is estimated under one fixed key
along a scan of that parameter, the others held at their published values:

* thick line and band: everything a walk samples from held at the published
  material (``lobe_probs=`` and ``sampling=``, detached directions), with the
  band at +-1 Monte Carlo standard error;
* medium line: the lobe-selection probabilities held fixed (``lobe_probs=``, as
  ``jaxcos.fit`` does), the directions drawn from the scanned material's own
  lobes (attached, by reparameterization): steep continuous features along
  ``g1``, ``g2``, ``alpha_p``, ``theta_p`` and ``phi_p``;
* thin line: the lobe probabilities recomputed from the material at every
  point (``simulate``'s default), which moves the lobe thresholds and so
  changes which lobe some walks pick. The probabilities depend on ``c_d``,
  ``w_g``, the albedos and ``alpha_p`` only: for the other parameters it
  coincides with the medium line.

Each panel's title gives the largest "jump" of each scan over all 6 pairs x 3
channels, in standard errors: the trapezoid residual
``|f(s_k+1) - f(s_k) - (f'(s_k) + f'(s_k+1)) ds / 2|`` (``f'`` by forward-mode
AD, ``s`` the scan variable, logarithmic for ``t`` and ``alpha_p``) over the
smaller standard error of the two points. See the section "Evidence" of
``docs/derivatives.md`` and ``tests/test_gradients.py`` for what the numbers
mean.

Budget: ``--walks`` walks, 64 bounces, ``--points`` points per scan, one
compiled program per scheme; about two minutes on two CPU cores.
"""

import argparse
import os
import time

import jax
import jax.numpy as jnp
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

import jaxcos  # noqa: E402

TI = [15.0, 15.0, 15.0, 45.0, 45.0, 45.0]
TO = [-40.0, 17.0, 35.0, -10.0, 47.0, 65.0]
PLOT_PAIR, PLOT_CHANNEL = 4, 1  # (45, 47) degrees, green
BOUNCES = 64
CHUNK = 512
KEY = 7
NAMES = ("t", "c_d", "albedo_d0", "albedo_d1", "albedo_d2", "g1", "g2", "w_g", "albedo_p0", "albedo_p1",
         "albedo_p2", "alpha_p", "theta_p", "phi_p")
IDX = {n: i for i, n in enumerate(NAMES)}
SCANS = {  # name: (low, high, log-spaced, label)
    "t": (0.5, 20.0, True, "t"), "c_d": (0.05, 0.95, False, "c_d"), "albedo_d1": (0.0, 1.0, False, "albedo_d (green)"),
    "w_g": (0.0, 1.0, False, "w_g"), "albedo_p1": (0.0, 1.0, False, "albedo_p (green)"),
    "g1": (-0.9, 0.9, False, "g1"), "g2": (-0.9, 0.9, False, "g2"), "alpha_p": (0.01, 1.0, True, "alpha_p"),
    "theta_p": (0.0, 60.0, False, "theta_p [deg]"), "phi_p": (-90.0, 90.0, False, "phi_p [deg]"),
}
PRODUCTS = ("dewy1", "matte2")


def _vec(material):
    l = material.layers[0]
    return np.concatenate([[l.t, l.c_d], l.albedo_d, [l.g1, l.g2, l.w_g], l.albedo_p,
                           [l.alpha_p, l.theta_p, l.phi_p]]).astype(np.float32)


def _material(v):
    layer = jaxcos.Layer(t=v[0], c_d=v[1], albedo_d=v[2:5], g1=v[5], g2=v[6], w_g=v[7], albedo_p=v[8:11],
                         alpha_p=v[11], theta_p=v[12], phi_p=v[13])
    return jaxcos.Material(layers=(layer,))


MODES = ("detached", "attached", "recomputed")


def _program(walks, detached):
    query = jaxcos.make_query(TI, TO)

    def one(v, dv, lp, key, ref):
        def est(v):
            e = jaxcos.simulate(_material(v), query, key, walks=walks, bounces=BOUNCES, lobe_probs=lp,
                                sampling=_material(ref) if detached else None)
            return e.f, e.stderr

        (f, se), (df, _) = jax.jvp(est, (v,), (dv,))
        return f, se, df

    return jax.jit(jax.vmap(one))


def _run(program, v, dv, lp, ref):
    n, out = len(v), []
    key = jax.random.key(KEY)
    for a in range(0, n, CHUNK):
        idx = np.minimum(np.arange(a, a + CHUNK), n - 1)
        res = program(v[idx], dv[idx], lp[idx], jnp.stack([key] * CHUNK), ref[idx])
        out.append([np.asarray(r)[: min(CHUNK, n - a)] for r in res])
    return tuple(np.concatenate([o[i] for o in out]) for i in range(3))


def scans(walks, points):
    """``{(product, name, mode): (x, s, f, se, df)}`` with f, se, df of shape ``(points, 18)``."""
    out = {}
    for mode in MODES:
        rows, v_all, dv_all, lp_all, ref_all = [], [], [], [], []
        for product in PRODUCTS:
            material = jaxcos.published(product)
            v0, lp0 = _vec(material), np.asarray(jaxcos.lobe_probabilities(material))
            for name, (lo, hi, log, _) in SCANS.items():
                s = np.linspace(np.log(lo), np.log(hi), points) if log else np.linspace(lo, hi, points)
                x = np.exp(s) if log else s
                rows.append((product, name, x, s))
                for xi in x:
                    v = v0.copy()
                    v[IDX[name]] = xi
                    dv = np.zeros_like(v)
                    dv[IDX[name]] = xi if log else 1.0
                    v_all.append(v), dv_all.append(dv), ref_all.append(v0)
                    lp_all.append(np.asarray(jaxcos.lobe_probabilities(_material(jnp.asarray(v))))
                                  if mode == "recomputed" else lp0)
        f, se, df = _run(_program(walks, mode == "detached"), np.array(v_all), np.array(dv_all),
                         np.array(lp_all, np.float32), np.array(ref_all))
        for i, (product, name, x, s) in enumerate(rows):
            sl = slice(i * points, (i + 1) * points)
            out[product, name, mode] = (x, s, f[sl].reshape(points, -1), se[sl].reshape(points, -1),
                                        df[sl].reshape(points, -1))
    return out


def jump_fraction(s, f, se, df):
    """Largest trapezoid residual over the smaller SE of its two ends, over all intervals and components."""
    ds = np.diff(s)[:, None]
    r = f[1:] - f[:-1] - 0.5 * (df[1:] + df[:-1]) * ds
    return float(np.max(np.abs(r) / np.minimum(se[1:], se[:-1])))


def figure(results, path, walks):
    ncol = 5
    fig, axes = plt.subplots(4, ncol, figsize=(17, 12.5), constrained_layout=True)
    comp = PLOT_PAIR * 3 + PLOT_CHANNEL
    for p, product in enumerate(PRODUCTS):
        for j, (name, (lo, hi, log, label)) in enumerate(SCANS.items()):
            ax = axes[2 * p + j // ncol, j % ncol]
            x, s, f, se, df = results[product, name, "detached"]
            ax.fill_between(x, f[:, comp] - se[:, comp], f[:, comp] + se[:, comp], color="C0", alpha=0.25, lw=0)
            ax.plot(x, f[:, comp], color="C0", lw=1.8, label="lobe probabilities and directions fixed (detached)")
            ax.plot(x, results[product, name, "attached"][2][:, comp], color="C1", lw=1.0,
                    label="lobe probabilities fixed, directions attached")
            ax.plot(x, results[product, name, "recomputed"][2][:, comp], color="C3", lw=0.6,
                    label="lobe probabilities recomputed at each point")
            if log:
                ax.set_xscale("log")
            ax.set_xlabel(label)
            jumps = " | ".join(f"{jump_fraction(*results[product, name, m][1:]):.2g}" for m in MODES)
            ax.set_title(f"{product}: max jump/SE {jumps}", fontsize=8.5)
            if j % ncol == 0:
                ax.set_ylabel("f(45°, 47°), green [1/sr]")
    axes[0, 0].legend(fontsize=8, loc="best")
    fig.suptitle(f"Estimates under one fixed key ({walks} walks, {BOUNCES} bounces) along 1-D parameter scans, "
                 f"band: ±1 standard error; titles: max jump/SE detached | attached | recomputed", fontsize=12)
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "..", "docs", "crn_scans.png"))
    parser.add_argument("--walks", type=int, default=64)
    parser.add_argument("--points", type=int, default=81)
    args = parser.parse_args()
    start = time.time()
    results = scans(args.walks, args.points)
    figure(results, args.out, args.walks)
    print(f"max jump / SE over all pairs and channels ({args.walks} walks, {args.points} points):")
    for product in PRODUCTS:
        for name in SCANS:
            print(f"  {product:7s} {name:10s} " + "   ".join(
                f"{mode} {jump_fraction(*results[product, name, mode][1:]):8.3f}" for mode in MODES))
    print(f"wrote {os.path.normpath(args.out)} in {time.time() - start:.0f} s")


if __name__ == "__main__":
    main()
