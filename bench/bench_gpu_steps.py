"""Time per step of the JAX Monte Carlo block, variant by variant: where a GPU step's time goes.

A step of ``model.freerun_jax``'s compiled block is one Gram product of the paths' output lags with the
points, the kernel block K(x_paths, Z) (P x M), its products with the mean weights w (eq. 8) and with the
variance factor F (eq. 9: k(x, x) - |F k|^2), the draws and the lag shift. This bench builds the
block program of each variant here (from the bundle's arrays, the same formulas and precision as the
product) and times the second call of a block of steps, at several path counts:

* ``joint``: one product K [F^T | w] (N = M + 1 columns): the previous product code, the baseline;
* ``split``: K F^T (N = M) and K w apart: what the product does now;
* ``split_reduce``: K w as a row reduction instead of a product;
* ``tri``: F replaced by the R of its QR (|F k| = |R k|) and the triangle's zero block skipped;
* ``f32``: ``split`` in float32 (the real rig's variance cannot afford it: ``model/freerun_jax.py``);
* ``nostats``: ``split`` without the per-block quantiles (what the band statistics cost);
* ``product``: ``GPNARX.simulate(backend="jax")`` itself over the same steps (host loop, draws and
  statistics included).

``ratio=`` is joint / split per step at ``--paths``' first count (equal work: same arrays, steps, paths).

    python bench/bench_gpu_steps.py --bundle DIR --record REC [--paths 4096,1024] [--steps 8192] [--quick]

--quick: a small Bouc-Wen sparse model (M = 64), 64 paths, 64 steps; for the smoke test only.
"""
from __future__ import annotations

import time

import numpy as np

import _common as C


def _args(ap):
    ap.add_argument("--bundle", help="bundle folder (registry/NAME/VERSION)")
    ap.add_argument("--record", help="record file or LMS folder")
    ap.add_argument("--paths", default="4096,1024", help="comma-separated path counts")
    ap.add_argument("--steps", type=int, default=8192, help="steps timed per variant")


def _program(jax, jnp, model, P, variant):
    from gpnarx.model.freerun import LAG_CLIP
    from gpnarx.model.kernels.jax_forms import jax_kernel, kernel_theta

    post = model.posterior_
    ny = model.ny
    f32 = variant == "f32"
    dt = jnp.float32 if f32 else jnp.float64
    hi = jax.lax.Precision.HIGHEST
    Z, w, F = post.points, post.mean_weights, post.variance_factor
    if variant == "tri":
        F = np.linalg.qr(F, mode="r")
    M = Z.shape[0]
    h = M // 2
    jk = jax_kernel(post.kernel)
    theta = jnp.asarray(kernel_theta(post.kernel))
    xm, xs = model.x_scaler_.mean_, model.x_scaler_.scale_
    ym, ysc = float(model.y_scaler_.mean_[0]), float(model.y_scaler_.scale_[0])
    Zy, Zu = jnp.asarray(Z[:, :ny], dt), jnp.asarray(Z[:, ny:], dt)
    sqZ = jnp.asarray(np.einsum("ij,ij->i", Z, Z), dt)
    FT = jnp.asarray(np.ascontiguousarray(F.T), dt)
    FTw = jnp.asarray(np.column_stack([F.T, w]), dt)
    wv = jnp.asarray(w, dt)
    a, c = jnp.asarray(ysc / xs[:ny]), jnp.asarray((ym - xm[:ny]) / xs[:ny])
    shift, noise = post.mean_shift, post.noise_var
    qs = jnp.asarray([0.005, 0.995])

    def program(ystd, Ub, eps):
        Gu = jnp.matmul(Ub.astype(dt), Zu.T, precision=hi)
        su = jnp.sum(Ub * Ub, axis=1)

        def step(y_lags, inp):
            gu, s_u, e = inp
            Y = jnp.clip(y_lags * a + c, -LAG_CLIP, LAG_CLIP)
            sq = jnp.sum(Y * Y, axis=1) + s_u
            K = jk.cross(theta.astype(dt), jnp.matmul(Y.astype(dt), Zy.T, precision=hi) + gu[None, :],
                         sq.astype(dt), sqZ)
            if variant == "joint":
                KF = jnp.matmul(K, FTw, precision=hi)
                vv, mu = jnp.sum(KF[:, :-1] ** 2, axis=1), KF[:, -1]
            elif variant == "tri":
                V1 = jnp.matmul(K[:, :h], FT[:h, :h], precision=hi)
                V2 = jnp.matmul(K, FT[:, h:], precision=hi)
                vv, mu = jnp.sum(V1 * V1, axis=1) + jnp.sum(V2 * V2, axis=1), jnp.matmul(K, wv, precision=hi)
            else:
                V = jnp.matmul(K, FT, precision=hi)
                vv = jnp.sum(V * V, axis=1)
                mu = jnp.sum(K * wv, axis=1) if variant == "split_reduce" else jnp.matmul(K, wv, precision=hi)
            mu = mu.astype(jnp.float64) + shift
            var = jnp.maximum(jk.diag(theta, sq) - vv.astype(jnp.float64), 1e-300)
            ys = mu + jnp.sqrt(var + noise) * e
            fs = mu + jnp.sqrt(var) * e
            return jnp.concatenate([ys[:, None], y_lags[:, :-1]], axis=1), (ys, fs, jnp.mean(mu))

        ystd, (ys, fs, mus) = jax.lax.scan(step, ystd, (Gu, su, eps), unroll=8)
        yo, fo = ys * ysc + ym, fs * ysc + ym
        out = {"mean": mus * ysc + ym, "std": jnp.std(yo, axis=1)}
        if variant != "nostats":
            out["q"], out["lq"] = jnp.quantile(yo, qs, axis=1), jnp.quantile(fo, qs, axis=1)
        return ystd, out

    return jax.jit(program)


def _time_variant(jax, jnp, model, Ulag, P, steps, variant):
    C_ = min(2048, max(16, (1 << 23) // P), steps)
    prog = _program(jax, jnp, model, P, variant)
    key = jax.random.PRNGKey(0)
    y0 = jnp.zeros((P, model.ny))

    def go():
        ystd = y0
        t = time.perf_counter()
        for b, s0 in enumerate(range(0, steps - C_ + 1, C_)):
            eps = jax.random.normal(jax.random.fold_in(key, b), (C_, P), dtype=jnp.float64)
            ystd, out = prog(ystd, jnp.asarray(Ulag[s0:s0 + C_]), eps)
            jax.tree_util.tree_map(np.asarray, out)
        return (time.perf_counter() - t) / ((steps // C_) * C_)

    go()  # compile
    return go()


def main() -> None:
    args = C.parse_args(__doc__, _args)
    from gpnarx.model.backend import jax_device, require_jax
    from gpnarx.model.freerun.spec import lagged_inputs

    jax = require_jax()
    jnp = jax.numpy
    if args.quick:
        from gpnarx.model.estimator import GPNARX

        pairs, _, r50 = C.protocol()
        model = GPNARX(ny=C.NY, nu=C.NU, mode="sparse", n_inducing=64, max_train_points=500).fit(
            pairs, theta=C.THETA_REF)
        u, what, counts, steps = r50.u, "bouc-wen-quick-M64", [64], 64
    else:
        from gpnarx.storage.bundle import load_bundle
        from gpnarx.storage.record_files import read_record

        b = load_bundle(args.bundle)
        model, what = b.model, f"{b.name}:{b.version}"
        u = read_record(args.record, fs_default=b.fs).u
        counts, steps = [int(p) for p in args.paths.split(",")], int(args.steps)
    xm, xs = model.x_scaler_.mean_, model.x_scaler_.scale_
    Ulag = (lagged_inputs(u, model.nu) - xm[model.ny:]) / xs[model.ny:]
    steps = min(steps, Ulag.shape[0])
    device = jax_device()
    print(f"model {what}, device {device}, {steps} steps per variant", flush=True)
    us = {}
    for P in counts:
        for variant in ("joint", "split", "split_reduce", "tri", "f32", "nostats"):
            us[(variant, P)] = 1e6 * _time_variant(jax, jnp, model, Ulag, P, steps, variant)
            print(f"{variant} P {P}: {us[(variant, P)]:.1f} us/step", flush=True)
        model.simulate(u[:steps], n_paths=P, seed=0, backend="jax")
        t = time.perf_counter()
        model.simulate(u[:steps], n_paths=P, seed=0, backend="jax")
        us[("product", P)] = 1e6 * (time.perf_counter() - t) / steps
        print(f"product P {P}: {us[('product', P)]:.1f} us/step", flush=True)
    P0 = counts[0]
    fields = {f"{v}_us_p{P}": us[(v, P)] for (v, P) in us}
    C.result(bench="gpu_steps", device=device.replace(" ", "_"), model=what, steps=steps, paths=P0,
             product_us=us[("split", P0)], baseline=us[("joint", P0)], baseline_what="joint_product_K_FTw_same_run",
             ratio=us[("joint", P0)] / us[("split", P0)], **fields)


if __name__ == "__main__":
    main()
