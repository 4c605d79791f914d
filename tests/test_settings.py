"""The service settings (pydantic-settings) and the limits table docs/api.md holds."""
from __future__ import annotations

import re
from pathlib import Path

import pytest

from gpnarx.service.settings import DEFAULT_BOUNDS, ENV, Settings, settings_table

API_MD = Path(__file__).resolve().parents[1] / "docs" / "api.md"


def test_api_md_holds_the_generated_settings_table():
    text = API_MD.read_text()
    m = re.search(r"<!-- settings-table[^>]*-->\n(.*?)<!-- /settings-table -->", text, re.S)
    assert m, "docs/api.md lost its settings-table markers"
    assert m.group(1) == settings_table(), (
        "docs/api.md's settings table is stale: replace it by `python -m gpnarx.service.settings`")


def test_every_setting_has_its_variable_and_the_bounds_are_the_defaults():
    assert set(ENV) == set(Settings.model_fields) - {"sighup_reload"}
    assert all(var == "GPNARX_" + name.upper() for name, var in ENV.items())
    s = Settings()
    assert s.bounds() == DEFAULT_BOUNDS
    assert DEFAULT_BOUNDS == {"max_samples": 65536, "max_batch": 64, "mc_paths_default": None, "mc_paths_max": 4096,
                              "max_mc_work": 2**24, "max_body_bytes": 32 * 1024 * 1024}


def test_settings_read_the_environment_through_pydantic_settings(monkeypatch):
    monkeypatch.setenv("GPNARX_MAX_BATCH", "7")
    monkeypatch.setenv("GPNARX_REGISTRY_POLL", "0.5")
    monkeypatch.setenv("GPNARX_MAX_SAMPLES", "")  # blank: unset
    monkeypatch.setenv("GPNARX_SIGHUP_RELOAD", "true")  # no environment setting
    s = Settings()
    assert s.max_batch == 7 and s.registry_poll == 0.5 and s.max_samples == 65536 and s.sighup_reload is False
    assert Settings.from_env().max_batch == 7
    assert Settings(max_batch=9).max_batch == 9 and Settings.from_env(max_batch=9).max_batch == 9  # arguments win
    assert Settings.from_env(max_batch=None).max_batch == 7  # None: not given
    assert Settings.from_env({}).max_batch == 64  # a given mapping instead of os.environ
    monkeypatch.setenv("GPNARX_MAX_BATCH", "seven")
    with pytest.raises(ValueError, match="environment variable GPNARX_MAX_BATCH must be an integer"):
        Settings()


@pytest.mark.parametrize("kw, match", [({"workers": 0}, "workers must be a positive integer"),
                                       ({"queue_size": -1}, "queue_size must be a non-negative integer"),
                                       ({"max_samples": True}, "max_samples"),
                                       ({"blas_threads": 1.5}, "blas_threads"),
                                       ({"registry_poll": float("inf")}, "registry_poll"),
                                       ({"nonsense": 1}, "nonsense")])
def test_bad_settings_are_refused(kw, match):
    with pytest.raises(ValueError, match=match):
        Settings(**kw)


def test_settings_are_frozen_and_with_validates():
    s = Settings(workers=1)
    with pytest.raises(Exception):  # noqa: B017 - pydantic's frozen-instance error
        s.workers = 2
    assert s.with_(workers=3).workers == 3 and s.workers == 1
    with pytest.raises(ValueError, match="workers"):
        s.with_(workers=0)
