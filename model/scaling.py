"""Per-column standardisation of NARX regressors and targets, stored with the model."""
from __future__ import annotations

import numpy as np


class Standardizer:
    """z = (x - mean_) / scale_ per column. Columns with zero spread get scale 1."""

    def fit(self, X: np.ndarray) -> "Standardizer":
        X = np.atleast_2d(np.asarray(X, dtype=float))
        self.mean_ = X.mean(axis=0)
        scale = X.std(axis=0)
        scale[~(scale > 0)] = 1.0
        self.scale_ = scale
        return self

    def transform(self, X):
        return (X - self.mean_) / self.scale_

    def inverse_transform(self, Z):
        return Z * self.scale_ + self.mean_

    def to_arrays(self, prefix: str) -> dict:
        return {f"{prefix}_mean": self.mean_, f"{prefix}_scale": self.scale_}

    @classmethod
    def from_arrays(cls, mean, scale) -> "Standardizer":
        s = cls()
        s.mean_ = np.asarray(mean, dtype=float)
        s.scale_ = np.asarray(scale, dtype=float)
        return s
