"""The mean gradient fused with the mean in the numpy pass 1 of the linearised run, measured before building it:
what the gradient's extra numpy calls would cost per step on (M,) rows inside pass 1's loop, over a 64 s record,
against what pass 2 spends on the gradient now (``value_and_grad_dot`` less ``from_gram``, blocks of 256 rows at the
record's mean regressors). Thread CPU time, so the machine's load matters less.

    python studies/fusion_numpy_study.py REGISTRY [RECORD]

Measured on the exact bert-real and the 20 Hz sine: +0.68 s in pass 1 against 0.43 s saved in pass 2, so the numpy
pass keeps the gradient in pass 2; the compiled pass 1 (``freerun.linear_compiled``) fuses it.
"""
import sys
import time

import numpy as np

from gpnarx.model.freerun import RunSpec, run
from gpnarx.runtime import tune_for_free_run
from gpnarx.storage.record_files import read_record
from gpnarx.storage.registry import Registry
from gpnarx.training.datapaths import bert_data_dir

tune_for_free_run(None)
b = Registry(sys.argv[1]).scan().get("bert-real")
m = b.model
P = m.predictor()
post = m.posterior_
rec = read_record(sys.argv[2] if len(sys.argv) > 2 else str(bert_data_dir() / "Sine" / "Sine_20Hz"), fs_default=1024.)
n = rec.u.size
ny = P.ny
Z = post.points
M = Z.shape[0]
w = post.mean_weights
Zy = np.ascontiguousarray(Z[:, :ny][:, ::-1])
rng = np.random.default_rng(0)
# pass-1 extra ops per step
a = rng.random(M)
g = rng.normal(size=M)
xy = rng.normal(size=ny)
E, t, d, gy = np.empty(M), np.empty(M), np.empty(M), np.empty(ny)
c1, c2, c3, sd = 0.1, 0.2, 0.3, -1.5
steps = 20000
t0 = time.thread_time()
for _ in range(steps):
    np.exp(a, out=E)                 # E = exp(-v) kept beside f
    np.multiply(E, sd, out=t)        # 2 var f'(r^2)
    t *= w
    sa = float(t.sum())
    np.multiply(g, 3.0 * c3, out=d)  # dmom = c1 + (2 c2 + 3 c3 g) g
    d += 2.0 * c2
    d *= g
    d += c1
    d *= w
    d -= t
    np.dot(d, Zy, out=gy)
    J = sa * xy + gy  # noqa: F841
extra = (time.thread_time() - t0) / steps * n
# pass-2 gradient share: value_and_grad_dot minus from_gram at the record's regressors
r = run(P, rec.u, RunSpec(method='linear', workers=0))
X = np.empty((n, ny + P.nu))
hist = np.concatenate([np.zeros(ny), r.mean])
win = np.lib.stride_tricks.sliding_window_view(hist, ny)[:, ::-1][:n]
X[:, :ny] = (win - P.x_mean[:ny]) / P.x_scale[:ny]
X[:, ny:] = P.input_lags(rec.u)
sqX = np.einsum('ij,ij->i', Z, Z)
k = post.kernel
t_vg = t_v = 0.0
for r0 in range(0, n, 256):
    xb = X[r0:r0 + 256]
    G = xb @ Z.T
    sq = np.einsum('ij,ij->i', xb, xb)
    c0 = time.thread_time()
    k.value_and_grad_dot(xb, Z, w, G.copy(), sq, sqX)
    t_vg += time.thread_time() - c0
    c0 = time.thread_time()
    k.from_gram(G.copy(), sq, sqX)
    t_v += time.thread_time() - c0
print(f"numpy pass 1 + gradient: +{extra:.2f} s CPU over the record; pass 2's gradient share "
      f"(value_and_grad_dot - from_gram): {t_vg - t_v:.2f} s of {t_vg:.2f} s")
