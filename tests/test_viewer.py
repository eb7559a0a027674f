"""The live viewer: JSON API behaviour, safety limits, concurrency, and an end-to-end browser test."""

from __future__ import annotations

import base64
import concurrent.futures
import io
import json
import os
import socket
import threading
import time
import urllib.error
import urllib.request
from pathlib import Path

import numpy as np
import pytest

fastapi = pytest.importorskip("fastapi")
from fastapi.testclient import TestClient  # noqa: E402

from n2f2.viewer.browser import CHROMIUM_PATH, launch_chromium  # noqa: E402
from n2f2.viewer.server import Viewer, ViewerLimits, create_app  # noqa: E402


@pytest.fixture(scope="module")
def viewer(trained_run):
    from n2f2.query.engine import QueryEngine

    engine = QueryEngine.from_run(trained_run.run_dir, scene=trained_run.scene_dir)
    return Viewer(engine, ViewerLimits(max_body_bytes=4096, max_queries=4))


@pytest.fixture(scope="module")
def client(viewer):
    return TestClient(create_app(viewer), raise_server_exceptions=False)


def _png(b64: str) -> np.ndarray:
    from PIL import Image

    return np.asarray(Image.open(io.BytesIO(base64.b64decode(b64))))


def test_scene_lists_views_and_encoder(client, trained_run):
    r = client.get("/api/scene")
    assert r.status_code == 200
    data = r.json()
    assert len(data["views"]) == trained_run.num_views
    assert "composite" in data["modes"] and "explicit" in data["modes"]
    assert data["encoder"]  # the text encoder is named honestly
    assert {"azimuth", "elevation", "radius"} <= set(data["views"][0]["orbit"])


def test_orbit_of_a_training_view_reproduces_its_camera(viewer):
    cam = viewer.scene.cameras[2]
    o = viewer.orbit.orbit_of(cam)
    novel = viewer.orbit.camera(o["azimuth"], o["elevation"], o["radius"])
    np.testing.assert_allclose(novel.center, cam.center, atol=1e-6)
    # The novel camera looks at the orbit centre.
    uv, z = novel.project(viewer.orbit.center)
    np.testing.assert_allclose(uv, [novel.cx, novel.cy], atol=1e-6)
    assert z > 0


def test_query_returns_relevancy_mask_and_localization(client, trained_run):
    query = trained_run.part_query
    r = client.post("/api/query", json={"queries": [query, "teapot"], "camera": {"view": 0}})
    assert r.status_code == 200, r.text
    data = r.json()
    assert [x["query"] for x in data["results"]] == [query, "teapot"]
    res = data["results"][0]
    mask = _png(res["mask_png"])
    assert mask.shape[:2] == (data["height"], data["width"])
    assert res["mask_area"] == int((mask[..., 3] > 0).sum()) > 0
    x, y = res["localization"]
    assert 0 <= x <= data["width"] and 0 <= y <= data["height"]
    overlay, rgb = _png(res["overlay_png"]), _png(data["rgb_png"])
    assert overlay.shape == rgb.shape and np.abs(overlay.astype(int) - rgb.astype(int)).max() > 0


def test_query_overlay_is_the_query_commands_heatmap(client, viewer, trained_run):
    """The API's overlay is ``n2f2 query``'s heatmap, one opacity for both: turbo of the min-max
    normalised relevancy v over the RGB, opacity HEATMAP_ALPHA * v; the relevancy PNG is turbo(v)."""
    from matplotlib import colormaps

    from n2f2.query.outputs import HEATMAP_ALPHA

    texts = [trained_run.part_query, "teapot"]
    data = client.post("/api/query", json={"queries": texts, "camera": {"view": 0}}).json()
    view, result = viewer.query_view("view:0", 0, texts, "composite")  # the same cached render
    rgb = view.rgb.float().numpy()
    for qi, res in enumerate(data["results"]):
        r = result.relevancy[qi].float().numpy()
        v = (r - float(r.min())) / (float(r.max()) - float(r.min()))
        turbo = colormaps["turbo"](v)[..., :3]
        a = HEATMAP_ALPHA * v[..., None]
        want = rgb * (1 - a) + turbo * a
        assert np.abs(_png(res["overlay_png"]) / 255.0 - want).max() <= 1.0 / 255
        assert np.abs(_png(res["relevancy_png"]) / 255.0 - turbo).max() <= 1.0 / 255


def test_explicit_mode_and_novel_camera(client):
    r = client.post("/api/query", json={"queries": ["teapot"], "mode": "explicit",
                                        "camera": {"orbit": {"azimuth": 30, "elevation": 25, "radius": 3.0}}})
    assert r.status_code == 200, r.text
    assert r.json()["results"][0]["chosen_scale"] is not None


def test_render_is_cached_per_camera(client):
    body = {"camera": {"orbit": {"azimuth": 10, "elevation": 20, "radius": 3.0}}}
    first = client.post("/api/render", json=body).json()
    second = client.post("/api/render", json=body).json()
    assert second["cached"] is True and first["rgb_png"] == second["rgb_png"]


def test_selection_download_is_a_loadable_ply(client, tmp_path):
    from n2f2.gaussians import read_ply

    r = client.post("/api/selection", json={"query": "teapot"})
    assert r.status_code == 200, r.text
    path = tmp_path / "sel.ply"
    path.write_bytes(r.content)
    g = read_ply(path)
    assert g.num == int(r.headers["X-Selected-Gaussians"]) > 0


@pytest.mark.parametrize("payload, status", [
    (b"{not json", 400),
    (b"[1, 2]", 400),
    (json.dumps({"queries": []}).encode(), 422),
    (json.dumps({"queries": ["a"] * 5}).encode(), 413),
    (json.dumps({"queries": ["x" * 500]}).encode(), 413),
    (json.dumps({"queries": ["mug"], "camera": {"view": 999}}).encode(), 404),
    (json.dumps({"queries": ["mug"], "camera": {"view": "../../etc/passwd"}}).encode(), 422),
    (json.dumps({"queries": ["mug"], "mode": "warp"}).encode(), 422),
    (json.dumps({"queries": ["mug"], "camera": {"orbit": {"azimuth": "nan", "elevation": 0, "radius": 1}}}).encode(), 422),
])
def test_bad_requests_get_json_errors(client, payload, status):
    r = client.post("/api/query", content=payload, headers={"Content-Type": "application/json"})
    assert r.status_code == status
    body = r.json()
    assert set(body) == {"error"} and "Traceback" not in body["error"]


def test_oversized_body_is_refused_before_parsing(client):
    big = json.dumps({"queries": ["mug"], "pad": "x" * 10_000}).encode()
    r = client.post("/api/query", content=big, headers={"Content-Type": "application/json"})
    assert r.status_code == 413 and "too large" in r.json()["error"]


@pytest.mark.parametrize("path", ["/static/../../../../etc/passwd", "/static/%2e%2e/%2e%2e/etc/passwd",
                                  "/static/..%2f..%2fpyproject.toml", "/api/../../etc/passwd",
                                  "/static/%2e%2e/server.py"])
def test_path_traversal_is_refused(client, path):
    r = client.get(path)
    assert r.status_code == 404
    assert b"root:" not in r.content and b"import" not in r.content


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def live_server(viewer):
    """The app under a real uvicorn server on loopback, in a background thread."""
    import uvicorn

    port = _free_port()
    config = uvicorn.Config(create_app(viewer), host="127.0.0.1", port=port, log_level="warning")
    server = uvicorn.Server(config)
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    deadline = time.time() + 30
    while not server.started:
        if time.time() > deadline:
            raise RuntimeError("viewer did not start")
        time.sleep(0.05)
    yield f"http://127.0.0.1:{port}"
    server.should_exit = True
    thread.join(timeout=10)


def _post(url: str, body: dict) -> tuple[int, float]:
    req = urllib.request.Request(url, data=json.dumps(body).encode(),
                                 headers={"Content-Type": "application/json"})
    t0 = time.perf_counter()
    try:
        with urllib.request.urlopen(req, timeout=120) as resp:
            json.loads(resp.read())
            status = resp.status
    except urllib.error.HTTPError as e:
        status = e.code
    return status, time.perf_counter() - t0


def test_fifty_concurrent_queries_finish_without_error(live_server, trained_run):
    queries = ["teapot", trained_run.part_query, "red mug", "bag of cookies", "plate"]
    bodies = [{"queries": [queries[i % len(queries)]], "camera": {"view": i % trained_run.num_views}}
              for i in range(50)]
    with concurrent.futures.ThreadPoolExecutor(max_workers=50) as pool:
        results = list(pool.map(lambda b: _post(live_server + "/api/query", b), bodies))
    statuses = [s for s, _ in results]
    assert statuses == [200] * 50
    lat = np.array([t for _, t in results]) * 1000
    print(f"\n50 concurrent queries: p50 {np.percentile(lat, 50):.0f} ms, p95 {np.percentile(lat, 95):.0f} ms")


@pytest.mark.skipif(not Path(CHROMIUM_PATH).exists(),
                    reason="Debian chromium is not installed (apt-get install chromium); .ci/run installs it")
def test_browser_types_a_query_and_sees_the_overlay(live_server, trained_run, tmp_path):
    sync_api = pytest.importorskip("playwright.sync_api")
    shot_dir = Path(os.environ.get("N2F2_SCREENSHOT_DIR", tmp_path))
    shot_dir.mkdir(parents=True, exist_ok=True)
    with sync_api.sync_playwright() as p:
        browser = launch_chromium(p)
        try:
            page = browser.new_page(viewport={"width": 1100, "height": 800})
            page.goto(live_server + "/")
            page.wait_for_function("document.getElementById('view').options.length > 0")
            page.wait_for_function("!document.getElementById('loading').classList.contains('on')")
            canvas = page.locator("#canvas")
            before = canvas.screenshot()
            page.fill("#queries", trained_run.part_query)
            with page.expect_response(lambda r: r.url.endswith("/api/query")) as resp_info:
                page.click("#run")
            data = resp_info.value.json()
            page.wait_for_function("document.getElementById('canvas').dataset.queried === '1'")
            after = canvas.screenshot()
            page.screenshot(path=str(shot_dir / "viewer.png"), full_page=True)
        finally:
            browser.close()
    assert data["results"][0]["mask_area"] > 0 and data["results"][0]["mask_png"]
    from PIL import Image

    a = np.asarray(Image.open(io.BytesIO(before)).convert("RGB"), dtype=int)
    b = np.asarray(Image.open(io.BytesIO(after)).convert("RGB"), dtype=int)
    assert a.shape == b.shape and np.abs(a - b).mean() > 1.0  # the overlay changed the image
    assert (shot_dir / "viewer.png").stat().st_size > 0
