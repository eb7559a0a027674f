"""Viewer load test: N concurrent ``POST /api/query`` requests against a running viewer.

Start the viewer in another process, then point this at it:

    n2f2 view RUN_DIR &
    python benchmarks/bench_viewer.py [--url http://127.0.0.1:7008] [--requests 50] [--screenshot out.png]

``--url`` is the viewer's JSON API and 2D page (``n2f2 view --api-port``), not the 3D viewer's port.

Each request asks one query (cycling through a few of the demo scene's queries) in one view
(cycling through the training views, so the first requests also pay for rendering and caching
their view). Prints the status counts and the latency percentiles (p50, p95, max) seen by the
clients, and the wall time of the whole burst. The viewer serialises its engine with one lock,
so latency grows with the queue: p95 is close to the time to drain the burst.

``--screenshot PATH`` also drives Debian's Chromium (Playwright, ``/usr/bin/chromium``) to type
"lid of the teapot" on the page and saves a screenshot after the overlay arrives.
"""

from __future__ import annotations

import argparse
import concurrent.futures
import json
import time
import urllib.error
import urllib.request

import numpy as np

from n2f2.viewer.settings import API_PORT, HOST

QUERIES = ["teapot", "lid of the teapot", "red mug", "bag of cookies", "plate of fruit"]


def post(url: str, body: dict, timeout: float = 300.0) -> tuple[int, float]:
    """(HTTP status, seconds) of one JSON POST; the response body is read and parsed."""
    req = urllib.request.Request(url, data=json.dumps(body).encode(), headers={"Content-Type": "application/json"})
    t0 = time.perf_counter()
    try:
        with urllib.request.urlopen(req, timeout=timeout) as resp:
            json.loads(resp.read())
            status = resp.status
    except urllib.error.HTTPError as e:
        status = e.code
    return status, time.perf_counter() - t0


def load_test(url: str, requests: int) -> dict:
    with urllib.request.urlopen(url + "/api/scene", timeout=60) as resp:
        views = len(json.loads(resp.read())["views"])
    bodies = [{"queries": [QUERIES[i % len(QUERIES)]], "camera": {"view": i % views}} for i in range(requests)]
    t0 = time.perf_counter()
    with concurrent.futures.ThreadPoolExecutor(max_workers=requests) as pool:
        results = list(pool.map(lambda b: post(url + "/api/query", b), bodies))
    wall = time.perf_counter() - t0
    lat = np.array([t for _, t in results]) * 1000.0
    statuses: dict[int, int] = {}
    for s, _ in results:
        statuses[s] = statuses.get(s, 0) + 1
    return {"requests": requests, "views": views, "statuses": statuses, "wall_s": wall,
            "p50_ms": float(np.percentile(lat, 50)), "p95_ms": float(np.percentile(lat, 95)),
            "max_ms": float(lat.max())}


def screenshot(url: str, path: str, query: str = "lid of the teapot") -> None:
    from playwright.sync_api import sync_playwright

    from n2f2.viewer.browser import launch_chromium

    with sync_playwright() as p:
        browser = launch_chromium(p)
        try:
            page = browser.new_page(viewport={"width": 1200, "height": 860})
            page.goto(url + "/")
            page.wait_for_function("document.getElementById('view').options.length > 0")
            page.wait_for_function("!document.getElementById('loading').classList.contains('on')", timeout=120_000)
            page.fill("#queries", query)
            page.click("#run")
            page.wait_for_function("document.getElementById('canvas').dataset.queried === '1'", timeout=120_000)
            page.screenshot(path=path, full_page=True)
        finally:
            browser.close()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument(
        "--url", default=f"http://{HOST}:{API_PORT}", help="a running `n2f2 view`'s API (default %(default)s)"
    )
    ap.add_argument("--requests", type=int, default=50, help="concurrent requests (default 50)")
    ap.add_argument("--screenshot", default=None, metavar="PNG", help="also save a browser screenshot here")
    args = ap.parse_args()
    url = args.url.rstrip("/")
    if args.screenshot:
        screenshot(url, args.screenshot)
        print(f"screenshot: {args.screenshot}")
    r = load_test(url, args.requests)
    print(f"{r['requests']} concurrent queries over {r['views']} views: statuses {r['statuses']}, "
          f"p50 {r['p50_ms']:.0f} ms, p95 {r['p95_ms']:.0f} ms, max {r['max_ms']:.0f} ms, burst {r['wall_s']:.1f} s")


if __name__ == "__main__":
    main()
