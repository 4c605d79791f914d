"""The kernel contracts, the sum of kernels (``Sum``, eq. 12) and shared distance helpers.

Every kernel holds its hyperparameters in log space (``theta``), so ML-II (eq. 13) optimises an
unconstrained vector, and each kernel owns its formulas. ``Kernel`` is the core every kernel meets
(parameters, covariance, diagonal, serialisation: all a posterior needs); each consumer's needs are a
small contract of their own, which a kernel class joins by inheriting it:

* ``GradientKernel``: ML-II (eq. 13): dK/dtheta, starting values, bounds;
* ``WorkspaceKernel``: ML-II's fused workspace (``ml2.NLMLWorkspace``): K and its gradients by blocks;
* ``SparseBoundKernel``: the sparse bound of ``vfe``: cross-covariance and diagonal gradients;
* ``LinearisableKernel``: the linearised free run: the gradient of k(x*, X) in the test point x* and
  the kernel's share of the mean recursion (``MeanTerms``);
* ``LocalKernel``: the Monte Carlo free run's local model: second-order terms in the output lags.

``Kernel.supports(contract)`` says whether a kernel meets one (a ``Sum`` when every part does) and
``require`` refuses one that does not, naming the consumer and what is missing. A shipped kernel meets
them all by deriving from a family base that owns the derivations (``stationary.StationaryProfile``,
``dotproduct.DotProductProfile``) and declaring its formula there; ``class K(Base, spec="name")``
registers it for ``make_kernel`` and ``kernel_from_dict``. Inputs are standardised NARX regressors
(dimensionless).
"""
from __future__ import annotations

import copy
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

DEFAULT_LOG_BOUNDS = (-12.0, 12.0)  # every log-parameter unless a kernel's ``log_param_bounds`` says otherwise
KERNEL_TYPES: dict[str, type] = {}  # registered kernels by class name (``to_dict``'s "type")
KERNEL_SPECS: dict[str, type] = {}  # registered kernels by spec name (``make_kernel``'s parts)


def squared_distances(X: np.ndarray, X2: np.ndarray | None = None) -> np.ndarray:
    """Pairwise squared Euclidean distances by the expanded-norm identity |x|^2 + |x'|^2 - 2 x.x'.

    One BLAS-3 product; negatives from round-off are clipped to 0 and the diagonal of a
    self-distance matrix is set to exactly 0.
    """
    if X2 is None:
        sq = np.einsum("ij,ij->i", X, X)
        r2 = sq[:, None] + sq[None, :] - 2.0 * (X @ X.T)
        np.maximum(r2, 0.0, out=r2)
        np.fill_diagonal(r2, 0.0)
        return r2
    sq1 = np.einsum("ij,ij->i", X, X)
    sq2 = np.einsum("ij,ij->i", X2, X2)
    r2 = X @ X2.T
    r2 *= -2.0
    r2 += sq1[:, None]
    r2 += sq2[None, :]
    np.maximum(r2, 0.0, out=r2)
    return r2


def _r2_from_gram(G: np.ndarray, sq1: np.ndarray, sq2: np.ndarray) -> np.ndarray:
    r2 = G * -2.0
    r2 += sq1[:, None]
    r2 += sq2[None, :]
    np.maximum(r2, 0.0, out=r2)
    return r2


def _gram_parts(X1, X2, G=None, sq1=None, sq2=None):
    """(X1 X2^T, |x1|^2, |x2|^2), computing whichever was not given."""
    if G is None:
        G = X1 @ X2.T
    if sq1 is None:
        sq1 = np.einsum("ij,ij->i", X1, X1)
    if sq2 is None:
        sq2 = np.einsum("ij,ij->i", X2, X2)
    return G, sq1, sq2


class Kernel:
    """The core contract every kernel meets: its log-parameters, its covariance, its diagonal, a copy for
    posteriors and its serialisation. Posteriors (eqs. 8-9) and the exact Monte Carlo step need nothing
    more. What a consumer needs beyond this is a small contract of its own (below), which a kernel class
    joins by inheriting it; ``supports`` says whether a kernel (every part of a ``Sum``) meets one, and
    ``require`` refuses a kernel that does not, naming what is missing."""

    param_names: tuple[str, ...] = ()

    def __init_subclass__(cls, spec: str | None = None, **kw) -> None:
        """``class K(Kernel, spec="name")`` registers K for ``make_kernel`` (by spec) and ``kernel_from_dict``
        (by class name); a subclass without a spec of its own is not registered."""
        super().__init_subclass__(**kw)
        if spec is not None:
            if KERNEL_SPECS.get(spec, cls).__qualname__ != cls.__qualname__:
                raise ValueError(f"kernel spec {spec!r} is taken by {KERNEL_SPECS[spec].__name__}")
            cls.spec = spec
            KERNEL_SPECS[spec] = KERNEL_TYPES[cls.__name__] = cls

    def __init__(self) -> None:
        self.theta = np.zeros(len(self.param_names))

    @property
    def n_params(self) -> int:
        return len(self.param_names)

    def get_theta(self) -> np.ndarray:
        return np.array(self.theta, dtype=float)

    def set_theta(self, theta) -> None:
        theta = np.asarray(theta, dtype=float)
        if theta.shape != (self.n_params,):
            raise ValueError(f"theta must have {self.n_params} entries, got shape {theta.shape}")
        self.theta = theta.copy()

    @property
    def params(self) -> dict:
        """Hyperparameters in natural (not log) units, by name."""
        return {n: float(np.exp(t)) for n, t in zip(self.param_names, self.theta)}

    @property
    def parts(self) -> list["Kernel"]:
        """The summands of eq. (12): [self] for one kernel, the parts of a ``Sum``."""
        return [self]

    def supports(self, contract: type) -> bool:
        """Whether this kernel meets ``contract`` (one of the contracts below); a ``Sum`` when every part does."""
        return isinstance(self, contract)

    def __call__(self, X: np.ndarray, X2: np.ndarray | None = None) -> np.ndarray:
        raise NotImplementedError

    def from_gram(self, G: np.ndarray, sq1: np.ndarray, sq2: np.ndarray) -> np.ndarray:
        """Cross-covariance K(X1, X2) from the Gram matrix G = X1 X2^T and squared norms.

        Lets a sum of kernels share one BLAS-3 product per prediction step.
        """
        raise NotImplementedError

    def cross(self, X1: np.ndarray, X2: np.ndarray) -> np.ndarray:
        """K(X1, X2) through one shared Gram matrix."""
        return self.from_gram(X1 @ X2.T, np.einsum("ij,ij->i", X1, X1), np.einsum("ij,ij->i", X2, X2))

    def diag(self, X: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def __add__(self, other: "Kernel") -> "Sum":
        return Sum(self, other)

    def to_dict(self) -> dict:
        return {"type": type(self).__name__, "theta": [float(t) for t in self.theta]}

    def read_extra(self, d: dict) -> None:
        """Set what ``to_dict`` writes beside the theta (``kernel_from_dict``); nothing by default."""

    def jax_part(self):
        """(cross, diag, white) for ``jax_forms.jax_kernel``: cross(jnp, theta, G, sq1, sq2) or None (zero
        between points), diag(jnp, theta, sq), white True for a part that adds its variance on a training
        diagonal; None: no JAX form."""
        return None

    def clone(self) -> "Kernel":
        return copy.deepcopy(self)

    def for_posterior(self, constant_cap: float | None = None) -> "Kernel":
        """A copy with any constant term capped at ``constant_cap`` (see ``CubicPolynomial``);
        kernels without one return a plain copy. Posteriors take their variance from it."""
        return self.clone()

    def cap_shift(self) -> float:
        """How far the capped kernel lies below the uncapped one (a constant, >= 0; 0 if uncapped)."""
        return 0.0

    def __repr__(self) -> str:
        ps = ", ".join(f"{k}={v:.4g}" for k, v in self.params.items())
        return f"{type(self).__name__}({ps})"


def require(kernel: Kernel, contract: type, consumer: str) -> None:
    """Refuse (TypeError) a kernel that does not meet ``contract``, naming the consumer, the parts that
    lack it and the methods the contract asks for."""
    if kernel.supports(contract):
        return
    lacking = sorted({type(p).__name__ for p in kernel.parts if not p.supports(contract)})
    members = [n for n in vars(contract) if not n.startswith("_")]
    raise TypeError(f"{consumer} needs a {contract.__name__} ({', '.join(members)}); kernel part(s) "
                    f"{', '.join(lacking)} do not provide it")


class GradientKernel:
    """What ML-II (eq. 13, ``ml2.fit_ml2``, ``vfe.fit_vfe``) needs: dK/dtheta, starting values and bounds."""

    log_param_bounds: dict[str, tuple[float, float]] = {}  # per-parameter L-BFGS-B bounds in log space
    redundant: tuple[str, ...] = ()  # parameters another combination of the others can stand in for

    def K_and_grads(self, X: np.ndarray) -> tuple[np.ndarray, list[np.ndarray]]:
        """K(X, X) and [dK/dtheta_j] for each log-parameter."""
        raise NotImplementedError

    def initial_theta(self, var_y: float, median_distance: float, n_dims: int) -> np.ndarray:
        """Data-scaled starting log-parameters for ML-II (eq. 13) on standardised regressors: ``var_y``
        is the target variance, ``median_distance`` the median pairwise regressor distance and ``n_dims``
        the regressor dimension. Kernels without a rule start from their current theta."""
        return self.get_theta()

    def log_bounds(self) -> list[tuple[float, float]]:
        """Bounds on each log-parameter for L-BFGS-B, by name from ``log_param_bounds`` (default (-12, 12))."""
        return [tuple(self.log_param_bounds.get(n, DEFAULT_LOG_BOUNDS)) for n in self.param_names]

    def redundant_indices(self) -> list[int]:
        """Positions in theta of the parameters named in ``redundant`` (held fixed by ML-II on request)."""
        return [i for i, n in enumerate(self.param_names) if n in self.redundant]


class WorkspaceKernel:
    """Blocks of K for the ML-II workspace (``ml2.NLMLWorkspace``); a kernel without them takes the unfused
    path (``GradientKernel.K_and_grads``).

    The workspace precomputes, once per training set, what a kernel's blocks are a function of:
    ``workspace_input`` "distance" (r = |x - x'|) or "gram" (x.x'); None means the kernel only adds
    ``block_diagonal()`` to the diagonal. ``workspace_buffer`` asks for an N x N buffer the kernel
    fills in ``block_value`` and reads back in ``block_grad_sums`` (e.g. exp(-a)).
    """

    workspace_input: str | None = None
    workspace_buffer: bool = False

    def block_value(self, base: np.ndarray, buf: np.ndarray | None) -> np.ndarray:
        """One row block of K from the block ``base`` of the workspace input (a new array)."""
        raise NotImplementedError

    def block_diagonal(self) -> float:
        """Constant added to the diagonal of K(X, X) beyond ``block_value`` (White's variance)."""
        return 0.0

    def block_grad_sums(self, W: np.ndarray, base: np.ndarray, buf: np.ndarray | None) -> np.ndarray:
        """Partial sums over one block of W' (K^-1 - alpha alpha^T, lower triangle weighted) that
        ``grads_from_sums`` turns into gradients; one entry per sum the kernel needs."""
        return np.zeros(0)

    def grads_from_sums(self, sums: np.ndarray, tr_w: float) -> list[float]:
        """0.5 tr(W' dK/dtheta_j) per log-parameter from the summed block sums (lower triangle, so the
        full trace is twice the sum) and tr_w = tr(W')."""
        raise NotImplementedError


class SparseBoundKernel:
    """What the sparse (VFE) bound's gradient (``vfe``) needs: cross-covariance and diagonal gradients."""


    def iter_cross_grads(self, G: np.ndarray, sq1: np.ndarray, sq2: np.ndarray) -> Iterator[np.ndarray]:
        """dK(X1, X2)/dtheta_j for each log-parameter in order, from G = X1 X2^T and the squared norms.

        One (n1 x n2) array at a time, so the sparse bound (``vfe``) contracts and discards each."""
        raise NotImplementedError

    def diag_and_grads(self, X: np.ndarray, q: np.ndarray | None = None) -> tuple[np.ndarray, list[np.ndarray]]:
        """diag K(X, X) (N,) and [d diag / dtheta_j] for each log-parameter; q = |x|^2 when known."""
        raise NotImplementedError


@dataclass(frozen=True)
class MeanTerms:
    """A kernel's share of the posterior mean sum_m w_m k(x, z_m) (eq. 8), written in what the linearised
    free run's mean recursion (``freerun.linear``) computes once per step for all M points:
    g_m = z_m . x and r_m^2 = |x - z_m|^2 (standardised units).

    The share is ``const`` + sum_p moments[p-1] sum_m w_m g_m^p (p = 1..3; None: no such term) +
    sum over ``profiles`` (scale, fill) of scale * sum_m w_m f(r_m^2), where ``fill(a, out)`` writes
    f(r^2) into ``out`` from a = r^2 (a may be overwritten).
    """

    const: float = 0.0
    moments: tuple[float, float, float] | None = None
    profiles: tuple = ()


class LinearisableKernel:
    """What the linearised free run (``freerun.simulate_linear``) needs: the gradient of k(x*, X) in the
    test point x*, for one point (``grad_x``) and contracted with weights at many (``grad_dot``), and the
    kernel's share of the mean recursion (``mean_terms``)."""


    def grad_x(self, xs: np.ndarray, X: np.ndarray) -> np.ndarray:
        """d k(xs, X_n) / d xs for one test point xs (D,), returned as (N, D)."""
        raise NotImplementedError

    def grad_dot(self, Xs: np.ndarray, X: np.ndarray, w: np.ndarray, G: np.ndarray | None = None,
                 sq1: np.ndarray | None = None, sq2: np.ndarray | None = None) -> np.ndarray:
        """sum_n w_n d k(xs_r, X_n) / d xs_r for every row xs_r of Xs, as (rows, D): the gradient of a
        posterior mean K(xs, X) w (eq. 8) at many points at once. G = Xs X^T and the squared norms may
        be passed when already computed. This generic version loops over rows (``grad_x``)."""
        return np.stack([self.grad_x(x, X).T @ w for x in Xs]) if len(Xs) else np.zeros((0, X.shape[1]))

    def value_and_grad_dot(self, Xs, X, w, G, sq1, sq2):
        """(K(Xs, X), ``grad_dot``) from one Gram product; kernels that share work override it."""
        return self.from_gram(G, sq1, sq2), self.grad_dot(Xs, X, w, G, sq1, sq2)

    def mean_terms(self, w: np.ndarray) -> MeanTerms | None:
        """This kernel's ``MeanTerms`` for mean weights w (M,); None: no such form (the linearised run
        then takes its step-by-step loop)."""
        return None


class LocalKernel:
    """What the Monte Carlo free run's local model (``freerun.mc_local``) needs: second-order terms of
    k(x, X) and of k(x, x) in the output-lag coordinates. A kernel declares ``has_local_profile`` when
    ``local_profile`` gives them as coefficients (the local model's fused step); ``local_terms`` and
    ``diag_local`` then follow from it."""

    has_local_profile: bool = False

    def local_terms(self, x: np.ndarray, X: np.ndarray, ny: int):
        """Second-order terms of k(x, X_n) in the first ``ny`` coordinates of one point x (D,).

        Returns (k, J, hess): k = K(x, X) (N,), J = d k / d x[:ny] (N, ny), and hess(beta), the
        (ny, ny) matrix sum_n beta_n d^2 k(x, X_n) / d x[:ny]^2.
        """
        if not self.has_local_profile:
            raise NotImplementedError(f"{type(self).__name__} has no local_profile; it must define local_terms")
        d = x[None, :] - X
        prof = self.local_profile(np.einsum("ij,ij->i", d, d)[None, :], (X @ x)[None, :],
                                  np.array([float(x @ x)]))
        Dy, Zy = d[:, :ny], X[:, :ny]
        J = np.zeros((X.shape[0], ny))
        if prof.a is not None:
            J += prof.a[:, None] * Dy
        if prof.b is not None:
            J += prof.b[:, None] * Zy

        def hess(beta):
            H = np.zeros((ny, ny))
            if prof.p is not None:
                H += Dy.T @ ((beta * prof.p)[:, None] * Dy)
            if prof.t is not None:
                H += Zy.T @ ((beta * prof.t)[:, None] * Zy)
            if prof.q is not None:
                H[np.diag_indices(ny)] += beta @ prof.q
            return H

        return prof.k[0], J, hess

    def diag_local(self, x: np.ndarray, ny: int):
        """k(x, x), its gradient and Hessian in x[:ny] (float, (ny,), (ny, ny))."""
        if not self.has_local_profile:
            raise NotImplementedError(f"{type(self).__name__} has no local_profile; it must define diag_local")
        sq = float(x @ x)
        prof = self.local_profile(np.zeros((1, 1)), np.array([[sq]]), np.array([sq]))
        xy = x[:ny]
        H = prof.dH * np.outer(xy, xy)
        H[np.diag_indices(ny)] += prof.dI
        return float(prof.kd[0]), prof.dg * xy, H

    def local_profile(self, r2: np.ndarray, g: np.ndarray, sq: np.ndarray) -> LocalProfile | None:
        """``local_terms`` and ``diag_local`` as coefficients (``LocalProfile``), for ``LocalModel``'s
        fused step: r2 = |x_j - X_n|^2 and g = x_j . X_n (rows, N), sq = |x_j|^2 (rows,) for points x_j,
        the first of them the point x of the expansion; k(x_j, X_n) and k(x_j, x_j) at every row (as
        ``from_gram`` and ``diag`` give them), the derivatives at x. Only for ``has_local_profile``."""
        return None


@dataclass
class LocalProfile:
    """The second-order terms of k(x, X_n) (``LocalKernel.local_terms``) and of k(x, x)
    (``LocalKernel.diag_local``) as coefficients, with d = x - X_n and z = X_n in the output-lag
    coordinates:

        d k_n / d x = a_n d + b_n z,   d^2 k_n / d x^2 = p_n d d^T + q_n I + t_n z z^T   (vectors (N,)),
        d k(x, x) / d x = dg x,   d^2 k(x, x) / d x^2 = dH x x^T + dI I                (numbers),

    with k (rows, N) = k(x_j, X_n) and kd (rows,) = k(x_j, x_j) at the rows ``local_profile`` was given
    (the first is x). A coefficient vector that is zero for every point is None. ``Sum`` adds its
    parts' profiles.
    """

    k: np.ndarray
    kd: np.ndarray
    a: np.ndarray | None = None
    b: np.ndarray | None = None
    p: np.ndarray | None = None
    q: np.ndarray | None = None
    t: np.ndarray | None = None
    dg: float = 0.0
    dH: float = 0.0
    dI: float = 0.0

    def __add__(self, other: "LocalProfile") -> "LocalProfile":
        def add(u, v):
            return v if u is None else u if v is None else u + v

        return LocalProfile(self.k + other.k, self.kd + other.kd,
                            *(add(getattr(self, f), getattr(other, f)) for f in "abpqt"),
                            self.dg + other.dg, self.dH + other.dH, self.dI + other.dI)


CONTRACTS = (GradientKernel, WorkspaceKernel, SparseBoundKernel, LinearisableKernel, LocalKernel)


class Sum(Kernel, GradientKernel, SparseBoundKernel, LinearisableKernel, LocalKernel):
    """Sum of kernels, eq. (12): k = k1 + k2 (+ ...). Parameters are concatenated in order. It meets a
    contract when every part does (``supports``); ML-II's workspace walks the parts themselves."""

    def __init__(self, *parts: Kernel) -> None:
        flat: list[Kernel] = []
        for p in parts:
            flat.extend(p.parts)
        self._parts = flat

    @property
    def parts(self) -> list[Kernel]:  # type: ignore[override]
        return self._parts

    def supports(self, contract: type) -> bool:
        return all(p.supports(contract) for p in self._parts)

    @property
    def has_local_profile(self) -> bool:  # type: ignore[override]
        return all(getattr(p, "has_local_profile", False) for p in self._parts)

    @property
    def param_names(self):  # type: ignore[override]
        return tuple(f"{i}.{type(p).__name__}.{n}" for i, p in enumerate(self.parts) for n in p.param_names)

    @property
    def theta(self):  # type: ignore[override]
        return np.concatenate([p.theta for p in self.parts])

    @theta.setter
    def theta(self, value):
        self.set_theta(value)

    def set_theta(self, theta) -> None:
        theta = np.asarray(theta, dtype=float)
        if theta.shape != (self.n_params,):
            raise ValueError(f"theta must have {self.n_params} entries, got shape {theta.shape}")
        i = 0
        for p in self.parts:
            p.set_theta(theta[i : i + p.n_params])
            i += p.n_params

    def log_bounds(self):
        return [b for p in self.parts for b in p.log_bounds()]

    def __call__(self, X, X2=None):
        K = self.parts[0](X, X2)
        for p in self.parts[1:]:
            K += p(X, X2)
        return K

    def K_and_grads(self, X):
        K = None
        grads: list[np.ndarray] = []
        for p in self.parts:
            Kp, gp = p.K_and_grads(X)
            K = Kp if K is None else K + Kp
            grads.extend(gp)
        return K, grads

    def diag(self, X):
        return sum(p.diag(X) for p in self.parts)

    def from_gram(self, G, sq1, sq2):
        K = self.parts[0].from_gram(G, sq1, sq2)
        for p in self.parts[1:]:
            K += p.from_gram(G, sq1, sq2)
        return K

    def grad_x(self, xs, X):
        return sum(p.grad_x(xs, X) for p in self.parts)

    def grad_dot(self, Xs, X, w, G=None, sq1=None, sq2=None):
        G, sq1, sq2 = _gram_parts(Xs, X, G, sq1, sq2)
        out = self.parts[0].grad_dot(Xs, X, w, G, sq1, sq2)
        for p in self.parts[1:]:
            out += p.grad_dot(Xs, X, w, G, sq1, sq2)
        return out

    def value_and_grad_dot(self, Xs, X, w, G, sq1, sq2):
        K, out = self.parts[0].value_and_grad_dot(Xs, X, w, G, sq1, sq2)
        for p in self.parts[1:]:
            k, g = p.value_and_grad_dot(Xs, X, w, G, sq1, sq2)
            K += k
            out += g
        return K, out

    def local_terms(self, x, X, ny):
        terms = [p.local_terms(x, X, ny) for p in self.parts]
        k = sum(t[0] for t in terms)
        J = sum(t[1] for t in terms)
        return k, J, lambda beta: sum(t[2](beta) for t in terms)

    def local_profile(self, r2, g, sq):
        out = None
        for p in self.parts:
            prof = p.local_profile(r2, g, sq)
            if prof is None:
                return None
            out = prof if out is None else out + prof
        return out

    def diag_local(self, x, ny):
        terms = [p.diag_local(x, ny) for p in self.parts]
        return sum(t[0] for t in terms), sum(t[1] for t in terms), sum(t[2] for t in terms)

    def mean_terms(self, w):
        terms = [p.mean_terms(w) for p in self.parts]
        if any(t is None for t in terms):
            return None
        const, moments = 0.0, None
        for t in terms:
            const += t.const
            if t.moments is not None:
                moments = t.moments if moments is None else tuple(a + b for a, b in zip(moments, t.moments))
        return MeanTerms(const, moments, tuple(pr for t in terms for pr in t.profiles))

    def to_dict(self):
        return {"type": "Sum", "parts": [p.to_dict() for p in self.parts]}

    def for_posterior(self, constant_cap: float | None = None) -> "Sum":
        return Sum(*[p.for_posterior(constant_cap) for p in self.parts])

    def cap_shift(self) -> float:
        return float(sum(p.cap_shift() for p in self.parts))

    def __repr__(self):
        return " + ".join(repr(p) for p in self.parts)

    def redundant_indices(self):
        out, i = [], 0
        for p in self.parts:
            out += [i + j for j in p.redundant_indices()]
            i += p.n_params
        return out

    def initial_theta(self, var_y, median_distance, n_dims):
        return np.concatenate([p.initial_theta(var_y, median_distance, n_dims) for p in self.parts])

    def iter_cross_grads(self, G, sq1, sq2):
        for p in self.parts:
            yield from p.iter_cross_grads(G, sq1, sq2)

    def diag_and_grads(self, X, q=None):
        q = np.einsum("ij,ij->i", X, X) if q is None else q
        d = np.zeros(X.shape[0])
        grads: list[np.ndarray] = []
        for p in self.parts:
            dp, gp = p.diag_and_grads(X, q)
            d += dp
            grads += gp
        return d, grads
