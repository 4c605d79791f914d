"""Held-out calibration of the noise variance sigma_y^2 (model.heldout_noise, GPNARX.fit(heldout=...))."""
import numpy as np
import pytest

from gpnarx.model.estimator import GPNARX
from gpnarx.model.heldout_noise import heldout_noise_var
from gpnarx.model.metrics import coverage


def test_heldout_ml_recovers_a_known_noise_variance():
    rng = np.random.default_rng(0)
    v = rng.uniform(0.0, 0.02, size=20000)  # latent variances, as eq. 9 gives them
    r = rng.normal(size=v.size) * np.sqrt(v + 0.04)
    s2 = heldout_noise_var(r, v, floor=1e-8)
    assert abs(s2 / 0.04 - 1) < 0.05, s2
    # ignoring the latent variance would over-estimate it by the mean latent variance
    assert heldout_noise_var(r, np.zeros_like(v), floor=1e-8) > s2 + 0.005


def test_heldout_ml_respects_the_floor_and_ceiling():
    rng = np.random.default_rng(1)
    v = np.full(500, 1.0)
    r = rng.normal(size=v.size) * 0.5  # residuals smaller than the latent variance alone explains
    assert heldout_noise_var(r, v, floor=1e-6) == 1e-6
    assert heldout_noise_var(rng.normal(size=500) * 100.0, np.zeros(500), floor=1e-6, ceiling=10.0) == 10.0


@pytest.mark.parametrize("args, match", [
    (([], [], 1e-8), "residual is empty"),
    (([1.0, 2.0], [0.1], 1e-8), "latent_var has 1 values for 2 residuals"),
    (([np.nan], [0.1], 1e-8), "must be finite"),
    (([1.0], [0.1], 0.0), "need 0 < floor <= ceiling"),
])
def test_heldout_ml_refuses_bad_input(args, match):
    with pytest.raises(ValueError, match=match):
        heldout_noise_var(*args)


@pytest.fixture(scope="module")
def clean_and_noisy(sdof_data):
    rng = np.random.default_rng(3)
    u, y = sdof_data["u"][:1500], sdof_data["y"][:1500]
    u2, y2 = sdof_data["u2"][:1200], sdof_data["y2"][:1200]
    y2n = y2 + 0.05 * np.std(y2) * rng.normal(size=y2.size)
    return (u, y), (u2[:600], y2n[:600]), (u2[600:], y2n[600:])


@pytest.mark.parametrize("mode", ["exact", "sparse"])
def test_heldout_calibration_widens_an_overconfident_model(clean_and_noisy, mode):
    train, held, test = clean_and_noisy
    kw = dict(ny=4, nu=4, mode=mode, n_inducing=64, max_train_points=400, n_restarts=0)
    plain = GPNARX(**kw).fit([train])
    cal = GPNARX(**kw).fit([train], heldout=[held])
    # trained on noise-free outputs, ML-II's sigma_y^2 is tiny; the held-out 5 % noise raises it
    assert cal.noise_var_ml2_ == pytest.approx(plain.noise_var_, rel=1e-9)
    assert cal.noise_var_ > 100 * plain.noise_var_
    nc = cal.noise_calibration_
    assert nc["method"] == "heldout_ml" and nc["n_records"] == 1 and nc["n_residuals"] == 600 - 4
    assert nc["noise_var"] == cal.noise_var_ and nc["noise_var_ml2"] == plain.noise_var_
    assert cal.posterior_.noise_var == cal.noise_var_ and np.exp(cal.theta_[-1]) == pytest.approx(cal.noise_var_)
    # the one-step 99 % band on a third, unseen noisy segment: too narrow before, right after
    i0 = 4
    mu_p, sd_p = plain.predict_one_step([test])
    mu_c, sd_c = cal.predict_one_step([test])
    y = test[1][i0:]
    cov_p = coverage(y, mu_p - 2.576 * sd_p, mu_p + 2.576 * sd_p)
    cov_c = coverage(y, mu_c - 2.576 * sd_c, mu_c + 2.576 * sd_c)
    print(mode, "noise", plain.noise_var_, "->", cal.noise_var_, "coverage", cov_p, "->", cov_c)
    assert cov_p < 80.0 and cov_c >= 97.0


@pytest.mark.parametrize("mode", ["exact", "sparse"])
def test_predict_rows_in_blocks_is_one_call(clean_and_noisy, mode):
    """eqs. 8-9 over many rows in row blocks (estimator._predict_rows: the memory of a few blocks, not of
    K(all rows, points)) give what one posterior.predict over every row gives."""
    from gpnarx.model.estimator import ROW_BLOCK_ALIGN, _predict_rows
    from gpnarx.model.regressors import stack_regressors

    train, held, test = clean_and_noisy
    m = GPNARX(ny=4, nu=4, mode=mode, n_inducing=64, max_train_points=400, n_restarts=0).fit([train])
    X = m.x_scaler_.transform(stack_regressors([train, held, test], 4, 4)[0])  # 2688 rows: 10 blocks and a tail
    mu, var = m.posterior_.predict(X)
    floats = ROW_BLOCK_ALIGN * m.posterior_.n_points  # blocks of ROW_BLOCK_ALIGN rows
    bm, bv = _predict_rows(m.posterior_, X, block_floats=floats)
    np.testing.assert_allclose(bm, mu, rtol=1e-12, atol=0)
    np.testing.assert_allclose(bv, var, rtol=1e-12, atol=1e-15)
    mean_only, none = _predict_rows(m.posterior_, X, return_var=False, block_floats=floats)
    assert none is None
    np.testing.assert_array_equal(mean_only, bm)
    # fewer floats than one aligned block: still whole ROW_BLOCK_ALIGN-row blocks
    np.testing.assert_array_equal(_predict_rows(m.posterior_, X, block_floats=1)[0], bm)


def test_heldout_calibration_in_row_blocks_is_the_one_call_calibration(clean_and_noisy, monkeypatch):
    """The held-out calibration's one-step predictions run in row blocks (ROW_BLOCK_FLOATS): the same
    calibrated sigma_y^2 and posterior as one call over every held-out row (the code before the blocks)."""
    import gpnarx.model.estimator as est

    train, held, test = clean_and_noisy
    kw = dict(ny=4, nu=4, max_train_points=400, n_restarts=0)
    theta = GPNARX(**kw).fit([train]).theta_
    monkeypatch.setattr(est, "ROW_BLOCK_FLOATS", 1 << 62)  # one call over every row
    one = GPNARX(**kw).fit([train], theta=theta, heldout=[held, test])
    monkeypatch.setattr(est, "ROW_BLOCK_FLOATS", est.ROW_BLOCK_ALIGN * 400)  # 1192 rows in 5 blocks
    blocks = GPNARX(**kw).fit([train], theta=theta, heldout=[held, test])
    for key, value in one.noise_calibration_.items():
        assert blocks.noise_calibration_[key] == (value if isinstance(value, str) else pytest.approx(value, rel=1e-12))
    assert blocks.noise_var_ > 100 * blocks.noise_var_ml2_  # the calibration did raise it
    for name, arr in one.fitted_arrays().items():
        np.testing.assert_allclose(blocks.fitted_arrays()[name], arr, rtol=1e-12, atol=0, err_msg=name)


def test_calibration_never_lowers_ml2_noise(sdof_data):
    u, yn = sdof_data["u"][:1500], sdof_data["yn"][:1500]
    m = GPNARX(ny=4, nu=4, max_train_points=400, n_restarts=0).fit(
        [(u, yn)], heldout=[(sdof_data["u2"][:600], sdof_data["y2"][:600])])  # clean held-out outputs
    assert m.noise_var_ == m.noise_var_ml2_ and m.noise_calibration_["noise_var"] == m.noise_var_ml2_


def test_bad_heldout_fails_before_ml2(sdof_data):
    m = GPNARX(ny=4, nu=4, max_train_points=400, n_restarts=0)
    with pytest.raises(ValueError, match=r"heldout\[0\] has 3 samples"):
        m.fit([(sdof_data["u"][:500], sdof_data["y"][:500])], heldout=[(np.ones(3), np.ones(3))])
    with pytest.raises(ValueError, match="heldout: records must be a non-empty list"):
        m.fit([(sdof_data["u"][:500], sdof_data["y"][:500])], heldout=[])
    assert not hasattr(m, "posterior_")


def test_calibrated_model_round_trips_through_a_bundle(clean_and_noisy, tmp_path):
    from gpnarx.storage.bundle import load_bundle, save_bundle

    train, held, test = clean_and_noisy
    m = GPNARX(ny=4, nu=4, mode="sparse", n_inducing=64, max_train_points=400, n_restarts=0).fit(
        [train], heldout=[held])
    b = load_bundle(save_bundle(m, tmp_path, "cal", fs=1.0, units={"u": "N", "y": "m"}))
    assert b.manifest["noise_calibration"]["noise_var"] == m.noise_var_
    assert b.model.noise_var_ == m.noise_var_ and b.model.noise_var_ml2_ == m.noise_var_ml2_
    r1 = m.simulate(test[0], n_paths=32, seed=1)
    r2 = b.model.simulate(test[0], n_paths=32, seed=1)
    assert np.array_equal(r1.upper, r2.upper)
