"""The /ui page, /docs and /redoc in a real headless Chromium, with every request outside loopback blocked.

Debian's ``chromium`` package is driven by Playwright's Python API through its executable path (no
browser download). The service runs under uvicorn on 127.0.0.1 (a free port) over the small trained
registry of ``test_service_support`` plus training reports (``test_ui.make_reports``). The page is
used as an engineer would: upload a record file (or load an example, or enter the API key), run, and
read the verdict and the plot; the same record is then sent to the API directly and the answers must
agree. Skipped, with the reason, only when Chromium or Playwright is not installed (``.ci/run``
installs both).

Screenshots go to ``$GPNARX_UI_SCREENSHOTS`` when set (the ones in docs/img were made with
``GPNARX_UI_SCREENSHOTS=docs/img``), else to the test's temporary folder.
"""
from __future__ import annotations

import os
import shutil
from pathlib import Path
from urllib.parse import urlparse

import httpx
import numpy as np
import pytest
from test_service_support import FS, LiveServer, copy_registry, short_record
from test_ui import make_reports

from gpnarx.model.records import Record
from gpnarx.service.app import create_app
from gpnarx.service.settings import Settings
from gpnarx.service.ui import STATIC_DIR
from gpnarx.training.records import write_record

CHROMIUM = os.environ.get("GPNARX_CHROMIUM") or shutil.which("chromium") or shutil.which("chromium-browser")
API_KEY = "s3cret-key"
LOOPBACK = {"127.0.0.1", "localhost", "::1"}
RUN_TIMEOUT_MS = 120_000


def _playwright():
    if not CHROMIUM:
        pytest.skip("Chromium is not installed (Debian: apt-get install -y chromium; .ci/run does it)")
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        pytest.skip("Playwright's Python package is not installed (pip install -e '.[test]')")
    return sync_playwright


@pytest.fixture(scope="module")
def browser():
    sync_playwright = _playwright()
    with sync_playwright() as pw:
        b = pw.chromium.launch(executable_path=CHROMIUM, args=["--no-sandbox", "--disable-dev-shm-usage"])
        yield b
        b.close()


@pytest.fixture(scope="module")
def registry(tmp_path_factory):
    return make_reports(copy_registry(tmp_path_factory.mktemp("uib") / "registry"))


@pytest.fixture(scope="module")
def live(registry):
    with LiveServer(create_app(registry, Settings(workers=2, queue_size=8))) as srv:
        yield srv.url


@pytest.fixture(scope="module")
def live_keyed(registry):
    with LiveServer(create_app(registry, Settings(workers=2, queue_size=8, api_key=API_KEY))) as srv:
        yield srv.url


class Watch:
    """Requests that tried to leave loopback (blocked), failed local responses, and page errors."""

    def __init__(self):
        self.blocked, self.failed, self.errors = [], [], []


@pytest.fixture
def page(browser):
    ctx = browser.new_context(viewport={"width": 1280, "height": 900})
    watch = Watch()

    def route(r):
        if urlparse(r.request.url).hostname in LOOPBACK:
            r.continue_()
        else:
            watch.blocked.append(r.request.url)
            r.abort()

    ctx.route("**/*", route)
    pg = ctx.new_page()
    pg.on("pageerror", lambda e: watch.errors.append(f"page error: {e}"))
    pg.on("console", lambda m: watch.errors.append(f"console: {m.text}") if m.type == "error" else None)
    pg.on("response", lambda r: watch.failed.append(f"{r.status} {r.url}") if r.status >= 400 else None)
    pg.watch = watch
    yield pg
    ctx.close()


@pytest.fixture
def shots(tmp_path):
    d = Path(os.environ.get("GPNARX_UI_SCREENSHOTS") or tmp_path)
    d.mkdir(parents=True, exist_ok=True)
    return d


def api_answers(url, files, *, key=None, mc_paths=64, seed=0, confidence=0.99, method="mc", operations=(),
                window=None, start=None):
    """What the page asks for (its defaults unless given), sent by a plain HTTP client: the parsed record
    (``window`` = (first sample, count)), then each operation."""
    headers = {"X-API-Key": key} if key else {}
    with httpx.Client(base_url=url, timeout=120, headers=headers) as c:
        rec = c.post("/v1/records/parse", files=[("files", f) for f in files])
        rec.raise_for_status()
        rec = rec.json()
        i0, n = window or (0, rec["n_samples"])
        body = {"u": rec["u"][i0:i0 + n], "fs": rec["fs"], "mc_paths": mc_paths, "seed": seed,
                "confidence": confidence, "method": method}
        if rec["y"] is not None:
            body["y"] = rec["y"][i0:i0 + n]
        if start:
            body["start"] = start
        out = {"record": rec}
        for op in operations:
            r = c.post(f"/v1/models/boucwen/versions/2/{op}", json=body)
            assert r.status_code == 200, r.text
            out[op] = r.json()
        return out


def run_in_page(pg):
    pg.wait_for_selector("#run:not([disabled])")
    pg.click("#run")
    pg.wait_for_selector("#time-plot[data-ready='1']", timeout=RUN_TIMEOUT_MS)
    pg.wait_for_selector("#psd-plot[data-ready='1']", timeout=RUN_TIMEOUT_MS)
    pg.wait_for_selector("#loops-plot[data-ready='1']", timeout=RUN_TIMEOUT_MS)
    pg.wait_for_selector("#verdict[data-verdict]", timeout=RUN_TIMEOUT_MS)
    return {"plotted": int(pg.get_attribute("#time-plot", "data-samples")),
            "predicted": int(pg.get_attribute("#predict-metrics", "data-samples")),
            "verdict": pg.get_attribute("#verdict", "data-verdict"),
            "shown": pg.inner_text("#verdict").strip().lower(),
            "score": float(pg.get_attribute("#verdict", "data-score")),
            "canvases": pg.locator("#time-plot canvas").count()}


# ------------------------------------------------------------------------------------------ the page
def test_uploaded_record_plot_and_verdict_match_the_api(page, live, tmp_path, shots):
    page.goto(f"{live}/ui")
    page.wait_for_selector("#models tbody tr.selected[data-name='boucwen']")
    assert page.input_value("#version") == "2"
    results = {}
    for label, scale in (("healthy", 1.0), ("changed", 1.3)):
        u, y = short_record(1500, 21)
        path = write_record(tmp_path / f"{label}.csv", Record(u, scale * y, FS, {"u": "N", "y": "m"}, label))
        page.set_input_files("#file", str(path))
        page.wait_for_selector(f"#record-info[data-samples='1500']:has-text('{label} (csv)')")
        shown = run_in_page(page)
        api = api_answers(live, [(path.name, path.read_bytes())], operations=("predict", "novelty"))
        assert shown["plotted"] == shown["predicted"] == api["predict"]["n_samples"] == 1500
        assert len(api["predict"]["mean"]) == 1500
        assert shown["verdict"] == shown["shown"] == api["novelty"]["verdict"]
        assert shown["score"] == pytest.approx(api["novelty"]["score"], rel=1e-12)
        assert shown["canvases"] >= 1
        results[label] = shown["verdict"]
        if label == "healthy":
            page.screenshot(path=str(shots / "ui-prediction.png"), full_page=True)
    assert results == {"healthy": "healthy", "changed": "novel"}  # the test sees both verdicts
    assert page.watch.blocked == [] and page.watch.failed == [] and page.watch.errors == []


def test_a_longer_record_is_used_whole_and_a_narrowed_run_says_so(page, live, tmp_path):
    """A 1500-sample record, then a 2500-sample one: the second is predicted whole (the samples field follows
    the record, not the previous record's length); narrowed by the user, the page says how much it ran on."""
    page.goto(f"{live}/ui")
    page.wait_for_selector("#models tbody tr.selected[data-name='boucwen']")
    for n in (1500, 2500):
        u, y = short_record(n, 23)
        path = write_record(tmp_path / f"r{n}.csv", Record(u, y, FS, {"u": "N", "y": "m"}, f"r{n}"))
        page.set_input_files("#file", str(path))
        page.wait_for_selector(f"#record-info[data-samples='{n}']")
        assert page.input_value("#count") == str(n)
        shown = run_in_page(page)
        assert shown["plotted"] == shown["predicted"] == n
        assert page.get_attribute("#run-state", "data-narrowed") == "false"
        assert "the whole record" in page.inner_text("#run-state")
    page.fill("#count", "1000")
    shown = run_in_page(page)
    assert shown["plotted"] == 1000 and page.get_attribute("#run-state", "data-narrowed") == "true"
    assert "1000 of the record's 2500 samples" in page.inner_text("#run-state")


def test_api_key_example_and_training_report(page, live_keyed, shots):
    page.goto(f"{live_keyed}/ui")
    page.wait_for_selector("#error:not([hidden])")
    assert "401" in page.inner_text("#error") and "API key" in page.inner_text("#error")
    page.fill("#api-key", API_KEY)
    page.click("#key-form button[type=submit]")
    page.wait_for_selector("#models tbody tr.selected[data-name='boucwen']")
    assert page.is_hidden("#error")

    example = "bouc-wen-multisine-3N-rms.npz"
    page.select_option("#examples", example)
    page.click("#load-example")
    page.wait_for_selector("#record-info[data-samples='2048']")
    # a window from the middle of the record, its free run started from the measured outputs
    page.fill("#t0", "0.5")
    page.fill("#count", "1024")
    page.select_option("#start", "measured")
    shown = run_in_page(page)
    api = api_answers(live_keyed, [(example, (STATIC_DIR / "examples" / example).read_bytes())], key=API_KEY,
                      operations=("predict", "novelty"), window=(375, 1024), start="measured")
    assert shown["plotted"] == api["predict"]["n_samples"] == 1024
    assert api["predict"]["start"] == "measured"
    assert shown["verdict"] == api["novelty"]["verdict"]
    assert shown["score"] == pytest.approx(api["novelty"]["score"], rel=1e-12)

    page.click("#show-report")
    page.wait_for_selector("#report-frame:not([hidden])")
    frame = page.frame_locator("#report-frame")
    frame.locator("h1").wait_for()
    assert "GP-NARX boucwen (test)" in frame.locator("h1").inner_text()
    imgs = frame.locator("img")
    assert imgs.count() >= 1
    for i in range(imgs.count()):  # embedded figures decode and draw
        assert imgs.nth(i).get_attribute("src").startswith("data:image/png;base64,")
        assert imgs.nth(i).evaluate("img => img.complete && img.naturalWidth > 100")
    page.locator("#report-frame").evaluate("f => f.scrollIntoView()")
    frame.locator("h2", has_text="Figures").evaluate("h => h.scrollIntoView()")  # the report's figures
    page.screenshot(path=str(shots / "ui-report.png"))
    assert page.watch.blocked == []
    # the only failed requests were the ones made before the key was entered
    assert page.watch.failed and all(f.startswith("401 ") for f in page.watch.failed), page.watch.failed
    assert all("401" in e for e in page.watch.errors), page.watch.errors


def test_page_psd_matches_scipy_welch(page, live):
    from scipy import signal

    page.goto(f"{live}/ui")
    rng = np.random.default_rng(3)
    x = np.sin(2 * np.pi * 37.0 * np.arange(3000) / FS) + 0.1 * rng.normal(size=3000)
    got = page.evaluate("async ([x, fs]) => { const m = await import('/static/ui/dsp.js'); "
                        "const r = m.welch(x, fs); return [Array.from(r.f), Array.from(r.p)]; }", [x.tolist(), FS])
    f, p = signal.welch(x, fs=FS, window="hann", nperseg=512, noverlap=256, detrend="constant", scaling="density")
    np.testing.assert_allclose(got[0], f, rtol=1e-12)
    np.testing.assert_allclose(got[1], p, rtol=1e-9, atol=1e-12 * p.max())
    assert page.watch.blocked == []


# ------------------------------------------------------------------------------------------ API docs
def test_docs_and_redoc_render_offline(page, live, shots):
    doc = httpx.get(f"{live}/openapi.json").json()
    n_ops = sum(1 for item in doc["paths"].values() for m in item if m in {"get", "post", "put", "delete", "patch"})
    page.goto(f"{live}/docs")
    page.wait_for_selector(".opblock")
    page.wait_for_function(f"() => document.querySelectorAll('.opblock').length >= {n_ops}")
    assert page.locator(".opblock").count() == n_ops
    assert page.locator(".opblock-summary-path", has_text="/v1/records/parse").count() == 1
    page.screenshot(path=str(shots / "ui-docs.png"))
    page.goto(f"{live}/redoc")
    page.wait_for_selector("[id='operation/parse_record']", state="attached", timeout=60_000)
    assert page.locator("[id^='operation/']").count() == n_ops
    assert page.watch.blocked == [] and page.watch.failed == []
    # ReDoc's sidebar logo is an outside image: the page's CSP refuses it, nothing leaves the machine
    assert all("cdn.redoc.ly" in e for e in page.watch.errors), page.watch.errors
