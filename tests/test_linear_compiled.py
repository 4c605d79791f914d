"""The linearised run's compiled pass 1 (numba, optional: those tests skip without it), the strided variance of eq. 9
(``RunSpec.variance_stride``) and the bound on queued chunks; what runs without numba is tested here too."""
from __future__ import annotations

import threading
import time
from dataclasses import replace

import numpy as np
import pytest

from gpnarx.model.estimator import GPNARX
from gpnarx.model.freerun import RunSpec, linear, linear_compiled, reference, run
from gpnarx.model.gp import interpolate_rows, stride_rows
from gpnarx.model.kernels import make_kernel
from gpnarx.model.kernels.stationary import RBF, Matern32, Matern52

THETA = np.log([3.7e-4, 3.6, 7.67e-3, 2.0e-5, 126.4, 3.6e-4])  # tests/test_freerun_fast.py's (fixed: no ML-II)
THETA_KERNELS = {"matern32+cubic": THETA, "rbf+cubic": THETA, "matern52": np.log([3.7e-4, 3.6, 3.6e-4])}


def _model(sdof_data, kernel: str, mode: str = "exact"):
    kw = {"n_inducing": 48} if mode == "sparse" else {}
    return GPNARX(ny=5, nu=5, mode=mode, max_train_points=250, kernel=kernel, **kw).fit(
        [(sdof_data["u"][:900], sdof_data["yn"][:900])], theta=THETA_KERNELS[kernel])


@pytest.fixture(scope="module")
def models(sdof_data):
    return {k: _model(sdof_data, k) for k in THETA_KERNELS} | {"sparse": _model(sdof_data, "matern32+cubic", "sparse")}


@pytest.mark.parametrize("kernel", [Matern32(0.7, 1.3), Matern52(1.1, 0.8), RBF(0.9, 1.7)])
def test_profile_form_gives_the_kernel_and_its_gradient(kernel):
    # the compiled form (f and 2 f'(r^2) as polynomials in v times exp(-v / m)) against the kernel itself
    scale, g, m, c, dc, dscale = linear_compiled._profile_form(kernel)
    rng = np.random.default_rng(0)
    x, Z = rng.normal(size=4), rng.normal(size=(7, 4))
    r2 = np.sum((x - Z) ** 2, axis=1)
    v = g * (np.sqrt(r2) if m == 1 else r2)
    E = np.exp(-v / m)
    f = scale * np.polyval(c[::-1], v) * E
    assert np.allclose(f, kernel(x[None, :], Z)[0], rtol=1e-12)
    d = scale * dscale * np.polyval(dc[::-1], v) * E  # 2 var f'(r^2): d k / d x = d (x - z)
    assert np.allclose(d[:, None] * (x - Z), kernel.grad_x(x, Z), rtol=1e-10, atol=1e-14)


def test_profile_form_refuses_what_it_cannot_compile():
    assert linear_compiled._profile_form(make_kernel("cubic")) is None


def test_compiled_off_by_environment(monkeypatch, models):
    monkeypatch.setenv("GPNARX_COMPILED", "0")
    m = models["matern32+cubic"]
    fast = linear._MeanRecursion.build(m.predictor())
    assert linear_compiled.CompiledMean.build(fast, m.posterior_) is None


@pytest.mark.parametrize("which", [*THETA_KERNELS, "sparse"])
@pytest.mark.parametrize("kw", [{}, {"y0": "measured"}, {"cov_window": 9}])
def test_compiled_pass_matches_the_reference(which, kw, models, sdof_data, monkeypatch):
    pytest.importorskip("numba")
    monkeypatch.setenv("GPNARX_COMPILED", "1")
    m = models[which]
    P = m.predictor()
    assert linear_compiled.CompiledMean.build(linear._MeanRecursion.build(P), m.posterior_) is not None
    u = sdof_data["u2"][:2500]  # three chunks of pass 1
    kw = dict(kw)
    if kw.get("y0") == "measured":
        kw["y0"] = sdof_data["y2"][:5]
    args = (m.posterior_, m.x_scaler_, m.y_scaler_, m.ny, m.nu, u)
    new = linear.simulate_linear(*args, **kw)
    ref = reference.simulate_linear_reference(*args, **kw)
    scale = np.abs(ref.mean).max()
    assert np.allclose(new.mean, ref.mean, rtol=0, atol=1e-9 * scale)
    assert np.allclose(new.std, ref.std, rtol=1e-7, atol=1e-12 * scale)
    assert np.allclose(new.latent_upper, ref.latent_upper, rtol=0, atol=1e-9 * scale)
    if "cov_window" in kw:
        assert np.allclose(new.cov_band, ref.cov_band, rtol=1e-7, atol=1e-12 * scale ** 2)
    monkeypatch.setenv("GPNARX_COMPILED", "0")
    numpy_run = linear.simulate_linear(*args, **kw)
    assert np.allclose(new.std, numpy_run.std, rtol=1e-9)
    # workers or none: same numbers
    alone = linear.simulate_linear(*args, workers=0, **kw)
    monkeypatch.setenv("GPNARX_COMPILED", "1")
    assert np.array_equal(linear.simulate_linear(*args, workers=0, **kw).std,
                          linear.simulate_linear(*args, workers=2, **kw).std)
    assert np.allclose(alone.std, new.std, rtol=1e-9)


def test_compiled_stream_in_chunks_equals_the_record_whole(models, sdof_data, monkeypatch):
    pytest.importorskip("numba")
    monkeypatch.setenv("GPNARX_COMPILED", "1")
    m = models["matern32+cubic"]
    P, u = m.predictor(), sdof_data["u2"][:1500]
    spec = RunSpec(method="linear")
    whole = run(P, u, spec)
    a = run(P, u[:700], spec)
    b = run(P, u[700:], replace(spec, state=a.state))
    assert np.allclose(np.concatenate([a.mean, b.mean]), whole.mean, rtol=0, atol=1e-10 * np.abs(whole.mean).max())
    assert np.allclose(np.concatenate([a.std, b.std]), whole.std, rtol=1e-8)


def test_stride_rows_and_interpolation():
    assert stride_rows(10, 4).tolist() == [0, 4, 8, 9]
    assert stride_rows(9, 4).tolist() == [0, 4, 8]
    assert stride_rows(5, 1).tolist() == [0, 1, 2, 3, 4]
    assert interpolate_rows(np.array([0.0, 4.0, 5.0]), np.array([0, 4, 5]), 6).tolist() == [0, 1, 2, 3, 4, 5]


def test_strided_variance_is_exact_at_its_rows_and_interpolated_between(models, sdof_data):
    m = models["matern32+cubic"]
    post = m.posterior_
    X = m.x_scaler_.transform(np.random.default_rng(2).normal(size=(300, m.ny + m.nu)) * 0.3)
    mean1, var1, grad1 = post.mean_var_grad(X)
    mean4, var4, grad4 = post.mean_var_grad(X, stride=4)
    keep = stride_rows(300, 4)
    assert np.array_equal(mean1, mean4) and np.array_equal(grad1, grad4)
    assert np.allclose(var4[keep], var1[keep], rtol=1e-12)
    assert np.allclose(var4, np.maximum(np.interp(np.arange(300), keep, var1[keep]), 1e-300), rtol=1e-12)
    assert not np.allclose(var4, var1, rtol=1e-6)  # the rows between differ: the stride does something


def test_strided_run_keeps_the_mean_and_moves_the_band(models, sdof_data, monkeypatch):
    monkeypatch.setenv("GPNARX_COMPILED", "0")
    m = models["matern32+cubic"]
    P, u = m.predictor(), sdof_data["u2"][:1200]
    exact = run(P, u, RunSpec(method="linear"))
    one = run(P, u, RunSpec(method="linear", variance_stride=1))
    four = run(P, u, RunSpec(method="linear", variance_stride=4))
    assert np.array_equal(one.std, exact.std)
    assert np.array_equal(four.mean, exact.mean)
    assert not np.array_equal(four.std, exact.std)
    for bad in (0, -2, 1.5, True, "2"):
        with pytest.raises(ValueError, match="variance_stride"):
            run(P, u, RunSpec(method="linear", variance_stride=bad))


def test_workers_bound_the_queued_tasks_by_running_them_on_the_caller():
    ran_on, queued_seen = [], []
    followed = []
    main = threading.get_ident()

    def fn(k):
        ran_on.append((k, threading.get_ident() == main))
        if threading.get_ident() != main:
            time.sleep(0.02)

    with linear._Workers(fn, 1, then=followed.append, queued=1) as pool:
        for k in range(8):
            pool.submit(k)
            queued_seen.append(pool.tasks.qsize())
    assert sorted(k for k, _ in ran_on) == list(range(8))
    assert followed == list(range(8))  # then() in submission order
    assert any(on_main for _, on_main in ran_on)
    assert max(queued_seen) <= 1


def test_numerics_page_holds_the_render_of_the_stored_stride_run():
    import json
    from pathlib import Path

    from gpnarx.training.pages.variance_stride import BEGIN, END, render, worst

    root = Path(__file__).resolve().parents[1]
    table = json.loads((root / "docs" / "runs" / "variance-stride" / "table.json").read_text())
    page = (root / "docs" / "numerics.md").read_text()
    assert BEGIN + page.split(BEGIN, 1)[1].split(END, 1)[0] + END == render(table)
    assert len(table["records"]) >= 19 and set(table["strides"]) == {2, 4, 8}
    assert min(worst(table, "gp").values()) > table["bound"]  # the page's verdict: no stride is within the bound


@pytest.mark.parametrize("L", [4, 9])
def test_compiled_covariance_recursion_matches_numpy_with_its_guards(L):
    pytest.importorskip("numba")
    from gpnarx.model.freerun.linear_kernels import cov_steps

    rng = np.random.default_rng(3)
    ny, steps = 4, 1300  # past two rebases of the 512-step buffer
    q = rng.random(steps) * 1e-3
    J = rng.normal(size=(steps, ny)) * 0.6
    J[400] = 1e200  # the guards: a term past the cap, then non-finite ones
    J[401, 0] = np.inf
    J[402, 1] = np.nan
    runs = []
    for compiled in (None, cov_steps):
        band = np.zeros((steps, L)) if L > ny else None
        rec = linear._CovarianceRecursion(steps, ny, L, 2.0, band, 0)
        rec.compiled = compiled
        for k0 in range(0, steps, 256):
            rec.advance(q[k0:k0 + 256], J[k0:k0 + 256])
        runs.append((rec.out, rec.prop, rec.state(), band))
    (a, pa, sa, ba), (b, pb, sb, bb) = runs
    cap = float(np.nanmax(a))  # the variance cap the guards held the diverged steps at
    assert np.array_equal(np.isfinite(pa), np.isfinite(pb)) and cap == float(np.nanmax(b))
    close = {"rtol": 1e-12, "atol": 1e-12 * cap, "equal_nan": True}  # a sum's order: round-off of the cap's size
    assert np.allclose(a, b, **close) and np.allclose(sa, sb, **close)
    if ba is not None:
        assert np.allclose(ba, bb, **close)


def test_compiled_strided_run_equals_the_numpy_strided_run(models, sdof_data, monkeypatch):
    pytest.importorskip("numba")
    m = models["matern32+cubic"]
    P, u = m.predictor(), sdof_data["u2"][:2100]
    runs = {}
    for flag in ("0", "1"):
        monkeypatch.setenv("GPNARX_COMPILED", flag)
        runs[flag] = run(P, u, RunSpec(method="linear", variance_stride=4))
    assert np.allclose(runs["1"].std, runs["0"].std, rtol=1e-8)
    assert np.allclose(runs["1"].mean, runs["0"].mean, rtol=0, atol=1e-10 * np.abs(runs["0"].mean).max())


def test_empty_record_runs_on_either_pass(models, monkeypatch):
    m = models["matern32+cubic"]
    for flag in ("0", "1"):
        monkeypatch.setenv("GPNARX_COMPILED", flag)
        r = run(m.predictor(), np.zeros(0), RunSpec(method="linear"))
        assert r.mean.size == 0 and r.std.size == 0
