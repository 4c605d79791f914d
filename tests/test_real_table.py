"""The real-rig table's parts on synthetic data: the excitation class of a record, the ARX chosen by the
lag search, the class ARX never fitted on the record it scores, and the acceptance checks."""
import numpy as np
import pytest

from gpnarx.model.record import Record
from gpnarx.training.baselines import LinearARX, arx_lag_search
from studies import real_table as rt

FS = 1024.0


def _rec(u, y, name, **meta):
    return Record(np.asarray(u, float), np.asarray(y, float), FS, {"u": "V", "y": "m/s"}, name, meta)


def _filter(u, a=(1.6, -0.8), b=(0.05, 0.02)):
    """y_i = a1 y_{i-1} + a2 y_{i-2} + b0 u_i + b1 u_{i-1}: an exact second-order ARX."""
    y = np.zeros_like(u)
    for i in range(u.size):
        y[i] = (a[0] * y[i - 1] if i >= 1 else 0.0) + (a[1] * y[i - 2] if i >= 2 else 0.0) \
            + b[0] * u[i] + (b[1] * u[i - 1] if i >= 1 else 0.0)
    return y


def test_record_class_by_folder_and_drive(tmp_path):
    t = np.arange(4096) / FS
    sine = lambda f: _rec(0.15 * np.sin(2 * np.pi * f * t), np.zeros(t.size), "s")  # noqa: E731
    noise = _rec(np.random.default_rng(0).normal(size=t.size), np.zeros(t.size), "n")
    assert rt.record_class(tmp_path / "Sine" / "Sine_19Hz", sine(19.0)) == "sine near resonance"
    assert rt.record_class(tmp_path / "Sine" / "Sine_09Hz", sine(9.0)) == "sine away from resonance"
    assert rt.record_class(tmp_path / "Chirp" / "Chirp0to40Hz" / "Chirp0p05", sine(9.0)) == "sweep"
    assert rt.record_class(tmp_path / "Rand" / "Rand0p10", noise) == "noise"


def test_arx_lag_search_finds_the_true_order_and_scores_every_cell():
    rng = np.random.default_rng(1)
    u = rng.normal(size=3000)
    train = [_rec(u[:2000], _filter(u[:2000]), "train")]
    lags = [_rec(u[2000:], _filter(u[2000:]), "lags")]
    s = arx_lag_search(train, lags, [1, 2, 4], [1, 2], criterion="worst")
    assert (s["ny"], s["nu"]) == (2, 2)  # the smallest cell that is exact (ties: fewer lags)
    assert s["fit"] == pytest.approx(100.0, abs=1e-6)
    assert len(s["cells"]) == 6 and all(set(c["fits"]) == {"lags"} for c in s["cells"])
    assert next(c for c in s["cells"] if (c["ny"], c["nu"]) == (1, 1))["fits"]["lags"] < 99.0
    with pytest.raises(ValueError, match="criterion"):
        arx_lag_search(train, lags, [2], [2], criterion="median")


def test_arx_lag_search_takes_the_fewest_lags_among_cells_equal_to_round_off(monkeypatch):
    """Two exact cells whose fits differ by round-off (as another BLAS gives them): the smaller order wins; a
    cell better by more than round-off still wins over fewer lags."""
    import gpnarx.training.baselines as bl

    rng = np.random.default_rng(1)
    u = rng.normal(size=1200)
    train, lags = [_rec(u[:800], _filter(u[:800]), "train")], [_rec(u[800:], _filter(u[800:]), "lags")]
    # cells in grid order (ny, nu) = (1, 2), (2, 2), (4, 2): the fits another machine computed
    for fits, chosen in (([24.9, 99.9999999999988, 99.99999999999899], (2, 2)),
                         ([99.99999999999899, 99.9999999999988, 24.9], (1, 2)),
                         ([24.9, 99.0, 99.5], (4, 2))):
        given = iter(fits)
        monkeypatch.setattr(bl, "fit_percent", lambda y, m, given=given: next(given))
        s = arx_lag_search(train, lags, [1, 2, 4], [2], criterion="worst")
        assert (s["ny"], s["nu"]) == chosen, fits
    assert bl.ARX_TIE_TOLERANCE <= 1e-6  # round-off only: the baseline stays the best ARX of the grid


def test_class_arx_is_fitted_on_the_other_records_of_its_class_only():
    rng = np.random.default_rng(2)
    recs = {n: _rec(u, _filter(u), n) for n, u in (("a", rng.normal(size=800)), ("b", rng.normal(size=800)),
                                                   ("c", rng.normal(size=800)))}
    classes = {"a": "noise", "b": "noise", "c": "sweep"}
    out = rt._class_arx(recs, classes)
    assert out["a"][1] == ["b"] and out["b"][1] == ["a"] and out["c"] is None
    assert isinstance(out["a"][0], LinearARX)


def _row(role, cls, fit, cov, arx_s, arx_c, sharp=None, peak=1.0, diverged=0):
    g = {"fit": fit, "coverage": cov, "peak_ratio": peak, "diverged_paths": diverged, "sharpness": sharp}
    return {"role": role, "class": cls, "whole_linear": g, "arx_search": {"fit": arx_s}, "arx_class": {"fit": arx_c}}


def test_table_checks_apply_every_target_to_held_out_records():
    rows = {"n1": _row("validate", "noise", 70.0, 99.0, 10.0, 68.0, sharp=1.2),
            "n2": _row("train", "noise", 80.0, 100.0, 10.0, 84.0, sharp=1.4),
            "s1": _row("validate", "sweep", 90.0, 95.0, 70.0, 68.0),
            "t1": _row("train", "sweep", 20.0, 10.0, 90.0, 90.0)}  # a training record is not held to the targets
    c = rt.table_checks({"records": rows, "mc_paths": 0})
    m = c["methods"]["whole_linear"]
    assert c["met"] and m["met"] and m["below_better_arx"] == []
    assert m["min_heldout_coverage"] == {"noise": 99.0, "sweep": 95.0} and m["max_noise_sharpness"] == 1.4
    rows["n1"] = _row("validate", "noise", 60.0, 99.0, 10.0, 68.0, sharp=1.2)  # below the class ARX
    rows["s1"] = _row("validate", "sweep", 90.0, 85.0, 70.0, 68.0)  # coverage below 90 %
    c = rt.table_checks({"records": rows, "mc_paths": 0})
    assert not c["met"] and c["methods"]["whole_linear"]["below_better_arx"] == ["n1"]
    rows["n2"] = _row("train", "noise", 80.0, 100.0, 10.0, 84.0, sharp=1.6)  # a band too wide on a noise run
    assert rt.table_checks({"records": rows, "mc_paths": 0})["methods"]["whole_linear"]["max_noise_sharpness"] == 1.6
    rows["t1"] = _row("train", "sweep", 20.0, 10.0, 90.0, 90.0, peak=4.0)
    assert rt.table_checks({"records": rows, "mc_paths": 0})["diverged"] == ["t1"]


@pytest.fixture(scope="module")
def small_real():
    """A small GP-NARX (ny = nu = 4, 300 rows) fitted on the first 4 s of the real 0.25 V noise run, and the lab
    data folder (skipped without it)."""
    from conftest import BERT_DATA

    from gpnarx.model.estimator import GPNARX
    from gpnarx.storage.record_files import read_record

    folders = {p.name: p for p in rt.find_records(BERT_DATA)} if BERT_DATA.is_dir() else {}
    if "Rand0p25" not in folders or "Sine_20Hz" not in folders:
        pytest.skip("the lab records are not here")
    rec = read_record(folders["Rand0p25"]).window(0.0, 4.0)
    return GPNARX(ny=4, nu=4, max_train_points=300, n_restarts=0).fit([rec]), BERT_DATA


def test_kstep_rows_and_the_gap_record(small_real, tmp_path):
    model, data = small_real
    table = {"records": {"Sine_20Hz": {"class": "sine near resonance", "role": "validate"},
                         "Rand0p10": {"class": "noise", "role": "validate"}}, "max_seconds": 3.0}
    rt.add_kstep_rows(model, table, data, horizons=(1, 8, 64))
    assert table["kstep_horizons"] == [1, 8, 64]
    for name, row in table["records"].items():
        f = {k: v["fit"] for k, v in row["k_step"].items() if k != "seconds"}
        assert f["1"] > f["8"] > f["64"] > f["free_run"] - 1.0, (name, f)  # farther ahead, worse
        assert all(0.0 <= v["coverage"] <= 100.0 for k, v in row["k_step"].items() if k != "seconds")
    text = rt.kstep_markdown(table)
    assert "| k = 1 | k = 8 | k = 64 | free run (measured start) |" in text and "| Rand0p10 | noise |" in text
    g = rt.gap_record(model, data, tmp_path, seconds=3.0)
    assert g["nan_through_gap"] and g["gap_seconds"] == pytest.approx(0.5, abs=1e-3)
    assert g["gaps"] == [[int(round(1.25 * 1024)), int(round(1.75 * 1024))]]
    assert (tmp_path / g["figure"]).stat().st_size > 10_000
    # after the gap the run restarts from the measured outputs: no worse than the whole record's free run there
    assert g["cut_after"]["fit"] >= g["whole_after"]["fit"] - 1.0
    assert "![Sine_20Hz with a gap](runs/bert-real/gap_record.png)" in rt.gap_markdown(g)
