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

import json
import os
import shutil
from pathlib import Path
from urllib.parse import urlparse

import httpx
import numpy as np
import pytest
from test_service_support import FS, LiveServer, built_registry, copy_registry, noisy, short_record, simulate
from test_ui import make_reports

from gpnarx.model.record import Record
from gpnarx.service.app import create_app
from gpnarx.service.settings import Settings
from gpnarx.service.ui import STATIC_DIR
from gpnarx.storage.record_files import write_record

CHROMIUM = os.environ.get("GPNARX_CHROMIUM") or shutil.which("chromium") or shutil.which("chromium-browser")
API_KEY = "s3cret-key"
LOOPBACK = {"127.0.0.1", "localhost", "::1"}
RUN_TIMEOUT_MS = 300_000  # a hang guard for a page's runs, not a speed limit (timings are in bench/)


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


def api_answers(url, files, *, key=None, mc_paths=None, seed=0, confidence=0.99, method="mc", operations=(),
                window=None, start=None):
    """What the page asks for (its defaults unless given), sent by a plain HTTP client: the parsed record
    (``window`` = (first sample, count)), then each operation."""
    headers = {"X-API-Key": key} if key else {}
    with httpx.Client(base_url=url, timeout=120, headers=headers) as c:
        rec = c.post("/v1/records/parse", files=[("files", f) for f in files])
        rec.raise_for_status()
        rec = rec.json()
        i0, n = window or (0, rec["n_samples"])
        body = {"u": rec["u"][i0:i0 + n], "fs": rec["fs"], "seed": seed, "confidence": confidence, "method": method}
        if mc_paths is not None:  # the page sends none unless its paths field is filled: the model's default
            body["mc_paths"] = mc_paths
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


#: Monte Carlo paths the page sends to predict and loops unless its paths field is changed
PAGE_PATHS = 64


def steady_window(loops, fs):
    """[first, end) samples of the steady cycles of a loops answer, as the page draws them."""
    n = len(loops["predicted"]["x"])
    cyc = loops["cycles"]
    return int(np.floor(cyc[0]["start"] * fs)), min(n, int(np.ceil(cyc[-1]["end"] * fs)) + 1)


def page_loops(loops, fs, fc, guard=5):
    """The loops the page draws by default, computed with scipy: over the steady cycles, each low-passed at fc by
    a zero-phase order-4 Butterworth run over the stretch with up to three periods of fc of the record on each
    side (not within ``guard`` samples of its ends) and as much odd padding (static/ui/dsp.js lowpassStretch)."""
    from scipy import signal

    n = len(loops["predicted"]["x"])
    i0, i1 = steady_window(loops, fs)
    m = int(np.ceil(3 * fs / fc))
    a, b = min(i0, max(guard, i0 - m)), max(i1, min(n - guard, i1 + m))
    sos = signal.butter(4, fc, fs=fs, output="sos")

    def smooth(v):
        return signal.sosfiltfilt(sos, np.asarray(v, float)[a:b], padlen=min(m, b - a - 1))[i0 - a:i1 - a]

    return {k: (smooth(loops[k]["x"]), smooth(loops[k]["force"])) for k in ("lower", "upper", "measured", "predicted")}


def robust_view(arrays):
    """The page's axis limits: 0.5-99.5 % quantiles of all the values, widened 8 % of their span."""
    v = np.sort(np.concatenate(arrays))
    q = [v[int(np.floor(p * (v.size - 1) + 0.5))] for p in (0.005, 0.995)]
    pad = 0.08 * (q[1] - q[0])
    return [q[0] - pad, q[1] + pad]


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
    """A 1500-sample record, then a 4096-sample one: every sample of the second is predicted and scored (the
    samples field follows the record, not the previous record's length: the requests the page sends to predict
    and novelty carry the whole record, and the novelty answer equals the API's on the whole record); narrowed
    by the user, the page says how much it ran on."""
    sent = {}

    def on_request(req):
        for op in ("predict", "novelty", "loops"):
            if req.method == "POST" and req.url.endswith(f"/{op}"):
                sent[op] = len(req.post_data_json["u"])

    page.on("request", on_request)
    page.goto(f"{live}/ui")
    page.wait_for_selector("#models tbody tr.selected[data-name='boucwen']")
    for n in (1500, 4096):
        u, y = short_record(n, 23)
        path = write_record(tmp_path / f"r{n}.csv", Record(u, y, FS, {"u": "N", "y": "m"}, f"r{n}"))
        page.set_input_files("#file", str(path))
        page.wait_for_selector(f"#record-info[data-samples='{n}']")
        assert page.input_value("#count") == str(n)
        sent.clear()
        shown = run_in_page(page)
        assert sent == {"predict": n, "novelty": n, "loops": n}, sent  # every sample sent to every operation
        assert shown["plotted"] == shown["predicted"] == n
        assert page.get_attribute("#run-state", "data-narrowed") == "false"
        assert "the whole record" in page.inner_text("#run-state")
        api = api_answers(live, [(path.name, path.read_bytes())], operations=("novelty",))
        assert int(page.get_attribute("#verdict", "data-samples")) == api["novelty"]["n_samples"]
        assert shown["score"] == pytest.approx(api["novelty"]["score"], rel=1e-12)
    page.fill("#count", "1000")
    shown = run_in_page(page)
    assert shown["plotted"] == 1000 and page.get_attribute("#run-state", "data-narrowed") == "true"
    assert sent["novelty"] == 1000
    assert "1000 of the record's 4096 samples" in page.inner_text("#run-state")
    assert page.watch.errors == []


@pytest.fixture(scope="module")
def live_monitor(tmp_path_factory):
    """A monitor whose probe contract is a 30 Hz sine (the test model's calibration, with a probe added)."""
    from gpnarx.storage.bundle import save_bundle
    from gpnarx.storage.registry import Registry

    root = copy_registry(tmp_path_factory.mktemp("uim") / "registry")
    src = Registry(root).scan().get("boucwen", "2").manifest
    probe = {"kind": "sine", "frequency": 30.0, "frequency_tolerance": 0.9, "amplitude": [9.0, 11.0],
             "amplitude_kind": "peak", "amplitude_tolerance": 0.2, "start": "measured", "n_records": 3}
    save_bundle(built_registry().model, root, "monitor", "1", fs=FS, units={"u": "N", "y": "m"},
                physics=src["physics"], novelty={**src["novelty"], "probe": probe},
                training={"records": {"sine-30Hz": {"role": "healthy", "fit": 91.5, "rmse": 2.1e-5,
                                                    "coverage": 99.2, "n_samples": 1024, "drive_freq": 30.0}}})
    with LiveServer(create_app(root, Settings(workers=2, queue_size=8))) as srv:
        yield srv.url


def test_novelty_card_explains_a_probe_mismatch(page, live_monitor, tmp_path, shots):
    """A 45 Hz sine on a monitor calibrated with a 30 Hz probe: the verdict is 'unjudged' (not a red alarm, not
    healthy), and the card says why: the probe mismatch with the API's reason, the drive found, the score
    against the threshold (not compared). The training metrics show as a table by record with units."""
    page.goto(f"{live_monitor}/ui")
    page.wait_for_selector("#models tbody tr[data-name='monitor']")
    page.click("#models tbody tr[data-name='monitor']")
    page.wait_for_selector("#models tbody tr.selected[data-name='monitor']")
    page.wait_for_selector("#training-records tr[data-record='sine-30Hz']")
    heads = page.locator("#training-records thead th").all_inner_texts()
    assert "fit [%]" in heads and "RMSE [m]" in heads and "drive [Hz]" in heads, heads
    n = 1536
    u = 10.0 * np.sin(2 * np.pi * 45.0 * np.arange(n) / FS)
    path = write_record(tmp_path / "sine45.csv", Record(u, noisy(simulate(u), 7), FS, {"u": "N", "y": "m"}, "sine45"))
    page.set_input_files("#file", str(path))
    page.wait_for_selector(f"#record-info[data-samples='{n}']")
    shown = run_in_page(page)
    with httpx.Client(base_url=live_monitor, timeout=120) as c:
        rec = c.post("/v1/records/parse", files=[("files", (path.name, path.read_bytes()))]).json()
        body = {"u": rec["u"], "y": rec["y"], "fs": FS, "seed": 0, "confidence": 0.99, "method": "mc"}
        api = c.post("/v1/models/monitor/versions/1/novelty", json=body).json()
    assert api["verdict"] == "unjudged" and api["probe_match"] is False and "probe" in api["out_of_range"]
    assert shown["verdict"] == shown["shown"] == "unjudged"
    assert shown["score"] == pytest.approx(api["score"], rel=1e-12)
    reasons = {li.get_attribute("data-reason"): li.inner_text()
               for li in page.locator("#novelty-reasons li").all()}
    assert "unjudged" in reasons and "not judged" in reasons["unjudged"].lower()
    assert api["probe_reasons"][0] in reasons["probe-mismatch"]
    assert "45" in reasons["drive"] and "sine" in reasons["drive"]
    assert "not compared" in reasons["score"] and "threshold" in reasons["score"]
    assert "30 Hz" in reasons["probe"]
    assert page.locator("#verdict.unjudged").count() == 1 and page.locator("#verdict.novel").count() == 0
    page.locator("#verdict-card").screenshot(path=str(shots / "ui-novelty-unjudged.png"))
    # the loops view: units from the answer in the table's header, intervals ordered
    heads = page.locator("#cycles th").all_inner_texts()
    assert "energy [J]" in heads and "start [s]" in heads and any(h.startswith("stiffness [N/m") for h in heads)
    note = page.inner_text("#loops-note")
    assert "[J]" in note and "N m" not in note
    lo, hi = (float(v) for v in note.split("band edges ")[1].split(",")[0].split(" to "))
    assert lo <= hi
    # the loops drawn: the steady cycles only, so the free run's start-up from rest is left out
    loops = httpx.post(f"{live_monitor}/v1/models/monitor/versions/1/loops", json={**body, "mc_paths": PAGE_PATHS},
                       timeout=120).json()
    window = json.loads(page.get_attribute("#loops-plot", "data-window"))
    assert window == list(steady_window(loops, FS)) and window[0] > 0 and "start-up transient" in note
    assert page.watch.blocked == [] and page.watch.errors == []


def test_loops_are_band_limited_over_the_steady_cycles_and_the_measured_cloud_is_hidden(page, live, tmp_path):
    """The measured loop R = g u - m y'' holds the noisy output differentiated twice: a cloud that hid the
    prediction. By default the page draws the loops of the API's answer over its steady cycles only, each low-passed
    (zero-phase) at 3.5 x the sine drive's frequency, with axes that fit those loops; the unfiltered measured loop
    is drawn only when asked, and never sets the axes. The loops, window and axes equal a scipy computation of the
    same answer. Predict and loops are sent the page's 64 paths, novelty none (its calibration's)."""
    sent = {}
    page.on("request", lambda r: sent.__setitem__(r.url.rsplit("/", 1)[1], r.post_data_json)
            if r.method == "POST" and r.url.endswith(("/predict", "/loops", "/novelty")) else None)
    page.goto(f"{live}/ui")
    page.wait_for_selector("#models tbody tr.selected[data-name='boucwen']")
    n = 1536
    u = 10.0 * np.sin(2 * np.pi * 30.0 * np.arange(n) / FS)
    path = write_record(tmp_path / "sine30.csv", Record(u, noisy(simulate(u), 9), FS, {"u": "N", "y": "m"}, "sine30"))
    page.set_input_files("#file", str(path))
    page.wait_for_selector(f"#record-info[data-samples='{n}']")
    assert page.input_value("#mc-paths") == str(PAGE_PATHS)
    assert "64 Monte Carlo paths" in page.inner_text("#paths-note") and "calibrated" in page.inner_text("#paths-note")
    run_in_page(page)
    assert sent["predict"]["mc_paths"] == sent["loops"]["mc_paths"] == PAGE_PATHS
    assert "mc_paths" not in sent["novelty"] and "method" not in sent["novelty"]  # as calibrated
    loops = httpx.post(f"{live}/v1/models/boucwen/versions/2/loops", json=sent["loops"], timeout=120).json()

    plot = "#loops-plot"
    series = json.loads(page.get_attribute(plot, "data-series"))
    fc = float(page.get_attribute(plot, "data-cutoff"))
    assert loops["cycle_basis"]["basis"] == "drive"  # a sine: its first harmonics kept
    assert fc == pytest.approx(3.5 * loops["cycle_basis"]["frequency"], rel=5e-3)
    assert series == [f"{k}, low-passed {fc:g} Hz" for k in ("band lower", "band upper", "measured", "predicted mean")]
    assert "measured, unfiltered" not in series and not page.is_checked("#loops-raw")
    i0, i1 = steady_window(loops, FS)
    assert json.loads(page.get_attribute(plot, "data-window")) == [i0, i1] and i0 > 0 and i1 < n
    drawn = page_loops(loops, FS, fc)
    view = json.loads(page.get_attribute(plot, "data-view"))
    np.testing.assert_allclose(view["x"], robust_view([x for x, _ in drawn.values()]), rtol=1e-9)
    np.testing.assert_allclose(view["y"], robust_view([f for _, f in drawn.values()]), rtol=1e-9)
    # the measured loop as the API computes it is a cloud several times the loops' height; low-passed, it is a loop
    raw = np.asarray(loops["measured"]["force"])[i0:i1]
    height = view["y"][1] - view["y"][0]
    assert np.ptp(raw) > 2 * height, (np.ptp(raw), height)
    assert np.ptp(drawn["measured"][1]) < height
    # and the start-up transient of the free run from rest lies outside the steady window
    force = np.asarray(loops["predicted"]["force"])
    assert np.abs(force[:i0]).max() > view["y"][1]
    assert "low-passed at" in page.inner_text("#loops-note") and "steady cycles" in page.inner_text("#loops-note")

    page.check("#loops-raw")  # the cloud, when asked for: drawn, the axes kept
    page.wait_for_function("() => document.querySelector('#loops-plot').dataset.series.includes('unfiltered')")
    assert json.loads(page.get_attribute(plot, "data-view")) == view
    page.check("#loops-whole")
    page.wait_for_function(f"() => document.querySelector('#loops-plot').dataset.window === '[0,{n}]'")
    page.uncheck("#loops-filter")
    page.wait_for_function("() => document.querySelector('#loops-plot').dataset.cutoff === ''")
    assert "measured" in json.loads(page.get_attribute(plot, "data-series"))

    # the PSD axis: the top 7 decades below the peak (a clean simulation reaches round-off 15 decades down)
    lo, hi = json.loads(page.get_attribute("#psd-plot", "data-range"))
    assert np.log10(hi / lo) == pytest.approx(8)
    from scipy import signal

    peak = signal.welch(np.asarray(sent["predict"]["y"]), fs=FS, nperseg=512)[1].max()
    assert lo < peak < hi
    assert page.watch.blocked == [] and page.watch.errors == [] and page.watch.failed == []


def test_page_lowpass_matches_scipy_sosfiltfilt(page, live):
    from scipy import signal

    page.goto(f"{live}/ui")
    rng = np.random.default_rng(5)
    x = np.sin(2 * np.pi * 30.0 * np.arange(2000) / FS) + 0.3 * rng.normal(size=2000)
    got = page.evaluate("async ([x, fs]) => { const m = await import('/static/ui/dsp.js'); "
                        "return [Array.from(m.lowpass(x, 105, fs)), Array.from(m.lowpassStretch(x, 300, 1700, 60, fs)),"
                        " m.butterLowpass(4, 105, fs)]; }", [x.tolist(), FS])
    sos = signal.butter(4, 105, fs=FS, output="sos")
    np.testing.assert_allclose(got[0], signal.sosfiltfilt(sos, x), rtol=0, atol=1e-12)
    # the same cascade (scipy orders its sections and splits the gain otherwise)
    assert np.prod([s[0] + s[1] + s[2] for s in got[2]]) / np.prod([1 + s[3] + s[4] for s in got[2]]) \
        == pytest.approx(1.0, rel=1e-12)
    m = int(np.ceil(3 * FS / 60))
    want = signal.sosfiltfilt(signal.butter(4, 60, fs=FS, output="sos"), x[300 - m:1700 + m], padlen=m)[m:-m]
    np.testing.assert_allclose(got[1], want, rtol=0, atol=1e-12)
    assert page.watch.errors == []


@pytest.fixture
def live_audited(registry, tmp_path):
    """A server whose audit trail is a file, so the page's trend has points."""
    trail = tmp_path / "audit.jsonl"
    with LiveServer(create_app(registry, Settings(workers=2, queue_size=8, audit_log=str(trail)))) as srv:
        yield srv.url, trail


def _history(url, n, timeout=30.0):
    """The history once it holds ``n`` points (the audit trail is written off the request path)."""
    import time

    t0 = time.monotonic()
    while True:
        h = httpx.get(f"{url}/v1/models/boucwen/novelty/history").json()
        if len(h["points"]) >= n or time.monotonic() - t0 > timeout:
            return h
        time.sleep(0.1)


def test_novelty_trend_is_drawn_from_the_audit_trail(page, live_audited, tmp_path):
    url, _ = live_audited
    with httpx.Client(base_url=url, timeout=120) as c:
        for seed, scale in ((31, 1.0), (32, 1.0), (33, 1.3)):
            u, y = short_record(512, seed)
            r = c.post("/v1/models/boucwen/novelty", json={"u": u.tolist(), "y": (scale * y).tolist(), "fs": FS})
            assert r.status_code == 200, r.text
    h = _history(url, 3)
    assert [p["verdict"] for p in h["points"]] == ["healthy", "healthy", "novel"]
    page.goto(f"{url}/ui")
    page.wait_for_selector("#models tbody tr.selected[data-name='boucwen']")
    page.wait_for_selector("#trend-plot[data-ready='1'][data-points='3']")
    assert page.locator("#trend-plot canvas").count() >= 1
    note = page.inner_text("#trend-note")
    assert "3 verdicts" in note and "2 healthy, 1 novel, 0 unjudged" in note
    # a run in the page adds its verdict to the trend
    u, y = short_record(1500, 21)
    path = write_record(tmp_path / "healthy.csv", Record(u, y, FS, {"u": "N", "y": "m"}, "healthy"))
    page.set_input_files("#file", str(path))
    page.wait_for_selector("#record-info[data-samples='1500']")
    shown = run_in_page(page)
    page.wait_for_selector("#trend-plot[data-ready='1'][data-points='4']", timeout=30_000)
    last = json.loads(page.get_attribute("#trend-plot", "data-last"))
    assert last["verdict"] == shown["verdict"] and last["score"] == pytest.approx(shown["score"], rel=1e-12)
    assert _history(url, 4)["points"][-1]["score"] == pytest.approx(shown["score"], rel=1e-12)
    assert page.watch.blocked == [] and page.watch.errors == [] and page.watch.failed == []


def test_a_failed_run_says_it_failed(page, live, tmp_path):
    """A record the API refuses: the run says it failed, with each call's status and problem detail, not that it
    "answered in" some time. A run where only some calls fail says which, and shows what did answer."""
    page.goto(f"{live}/ui")
    page.wait_for_selector("#models tbody tr.selected[data-name='boucwen']")
    n = 1200
    u, y = short_record(n, 41)
    path = write_record(tmp_path / "at1000.csv", Record(u, y, 1000.0, {"u": "N", "y": "m"}, "at1000"))
    page.set_input_files("#file", str(path))
    page.wait_for_selector(f"#record-info[data-samples='{n}']")
    page.click("#run")
    page.wait_for_selector("#run-state[data-outcome]", timeout=RUN_TIMEOUT_MS)
    state = page.inner_text("#run-state")
    body = {"u": u.tolist(), "y": y.tolist(), "fs": 1000.0, "seed": 0, "mc_paths": PAGE_PATHS}
    api = httpx.post(f"{live}/v1/models/boucwen/versions/2/predict", json=body, timeout=60)
    assert api.status_code == 422 and api.json()["field"] == "fs"
    assert page.get_attribute("#run-state", "data-outcome") == "failed"
    assert sorted(page.get_attribute("#run-state", "data-failed").split(",")) == ["loops", "novelty", "predict"]
    assert state.startswith("Run failed") and "answered in" not in state
    assert f"predict: 422 {api.json()['title']}: {api.json()['detail']} (field fs)" in state
    assert "the predict call failed: 422" in page.inner_text("#predict-metrics")
    assert page.inner_text("#verdict").strip().lower() == "failed"
    assert api.json()["detail"] in page.inner_text("#error")

    # only predict and loops refused (too many paths for them; novelty runs as calibrated): said so, verdict shown
    u, y = short_record(n, 42)
    path = write_record(tmp_path / "ok.csv", Record(u, y, FS, {"u": "N", "y": "m"}, "ok"))
    page.set_input_files("#file", str(path))
    page.wait_for_selector("#record-info:has-text('ok (csv)')")
    page.fill("#mc-paths", "100000")
    page.click("#run")
    page.wait_for_selector("#run-state[data-outcome]", timeout=RUN_TIMEOUT_MS)
    state = page.inner_text("#run-state")
    assert sorted(page.get_attribute("#run-state", "data-failed").split(",")) == ["loops", "predict"]
    assert state.startswith("Run partly failed (") and "mc_paths" in state and "novelty" in state.split("Answered:")[1]
    page.wait_for_selector("#verdict[data-verdict]")
    assert page.watch.blocked == []


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
