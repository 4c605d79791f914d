"""Schema fuzzing: schemathesis against a running uvicorn server, driven by the committed OpenAPI document.

Every operation gets a bounded, deterministic number of examples (``MAX_EXAMPLES``, derandomized
Hypothesis): schema-valid cases with random path parameters, schema-valid cases aimed at a real
model (``boucwen``, version 1; half of them with the model's fs so the free run really executes,
with hostile but schema-valid numbers such as 1e308), and schema-violating (negative) cases.
Asserted: no 5xx, and every 4xx is ``application/problem+json`` with ``status``, ``title``,
``type`` and a ``detail`` or ``field`` naming what was wrong.
"""
from __future__ import annotations

import json
from pathlib import Path

import pytest
import schemathesis
from hypothesis import HealthCheck, Phase, given
from hypothesis import settings as hsettings
from hypothesis import strategies as st
from schemathesis import GenerationMode
from test_service_support import FS, LiveServer, built_registry

from gpnarx.service.app import create_app
from gpnarx.service.settings import Settings

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "openapi" / "openapi.json"
MAX_EXAMPLES = 25
SCHEMA = schemathesis.openapi.from_path(str(DOC))
OPERATIONS = sorted(f"{m.upper()} {p}" for p, item in json.loads(DOC.read_text())["paths"].items() for m in item)


@pytest.fixture(scope="module")
def server():
    # small Monte Carlo bounds keep generated predictions cheap; the schema is the same
    s = Settings(workers=2, queue_size=64, mc_paths_default=16, mc_paths_max=64, max_samples=512)
    with LiveServer(create_app(built_registry().root, s)) as srv:
        yield srv


def _operation(label: str):
    method, path = label.split(" ", 1)
    return SCHEMA[path][method.lower()]


def _aim(case_and_flag):
    case, use_fs = case_and_flag
    if use_fs and isinstance(case.body, dict) and "fs" in case.body:
        case.body["fs"] = FS
    return case


def _strategy(op):
    params = {p.name for p in op.path_parameters}
    strategies = [op.as_strategy(GenerationMode.POSITIVE), op.as_strategy(GenerationMode.NEGATIVE)]
    if "name" in params:
        fixed = {"name": "boucwen", **({"version": "1"} if "version" in params else {})}
        aimed = op.as_strategy(GenerationMode.POSITIVE, path_parameters=fixed)
        strategies.append(st.tuples(aimed, st.booleans()).map(_aim))
    return st.one_of(strategies)


def check_response(case, response):
    status = response.status_code
    where = f"{case.method} {case.formatted_path} -> {status}: {response.text[:300]}"
    assert status < 500, where
    if 400 <= status < 500:
        ctype = response.headers.get("content-type") or response.headers.get("Content-Type") or ""
        if isinstance(ctype, (list, tuple)):  # schemathesis keeps every value of a header
            ctype = ctype[0] if ctype else ""
        assert ctype.startswith("application/problem+json"), where
        body = response.json()
        assert body["status"] == status and body["title"] and body["type"], where
        assert body.get("detail") or body.get("field"), where
        assert "Traceback" not in response.text, where


@pytest.mark.parametrize("label", OPERATIONS)
def test_fuzz_operation(server, label):
    op = _operation(label)
    seen = []

    @hsettings(max_examples=MAX_EXAMPLES, derandomize=True, deadline=None, database=None,
               phases=[Phase.explicit, Phase.generate], suppress_health_check=list(HealthCheck))
    @given(case=_strategy(op))
    def run(case):
        response = case.call(base_url=server.url, timeout=60)
        seen.append(response.status_code)
        check_response(case, response)

    run()
    assert seen, "no case was generated"
    print(label, sorted(__import__("collections").Counter(seen).items()))
