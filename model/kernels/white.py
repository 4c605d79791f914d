"""White noise as a kernel part: a variance on the diagonal of K(X, X) only."""
from __future__ import annotations

import numpy as np

from .base import CONTRACTS, Kernel, LocalProfile, MeanTerms


class White(Kernel, *CONTRACTS, spec="white"):  # meets every contract of kernels.base
    """White-noise kernel: sigma^2 on the diagonal of K(X, X), zero between distinct sets."""

    param_names = ("variance",)
    has_local_profile = True

    def __init__(self, variance: float = 1e-2) -> None:
        self.theta = np.log([variance]).astype(float)

    def __call__(self, X, X2=None):
        if X2 is None:
            return np.exp(self.theta[0]) * np.eye(X.shape[0])
        return np.zeros((X.shape[0], X2.shape[0]))

    def K_and_grads(self, X):
        K = self(X)
        return K, [K.copy()]

    def diag(self, X):
        return np.full(X.shape[0], np.exp(self.theta[0]))

    def from_gram(self, G, sq1, sq2):
        return np.zeros_like(G)

    def grad_x(self, xs, X):
        return np.zeros_like(X)

    def grad_dot(self, Xs, X, w, G=None, sq1=None, sq2=None):
        return np.zeros((Xs.shape[0], X.shape[1]))

    def mean_terms(self, w):
        return MeanTerms()  # zero between distinct sets: no share of the mean

    def local_profile(self, r2, g, sq):
        return LocalProfile(np.zeros_like(r2), np.full(sq.shape[0], np.exp(self.theta[0])))

    def initial_theta(self, var_y, median_distance, n_dims):
        return np.log([1e-3 * var_y])

    def iter_cross_grads(self, G, sq1, sq2):
        yield np.zeros_like(G)              # zero between distinct input sets

    def diag_and_grads(self, X, q=None):
        var = float(np.exp(self.theta[0]))
        n = X.shape[0]
        return np.full(n, var), [np.full(n, var)]

    # workspace_input None: only the diagonal

    def block_diagonal(self):
        return float(np.exp(self.theta[0]))

    def grads_from_sums(self, sums, tr_w):
        return [0.5 * np.exp(self.theta[0]) * tr_w]  # dK/dlog var = var I

    def jax_part(self):
        def diag(jnp, th, sq):
            return jnp.exp(th[0]) * jnp.ones_like(sq)

        return None, diag, True
