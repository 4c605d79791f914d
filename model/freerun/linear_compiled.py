"""Pass 1 of the linearised free run (``freerun.linear``) as compiled code, where numba is installed (the extra
``fast``): the mean recursion of eq. 8 with, from the same kernel-row evaluation, the mean's gradient in the output
lags (J of the covariance recursion) and, at the steps pass 2 asks for, the row k(x_i, points) of eq. 9's
variance. Pass 2 is then only eq. 9's triangular products on those rows; the numbers are the numpy passes' to
round-off (a sum's order differs).

One step, for all M points at once, as the numpy recursion writes it (``MeanTerms``): g_m = z_m . x,
r_m^2 = |x - z_m|^2, the kernel's moments sum_m w_m g_m^p (p <= 3) and its stationary profiles f(r^2) =
p(v) exp(-v / m) with v = g r^m' (``StationaryProfile``). The gradient of sum_m w_m k(x, z_m) in x is
x sum_m a_m + sum_m (w_m dmom_m - a_m) z_m with a_m = w_m scale 2 f'(r_m^2) and dmom the moments' derivative in
g: one more pass over the same (M, ny) block of points.

``build(predictor, terms)`` gives a ``CompiledMean`` or None (numba absent, ``GPNARX_COMPILED=0``, or a kernel
whose profiles have no compiled form: the numpy passes run as before).
"""
from __future__ import annotations

import os
import weakref

import numpy as np

from .spec import LAG_CLIP

_KERNEL = []  # the compiled step loop, built on first use
_NUMBA: list = []  # [whether numba imports], filled on first use
_CHECKED: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()  # posterior -> whether its rows check out


def enabled() -> bool:
    """Whether the compiled pass may run: numba importable and ``GPNARX_COMPILED`` not 0."""
    if os.environ.get("GPNARX_COMPILED", "1").strip() in ("0", "false", "no", "off"):
        return False
    if not _NUMBA:  # looked up once: a failed import is not remembered by Python
        try:
            import numba  # noqa: F401

            _NUMBA.append(True)
        except ImportError:
            _NUMBA.append(False)
    return _NUMBA[0]


def _compile():
    if not _KERNEL:
        from .linear_kernels import steps

        _KERNEL.append(steps)
    return _KERNEL[0]


def _profile_form(kernel_part):
    """(scale, g, power, f's coefficients in v, 2 f'(r^2)'s coefficients in v and their factor) of a stationary
    profile var p(v) exp(-v / m) (``StationaryProfile``), or None where the form has no compiled equivalent."""
    from ..kernels.stationary import StationaryProfile

    if not isinstance(kernel_part, StationaryProfile):
        return None
    var, g = (float(v) for v in kernel_part._scales())
    c = [float(x) for x in kernel_part._f]
    m = kernel_part.power
    dp = [k * c[k] for k in range(1, len(c))] + [0.0]  # p'(v), padded to len(c)
    if m == 1:
        # 2 f'(r^2) = (p'(v) - p(v)) E dv/dr^2 with dv/dr^2 = g^2 / (2 v) ... times 2: (p' - p)(v) / v g^2 E
        q = [dp[k] - c[k] for k in range(len(c))]
        if abs(q[0]) > 0.0:  # f' unbounded at r = 0 (Matern 1/2): no compiled form
            return None
        return var, g, 1, np.array(c), np.array(q[1:] or [0.0]), g * g
    # m = 2: 2 f'(r^2) = 2 (p'(v) - p(v) / 2) E g = (2 p' - p)(v) g E
    return var, g, 2, np.array(c), np.array([2.0 * dp[k] - c[k] for k in range(len(c))]), g


def _parts(kernel):
    from ..kernels.base import Sum

    return list(kernel.parts) if isinstance(kernel, Sum) else [kernel]


class CompiledMean:
    """Pass 1 compiled (see the module docstring): ``run`` fills the mean outputs, J at every step and the
    kernel rows pass 2 asks for."""

    def __init__(self, recursion, forms, kconst: float):
        r = recursion
        self.r = r
        self.ZyT = np.ascontiguousarray(r.Zy_rev.T)
        P = len(forms)
        width = max([len(f[3]) for f in forms] + [len(f[4]) for f in forms] + [1])
        self.pscale = np.array([f[0] for f in forms], dtype=float)
        self.pg = np.array([f[1] for f in forms], dtype=float)
        self.ppow = np.array([f[2] for f in forms], dtype=np.int64)
        self.pc = np.zeros((P, width))
        self.pdc = np.zeros((P, width))
        for p, f in enumerate(forms):
            self.pc[p, :len(f[3])] = f[3]
            self.pdc[p, :len(f[4])] = f[4]
        self.pdscale = np.array([f[5] for f in forms], dtype=float)
        self.mom = np.array(r.moments, dtype=float)
        self.kconst = float(kconst)
        self.steps = _compile()
        from .linear_kernels import cov_steps

        self.cov_steps = cov_steps  # pass 3's loop compiled too

    @classmethod
    def build(cls, recursion, posterior):
        """For a ``linear._MeanRecursion`` of ``posterior``, or None (see the module docstring)."""
        if recursion is None or not enabled():
            return None
        kernel = posterior.kernel
        forms = []
        for part in _parts(kernel):
            t = part.mean_terms(np.asarray(posterior.mean_weights, dtype=float))
            if t is None:
                return None
            if not t.profiles:
                continue
            form = _profile_form(part)
            if form is None or len(t.profiles) != 1:
                return None
            forms.append(form)
        if len(forms) != len(recursion.profiles):
            return None
        # the kernel row's constant: k(0, 0) less the profiles' f(0) = 1 (the moments vanish at g = 0)
        z = np.zeros((1, 1))
        kconst = float(kernel.from_gram(z, np.zeros(1), np.zeros(1))[0, 0]) - sum(f[0] for f in forms)
        out = cls(recursion, forms, kconst)
        try:
            agree = _CHECKED[posterior]
        except (KeyError, TypeError):
            agree = out._rows_agree(posterior)
            try:
                _CHECKED[posterior] = agree
            except TypeError:  # not weakly referable: checked at every run
                pass
        return out if agree else None

    def _rows_agree(self, posterior) -> bool:
        """Whether the compiled kernel rows and gradient are the posterior's (to round-off) at a few points: a
        guard against a kernel whose parts the forms above misread."""
        r = self.r
        ny = r.ny
        P = posterior.points
        X = P[: min(3, P.shape[0])].copy() * 0.9 + 0.05
        out = []
        for x in X:
            hist = np.concatenate([(x[:ny] * r.xs[:ny] + r.xm[:ny])[::-1], [0.0]])
            Ulag = x[ny:][None, :]
            Jout = np.empty((1, ny))
            K = np.empty((1, P.shape[0]))
            GU = Ulag @ r.Zu.T
            R0 = GU * -2.0 + r.sqZ + float(Ulag[0] @ Ulag[0])
            self.steps(hist, GU, R0, 0, 1, ny, self.ZyT, r.w, r.xm_rev, r.inv_rev, -np.inf, np.inf, LAG_CLIP,
                       np.array([-1]), r.const, self.mom, self.kconst, self.pscale, self.pg, self.ppow, self.pc,
                       self.pdc, self.pdscale, 1.0, 0.0, Jout, np.zeros(1, dtype=np.int64), K)
            mean, _, grad = posterior.mean_var_grad(x[None, :])
            krow = posterior.cross(x[None, :])[0]
            J = grad[0, :ny] / r.xs[:ny]
            out.append(np.allclose(K[0], krow, rtol=1e-9, atol=1e-12 * max(1.0, np.abs(krow).max()))
                       and np.allclose(Jout[0], J, rtol=1e-7, atol=1e-9 * max(1.0, np.abs(J).max()))
                       and np.isclose(hist[ny], mean[0], rtol=1e-9, atol=1e-12))
        return all(out)

    def run(self, hist, Ulag, i0, n, ym, ys, Jall, want_rows, progress=None, chunk=1024, on_chunk=None):
        """Fill hist[ny + i] with the mean output of every step i0 <= i < n (output units) and Jall[i - i0] with
        d mean / d y_lag (output units, lag order), ``chunk`` steps at a time; ``want_rows(c0, c1)`` gives the
        chunk's slot per step (-1: no row) and the (slots, M) array for the kernel rows; ``on_chunk(c0, c1, K)``
        after the chunk is final."""
        r = self.r
        ny = r.ny
        lo = float(np.max(r.xm[:ny] - LAG_CLIP * r.xs[:ny]))
        hi = float(np.min(r.xm[:ny] + LAG_CLIP * r.xs[:ny]))
        state = np.array([-1], dtype=np.int64)
        for k in range(ny):
            v = hist[i0 + k]
            if not lo <= v <= hi:
                state[0] = i0 + ny
        for c0 in range(i0, n, chunk):
            c1 = min(n, c0 + chunk)
            Uc = Ulag[c0:c1]
            GU = Uc @ r.Zu.T
            R0 = GU * -2.0
            R0 += r.sqZ
            R0 += np.einsum("ij,ij->i", Uc, Uc)[:, None]
            slots, K = want_rows(c0, c1)
            self.steps(hist, GU, R0, c0, c1, ny, self.ZyT, r.w, r.xm_rev, r.inv_rev, lo, hi, LAG_CLIP, state, r.const,
                       self.mom, self.kconst, self.pscale, self.pg, self.ppow, self.pc, self.pdc, self.pdscale, ys,
                       ym, Jall[c0 - i0: c1 - i0], slots, K)
            if progress is not None:
                progress(c1, n)
            if on_chunk is not None:
                on_chunk(c0, c1, K)
