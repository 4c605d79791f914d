"""A chain of three masses with a Bouc-Wen joint between the first two: a known truth with several outputs.

The independent check of the model with several outputs (``model.mimo``, issue 52): one force in, a sensor on
each mass out, and a hysteretic joint whose restoring force the model never sees::

    ground --k1, c1-- m1 ==joint== m2 --k3, c3-- m3 <- u(t)

    m1 x1'' = -k1 x1 - c1 x1' + kj d + cj d' + z
    m2 x2'' = -kj d - cj d' - z + k3 (x3 - x2) + c3 (x3' - x2')
    m3 x3'' = -k3 (x3 - x2) - c3 (x3' - x2') + u
    z'      = alpha d' - beta (gamma |d'| |z|^(nu-1) z + delta d' |z|^nu),     d = x2 - x1

(the joint is a linear spring kj and damper cj in parallel with a Bouc-Wen element of eqs. 15-16's form,
z [N] its hysteretic force). Units: masses kg, stiffnesses N/m, damping N s/m, force u [N], displacements x
[m], velocities [m/s]. Defaults: m = 1 kg each, k1 = 2e4, kj = 5e3, alpha = 1e4, k3 = 1e4 N/m, c = 2 N s/m,
Bouc-Wen beta = 100, gamma = 0.8 1/m, delta = -1.1 1/m, nu = 1 (Table 1's gamma, delta and nu, a tenth of its
beta: a hardening joint whose hysteretic force reaches about 40 N at 5 N of drive); fs = 200 Hz. Linear modes at
small amplitude (z = alpha d): about 9.0, 22.5 and 34.4 Hz (``linear_modes``).

Integration: classic RK4 at ``substeps`` steps per sample (default 20, 4 kHz) on (x1, x2, x3, v1, v2, v3, z),
the input linear between samples; the system starts from rest. The sensors are the three displacements
(``output="displacement"``, m) or velocities (``"velocity"``, m/s).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["Chain", "CHANNELS"]

#: the sensors' channel names: one on each mass
CHANNELS = ("x1", "x2", "x3")


@dataclass
class Chain:
    """The three-mass chain of the module docstring; SI units (kg, N/m, N s/m; beta, nu [-], gamma, delta
    [1/m]); fs: sampling frequency [Hz]; substeps: RK4 steps per sample."""

    m1: float = 1.0
    m2: float = 1.0
    m3: float = 1.0
    k1: float = 2e4
    kj: float = 5e3
    k3: float = 1e4
    c1: float = 2.0
    cj: float = 2.0
    c3: float = 2.0
    alpha: float = 1e4
    beta: float = 100.0
    gamma: float = 0.8
    delta: float = -1.1
    nu: float = 1.0
    fs: float = 200.0
    substeps: int = 20

    def __post_init__(self) -> None:
        for name in ("m1", "m2", "m3", "k1", "k3", "fs"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be a finite positive number, got {v!r}")
        if int(self.substeps) < 1:
            raise ValueError(f"substeps must be >= 1, got {self.substeps}")

    def linear_modes(self) -> np.ndarray:
        """Undamped natural frequencies [Hz] at small amplitude (joint stiffness kj + alpha), ascending."""
        kj = self.kj + self.alpha
        K = np.array([[self.k1 + kj, -kj, 0.0], [-kj, kj + self.k3, -self.k3], [0.0, -self.k3, self.k3]])
        M = np.diag([self.m1, self.m2, self.m3])
        w2 = np.linalg.eigvals(np.linalg.solve(M, K)).real
        return np.sort(np.sqrt(w2)) / (2 * np.pi)

    def simulate(self, u, output: str = "displacement") -> dict:
        """Response to force u [N] sampled at ``fs``, from rest. Returns ``{"y": (n, 3) sensors (m or m/s),
        "x": (n, 3) displacements [m], "v": (n, 3) velocities [m/s], "z": (n,) joint hysteretic force [N]}``."""
        if output not in ("displacement", "velocity"):
            raise ValueError(f"output must be 'displacement' or 'velocity', got {output!r}")
        u = np.asarray(u, dtype=float)
        if u.ndim != 1 or u.size == 0:
            raise ValueError(f"u must be a non-empty 1-D force record [N], got shape {u.shape}")
        if not np.all(np.isfinite(u)):
            raise ValueError("u holds NaN/inf")
        n = u.size
        h = 1.0 / (self.fs * int(self.substeps))
        ns = int(self.substeps)
        m1, m2, m3 = self.m1, self.m2, self.m3
        k1, kj, k3, c1, cj, c3 = self.k1, self.kj, self.k3, self.c1, self.cj, self.c3
        al, be, ga, de, nu = self.alpha, self.beta, self.gamma, self.delta, self.nu
        unit_nu = nu == 1.0

        def rhs(s, f):
            x1, x2, x3, v1, v2, v3, z = s
            d, dv = x2 - x1, v2 - v1
            fj = kj * d + cj * dv + z  # force of the joint on m1 (and minus it on m2)
            f3 = k3 * (x3 - x2) + c3 * (v3 - v2)
            az = abs(z)
            if unit_nu:
                zd = al * dv - be * (ga * abs(dv) * z + de * dv * az)
            else:
                zd = al * dv - be * (ga * abs(dv) * az ** (nu - 1) * z + de * dv * az ** nu)
            return (v1, v2, v3, (-k1 * x1 - c1 * v1 + fj) / m1, (-fj + f3) / m2, (-f3 + f) / m3, zd)

        def add(s, k, a):
            return tuple(si + a * ki for si, ki in zip(s, k))

        s = (0.0,) * 7
        X = np.zeros((n, 3))
        V = np.zeros((n, 3))
        Z = np.zeros(n)
        up = np.concatenate([u, u[-1:]])
        for i in range(n):
            X[i] = s[:3]
            V[i] = s[3:6]
            Z[i] = s[6]
            if i == n - 1:
                break
            u0, u1 = up[i], up[i + 1]
            for j in range(ns):
                fa = u0 + (u1 - u0) * (j / ns)
                fm = u0 + (u1 - u0) * ((j + 0.5) / ns)
                fb = u0 + (u1 - u0) * ((j + 1) / ns)
                k_1 = rhs(s, fa)
                k_2 = rhs(add(s, k_1, h / 2), fm)
                k_3 = rhs(add(s, k_2, h / 2), fm)
                k_4 = rhs(add(s, k_3, h), fb)
                s = tuple(si + h / 6 * (a + 2 * b + 2 * c + d) for si, a, b, c, d in zip(s, k_1, k_2, k_3, k_4))
        if not (np.all(np.isfinite(X)) and np.all(np.isfinite(Z))):
            raise ValueError("the simulation diverged (NaN/inf): lower the force or raise substeps")
        return {"y": X.copy() if output == "displacement" else V.copy(), "x": X, "v": V, "z": Z}
