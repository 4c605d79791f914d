"""The compiled step loop of ``linear_compiled`` (numba, the extra ``fast``): imported only where numba is, by
``linear_compiled``. Module-level functions, so that numba's on-disk cache serves later processes."""
from __future__ import annotations

import numba
import numpy as np

FLAGS = {"reassoc", "contract"}  # a sum's order, fused multiply-adds; no change to inf or NaN handling


@numba.njit(cache=True, nogil=True, fastmath={"contract"})  # no reassociation: the shift and the split
def exp_neg(v, out, bits):
    """out[m] = exp(-v[m]) for v >= 0, in loops the compiler vectorises: 2^k exp(r) with k = round(-v / ln 2)
    by the 1.5 2^52 shift, r = -v - k ln 2 in two parts (|r| <= ln 2 / 2), exp(r) by its Taylor polynomial
    to degree 12 (truncation below 2e-16 relative), 2^k from k's bits; 0 below exp(-708)."""
    M = v.shape[0]
    kf = out  # the shifted k first, then the result
    for m in range(M):
        kf[m] = -v[m] * 1.4426950408889634 + 6755399441055744.0
    ib = kf.view(np.int64)
    for m in range(M):
        bits[m] = (ib[m] - 0x4338000000000000 + 1023) << 52
    scale = bits.view(np.float64)
    for m in range(M):
        x = -v[m]
        k = kf[m] - 6755399441055744.0
        r = (x - k * 0.6931471803691238) - k * 1.9082149292705877e-10
        p = 1.0 / 479001600.0
        p = p * r + 1.0 / 39916800.0
        p = p * r + 1.0 / 3628800.0
        p = p * r + 1.0 / 362880.0
        p = p * r + 1.0 / 40320.0
        p = p * r + 1.0 / 5040.0
        p = p * r + 1.0 / 720.0
        p = p * r + 1.0 / 120.0
        p = p * r + 1.0 / 24.0
        p = p * r + 1.0 / 6.0
        p = p * r + 0.5
        p = p * r + 1.0
        p = p * r + 1.0
        out[m] = p * scale[m] if x >= -708.0 else 0.0

@numba.njit(cache=True, nogil=True, fastmath=FLAGS)
def steps(hist, GU, R0, c0, c1, ny, ZyT, w, xm_r, inv_r, lo, hi, clip, state, const, mom, kconst, pscale, pg,
          ppow, pc, pdc, pdscale, ys, ym, Jout, slots, K):
    M = w.shape[0]
    P = pscale.shape[0]
    xy = np.empty(ny)
    g = np.empty(M)
    r2 = np.empty(M)
    coef = np.empty(M)
    val = np.empty(M)
    v = np.empty(M)
    E = np.empty(M)
    fp = np.empty(M)
    dp = np.empty(M)
    bits = np.empty(M, dtype=np.int64)
    m1, m2, m3 = mom[0], mom[1], mom[2]
    clip_until = state[0]
    for i in range(c0, c1):
        j = i - c0
        ss = 0.0
        for k in range(ny):
            x = (hist[i + k] - xm_r[k]) * inv_r[k]
            if i <= clip_until:
                if x < -clip:
                    x = -clip
                elif x > clip:
                    x = clip
            xy[k] = x
            ss += x * x
        for m in range(M):
            g[m] = 0.0
        for k in range(ny):
            xk = xy[k]
            for m in range(M):
                g[m] += ZyT[k, m] * xk
        for m in range(M):
            gy = g[m]
            r = R0[j, m] - 2.0 * gy + ss
            r2[m] = r if r > 0.0 else 0.0
            gm = gy + GU[j, m]
            g[m] = gm
            val[m] = (m1 + (m2 + m3 * gm) * gm) * gm
            coef[m] = w[m] * (m1 + (2.0 * m2 + 3.0 * m3 * gm) * gm)
        sa = 0.0
        for p in range(P):
            gp = pg[p]
            if ppow[p] == 1:
                for m in range(M):
                    v[m] = gp * np.sqrt(r2[m])
                exp_neg(v, E, bits)
            else:
                for m in range(M):
                    v[m] = gp * r2[m]
                    fp[m] = 0.5 * v[m]
                exp_neg(fp, E, bits)
            nc = pc.shape[1]
            for m in range(M):
                fp[m] = pc[p, nc - 1]
                dp[m] = pdc[p, nc - 1]
            for k in range(nc - 2, -1, -1):
                ck, dk = pc[p, k], pdc[p, k]
                for m in range(M):
                    fp[m] = fp[m] * v[m] + ck
                    dp[m] = dp[m] * v[m] + dk
            sc, sd = pscale[p], pscale[p] * pdscale[p]
            for m in range(M):
                val[m] += sc * fp[m] * E[m]
                a = w[m] * sd * dp[m] * E[m]
                sa += a
                coef[m] -= a
        acc = 0.0
        for m in range(M):
            acc += w[m] * val[m]
        slot = slots[j]
        if slot >= 0:
            for m in range(M):
                K[slot, m] = val[m] + kconst
        for k in range(ny):
            s = 0.0
            for m in range(M):
                s += coef[m] * ZyT[k, m]
            # d mu / d y_{i-1-l} in output units: the lag l is column ny - 1 - k of the time-ordered block
            Jout[j, ny - 1 - k] = (sa * xy[k] + s) * ys * inv_r[k]
        y = (const + acc) * ys + ym
        hist[ny + i] = y
        if not (lo <= y and y <= hi):
            clip_until = i + ny
    state[0] = clip_until


@numba.njit(cache=True, nogil=True)
def cov_steps(B, o, block, L, ny, q, Jall, k0, out, prop, cap, band, i0, has_band):
    """``linear._CovarianceRecursion.advance`` for q.size steps from step k0, S = B[o:o+L, o:o+L] moving down the
    diagonal of the buffer B (rebased every ``block`` steps), with the reference loop's guards; returns the new o."""
    safe = 0.25 * cap
    SJ = np.empty(L)
    for j in range(q.shape[0]):
        k = k0 + j
        if o == 0:  # rebase: S to the bottom-right corner
            B[block:, block:] = B[:L, :L].copy()
            o = block
        for a in range(L):
            s = 0.0
            for c in range(ny):
                s += B[o + a, o + c] * Jall[j, c]
            SJ[a] = s
        t = 0.0
        for c in range(ny):
            t += Jall[j, c] * SJ[c]
        if not (np.isfinite(t) and -safe < t and t < safe):
            for a in range(L):
                x = SJ[a]
                if np.isnan(x):
                    x = cap
                elif x > cap:
                    x = cap
                elif x < -cap:
                    x = -cap
                SJ[a] = x
            t = 0.0
            for c in range(ny):
                t += Jall[j, c] * SJ[c]
        prop[k] = t
        v = q[j] + t
        if np.isfinite(v):
            if v > cap:
                v = cap
        else:
            v = cap
        out[k] = v
        o -= 1
        B[o, o] = v
        for a in range(L - 1):
            B[o, o + 1 + a] = SJ[a]
            B[o + 1 + a, o] = SJ[a]
        if has_band:
            band[i0 + k, 0] = v
            for a in range(L - 1):
                band[i0 + k, 1 + a] = SJ[a]
    return o
