"""Reference numbers of the shipped kernels, kept in kernel_numbers.json beside this script and checked by
tests/test_kernel_numbers.py: every method of every kernel contract on small fixed inputs, ML-II's NLML and
gradient (workspace and materialised paths), the sparse bound and its gradient, and the linearised and Monte
Carlo free runs of a small GPNARX per kernel spec at fixed hyperparameters (ML-II's on that record).

Regenerate only on purpose (a deliberate change of the numbers): ``python tests/data/kernel_numbers.py``.
"""
from __future__ import annotations

import json
import os
from pathlib import Path

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")  # one BLAS thread, as the test suite runs (tests/conftest.py)

import numpy as np  # noqa: E402

OUT = Path(__file__).with_name("kernel_numbers.json")
SPECS = ["matern32+cubic", "matern32", "rbf", "rbf+cubic+white", "cubic"]


def kernels():
    """The shipped kernels at fixed parameters, by a name the test rebuilds them from."""
    from gpnarx.model.kernels import RBF, CubicPolynomial, Matern32, White

    return {
        "matern32": Matern32(1.3, 0.9),
        "rbf": RBF(0.7, 1.4),
        "cubic": CubicPolynomial(0.3, 0.5, 1.1),
        "cubic_capped": CubicPolynomial(0.3, 0.5, 20.0, constant_cap=5.0),
        "white": White(0.2),
    }


def inputs():
    rng = np.random.default_rng(51)
    return {"X": rng.normal(size=(6, 3)), "X2": rng.normal(size=(5, 3)), "w": rng.normal(size=5),
            "beta": rng.normal(size=5)}


def record(n: int, seed: int):
    """A small nonlinear second-order system: input u, output y (with 5 % noise)."""
    rng = np.random.default_rng(seed)
    u = rng.normal(size=n)
    y = np.zeros(n)
    for t in range(2, n):
        y[t] = 0.5 * y[t - 1] - 0.2 * y[t - 2] + np.tanh(u[t - 1]) + 0.2 * u[t - 2] * y[t - 1]
    return u, y + 0.05 * np.std(y) * rng.normal(size=n)


def _a(x):
    return None if x is None else np.asarray(x, dtype=float).tolist()


def kernel_methods(k, X, X2, w, beta) -> dict:
    """Every contract method of one kernel at the inputs (None where the kernel refuses)."""
    from gpnarx.model.kernels.base import _r2_from_gram

    ny = 2
    G = X @ X2.T
    sq1, sq2 = np.einsum("ij,ij->i", X, X), np.einsum("ij,ij->i", X2, X2)
    out = {"call": _a(k(X, X2)), "call_self": _a(k(X)), "from_gram": _a(k.from_gram(G, sq1, sq2)),
           "diag": _a(k.diag(X)), "cap_shift": float(k.cap_shift())}
    try:
        K, grads = k.K_and_grads(X)
        out["K_and_grads"] = [_a(K)] + [_a(g) for g in grads]
    except ValueError:  # a capped kernel is for posteriors only
        out["K_and_grads"] = None
    out["iter_cross_grads"] = [_a(g) for g in k.iter_cross_grads(G, sq1, sq2)]
    d, dg = k.diag_and_grads(X)
    out["diag_and_grads"] = [_a(d)] + [_a(g) for g in dg]
    x = X[0]
    out["grad_x"] = _a(k.grad_x(x, X2))
    out["grad_dot"] = _a(k.grad_dot(X, X2, w))
    Kv, gd = k.value_and_grad_dot(X, X2, w, G, sq1, sq2)
    out["value_and_grad_dot"] = [_a(Kv), _a(gd)]
    kv, J, hess = k.local_terms(x, X2, ny)
    out["local_terms"] = [_a(kv), _a(J), _a(hess(beta))]
    d0, dgl, dH = k.diag_local(x, ny)
    out["diag_local"] = [float(d0), _a(dgl), _a(dH)]
    Xa = X[:3]
    Ga = Xa @ X2.T
    sqa = np.einsum("ij,ij->i", Xa, Xa)
    prof = k.local_profile(_r2_from_gram(Ga, sqa, sq2), Ga, sqa)
    out["local_profile"] = {f: (_a(getattr(prof, f)) if f in "k kd a b p q t".split() else float(getattr(prof, f)))
                            for f in ("k", "kd", "a", "b", "p", "q", "t", "dg", "dH", "dI")}
    terms = k.mean_terms(w)
    r2 = _r2_from_gram(Ga, sqa, sq2)[0]
    fills = []
    for scale, fill in terms.profiles:
        f = np.empty_like(r2)
        fill(r2.copy(), f)
        fills.append([float(scale), _a(f)])
    out["mean_terms"] = {"const": float(terms.const), "moments": None if terms.moments is None else
                         [float(m) for m in terms.moments], "profiles": fills}
    return out


def ml2_numbers(spec: str, ulp_seed: int | None = None) -> dict:
    """NLML and gradient (workspace, materialised) and the sparse bound with its gradient at fixed theta
    (perturbed by one unit in the last place per entry, of random sign, with ``ulp_seed``)."""
    from gpnarx.model.kernels import make_kernel
    from gpnarx.model.ml2 import NLMLWorkspace, _nlml_and_grad_generic, initial_theta, nlml_and_grad
    from gpnarx.model.vfe import vfe_nlml_and_grad

    rng = np.random.default_rng(7)
    X = rng.normal(size=(90, 3))  # 90 rows: two row blocks of the workspace
    y = np.tanh(X[:, 0]) + 0.3 * X[:, 1] * X[:, 2] + 0.05 * rng.normal(size=90)
    k = make_kernel(spec)
    th = initial_theta(k, X, y) + rng.normal(0, 0.3, k.n_params + 1)
    if ulp_seed is not None:
        th = th + np.random.default_rng(ulp_seed).choice([-1.0, 1.0], th.size) * np.spacing(th)
    f, g = nlml_and_grad(th, k, X, y, NLMLWorkspace(k, X, chunk=64))
    f0, g0 = _nlml_and_grad_generic(th, k, X, y, float(np.exp(th[-1])))
    fv, gv = vfe_nlml_and_grad(th, k, X, y, X[::4].copy())
    return {"theta": _a(th), "nlml": float(f), "grad": _a(g), "nlml_generic": float(f0), "grad_generic": _a(g0),
            "vfe": float(fv), "vfe_grad": _a(gv)}


def ml2_floors(spec: str, n: int = 8) -> dict:
    """Per quantity of ``ml2_numbers``, the largest relative change (normwise) that one-ulp perturbations of
    theta make: the quantity's own round-off floor (large for the sparse bound of an ill-conditioned K_mm)."""
    base = ml2_numbers(spec)
    floors = dict.fromkeys(base, 0.0)
    for seed in range(n):
        new = ml2_numbers(spec, ulp_seed=seed)
        for key, b in base.items():
            a, b = np.asarray(new[key]), np.asarray(b)
            floors[key] = max(floors[key], float(np.max(np.abs(a - b)) / np.max(np.abs(b))))
    floors.pop("theta")
    return floors


def fit_numbers(spec: str, theta=None) -> dict:
    """A small GPNARX (exact; sparse for the paper's kernel): ML-II's theta (or the given one) and the
    free runs (linearised; Monte Carlo, 64 paths, seed 0) on a second record."""
    from gpnarx.model.estimator import GPNARX

    u, y = record(400, 1)
    u2, _ = record(120, 2)
    out = {}
    for mode in ("exact", "sparse") if spec == "matern32+cubic" else ("exact",):
        kw = {"n_inducing": 40} if mode == "sparse" else {}
        m = GPNARX(ny=2, nu=2, kernel=spec, mode=mode, max_train_points=150, n_restarts=0, **kw)
        th = None if theta is None else np.asarray(theta[mode]["theta"])
        m.fit([(u, y)], theta=th)
        lin = m.simulate(u2, method="linear")
        mc = m.simulate(u2, method="mc", n_paths=64, seed=0)
        out[mode] = {"theta": _a(m.theta_), "nlml": float(m.nlml_), "linear_mean": _a(lin.mean),
                     "linear_std": _a(lin.std), "mc_mean": _a(mc.mean), "mc_std": _a(mc.std),
                     "mc_local_steps": int(mc.local_steps)}
    return out


def main() -> None:
    from threadpoolctl import threadpool_limits

    threadpool_limits(limits=1)
    ins = inputs()
    data = {"kernels": {name: kernel_methods(k, ins["X"], ins["X2"], ins["w"], ins["beta"])
                        for name, k in kernels().items()},
            "ml2": {spec: ml2_numbers(spec) for spec in SPECS},
            "ml2_floor": {spec: ml2_floors(spec) for spec in SPECS},
            "fits": {spec: fit_numbers(spec) for spec in SPECS}}
    OUT.write_text(json.dumps(data, indent=0, sort_keys=True) + "\n")
    print(f"wrote {OUT} ({OUT.stat().st_size} bytes)")


if __name__ == "__main__":
    main()
