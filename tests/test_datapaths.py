"""One lookup of the lab data (training.datapaths.bert_data_dir) for the code and the tests alike."""
from __future__ import annotations

import re
from pathlib import Path

from gpnarx.training import config, datapaths, defaults
from gpnarx.training.simulators import bert_standin

ROOT = Path(__file__).resolve().parents[1]


def test_env_variable_wins_then_the_shared_folder(monkeypatch, tmp_path):
    monkeypatch.setenv("GPNARX_BERT_DATA", str(tmp_path / "rig"))
    assert datapaths.bert_data_dir() == tmp_path / "rig"
    # every user of the lookup sees the same folder
    assert config.bert_data_dir() == tmp_path / "rig" and bert_standin._bert_data_dir() == tmp_path / "rig"
    assert config.expand_path("${BERT_DATA}/Sine", tmp_path) == tmp_path / "rig" / "Sine"
    assert not defaults._bert_data_present()  # no Sine/ there
    (tmp_path / "rig" / "Sine").mkdir(parents=True)
    assert defaults._bert_data_present()
    monkeypatch.delenv("GPNARX_BERT_DATA")
    monkeypatch.chdir(tmp_path)
    assert datapaths.bert_data_dir().parts[-3:] == ("shared", "data", "bert-t5nm")


def test_no_test_or_package_module_builds_the_lab_data_path_itself():
    """A hard-coded ``shared/data/bert-t5nm`` path ignores GPNARX_BERT_DATA (tests skipped with the variable
    set): everything goes through bert_data_dir()."""
    pattern = re.compile(r"""["']bert-t5nm["']|shared/data/bert-t5nm["']""")
    offenders = []
    for folder in ("tests", "model", "operations", "storage", "training", "service", "cli", "bench", "tools"):
        for f in (ROOT / folder).rglob("*.py"):
            if f.name in ("datapaths.py", "test_datapaths.py"):
                continue
            if pattern.search(f.read_text()):
                offenders.append(str(f.relative_to(ROOT)))
    assert offenders == [], offenders
