"""studies.split_study: the plan parser and the config it varies (the study itself runs on an accelerator)."""
from __future__ import annotations

import pytest

from studies.split_study import parse_plan, split_config_text


def test_plan_cells_parse_and_bad_cells_name_themselves():
    assert parse_plan("7:exact:1500:0, 5:sparse:1500:512") == [(7.0, "exact", 1500, 0), (5.0, "sparse", 1500, 512)]
    with pytest.raises(ValueError, match="7:fast:1500:0"):
        parse_plan("7:fast:1500:0")


def test_split_moves_the_noise_run_between_train_and_lags(tmp_path):
    from gpnarx.training.config import load_config
    from gpnarx.training.defaults import shipped_config

    text = shipped_config("bert-real").read_text()
    moved = split_config_text(text, 9.0)
    assert "window = [0.0, 9.0]" in moved and "window = [9.0, 16.0]" in moved
    path = tmp_path / "bert-real.toml"
    path.write_text(moved)
    cfg = load_config(path)
    noise = {s.name: tuple(s.window) for s in cfg.records if "noise" in s.name and s.window}
    assert sorted(noise.values()) == [(0.0, 9.0), (9.0, 16.0)]
    with pytest.raises(ValueError, match="7 s"):
        split_config_text(moved, 11.0)
