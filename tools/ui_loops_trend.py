"""Take docs/img/ui-loops-trend.png: the /ui page with the novelty trend and the band-limited loops.

Against a running service over the default bundles, e.g.::

    gpnarx build-defaults --registry /tmp/reg-ui --only bouc-wen,bert-standin,bert-standin-monitor
    GPNARX_AUDIT_LOG=/tmp/reg-ui-audit.jsonl gpnarx serve --registry /tmp/reg-ui --port 8012
    python tools/ui_loops_trend.py --url http://127.0.0.1:8012

The script first sends novelty calls on the monitor (``bert-standin-monitor``) with windows of the shipped
probe examples (the 5 N m probe: healthy; the 9 N m probe: novel; the 18 Hz sine: unjudged), so the trend has
points, then opens /ui in headless Chromium (Debian's ``chromium`` through Playwright, every request off
loopback refused), selects the monitor, loads the 9 N m probe example, runs it and saves a full-page
screenshot. The audit trail must be a file (``GPNARX_AUDIT_LOG``) for the trend to have points.
"""
from __future__ import annotations

import argparse
import io
import shutil
import sys
import time
from pathlib import Path
from urllib.parse import urlparse

import httpx
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
MODEL = "bert-standin-monitor"
#: (example file, first sample, samples) of the novelty calls made before the screenshot, oldest first
CALLS = [("bert-standin-probe-9Hz-5Nm.npz", 0, 4096), ("bert-standin-probe-9Hz-5Nm.npz", 0, 3072),
         ("bert-standin-probe-9Hz-5Nm.npz", 1024, 3072), ("bert-standin-sine-18Hz-5Nm.npz", 0, 4096),
         ("bert-standin-probe-9Hz-5Nm.npz", 512, 3584), ("bert-standin-probe-9Hz-9Nm.npz", 0, 3072),
         ("bert-standin-probe-9Hz-9Nm.npz", 1024, 3072)]
EXAMPLE = "bert-standin-probe-9Hz-9Nm.npz"  # the record run in the page


def wait_ready(c: httpx.Client, model: str, timeout: float) -> None:
    t0 = time.monotonic()
    while True:
        try:
            r = c.get("/health/ready")
            if r.status_code == 200 and model in (r.json().get("models") or {}):
                return
        except httpx.HTTPError:
            pass
        if time.monotonic() - t0 > timeout:
            raise SystemExit(f"{model} is not served after {timeout:.0f} s (see /health/ready)")
        time.sleep(2)


def novelty_calls(c: httpx.Client, model: str) -> None:
    for name, i0, n in CALLS:
        rec = np.load(io.BytesIO(c.get(f"/static/examples/{name}").content))
        body = {"u": rec["u"][i0:i0 + n].tolist(), "y": rec["y"][i0:i0 + n].tolist(), "fs": float(rec["fs"]),
                "seed": 0}
        r = c.post(f"/v1/models/{model}/novelty", json=body)
        r.raise_for_status()
        a = r.json()
        print(f"{name}[{i0}:{i0 + n}]: {a['verdict']}, score {a['score']:.3g} (threshold {a['threshold']:.3g})")


def screenshot(url: str, model: str, out: Path, key: str | None, chromium: str) -> None:
    from playwright.sync_api import sync_playwright

    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=chromium, args=["--no-sandbox", "--disable-dev-shm-usage"])
        ctx = browser.new_context(viewport={"width": 1280, "height": 900})
        ctx.route("**/*", lambda r: r.continue_() if urlparse(r.request.url).hostname in ("127.0.0.1", "localhost")
                  else r.abort())
        page = ctx.new_page()
        errors = []
        page.on("pageerror", lambda e: errors.append(str(e)))
        page.goto(f"{url}/ui")
        if key:
            page.fill("#api-key", key)
            page.click("#key-form button[type=submit]")
        page.wait_for_selector(f"#models tbody tr[data-name='{model}']")
        page.click(f"#models tbody tr[data-name='{model}']")
        page.wait_for_selector("#trend-plot[data-ready='1']")
        before = int(page.get_attribute("#trend-plot", "data-points") or 0)
        page.select_option("#examples", EXAMPLE)
        page.click("#load-example")
        page.wait_for_selector("#record-info[data-samples]")
        page.click("#run")
        page.wait_for_selector("#run-state[data-outcome]", timeout=600_000)
        # the run's own verdict joins the trend once its audit line is written and read back
        page.wait_for_function(f"() => Number(document.querySelector('#trend-plot').dataset.points) > {before}",
                               timeout=30_000)
        print(page.inner_text("#run-state"))
        print(page.inner_text("#trend-note"))
        print(page.inner_text("#loops-note"))
        out.parent.mkdir(parents=True, exist_ok=True)
        page.screenshot(path=str(out), full_page=True)
        browser.close()
    if errors:
        raise SystemExit(f"script errors on the page: {errors}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--url", default="http://127.0.0.1:8012")
    ap.add_argument("--model", default=MODEL)
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "img" / "ui-loops-trend.png")
    ap.add_argument("--api-key", default=None)
    ap.add_argument("--no-calls", action="store_true", help="make no novelty call first (the trend as it is)")
    ap.add_argument("--ready-timeout", type=float, default=1800.0, help="seconds to wait for the model [s]")
    args = ap.parse_args(argv)
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    if not chromium:
        raise SystemExit("Chromium is not installed (Debian: apt-get install -y chromium)")
    headers = {"X-API-Key": args.api_key} if args.api_key else {}
    with httpx.Client(base_url=args.url, timeout=600, headers=headers) as c:
        wait_ready(c, args.model, args.ready_timeout)
        if not args.no_calls:
            novelty_calls(c, args.model)
    screenshot(args.url, args.model, args.out, args.api_key, chromium)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
