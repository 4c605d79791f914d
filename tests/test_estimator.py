import numpy as np
import pytest

from gpnarx.model.estimator import GPNARX
from gpnarx.model.metrics import band_width, coverage, fit_percent, nrmse, rmse
from gpnarx.model.psd import peak_frequencies, psd
from gpnarx.model.record import Record, RecordError
from gpnarx.model.regressors import narx_regressors, stack_regressors


def test_regressors_follow_eq3_and_never_straddle_records():
    u = np.arange(10.0)
    y = 100 + np.arange(10.0)
    X, Y = narx_regressors(u, y, ny=2, nu=3)
    # first complete row is i = max(ny, nu-1) = 2: [y1, y0, u2, u1, u0]
    assert np.array_equal(X[0], [101, 100, 2, 1, 0])
    assert Y[0] == 102
    X2, Y2, idx = stack_regressors([(u, y), (u + 50, y + 50)], 2, 3)
    assert X2.shape == (16, 5) and np.array_equal(np.bincount(idx), [8, 8])
    # first row of the second record only uses the second record's samples
    assert np.array_equal(X2[8], [151, 150, 52, 51, 50])


def test_sdof_free_run_and_one_step(sdof_data, sdof_model):
    m = sdof_model
    run = m.simulate(sdof_data["u2"], n_paths=256, seed=0)
    fit = fit_percent(sdof_data["y2"], run.mean)
    cov = coverage(sdof_data["y2"], run.lower, run.upper)
    print(f"SDOF free-run fit {fit:.2f}% coverage {cov:.2f}%")
    assert fit >= 95.0
    assert cov >= 95.0
    mu = m.predict_one_step([(sdof_data["u2"], sdof_data["y2"])], return_std=False)
    osa = fit_percent(sdof_data["y2"][16:], mu)
    print(f"SDOF one-step fit {osa:.2f}%")
    assert osa >= 99.0


def test_free_run_is_deterministic_for_a_seed(sdof_data, sdof_model):
    u = sdof_data["u2"][:100]
    a = sdof_model.simulate(u, n_paths=1024, seed=7)
    b = sdof_model.simulate(u, n_paths=1024, seed=7)
    c = sdof_model.simulate(u, n_paths=1024, seed=8)
    assert np.array_equal(a.mean, b.mean) and np.array_equal(a.lower, b.lower) and np.array_equal(a.std, b.std)
    assert not np.array_equal(a.lower, c.lower)


def test_band_widens_with_training_noise(sdof_data):
    rng = np.random.default_rng(5)
    u, y = sdof_data["u"][:1200], sdof_data["y"][:1200]
    noise = rng.normal(size=y.size) * np.std(y)
    widths = []
    for level in (0.01, 0.05, 0.2):
        m = GPNARX(ny=6, nu=6, max_train_points=300, n_restarts=0).fit([(u, y + level * noise)])
        run = m.simulate(sdof_data["u2"][:400], n_paths=256, seed=0)
        widths.append(band_width(run.lower, run.upper))
    print("band widths", widths)
    assert widths[0] < widths[1] < widths[2]


def test_linearised_band_close_to_monte_carlo(sdof_data, sdof_model):
    u = sdof_data["u2"][:300]
    mc = sdof_model.simulate(u, n_paths=512, seed=0)
    lin = sdof_model.simulate(u, method="linear")
    ratio = band_width(lin.lower, lin.upper) / band_width(mc.lower, mc.upper)
    assert 0.8 < ratio < 1.2, ratio
    assert fit_percent(mc.mean, lin.mean) > 98


def test_initial_outputs_are_used(sdof_data, sdof_model):
    y2, u2 = sdof_data["y2"], sdof_data["u2"]
    run = sdof_model.simulate(u2[:200], n_paths=64, seed=0, y0=y2[:16])
    assert np.array_equal(run.mean[:16], y2[:16])
    with pytest.raises(ValueError, match="y0 must hold at least ny=16"):
        sdof_model.simulate(u2[:200], y0=y2[:3])


def test_sparse_mode_tracks_exact(sdof_data, sdof_model):
    u, yn = sdof_data["u"], sdof_data["yn"]
    # same hyperparameters as the exact model; posterior over all rows with 256 inducing points
    m = GPNARX(ny=16, nu=16, mode="sparse", n_inducing=256, max_train_points=1500).fit([(u, yn)],
                                                                                     theta=sdof_model.theta_)
    run = m.simulate(sdof_data["u2"], n_paths=256, seed=0)
    fit = fit_percent(sdof_data["y2"], run.mean)
    print("sparse fit", fit)
    assert fit >= 93.0
    assert coverage(sdof_data["y2"], run.lower, run.upper) >= 95.0


@pytest.mark.parametrize(
    "kwargs, match",
    [({"ny": 0}, "ny must be between 1"), ({"nu": 500}, "nu must be between 1"), ({"ny": 2.5}, "ny must be an integer"),
     ({"mode": "fast"}, "mode must be one of"), ({"selection": "best"}, "selection must be one of")],
)
def test_bad_parameters_name_the_argument(kwargs, match):
    u = np.random.default_rng(0).normal(size=100)
    with pytest.raises(ValueError, match=match):
        GPNARX(**{"ny": 2, "nu": 2, **kwargs}).fit([(u, u)])


def test_bad_records_are_refused():
    u = np.ones(50)
    with pytest.raises(RecordError, match="non-finite"):
        GPNARX(ny=2, nu=2).fit([Record(np.r_[u[:-1], np.nan], u, 100.0)])
    with pytest.raises(ValueError, match="need at least"):
        GPNARX(ny=10, nu=2).fit([(u[:8], u[:8])])
    with pytest.raises(RecordError, match="must match"):
        Record(u, u[:10], 100.0)
    with pytest.raises(RecordError, match="fs must be a finite positive"):
        Record(u, u, -1.0)
    with pytest.raises(RuntimeError, match="not fitted"):
        GPNARX().simulate(u)


def test_simulate_validates_inputs(sdof_model):
    with pytest.raises(ValueError, match="n_paths must be an integer between 1"):
        sdof_model.simulate(np.ones(30), n_paths=0)
    with pytest.raises(ValueError, match="non-finite"):
        sdof_model.simulate(np.r_[np.ones(30), np.inf])
    with pytest.raises(ValueError, match="u must be 1-D"):
        sdof_model.simulate(np.ones((3, 3)))
    with pytest.raises(ValueError, match="confidence must be"):
        sdof_model.simulate(np.ones(30), confidence=1.5)


def test_metrics_exact_values():
    y = np.array([1.0, -1.0, 2.0, 0.0])
    yhat = np.array([1.0, -1.0, 1.0, 0.0])
    assert fit_percent(y, yhat) == pytest.approx(100 * (1 - np.sqrt(1 / 6)))  # eq. (14)
    assert rmse(y, yhat) == pytest.approx(0.5)
    assert nrmse(y, yhat) == pytest.approx(0.5 / np.std(y))
    assert coverage(y, y - 0.1, y + 0.1) == 100.0
    assert coverage(y, yhat - 0.1, yhat + 0.1) == 75.0
    assert band_width(np.zeros(3), np.full(3, 2.0)) == 2.0


def test_psd_peak_and_windows():
    fs = 1024.0
    t = np.arange(8192) / fs
    x = np.sin(2 * np.pi * 18.75 * t) + 0.1 * np.sin(2 * np.pi * 37.5 * t)
    assert peak_frequencies(x, fs, n_peaks=2, nperseg=1024) == pytest.approx([18.75, 37.5], abs=1.0)
    f, p = psd(x, fs, nperseg=None, window="boxcar")
    assert f[np.argmax(p)] == pytest.approx(18.75, abs=0.2)


def test_sparse_vfe_refines_hyperparameters_on_all_rows(sdof_data):
    from gpnarx.model.vfe import vfe_nlml_and_grad

    u, yn = sdof_data["u"][:2000], sdof_data["yn"][:2000]
    sub = GPNARX(ny=8, nu=8, mode="sparse", n_inducing=96, max_train_points=300, n_restarts=0).fit([(u, yn)])
    vfe = GPNARX(ny=8, nu=8, mode="sparse", n_inducing=96, max_train_points=300, n_restarts=0,
                 hyper="vfe").fit([(u, yn)])
    # the refined hyperparameters have a better (lower) negative VFE bound on all rows
    from gpnarx.model.regressors import narx_regressors

    X, Y = narx_regressors(u, yn, 8, 8)
    Xs = vfe.x_scaler_.transform(X)
    Ys = (Y - vfe.y_scaler_.mean_[0]) / vfe.y_scaler_.scale_[0]
    Z = vfe.posterior_.points
    k = vfe.kernel_.clone()
    f_sub, _ = vfe_nlml_and_grad(sub.theta_, k, Xs, Ys, Z)
    f_vfe, _ = vfe_nlml_and_grad(vfe.theta_, k, Xs, Ys, Z)
    assert f_vfe <= f_sub + 1e-6
    run = vfe.simulate(sdof_data["u2"][:800], n_paths=128, seed=0)
    assert fit_percent(sdof_data["y2"][:800], run.mean) > 85


def test_novelty_start_rule():
    from gpnarx.model.novelty import novelty_start

    y = np.arange(10.0)
    assert np.array_equal(novelty_start(y, 3), [0.0, 1.0, 2.0])
    assert novelty_start(y, 3, y0=[5.0, 6.0, 7.0]) == [5.0, 6.0, 7.0]
    assert novelty_start(y[:3], 3) is None  # not longer than ny: from rest
    assert novelty_start(y, 3, y0=[]) is not None  # an empty y0 means "not given"


def test_calibration_envelope_and_verdict():
    from gpnarx.model.novelty import outside_envelope, record_envelope, verdict

    t = np.linspace(0, 1, 200)
    healthy = [(a * np.sin(20 * t), 0.1 * a * np.cos(20 * t)) for a in (1.0, 1.5)]
    env = record_envelope(healthy)
    assert env["u"][0] == pytest.approx(1.0, rel=1e-3) and env["u"][1] == pytest.approx(1.5, rel=1e-3)
    assert env["y"][1] == pytest.approx(0.15, rel=1e-3)
    u, y = healthy[0]
    assert outside_envelope(u, y, env) == []
    assert outside_envelope(2.9 * u, y, env) == []  # within 2x of the largest healthy peak
    assert outside_envelope(3.1 * u, y, env) == ["u"]
    assert outside_envelope(u, 0.4 * y, env) == ["y"]  # below half the smallest healthy peak
    assert outside_envelope(u, np.full_like(y, np.inf), env) == ["y"]
    assert outside_envelope(1e30 * u, 1e30 * y, None) == []  # no envelope (older bundle): no check
    assert verdict(0.5, 1.0) == "healthy" and verdict(1.5, 1.0) == "novel"
    assert verdict(0.5, 1.0, ["y"]) == "novel"
    with pytest.raises(ValueError, match="healthy record"):
        record_envelope([])


def test_constant_cap_keeps_the_predictive_variance_exact(sdof_data):
    # hyperparameters where ML-II leaves the cubic kernel's constant sigma_p^2 b^3 at ~1.6e4 against a
    # latent variance near 1e-4 (the BERT stand-in's eq. 13 optimum): without the cap the variance
    # k(x,x) - k A k of eq. 9 cancels below float64 precision and is clipped at its floor
    theta = np.log([3.7e-4, 3.6, 7.67e-3, 2.0e-5, 126.4, 3.6e-4])
    data = [(sdof_data["u"][:2000], sdof_data["yn"][:2000])]
    kw = dict(ny=8, nu=8, mode="sparse", n_inducing=128, max_train_points=500)
    Xq = np.vstack([narx_regressors(sdof_data["u2"][:600], sdof_data["y2"][:600], 8, 8)[0]])
    var, mean, grad = {}, {}, {}
    for cap in (None, 1.0, 0.25):
        m = GPNARX(constant_cap=cap, **kw).fit(data, theta=theta)
        Xs = m.x_scaler_.transform(Xq)
        mean[cap], var[cap] = m.posterior_.predict(Xs)
        grad[cap] = m.posterior_.mean_grad(Xs[5])
    # the mean (eq. 8) is the uncapped kernel's: the cap only changes how the variance is computed
    scale = np.abs(mean[None]).max()
    assert np.allclose(mean[1.0], mean[None], rtol=0, atol=1e-6 * scale)
    assert np.allclose(mean[0.25], mean[None], rtol=0, atol=1e-6 * scale)
    assert grad[1.0][0] == pytest.approx(grad[None][0], abs=1e-6 * scale)
    assert np.allclose(grad[1.0][2], grad[None][2], rtol=1e-6, atol=1e-9)
    assert np.all(var[1.0] > 1e-8)  # a real latent variance, well above the 1e-300 floor
    # with a well-conditioned offset prior the variance does not depend on the cap's value
    assert np.allclose(var[1.0], var[0.25], rtol=0.02)
    # the uncapped evaluation is wrong: Kmm's jitter is relative to its diagonal, which the constant
    # inflates 1e4-fold, and biases the variance by about 30 % (before the factored sparse variance of
    # 2026-11-24 it was also lost to cancellation, mostly clipped at the floor)
    assert np.median(np.abs(var[None] - var[1.0]) / var[1.0]) > 0.1
    with pytest.raises(ValueError, match="constant_cap must be a positive number"):
        GPNARX(constant_cap=0.0, **kw).fit(data, theta=theta)


def test_capped_model_round_trips_through_a_bundle(sdof_data, tmp_path):
    from gpnarx.storage.bundle import load_bundle, save_bundle

    theta = np.log([3.7e-4, 3.6, 7.67e-3, 2.0e-5, 126.4, 3.6e-4])
    for mode in ("sparse", "exact"):
        m = GPNARX(ny=6, nu=6, mode=mode, n_inducing=64, max_train_points=400).fit(
            [(sdof_data["u"][:1200], sdof_data["yn"][:1200])], theta=theta)
        assert m.posterior_.kernel.cap_shift() > 1e4  # the cap is active
        b = load_bundle(save_bundle(m, tmp_path, f"cap-{mode}", fs=1.0, units={"u": "N", "y": "m"}))
        assert b.model.constant_cap == 1.0 and b.manifest["kernel"]["parts"][1]["constant_cap"] == 1.0
        r1 = m.simulate(sdof_data["u2"][:300], n_paths=32, seed=3)
        r2 = b.model.simulate(sdof_data["u2"][:300], n_paths=32, seed=3)
        assert np.allclose(r1.mean, r2.mean, rtol=0, atol=1e-12 * np.abs(r1.mean).max())
        assert np.allclose(r1.upper, r2.upper, rtol=0, atol=1e-12 * np.abs(r1.upper).max())


def test_linearised_run_of_a_diverging_model_stays_finite_and_quiet():
    # a model whose gradient explodes (a diverging free run, e.g. a bad lag-surface cell): the state
    # covariance must stay finite, with no overflow/invalid RuntimeWarning from S @ J
    import warnings
    from types import SimpleNamespace

    from gpnarx.model.freerun import VAR_CAP, simulate_linear

    class Exploding:
        noise_var = 1e-3

        def mean_grad(self, x):
            return 1.0, 1e-3, np.full(x.size, 1e200)

    sc = SimpleNamespace(mean_=np.zeros(6), scale_=np.ones(6))
    ysc = SimpleNamespace(mean_=np.zeros(1), scale_=np.ones(1))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        run = simulate_linear(Exploding(), sc, ysc, 3, 3, np.ones(50))
    assert np.all(np.isfinite(run.std)) and np.all(np.isfinite(run.lower))
    assert run.std.max() <= np.sqrt(VAR_CAP) * 1.0000001


def test_bundle_built_before_the_variance_fix_warns_on_load(sdof_data, tmp_path):
    import json

    from gpnarx.storage.bundle import BundleWarning, _sha256, load_bundle, save_bundle

    theta = np.log([3.7e-4, 3.6, 7.67e-3, 2.0e-5, 126.4, 3.6e-4])
    m = GPNARX(ny=6, nu=6, mode="sparse", n_inducing=64, max_train_points=400, constant_cap=None).fit(
        [(sdof_data["u"][:1200], sdof_data["yn"][:1200])], theta=theta)
    p = save_bundle(m, tmp_path, "old", fs=1.0, units={"u": "N", "y": "m"})
    man = json.loads((p / "manifest.json").read_text())
    del man["estimator"]["constant_cap"]  # as written before the fix, in schema 1 (migrated on load)
    man["schema_version"] = 1
    (p / "manifest.json").write_text(json.dumps(man))
    (p / "manifest.sha256").write_text(_sha256(p / "manifest.json") + "\n")
    with pytest.warns(BundleWarning, match="Retrain it"):
        b = load_bundle(p)
    assert b.model.constant_cap is None  # it still loads and predicts as it was built
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        q = save_bundle(GPNARX(ny=6, nu=6, mode="sparse", n_inducing=64, max_train_points=400).fit(
            [(sdof_data["u"][:1200], sdof_data["yn"][:1200])], theta=theta), tmp_path, "new", fs=1.0,
            units={"u": "N", "y": "m"})
        load_bundle(q)


def test_sparse_variance_is_accurate_when_the_noise_is_at_its_floor(sdof_data, tmp_path):
    # sigma_y^2 at ML-II's 1e-8 floor (the real BERT model's case): A = Kmm^-1 - Sigma^-1 then has
    # entries near 1/jitter and the single-matrix form k^T A k loses precision on the 1e-5 variance;
    # the factored form |G k|^2 (A = G^T G) must match an independent QR evaluation, whatever
    # the BLAS thread count, and survive the bundle round trip bit for bit
    from threadpoolctl import threadpool_limits

    from gpnarx.model.gp import sparse_variance_reference
    from gpnarx.model.regressors import stack_regressors
    from gpnarx.storage.bundle import load_bundle, save_bundle

    # the real-BERT optimum's shape: a long Matérn length scale and a large cubic offset, so Kmm is
    # jitter-conditioned and the variance (1e-5) sits far below k(x, x) (1.2)
    theta = np.log([1e-3, 12.9, 0.017, 3.7e-5, 70.9, 1e-8])
    data = [(sdof_data["u"][:2000], sdof_data["y"][:2000])]
    m = GPNARX(ny=8, nu=8, mode="sparse", n_inducing=256, max_train_points=500).fit(data, theta=theta)
    post = m.posterior_
    X, _, _ = stack_regressors(data, 8, 8)
    Xt = m.x_scaler_.transform(X)
    Xs = m.x_scaler_.transform(narx_regressors(sdof_data["u2"][:800], sdof_data["y2"][:800], 8, 8)[0])
    ref = sparse_variance_reference(post.kernel, post.points, Xt, Xs, post.noise_var)
    var = {}
    for n in (1, 2):
        with threadpool_limits(limits=n, user_api="blas"):
            var[n] = post.predict(Xs)[1]
    assert np.median(ref) > 1e-7  # a resolved variance, not the clip floor
    err = np.abs(var[1] - ref) / ref
    assert np.max(err) < 1e-6  # measured: median 2e-10
    assert np.allclose(var[2], var[1], rtol=1e-8, atol=0)
    # the old single-matrix evaluation of the same posterior is off by far more (measured: 2e-4)
    Ks = post.cross(Xs)
    old = post.kernel.diag(Xs) - np.einsum("ij,ij->i", Ks @ post.A, Ks)
    assert np.median(np.abs(old - ref) / ref) > 1e-5 > 100 * np.median(err)
    # the linearised path (mean_grad) uses the same factors
    assert post.mean_grad(Xs[7])[1] == pytest.approx(var[1][7], rel=1e-9)
    b = load_bundle(save_bundle(m, tmp_path, "floor", fs=1.0, units={"u": "N", "y": "m"}))
    assert set(b.manifest["files"]) >= {"posterior_G.npy"}
    assert np.array_equal(b.model.posterior_.predict(Xs)[1], var[1])


def test_sparse_bundle_with_the_single_matrix_variance_loads_and_warns(sdof_data, tmp_path):
    # bundles written before 2026-11-24 hold posterior_A.npy instead of its factor G: they load,
    # predict as they did (k** - k^T A k), and warn to retrain
    import json

    from gpnarx.storage.bundle import BundleWarning, _sha256, load_bundle, save_bundle

    theta = np.log([3.7e-4, 3.6, 7.67e-3, 2.0e-5, 126.4, 3.6e-4])
    m = GPNARX(ny=6, nu=6, mode="sparse", n_inducing=64, max_train_points=400).fit(
        [(sdof_data["u"][:1200], sdof_data["yn"][:1200])], theta=theta)
    p = save_bundle(m, tmp_path, "single", fs=1.0, units={"u": "N", "y": "m"})
    A = m.posterior_.A
    np.save(p / "posterior_A.npy", A)
    man = json.loads((p / "manifest.json").read_text())
    del man["files"]["posterior_G.npy"]
    (p / "posterior_G.npy").unlink()
    man["files"]["posterior_A.npy"] = _sha256(p / "posterior_A.npy")
    (p / "manifest.json").write_text(json.dumps(man))
    (p / "manifest.sha256").write_text(_sha256(p / "manifest.json") + "\n")
    with pytest.warns(BundleWarning, match="one matrix A"):
        b = load_bundle(p)
    Xs = m.x_scaler_.transform(narx_regressors(sdof_data["u2"][:300], sdof_data["y2"][:300], 6, 6)[0])
    Ks = m.posterior_.cross(Xs)
    want = np.maximum(m.posterior_.kernel.diag(Xs) - np.einsum("ij,ij->i", Ks @ A, Ks), 1e-300)
    assert np.allclose(b.model.posterior_.predict(Xs)[1], want, rtol=1e-12, atol=0)
    assert b.model.posterior_.predict(Xs[:5], float32=True)[1].shape == (5,)


def _default_path_fit(sdof_data, monkeypatch):
    """GPNARX.fit on 2000 ML-II rows (ny = nu = 2), recording what it passed to fit_ml2."""
    import gpnarx.model.estimator as est
    from gpnarx.model.ml2 import fit_ml2

    calls = []

    def spy(kernel, X, y, **kw):
        res = fit_ml2(kernel, X, y, **kw)
        calls.append((X.copy(), y.copy(), kw, res))
        return res

    monkeypatch.setattr(est, "fit_ml2", spy)
    m = GPNARX(ny=2, nu=2, max_train_points=2000, n_restarts=0).fit([(sdof_data["u"], sdof_data["yn"])])
    (X, Y, kw, warm), = calls
    return m, X, Y, kw, warm


def test_default_warm_start_ml2_reaches_the_cold_optimum(sdof_data, monkeypatch):
    """From 2000 ML-II rows GPNARX.fit warm-starts ML-II (model.ml2.default_warm_start_subset: N/4 rows
    first, with the cubic part's redundant scale held); on this small problem it lands within a
    tolerance of the cold ML-II optimum of the same problem (same rows, the same scale held): NLML
    within 0.01 %, sigma_y^2 within 5 %, one-step means within 1 % of the output RMS, in fewer full-N
    evaluations."""
    from gpnarx.model.gp import ExactPosterior
    from gpnarx.model.kernels import make_kernel
    from gpnarx.model.ml2 import default_warm_start_subset, fit_ml2

    m, X, Y, kw, warm = _default_path_fit(sdof_data, monkeypatch)
    assert X.shape[0] == 2000 and kw["warm_start_subset"] == default_warm_start_subset(2000) == 500
    assert kw["hold_redundant"] and warm.subset_rows == 500 and warm.subset_evals > 0
    assert default_warm_start_subset(1999) is None
    cold = fit_ml2(make_kernel(m.kernel), X, Y, n_restarts=0, hold_redundant=True)
    print(f"\nwarm NLML {warm.nlml:.3f} ({warm.n_evals} full + {warm.subset_evals} subset evals), "
          f"cold NLML {cold.nlml:.3f} ({cold.n_evals} evals)")
    assert abs(warm.nlml - cold.nlml) <= 1e-4 * abs(cold.nlml)
    assert abs(np.exp(warm.theta[-1]) / np.exp(cold.theta[-1]) - 1) < 0.05
    assert warm.n_evals < cold.n_evals
    kc = make_kernel(m.kernel)
    kc.set_theta(cold.theta[:-1])
    mu_cold, _ = ExactPosterior.fit(kc, float(np.exp(cold.theta[-1])), X, Y).predict(X[::7])
    mu_warm, _ = m.posterior_.predict(X[::7])
    assert np.sqrt(np.mean((mu_warm - mu_cold) ** 2)) < 0.01 * np.sqrt(np.mean(Y**2))


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason="known miss: holding the cubic part's scale (hold_redundant, set with the "
                   "warm start from 2000 rows) ends 13.2 nats above the free cold ML-II optimum on this problem "
                   "(NLML -1393.74 vs -1406.99; the warm start without the hold reaches -1406.99): the free optimum "
                   "has log s = -8.27, log sigma_p^2 = -4.27, log b = 5.53; with log s held at -1.39 the same kernel "
                   "needs log sigma_p^2 = -24.9 and log b = 12.4, outside the +/-12 bounds, so ML-II stops with the "
                   "cubic variance at its bound (model.ml2.fit_ml2's 'inside the bounds' does not hold here)")
def test_default_warm_start_ml2_reaches_the_free_cold_optimum(sdof_data, monkeypatch):
    from gpnarx.model.kernels import make_kernel
    from gpnarx.model.ml2 import fit_ml2

    m, X, Y, kw, warm = _default_path_fit(sdof_data, monkeypatch)
    cold = fit_ml2(make_kernel(m.kernel), X, Y, n_restarts=0)
    print(f"\nwarm (held scale) NLML {warm.nlml:.3f}, free cold NLML {cold.nlml:.3f}")
    assert warm.nlml <= cold.nlml + 1e-4 * abs(cold.nlml)


@pytest.fixture(scope="module")
def latent_runs(sdof_data):
    """The latent-band tests' model (ny = nu = 4, 500 ML-II rows, on sdof_data's noisy record) and its free
    runs of u2[:400] (512 paths, seed 1) by method, each run once for both parametrisations."""
    m = GPNARX(ny=4, nu=4, max_train_points=500, n_restarts=0).fit([(sdof_data["u"], sdof_data["yn"])])
    runs = {}

    def run(method):
        if method not in runs:
            runs[method] = m.simulate(sdof_data["u2"][:400], n_paths=512, seed=1, method=method)
        return runs[method]

    return m, run


@pytest.mark.parametrize("method", ["mc", "linear"])
def test_latent_band_leaves_out_the_noise_term(sdof_data, latent_runs, method):
    """FreeRun's latent band (latent_lower/latent_upper) is the band of the noise-free output: narrower
    than the predictive band by the noise term (linearised: inside it at every step, with var(y) = latent
    variance + sigma_y^2; Monte Carlo: quantiles of each path's latent draw, its fed-back paths unchanged),
    the same for both methods within Monte Carlo error, and the one a noise-free output is scored on."""
    m, runs = latent_runs
    u2, y2 = sdof_data["u2"][:400], sdof_data["y2"][:400]
    run = runs(method)
    lo, up, llo, lup = run.lower[4:], run.upper[4:], run.latent_lower[4:], run.latent_upper[4:]
    assert np.all(lup > llo) and np.mean(lup - llo) < np.mean(up - lo)
    if method == "linear":  # the same mean, a smaller variance: inside at every step
        assert np.all(llo >= lo - 1e-12) and np.all(lup <= up + 1e-12)
    noise_sd = np.sqrt(m.noise_var_) * m.y_scaler_.scale_[0]
    if method == "linear":  # exactly: var(y_i) = latent variance + sigma_y^2 at each step
        z = (run.upper - run.mean) / run.std
        lat_sd = (run.latent_upper - run.mean) / z
        assert np.allclose(run.std[4:] ** 2, lat_sd[4:] ** 2 + noise_sd**2, rtol=1e-9)
    else:  # the paths fed back are unchanged: the predictive band equals a run without the latent band
        plain = m.simulate(u2, n_paths=512, seed=1, method=method)
        assert np.array_equal(plain.lower, run.lower) and np.array_equal(plain.mean, run.mean)
    # the two bands of the same run agree between the methods to within Monte Carlo error
    other = runs("linear" if method == "mc" else "mc")
    w = np.median(run.latent_upper - run.latent_lower)
    assert abs(w / np.median(other.latent_upper - other.latent_lower) - 1) < 0.15
    assert coverage(y2, run.latent_lower, run.latent_upper) > 90


def test_scikit_learn_estimator_api():
    """GPNARX is a scikit-learn estimator: keyword-only parameters, get_params/set_params, clone (the
    protocol itself, ``model.params``: the product does not import scikit-learn)."""
    from sklearn.base import BaseEstimator, clone

    kw = dict(ny=3, nu=4, mode="sparse", n_inducing=32, max_train_points=150, n_restarts=0, seed=7)
    m = GPNARX(**kw)
    # the same parameters as scikit-learn's own BaseEstimator finds for the same __init__
    mirror = type("Mirror", (BaseEstimator,), {"__init__": GPNARX.__init__})(**kw)
    assert m.get_params() == mirror.get_params() and m.get_params(deep=False) == mirror.get_params(deep=False)
    params = m.get_params()
    assert params["ny"] == 3 and params["nu"] == 4 and params["mode"] == "sparse" and params["seed"] == 7
    assert set(params) == {"ny", "nu", "kernel", "mode", "n_inducing", "max_train_points", "selection",
                           "n_restarts", "seed", "include_noise", "sparse_max_rows", "hyper", "constant_cap",
                           "fit_backend"}
    with pytest.raises(TypeError):
        GPNARX(2, 2)  # keyword-only
    u = np.random.default_rng(0).normal(size=300)
    y = np.convolve(u, [0.5, 0.3, 0.1])[:300]
    m.fit([(u, y)])
    c = clone(m)
    assert c.get_params() == m.get_params()
    assert not hasattr(c, "posterior_") and hasattr(m, "posterior_")  # fitted attributes are not cloned
    assert all(k.endswith("_") for k in vars(m) if k not in params)
    assert c.set_params(ny=5, mode="exact") is c and c.ny == 5 and c.mode == "exact"
    with pytest.raises(ValueError, match="not_a_parameter.*valid parameters are"):
        c.set_params(not_a_parameter=1)
    assert c.set_params() is c
    with pytest.raises(ValueError, match="kernel__scale.*has no parameters"):
        c.set_params(kernel__scale=2.0)  # the kernel here is a name, not an estimator
    mean = clone(m).fit([(u, y)]).predict_one_step([(u, y)], return_std=False)
    np.testing.assert_allclose(mean, m.predict_one_step([(u, y)], return_std=False))


def test_estimator_docstring_example_runs():
    import doctest

    from gpnarx.model import estimator

    result = doctest.testmod(estimator, optionflags=doctest.ELLIPSIS)
    assert result.attempted > 0 and result.failed == 0


def test_fit_reports_progress_without_changing_the_fit(sdof_data):
    """fit(progress=print) says what it does while ML-II runs (the README's Python API example); the fitted
    hyperparameters are those of a silent fit."""
    pairs = [(sdof_data["u"][:800], sdof_data["yn"][:800])]
    lines = []
    a = GPNARX(ny=4, nu=4, max_train_points=400, n_restarts=0).fit(pairs, progress=lines.append)
    b = GPNARX(ny=4, nu=4, max_train_points=400, n_restarts=0).fit(pairs)
    assert np.array_equal(a.theta_, b.theta_)
    assert lines[0].startswith("regressors: 796 rows from 1 record(s) (ny=4, nu=4); ML-II on 400")
    assert any(line.startswith("ML-II (eq. 13) on 400 rows: 10 evaluations, best NLML") for line in lines), lines
    assert any(line.startswith("ML-II done: NLML") for line in lines)
    assert lines[-1].startswith("fitted: exact posterior on 400 rows")
