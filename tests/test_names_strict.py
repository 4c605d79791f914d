"""Names, versions and aliases are checked whole: a trailing newline is not a name.

Python's ``$`` also matches before a final ``\\n``, so ``^[a-z]+$`` accepts ``"prod\\n"``; every check of a
model name, version or alias (storage, the CLI, the service) must refuse it.
"""
from __future__ import annotations

import json

import pytest

from gpnarx.storage.bundle import NAME_RE, VERSION_RE, BundleError, check_name, check_version
from gpnarx.storage.registry import ALIAS_RE, check_alias, check_version_ref, parse_model_ref

BAD = ["prod\n", "boucwen\n", "1\n", "prod\r\n", "prod\n\n"]


@pytest.mark.parametrize("value", BAD)
def test_a_trailing_newline_is_refused_by_every_check(value):
    for check in (check_name, check_alias, check_version_ref):
        with pytest.raises(BundleError):
            check(value)
    with pytest.raises(BundleError):
        check_version(value)
    with pytest.raises(BundleError):
        parse_model_ref(f"boucwen:{value}")
    with pytest.raises(BundleError):
        parse_model_ref(value)
    for pattern in (NAME_RE, VERSION_RE, ALIAS_RE):  # whatever method a caller uses on the pattern
        assert pattern.match(value) is None and pattern.search(value) is None


def test_good_names_still_pass():
    assert check_name("bouc-wen.v2") == "bouc-wen.v2" and check_version("12") == "12"
    assert check_alias("production") == "production" and check_version_ref("latest") == "latest"
    assert parse_model_ref("boucwen:production") == ("boucwen", "production")


def test_cli_alias_set_refuses_a_name_with_a_newline(tmp_path, capsys):
    from test_service_support import copy_registry

    from gpnarx.cli.main import main

    reg = copy_registry(tmp_path / "reg")
    assert main(["alias", "set", "--registry", str(reg), "boucwen", "prod\n", "1"]) != 0
    assert "alias 'prod\\n' is invalid" in capsys.readouterr().err
    assert not (reg / "boucwen" / "aliases.json").exists()
    assert main(["alias", "set", "--registry", str(reg), "boucwen\n", "prod", "1"]) != 0
    assert main(["alias", "set", "--registry", str(reg), "boucwen", "prod", "1"]) == 0
    assert json.loads((reg / "boucwen" / "aliases.json").read_text())["aliases"] == {"prod": "1"}

