"""Records with several channels (issue 52): ``Record`` with two-dimensional u / y and named channels, the LMS
reader's every channel by its label with the unit it really holds, the .npz reader and writer with named
channels; the single-channel records stay exactly as they were."""
from __future__ import annotations

import io

import numpy as np
import pytest

from gpnarx.model.record import Channel, Record, RecordError
from gpnarx.storage.record_files import read_record, write_record
from gpnarx.storage.record_formats import RecordFileError, RecordTooLarge, lms_channels, parse_lms, parse_record
from gpnarx.training.datapaths import bert_data_dir

DATA = bert_data_dir()
SINE20 = DATA / "Sine" / "Sine_20Hz"
ALL_OUT = ["Laser:+X", "Acc1:+X", "Acc2:+X", "Acc3:+X", "Acc4:+X"]
needs_data = pytest.mark.skipif(not (SINE20 / "Time.mat").is_file(), reason=f"real BERT records not under {DATA}")


def test_record_two_dimensional_channels_select_window():
    n = 50
    u = np.linspace(0, 1, n)
    y = np.column_stack([np.sin(u), np.cos(u), u ** 2])
    rec = Record(u, y, 100.0, {"u": "V", "y": ""}, "r",
                 channels={"u": [("drive", "V")], "y": [("a", "m"), Channel("b", "m/s"), {"name": "c", "unit": "m"}]})
    assert rec.n == n and rec.n_inputs == 1 and rec.n_outputs == 3
    assert [c.name for c in rec.output_channels()] == ["a", "b", "c"]
    assert rec.outputs_2d().shape == (n, 3) and rec.inputs_2d().shape == (n, 1)
    sel = rec.select(outputs=["c", "a"])
    assert sel.y.shape == (n, 2) and np.array_equal(sel.y, y[:, [2, 0]]) and sel.units["y"] == "m"
    one = rec.select(outputs="b")
    assert one.y.shape == (n,) and one.units["y"] == "m/s" and np.array_equal(one.y, y[:, 1])
    w = rec.window(0.1, 0.3)
    assert w.y.shape == (20, 3) and w.output_channels() == rec.output_channels()
    with pytest.raises(RecordError, match="no output channel 'd'"):
        rec.select(outputs=["d"])
    with pytest.raises(RecordError, match="selected twice"):
        rec.select(outputs=["a", "a"])
    with pytest.raises(RecordError, match="3 channel"):
        Record(u, y, 100.0, channels={"y": [("a", "m")]})
    with pytest.raises(RecordError, match="unique"):
        Record(u, y, 100.0, channels={"y": [("a", "m")] * 3})
    with pytest.raises(RecordError, match="must match"):
        Record(u, y[:-1], 100.0)
    with pytest.raises(RecordError, match="non-finite"):
        Record(u, np.where(y > 0.99, np.nan, y), 100.0)


def test_single_channel_record_unchanged():
    u = np.arange(10.0)
    rec = Record(u[:, None], u, 10.0, {"u": "N", "y": "m"})  # (n, 1) is one channel, kept (n,)
    assert rec.u.shape == (10,) and rec.channels is None and rec.n_outputs == 1
    assert rec.input_channels() == [Channel("u", "N")] and rec.output_channels() == [Channel("y", "m")]
    with pytest.raises(RecordError, match="1-D"):
        Record(np.zeros((3, 2, 2)), None, 10.0)


@needs_data
def test_lms_every_channel_by_label_with_its_real_unit():
    default = read_record(SINE20)
    rec = read_record(SINE20, outputs=ALL_OUT)
    assert default.y.ndim == 1 and default.channels is None and default.units == {"u": "V", "y": "m/s"}
    assert rec.y.shape == (default.n, 5) and rec.u.shape == (default.n,)
    assert np.array_equal(rec.y[:, 0], default.y) and np.array_equal(rec.u, default.u)
    assert [(c.name, c.unit) for c in rec.output_channels()] == [("Laser:+X", "m/s")] + [
        (f"Acc{k}:+X", "m/s^2") for k in range(1, 5)]
    assert rec.input_channels() == [Channel("Shaker:-X", "V")]
    # the accelerometers hold m/s^2 (Test.Lab's MKS), not g: Acc1 is the time derivative of the laser velocity
    dv = np.gradient(rec.y[:, 0]) * rec.fs
    acc1 = rec.y[:, 1]
    assert np.corrcoef(dv, acc1)[0, 1] > 0.999
    assert abs(np.std(acc1) / np.std(dv) - 1.0) < 0.01  # in g it would be 0.102
    stds = np.std(rec.y[:, 1:], axis=0)
    assert np.all(np.diff(stds) < 0)  # falls from Acc1 to Acc4 (about 37 / 18 / 9 / 1.6 m/s^2)
    alias = read_record(SINE20, outputs=["Time_Laser__X", "Acc3:+X"])
    assert np.array_equal(alias.y, rec.y[:, [0, 3]])
    with pytest.raises(RecordFileError, match="no channel 'Acc5:\\+X'.*'Acc4:\\+X'"):
        read_record(SINE20, outputs=["Acc5:+X"])
    names = [c["name"] for c in lms_channels((SINE20 / "Time.mat").read_bytes())]
    assert names == ALL_OUT


@needs_data
def test_lms_channels_are_bounded():
    shaker, time = (SINE20 / "TimeShaker.mat").read_bytes(), (SINE20 / "Time.mat").read_bytes()
    with pytest.raises(RecordTooLarge):
        parse_lms(shaker, time, outputs=ALL_OUT, max_samples=1000)
    with pytest.raises(RecordTooLarge, match="65536"):
        parse_lms(shaker, time, outputs=["Acc1:+X"], max_samples=65535)
    ok = parse_lms(shaker, time, outputs=["Acc2:+X"], max_samples=70_000, max_bytes=10_000_000)
    assert ok.y.ndim == 1 and ok.units["y"] == "m/s^2"


def test_npz_named_channels_round_trip(tmp_path):
    n = 40
    rng = np.random.default_rng(0)
    rec = Record(rng.normal(size=(n, 2)), rng.normal(size=(n, 3)), 250.0, {"u": "", "y": ""}, "chain",
                 channels={"u": [("F1", "N"), ("F2", "N")], "y": [("x1", "m"), ("x2", "m"), ("v3", "m/s")]})
    p = write_record(tmp_path / "chain.npz", rec)
    back = read_record(p)
    assert np.array_equal(back.u, rec.u) and np.array_equal(back.y, rec.y) and back.fs == 250.0
    assert back.output_channels() == rec.output_channels() and back.input_channels() == rec.input_channels()
    assert back.units == {"u": "N", "y": ""}
    sel = read_record(p, outputs=["v3"], inputs=["F2"])
    assert np.array_equal(sel.y, rec.y[:, 2]) and np.array_equal(sel.u, rec.u[:, 1]) and sel.units["y"] == "m/s"
    # a two-dimensional u without channel names is refused, as before
    buf = io.BytesIO()
    np.savez(buf, u=np.zeros((3, 4)), y=np.zeros(3), fs=10.0)
    with pytest.raises(RecordFileError, match="1-D"):
        parse_record(buf.getvalue(), "x.npz")
    buf = io.BytesIO()
    np.savez(buf, u=np.zeros((5, 2)), fs=10.0, channels_u=np.array(["a"]))
    with pytest.raises(RecordFileError, match="names 1 channels but the signal has 2"):
        parse_record(buf.getvalue(), "x.npz")


def test_csv_named_channels_round_trip(tmp_path):
    n = 30
    rng = np.random.default_rng(2)
    rec = Record(rng.normal(size=n), rng.normal(size=(n, 2)), 1024.0, {"u": "V", "y": ""}, "rig",
                 channels={"u": [("Shaker:-X", "V")], "y": [("Laser:+X", "m/s"), ("Acc1:+X", "m/s^2")]})
    p = write_record(tmp_path / "rig.csv", rec)
    assert p.read_text().splitlines()[0] == "time,u:Shaker:-X [V],y:Laser:+X [m/s],y:Acc1:+X [m/s^2]"
    back = read_record(p)
    assert back.fs == pytest.approx(1024.0) and np.array_equal(back.y, rec.y) and np.array_equal(back.u, rec.u)
    assert back.output_channels() == rec.output_channels() and back.input_channels() == rec.input_channels()
    acc = read_record(p, outputs=["Acc1:+X"])
    assert acc.y.ndim == 1 and acc.units["y"] == "m/s^2"
    with pytest.raises(RecordFileError, match="both a column 'y' and named y channels"):
        parse_record(b"time,u,y,y:a\n0,1,2,3\n0.1,1,2,3\n", "x.csv")
    with pytest.raises(RecordFileError, match="appears twice"):
        parse_record(b"time,u,y:a,y:a\n0,1,2,3\n0.1,1,2,3\n", "x.csv")
    with pytest.raises(RecordFileError, match="written as .npz"):
        write_record(tmp_path / "rig.mat", rec)


def test_service_parse_refuses_several_channels_on_files(tmp_path):
    from gpnarx.service.problems import ProblemError
    from gpnarx.service.ui import parse_uploads

    rec = Record(np.arange(20.0), np.ones((20, 2)), 100.0, channels={"y": [("a", "m"), ("b", "m")]})
    data = write_record(tmp_path / "two.npz", rec).read_bytes()
    with pytest.raises(ProblemError) as err:
        parse_uploads([("two.npz", "", data)], None)
    assert err.value.status == 422 and err.value.field == "files" and "a, b" in err.value.detail
    one = write_record(tmp_path / "one.npz", Record(np.arange(20.0), np.ones(20), 100.0)).read_bytes()
    got, fmt = parse_uploads([("one.npz", "", one)], None)
    assert fmt == "npz" and got.y.shape == (20,)


def test_cli_refuses_a_record_with_several_channels(tmp_path):
    from gpnarx.cli.cmd_predict import read_cli_record
    from gpnarx.cli.errors import CLIError

    p = write_record(tmp_path / "two.npz", Record(np.arange(20.0), np.ones((20, 2)), 100.0,
                                                  channels={"y": [("a", "m"), ("b", "m")]}))
    with pytest.raises(CLIError, match=r"several channels \(u, a, b\)"):
        read_cli_record(p)
    one = write_record(tmp_path / "one.npz", Record(np.arange(20.0), np.ones(20), 100.0))
    assert read_cli_record(one).y.shape == (20,)
