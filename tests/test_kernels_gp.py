import numpy as np
import pytest

from gpnarx.model.kernels import (
    CONTRACTS,
    RBF,
    CubicPolynomial,
    GradientKernel,
    Kernel,
    LinearisableKernel,
    LocalKernel,
    Matern32,
    SparseBoundKernel,
    Sum,
    White,
    WorkspaceKernel,
    kernel_from_dict,
    make_kernel,
)
from gpnarx.model.linalg import NotPositiveDefiniteError, cholesky_jitter
from gpnarx.model.ml2 import fit_ml2, initial_theta, nlml_and_grad


def test_paper_kernel_equals_direct_evaluation():
    rng = np.random.default_rng(3)
    X, X2 = rng.normal(size=(30, 7)), rng.normal(size=(20, 7))
    sm, ell, sp, s, b = 1.7, 2.3, 0.4, 0.6, 1.3
    k = Matern32(sm, ell) + CubicPolynomial(sp, s, b)
    K = k(X, X2)
    direct = np.empty((30, 20))
    for i in range(30):
        for j in range(20):
            r = np.sqrt(np.sum((X[i] - X2[j]) ** 2))
            k1 = sm * (1 + np.sqrt(3) * r / ell) * np.exp(-np.sqrt(3) * r / ell)  # eq. (10)
            k2 = sp * (s * (X[i] @ X2[j]) + b) ** 3  # eq. (11)
            direct[i, j] = k1 + k2  # eq. (12)
    assert np.max(np.abs(K - direct)) < 1e-12 * np.max(np.abs(direct))
    assert np.allclose(k.cross(X, X2), direct, rtol=1e-12, atol=1e-12)
    Kself = k(X)
    assert np.allclose(np.diag(Kself), k.diag(X), rtol=1e-12)


@pytest.mark.parametrize("kernel", [Matern32(1.2, 0.8), RBF(0.7, 1.5), CubicPolynomial(0.3, 0.5, 1.1), White(0.2),
                                    Matern32() + CubicPolynomial()])
def test_kernel_parameter_gradients_match_finite_differences(kernel):
    rng = np.random.default_rng(0)
    X = rng.normal(size=(12, 4))
    _, grads = kernel.K_and_grads(X)
    th = kernel.get_theta()
    for j in range(th.size):
        e = np.zeros_like(th)
        e[j] = 1e-6
        kernel.set_theta(th + e)
        Kp = kernel(X)
        kernel.set_theta(th - e)
        Km = kernel(X)
        kernel.set_theta(th)
        fd = (Kp - Km) / 2e-6
        assert np.allclose(grads[j], fd, rtol=1e-5, atol=1e-8)


@pytest.mark.parametrize("kernel", [Matern32(1.2, 0.8), RBF(0.7, 1.5), CubicPolynomial(0.3, 0.5, 1.1)])
def test_kernel_input_gradient(kernel):
    rng = np.random.default_rng(1)
    X = rng.normal(size=(9, 3))
    xs = rng.normal(size=3)
    g = kernel.grad_x(xs, X)
    for d in range(3):
        e = np.zeros(3)
        e[d] = 1e-6
        fd = (kernel(xs[None] + e, X)[0] - kernel(xs[None] - e, X)[0]) / 2e-6
        assert np.allclose(g[:, d], fd, rtol=1e-5, atol=1e-8)


def test_nlml_gradient_matches_finite_differences():
    rng = np.random.default_rng(0)
    X = rng.normal(size=(80, 5))
    y = np.sin(X[:, 0]) + 0.1 * rng.normal(size=80)
    k = make_kernel("matern32+cubic")
    th = initial_theta(k, X, y) + rng.normal(0, 0.3, 6)
    _, g = nlml_and_grad(th, k, X, y)
    fd = np.empty_like(g)
    for j in range(th.size):
        e = np.zeros_like(th)
        e[j] = 1e-6
        fd[j] = (nlml_and_grad(th + e, k, X, y)[0] - nlml_and_grad(th - e, k, X, y)[0]) / 2e-6
    rel = np.max(np.abs(g - fd) / np.maximum(np.abs(fd), 1e-8))
    assert rel < 1e-5, rel


def test_nlml_objective_is_public_per_backend():
    """fit_ml2's objective of the numpy backend is nlml_and_grad itself (benchmarks time that, no wrapper)."""
    from gpnarx.model.ml2 import nlml_objective

    assert nlml_objective() is nlml_and_grad and nlml_objective("numpy") is nlml_and_grad
    with pytest.raises(ValueError, match="backend"):
        nlml_objective("torch")


@pytest.mark.parametrize("spec", ["matern32+cubic", "rbf+cubic+white", "matern32"])
def test_workspace_nlml_equals_materialised_gradients(spec):
    """The fused lower-triangle workspace path equals the textbook one (every dK materialised)."""
    from gpnarx.model.ml2 import NLMLWorkspace, _nlml_and_grad_generic

    rng = np.random.default_rng(5)
    X = rng.normal(size=(150, 4))  # 150 rows: several row blocks of the workspace (chunk 64)
    y = np.cos(X[:, 1]) + 0.1 * rng.normal(size=150)
    k = make_kernel(spec)
    th = initial_theta(k, X, y) + rng.normal(0, 0.3, k.n_params + 1)
    ws = NLMLWorkspace(k, X)
    assert ws.fused
    for _ in range(2):  # second call reuses the buffers
        f, g = nlml_and_grad(th, k, X, y, ws)
        f0, g0 = _nlml_and_grad_generic(th, k, X, y, float(np.exp(th[-1])))
        assert abs(f - f0) <= 1e-9 * abs(f0)
        assert np.max(np.abs(g - g0)) <= 1e-8 * np.max(np.abs(g0))
        th = th + 0.1


def test_warm_started_ml2_no_worse_than_cold():
    """fit_ml2(warm_start_subset=N/4) reaches an NLML no worse than the cold fit, in fewer full-N evaluations."""
    rng = np.random.default_rng(7)
    n = 400
    X = rng.normal(size=(n, 4))
    y = np.tanh(X[:, 0]) + 0.3 * X[:, 1] * X[:, 2] + 0.05 * rng.normal(size=n)
    cold = fit_ml2(make_kernel("matern32+cubic"), X, y, n_restarts=0)
    warm = fit_ml2(make_kernel("matern32+cubic"), X, y, n_restarts=0, warm_start_subset=n // 4)
    print(f"\ncold NLML {cold.nlml:.4f} ({cold.n_evals} evals), warm NLML {warm.nlml:.4f} "
          f"({warm.n_evals} full + {warm.subset_evals} on {warm.subset_rows} rows)")
    assert warm.subset_rows == n // 4 and warm.subset_evals > 0
    assert warm.nlml <= cold.nlml + 1e-6 * abs(cold.nlml) + 1e-3
    assert warm.n_evals < cold.n_evals


def test_ml2_improves_nlml_and_sets_kernel():
    rng = np.random.default_rng(2)
    X = rng.normal(size=(150, 3))
    y = np.tanh(X[:, 0]) + 0.05 * rng.normal(size=150)
    k = make_kernel("rbf")
    th0 = initial_theta(k, X, y)
    f0, _ = nlml_and_grad(th0, k, X, y)
    res = fit_ml2(k, X, y, n_restarts=1, seed=0)
    assert res.nlml < f0
    assert np.allclose(k.get_theta(), res.theta[:-1])
    assert 1e-4 < np.exp(res.theta[-1]) < 0.05  # noise variance near 0.05^2 on standardised-ish data


def test_jitter_escalation_and_clear_error():
    X = np.ones((5, 2))
    K = RBF()(X)  # rank one
    L, jitter = cholesky_jitter(K)
    assert jitter > 0 and np.all(np.isfinite(L))
    with pytest.raises(NotPositiveDefiniteError, match="not positive definite"):
        cholesky_jitter(-np.eye(3))


def test_kernel_round_trip_and_whitelist():
    k = Matern32(2.0, 3.0) + CubicPolynomial(0.1, 0.2, 0.3)
    k2 = kernel_from_dict(k.to_dict())
    X = np.random.default_rng(0).normal(size=(5, 2))
    assert np.array_equal(k(X), k2(X))
    with pytest.raises(ValueError, match="unknown kernel type"):
        kernel_from_dict({"type": "os.system", "theta": []})
    with pytest.raises(ValueError, match="unknown part"):
        make_kernel("matern72")
    assert isinstance(make_kernel("matern32+cubic"), Sum)


def test_capped_cubic_kernel_only_replaces_the_constant_term():
    # sigma_p^2 (s x.x' + b)^3 with sigma_p^2 b^3 = 1e4: the cap replaces that constant, nothing else
    k = CubicPolynomial(1e-2, 2e-3, 100.0)
    c0 = 1e-2 * 100.0**3
    capped = k.for_posterior(1.0)
    assert k.constant_cap is None and capped.constant_cap == 1.0
    rng = np.random.default_rng(0)
    X, X2 = rng.normal(size=(6, 3)), rng.normal(size=(4, 3))
    shift = c0 - 1.0
    assert np.allclose(capped(X, X2), k(X, X2) - shift, rtol=0, atol=1e-8)
    assert np.allclose(capped.diag(X), k.diag(X) - shift, rtol=0, atol=1e-8)
    G = X @ X2.T
    sq1, sq2 = np.einsum("ij,ij->i", X, X), np.einsum("ij,ij->i", X2, X2)
    assert np.allclose(capped.from_gram(G, sq1, sq2), capped(X, X2), rtol=1e-12, atol=0)
    assert np.allclose(capped.grad_x(X[0], X2), k.grad_x(X[0], X2))
    # a cap above the constant changes nothing
    assert np.allclose(k.for_posterior(1e6)(X, X2), k(X, X2), rtol=1e-12)
    # the cap travels with the kernel (bundles), a Sum caps its cubic part, ML-II refuses a capped kernel
    s = (Matern32(1.0, 2.0) + k).for_posterior(1.0)
    s2 = kernel_from_dict(s.to_dict())
    assert s2.parts[1].constant_cap == 1.0 and np.array_equal(s2(X, X2), s(X, X2))
    with pytest.raises(ValueError, match="constant_cap"):
        kernel_from_dict({"type": "CubicPolynomial", "theta": [0.0, 0.0, 0.0], "constant_cap": -1})
    with pytest.raises(ValueError, match="ML-II uses the uncapped"):
        capped.K_and_grads(X)


class _Linear(Kernel, GradientKernel, WorkspaceKernel, SparseBoundKernel):
    """A kernel written outside the package: var x.x' with its own workspace and gradient formulas (the
    contracts of ML-II, its workspace and the sparse bound; not the free runs' linearisation or local model)."""

    param_names = ("variance",)
    log_param_bounds = {"variance": (-5.0, 5.0)}
    workspace_input = "gram"

    def __init__(self, variance=1.0):
        self.theta = np.log([variance])

    def __call__(self, X, X2=None):
        return np.exp(self.theta[0]) * (X @ (X if X2 is None else X2).T)

    def K_and_grads(self, X):
        K = self(X)
        return K, [K.copy()]

    def from_gram(self, G, sq1, sq2):
        return np.exp(self.theta[0]) * G

    def iter_cross_grads(self, G, sq1, sq2):
        yield np.exp(self.theta[0]) * G

    def diag_and_grads(self, X, q=None):
        d = np.exp(self.theta[0]) * np.einsum("ij,ij->i", X, X)
        return d, [d.copy()]

    def block_value(self, base, buf):
        return np.exp(self.theta[0]) * base

    def block_grad_sums(self, W, base, buf):
        return np.array([np.einsum("ij,ij->", W, base)])

    def grads_from_sums(self, sums, tr_w):
        return [np.exp(self.theta[0]) * sums[0]]


def test_a_new_kernel_brings_its_own_formulas_to_ml2_and_vfe():
    """Kernels own their formulas: ML-II's workspace and the sparse bound use a kernel defined outside the
    package through its methods alone (no list of known types), with the same numbers as the textbook path;
    starting values, per-parameter bounds and redundant parameters come from the parts."""
    from gpnarx.model.ml2 import NLMLWorkspace, _nlml_and_grad_generic
    from gpnarx.model.vfe import vfe_nlml_and_grad

    rng = np.random.default_rng(11)
    X = rng.normal(size=(140, 3))
    y = X[:, 0] - 0.5 * X[:, 2] + np.sin(X[:, 1]) + 0.1 * rng.normal(size=140)
    k = make_kernel("matern32+cubic") + _Linear(0.5)
    ws = NLMLWorkspace(k, X)
    assert ws.fused
    th = initial_theta(k, X, y) + rng.normal(0, 0.2, k.n_params + 1)
    f, g = nlml_and_grad(th, k, X, y, ws)
    f0, g0 = _nlml_and_grad_generic(th, k, X, y, float(np.exp(th[-1])))
    assert abs(f - f0) <= 1e-9 * abs(f0) and np.max(np.abs(g - g0)) <= 1e-8 * np.max(np.abs(g0))
    # the sparse bound's gradient (the kernel's iter_cross_grads / diag_and_grads) against finite differences
    Z = X[::3].copy()
    _, gv = vfe_nlml_and_grad(th, k, X, y, Z, jitter=0.0)
    for j in range(th.size):
        e = np.zeros_like(th)
        e[j] = 1e-6
        fd = (vfe_nlml_and_grad(th + e, k, X, y, Z, jitter=0.0)[0]
              - vfe_nlml_and_grad(th - e, k, X, y, Z, jitter=0.0)[0]) / 2e-6
        assert abs(gv[j] - fd) <= 1e-4 * max(abs(fd), 1.0), (j, gv[j], fd)
    assert k.log_bounds()[-1] == (-5.0, 5.0) and k.log_bounds()[0] == (-12.0, 12.0)
    assert k.redundant_indices() == [3]  # the cubic part's log scale: Matern32 has 2 parameters first
    assert initial_theta(k, X, y)[-2] == k.parts[-1].theta[0]  # no rule of its own: its current theta


def test_kernels_meet_the_contracts_they_declare_and_consumers_refuse_the_others():
    """Each consumer asks a kernel for its own small contract (kernels.base): every shipped kernel meets all
    of them, a Sum meets one when every part does, and a consumer refuses a kernel that does not, naming the
    contract and the part (the linearised run), or leaves the optional fast path (ML-II's workspace, the
    Monte Carlo local model)."""
    from gpnarx.model import freerun, vfe
    from gpnarx.model.freerun.mc_local import has_local_model
    from gpnarx.model.gp import ExactPosterior
    from gpnarx.model.kernels import MeanTerms, require
    from gpnarx.model.ml2 import NLMLWorkspace
    from gpnarx.model.posterior import Posterior
    from gpnarx.model.scaling import Standardizer

    for k in (Matern32(), RBF(), CubicPolynomial(), White(), make_kernel("matern32+cubic")):
        assert all(k.supports(c) for c in CONTRACTS), k
    core = [n for n in vars(Kernel) if not n.startswith("__") or n in ("__call__", "__add__")]
    assert len(core) <= 18, core  # the core stays small: a consumer's needs go in its own contract
    mixed = make_kernel("matern32+cubic") + _Linear(0.5)
    assert mixed.supports(GradientKernel) and mixed.supports(SparseBoundKernel) and mixed.supports(WorkspaceKernel)
    assert not mixed.supports(LinearisableKernel) and not mixed.supports(LocalKernel)
    with pytest.raises(TypeError, match=r"needs a LinearisableKernel \(grad_x.*_Linear"):
        require(mixed, LinearisableKernel, "the linearised free run")

    class Bare(Kernel):  # the core alone: enough for a posterior, nothing else
        param_names = ("variance",)

        def from_gram(self, G, sq1, sq2):
            return np.exp(self.theta[0]) * G

        def __call__(self, X, X2=None):
            return self.from_gram(X @ (X if X2 is None else X2).T, None, None)

        def diag(self, X):
            return np.exp(self.theta[0]) * np.einsum("ij,ij->i", X, X)

    rng = np.random.default_rng(3)
    X, y = rng.normal(size=(40, 4)), rng.normal(size=40)
    assert not NLMLWorkspace(Bare(), X).fused
    with pytest.raises(TypeError, match="ML-II.*GradientKernel.*Bare"):
        fit_ml2(Bare(), X, y)
    with pytest.raises(TypeError, match="sparse bound.*Bare"):
        vfe.fit_vfe(Bare(), X, y, X[:5])
    post = ExactPosterior.fit(Bare(), 0.1, X, y)
    assert isinstance(post, Posterior) and not has_local_model(post)
    sc, ysc = Standardizer.from_arrays(np.zeros(4), np.ones(4)), Standardizer.from_arrays(np.zeros(1), np.ones(1))
    run = freerun.simulate_mc(post, sc, ysc, 2, 2, rng.normal(size=30), n_paths=64, seed=0)
    assert run.local_steps == 0 and np.all(np.isfinite(run.std))  # exact at every step, no local model
    with pytest.raises(TypeError, match=r"linearised free run.*LinearisableKernel.*Bare"):
        freerun.simulate_linear(post, sc, ysc, 2, 2, rng.normal(size=30))
    # a Sum's MeanTerms: the constants and moments of its parts add, the profiles line up in order
    w = rng.normal(size=40)
    t = (Matern32() + CubicPolynomial(2.0, 0.5, 1.5) + White() + RBF()).mean_terms(w)
    c = CubicPolynomial(2.0, 0.5, 1.5).mean_terms(w)
    assert isinstance(t, MeanTerms) and t.moments == c.moments and t.const == c.const and len(t.profiles) == 2
