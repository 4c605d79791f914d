"""The FRF comparison's parts (studies/frf_check.py) on synthetic data: the drive-frequency amplitude it
takes from model.probe, the LMS FRF reader and its refusal of other files, and a linear model checked
against its own FRF."""
import numpy as np
import pytest
import scipy.io as sio

from gpnarx.model.probe import sine_fit
from studies import frf_check as fc


def test_sine_amplitude_recovers_the_drive_component_next_to_an_offset_and_a_harmonic():
    fs = 1024.0
    t = np.arange(2048) / fs
    x = 0.3 + 0.07 * np.sin(2 * np.pi * 12.0 * t + 0.4) + 0.02 * np.sin(2 * np.pi * 24.0 * t)
    assert sine_fit(x, fs, 12.0)[0] == pytest.approx(0.07, rel=1e-9)
    assert sine_fit(x, fs, 24.0)[0] == pytest.approx(0.02, rel=1e-9)


def _write_frf(path, f, h):
    struct = {"x_values": {"start_value": float(f[0]), "increment": float(f[1] - f[0]),
                           "number_of_values": int(f.size)},
              "y_values": {"values": h}}
    sio.savemat(str(path), {fc.FRF_VARIABLE: struct})


def test_read_lms_frf_reads_the_export_and_refuses_other_files(tmp_path):
    f = np.arange(0, 50, 0.0625)
    h = 1.0 / (1.0 + 1j * f / 10.0)
    _write_frf(tmp_path / "FRF.mat", f, h)
    f2, h2 = fc.read_lms_frf(tmp_path / "FRF.mat")
    assert np.allclose(f2, f) and np.allclose(h2, h)
    assert fc.frf_gain(f2, h2, 10.03125) == pytest.approx(np.interp(10.03125, f, np.abs(h)))
    sio.savemat(str(tmp_path / "other.mat"), {"u": np.zeros(3)})
    with pytest.raises(ValueError, match="not an LMS FRF export with FRF_Laser__X_Shaker__X"):
        fc.read_lms_frf(tmp_path / "other.mat")


def test_frf_check_of_a_linear_model_against_its_own_frf(tmp_path):
    """A model that is an exact first-order linear filter y_i = a y_{i-1} + b u_{i-1} agrees with its own
    FRF to well under 1 %; no FRF export under the folder gives None."""
    fs, a, b = 1024.0, 0.97, 0.05

    class Linear:
        def simulate(self, u, method="linear"):
            y = np.zeros_like(u)
            for i in range(1, u.size):
                y[i] = a * y[i - 1] + b * u[i - 1]

            class Run:
                mean, lower, upper = y, y - 0.01, y + 0.01
            return Run

    assert fc.frf_check(Linear(), tmp_path, fs=fs) is None
    f = np.arange(0, 100, 0.0625)
    z = np.exp(2j * np.pi * f / fs)
    (tmp_path / "Rand" / "noise").mkdir(parents=True)
    _write_frf(tmp_path / "Rand" / "noise" / "FRF.mat", f, b / (z - a))
    check = fc.frf_check(Linear(), tmp_path, fs=fs, freqs=(3.0, 12.0, 18.0, 40.0), seconds=4.0)
    assert [r["freq"] for r in check["rows"]] == [3.0, 12.0, 40.0]  # 18 Hz lies in the resonance band
    assert check["worst_ratio_error"] < 0.01
    assert "| 12 |" in fc.markdown(check)
