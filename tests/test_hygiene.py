"""History stays in CHANGELOG.md: the README, the sources, the shipped configs and the CLI help
hold no dates, no work-session numbers and no work-log references, and the README stays a short
user's guide.

A failure lists every offending ``file:line`` (or ``gpnarx <command> --help:line``) with the
matched text, so it can be fixed where it is.
"""
from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
README_MAX_CHARS = 15_000

#: Patterns that mark history: an ISO date, a work-session number, a work-log reference.
PATTERNS = {
    "ISO date": re.compile(r"\b20\d\d-\d\d-\d\d\b"),
    "session number": re.compile(r"\bsessions?[\s-]*\d+", re.IGNORECASE),
    "work log": re.compile(r"\bwork[\s-]log", re.IGNORECASE),
}

#: Source folders whose ``*.py`` files are checked (CHANGELOG.md is the one place for history).
SOURCE_DIRS = ("model", "operations", "storage", "training", "service", "cli", "gpnarx", "bench", "studies", "tools")


def offences(text: str, where: str) -> list[str]:
    """``where:line: kind: matched text`` for every match of every pattern in ``text``."""
    found = []
    for kind, pattern in PATTERNS.items():
        for m in pattern.finditer(text):
            line = text.count("\n", 0, m.start()) + 1
            found.append(f"{where}:{line}: {kind}: {m.group(0)!r}")
    return sorted(found, key=lambda s: (s.split(":")[0], int(s.split(":")[1])))


def _report(found: list[str], what: str) -> str:
    return f"{len(found)} history reference(s) in {what} (move history to CHANGELOG.md):\n  " + "\n  ".join(found)


def source_files() -> list[Path]:
    files = [p for d in SOURCE_DIRS for p in sorted((ROOT / d).rglob("*.py"))]
    files += sorted((ROOT / "configs").glob("*.toml"))
    files.append(ROOT / "Dockerfile")
    return [p for p in files if p.is_file()]


def test_patterns_catch_what_they_should():
    text = "ok\nre-run on 2031-01-02\nsee session 7 and Sessions 5-6, session-6\nfrom the work log; work-log\n"
    kinds = [f.split(": ")[1] for f in offences(text, "x")]
    assert kinds.count("ISO date") == 1 and kinds.count("session number") == 3 and kinds.count("work log") == 2
    assert offences("a session of training, 2000-point sets, version 20.1-2", "x") == []
    assert offences(text, "f.py")[0].startswith("f.py:2: ")


def test_readme_has_no_history():
    found = offences((ROOT / "README.md").read_text(encoding="utf-8"), "README.md")
    assert not found, _report(found, "README.md")


def test_readme_is_short():
    n = len((ROOT / "README.md").read_text(encoding="utf-8"))
    assert n <= README_MAX_CHARS, f"README.md has {n} characters (at most {README_MAX_CHARS}): move material to docs/"


def test_sources_configs_and_dockerfile_have_no_history():
    files = source_files()
    assert any(p.suffix == ".toml" for p in files) and any(p.name == "estimator.py" for p in files)
    found = []
    for p in files:
        found += offences(p.read_text(encoding="utf-8"), str(p.relative_to(ROOT)))
    assert not found, _report(found, "sources, configs and Dockerfile")


def test_cli_help_has_no_history():
    import argparse

    from gpnarx.cli.main import build_parser

    parser = build_parser()
    texts = {"gpnarx --help": parser.format_help()}
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                texts[f"gpnarx {name} --help"] = sub.format_help()
    assert len(texts) > 5
    found = []
    for where, text in texts.items():
        found += offences(text, where)
    assert not found, _report(found, "CLI help")
