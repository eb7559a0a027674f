"""The 3D viewer (viser splats, frustums, queries that recolour the Gaussians) and the JSON API's
safety: the byte-bounded render cache and JSON errors for every malformed request."""

from __future__ import annotations

import io
import json
import math
import os
import socket
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

pytest.importorskip("viser")
pytest.importorskip("fastapi")

from n2f2.viewer.browser import CHROMIUM_PATH  # noqa: E402
from n2f2.viewer.cache import ByteLRU, compact_tensors, tensor_bytes  # noqa: E402
from n2f2.viewer.server import Viewer, ViewerLimits, create_app  # noqa: E402
from n2f2.viewer.splat_colors import heat_colors, selection_mask, splat_colors, splat_covariances  # noqa: E402
from n2f2.viewer.splats import camera_from_pose, pose_of, split_queries  # noqa: E402


# ----------------------------------------------------------------------------- splat conversion
def _rodrigues(axis, angle) -> np.ndarray:
    """Rotation matrix about a unit axis (Rodrigues' formula), written out independently of
    the quaternion code under test."""
    k = np.asarray(axis, dtype=np.float64)
    k = k / np.linalg.norm(k)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * K @ K


def test_covariance_is_R_diag_s2_RT_for_hand_built_rotations():
    # 90 degrees about z, quaternion (cos 45, 0, 0, sin 45): x -> y, y -> -x, so the variances
    # (1, 4, 9) along the local axes become 4 along x, 1 along y, 9 along z.
    h = math.sqrt(0.5)
    cov = splat_covariances(np.array([[1.0, 2.0, 3.0]]), np.array([[h, 0.0, 0.0, h]]))
    np.testing.assert_allclose(cov[0], np.diag([4.0, 1.0, 9.0]), atol=1e-6)

    # 60 degrees about (1, 1, 0) / sqrt 2, quaternion given unnormalised (x 3).
    axis, angle = np.array([1.0, 1.0, 0.0]) / math.sqrt(2.0), math.radians(60.0)
    q = 3.0 * np.array([math.cos(angle / 2), *(math.sin(angle / 2) * axis)])
    s = np.array([0.5, 0.1, 2.0])
    R = _rodrigues(axis, angle)
    expected = R @ np.diag(s ** 2) @ R.T
    got = splat_covariances(s[None], q[None])[0]
    np.testing.assert_allclose(got, expected, atol=1e-5)
    np.testing.assert_allclose(got, got.T, atol=1e-7)


def test_rgb_from_sh_dc_is_the_hand_formula():
    # colour = 0.28209479177387814 * dc + 0.5, clipped to [0, 1].
    dc = np.array([[1.0, -1.0, 0.0], [5.0, -5.0, 0.5]])
    want = np.array([[0.78209479, 0.21790521, 0.5], [1.0, 0.0, 0.64104740]])
    np.testing.assert_allclose(splat_colors(dc), want, atol=1e-6)


def test_queries_split_on_commas_semicolons_and_lines():
    assert split_queries(" teapot, red mug;plate\n\n ; ") == ["teapot", "red mug", "plate"]
    assert split_queries("") == []


def test_heat_colours_are_turbo_of_min_max_normalised_relevancy():
    from matplotlib import colormaps

    rel = np.array([[0.2, 0.5, 0.8, 0.2]], dtype=np.float32)  # normalised: 0, 0.5, 1, 0
    want = colormaps["turbo"](np.array([0.0, 0.5, 1.0, 0.0]))[:, :3] * 255
    np.testing.assert_allclose(heat_colors(rel).astype(float), want, atol=0.5)
    # Two queries: each Gaussian shows its larger normalised value.
    two = np.array([[0.0, 1.0, 0.5], [1.0, 0.0, 0.0]], dtype=np.float32)  # -> max(0, 1), max(1, 0), max(.5, 0)
    np.testing.assert_allclose(heat_colors(two).astype(float),
                               colormaps["turbo"](np.array([1.0, 1.0, 0.5]))[:, :3] * 255, atol=0.5)


def test_selection_is_the_protocol_rule_on_the_gaussians():
    # (r - min) / (max - min) mapped to [-1, 1] and clipped: 0, 0, 0.42, 1 -> > 0.4 keeps the last two.
    rel = np.array([[0.0, 0.5, 0.71, 1.0]], dtype=np.float32)
    assert selection_mask(rel, 0.4).tolist() == [False, False, True, True]
    assert selection_mask(rel, 0.5).tolist() == [False, False, False, True]
    # Several queries: the union.
    two = np.array([[0.0, 0.5, 0.71, 1.0], [1.0, 0.0, 0.0, 0.0]], dtype=np.float32)
    assert selection_mask(two, 0.4).tolist() == [True, False, True, True]


def test_browser_pose_round_trips_an_n2f2_camera():
    from n2f2.cameras import Camera, look_at

    R, t = look_at(np.array([2.0, -1.0, 1.5]), np.array([0.1, 0.2, 0.3]), np.array([0.0, 0.0, 1.0]))
    cam = Camera(50.0, 50.0, 40.0, 30.0, 80, 60, R=R, t=t)
    wxyz, position = pose_of(cam)
    back = camera_from_pose(wxyz, position, fov=2 * math.atan(30.0 / 50.0), aspect=80 / 60, width=80)
    np.testing.assert_allclose(back.R, cam.R, atol=1e-9)
    np.testing.assert_allclose(back.t, cam.t, atol=1e-9)
    assert (back.width, back.height) == (80, 60)
    np.testing.assert_allclose([back.fx, back.fy, back.cx, back.cy], [50.0, 50.0, 40.0, 30.0], atol=1e-9)
    uv, z = back.project(np.array([0.1, 0.2, 0.3]))  # the look-at point is at the image centre
    np.testing.assert_allclose(uv, [40.0, 30.0], atol=1e-9)
    assert z > 0


# ----------------------------------------------------------------------------- render cache
def test_byte_lru_evicts_least_recently_used_by_bytes():
    sizes = {"a": 40, "b": 30, "c": 50, "d": 20, "huge": 101}
    lru = ByteLRU(100, sizeof=lambda key: sizes[key])
    assert lru.put("a", "a") and lru.put("b", "b")
    assert lru.nbytes == 70
    assert lru.get("a") == "a"  # a is now the most recent: b is next to go
    assert lru.put("c", "c")  # 70 + 50 > 100: evict b (30) -> 40 + 50 = 90
    assert lru.keys() == ["a", "c"] and lru.nbytes == 90
    assert lru.put("d", "d")  # 90 + 20 > 100: evict a (40) -> 50 + 20 = 70
    assert lru.keys() == ["c", "d"] and lru.nbytes == 70
    assert lru.get("b") is None and lru.get("a") is None
    assert not lru.put("huge", "huge")  # larger than the bound: not stored, nothing evicted
    assert lru.keys() == ["c", "d"] and lru.nbytes == 70
    assert lru.put("c", "c")  # re-put: counted once, now the most recent
    assert lru.keys() == ["d", "c"] and lru.nbytes == 70
    lru.reserve(30)  # 70 + 30 fits: nothing evicted
    assert lru.keys() == ["d", "c"]
    lru.reserve(31)  # room for 31 more: the least recent (d, 20) goes
    assert lru.keys() == ["c"] and lru.nbytes == 50
    lru.reserve(1000)  # more than the bound: everything goes
    assert lru.keys() == [] and lru.nbytes == 0


@pytest.fixture(scope="module")
def engine(trained_run):
    from n2f2.query.engine import QueryEngine

    return QueryEngine.from_run(trained_run.run_dir, scene=trained_run.scene_dir)


def test_a_cached_view_costs_its_own_tensors(engine):
    shared = frozenset({engine.W.untyped_storage().data_ptr()})
    cam = engine.scene.cameras[0]
    H, W, D = cam.height, cam.width, engine.dim
    composite = engine.render_view(0, modes=["composite"], rgb=True)
    compact_tensors(composite, shared)
    # Theta~ [HW, D], 1/|phi| and the negatives' term [HW] each, alpha [H, W], RGB [H, W, 3]; float32.
    assert tensor_bytes(composite, exclude=shared) == 4 * H * W * (D + 2 + 1 + 3)
    assert engine.view_cache_bytes(0, ["composite"]) == 4 * H * W * (D + 2 + 1 + 3)  # known before rendering
    explicit = engine.render_view(0, modes=["explicit"], rgb=True)
    compact_tensors(explicit, shared)
    S = len(engine.scale_dims)  # k = 1: blocks [S, 1, HW], inverse norms and negatives [S, 1, HW]
    assert tensor_bytes(explicit, exclude=shared) == 4 * H * W * (S + 2 * S + 1 + 3)
    assert engine.view_cache_bytes(0, ["explicit"]) == 4 * H * W * (S + 2 * S + 1 + 3)


def test_the_viewer_cache_stays_under_its_byte_bound(engine):
    cam = engine.scene.cameras[0]
    per_view = 4 * cam.height * cam.width * (engine.dim + 6)  # one composite view, as above
    viewer = Viewer(engine, ViewerLimits(render_cache_bytes=2 * per_view + per_view // 2, render_transient_bytes=0))
    for i in range(4):
        viewer.render(f"view:{i}", i)
        assert viewer._renders.nbytes <= viewer.limits.render_cache_bytes
    assert viewer._renders.keys() == ["view:2|composite", "view:3|composite"]
    _, cached = viewer.render("view:3", 3)
    assert cached
    # The render in flight counts: with half a view of working memory a new view needs 1.5
    # views of room, so under a bound of 2.5 views no older view stays cached beside it.
    viewer = Viewer(engine, ViewerLimits(render_cache_bytes=2 * per_view + per_view // 2,
                                         render_transient_bytes=per_view // 2 + 1))
    for i in range(3):
        viewer.render(f"view:{i}", i)
        assert viewer._renders.nbytes <= viewer.limits.render_cache_bytes
    assert viewer._renders.keys() == ["view:2|composite"]


# ----------------------------------------------------------------------------- JSON API safety
@pytest.fixture(scope="module")
def api_viewer(engine):
    return Viewer(engine, ViewerLimits(max_body_bytes=8192, max_queries=4))


def test_deeply_nested_json_is_a_json_400(api_viewer):
    from fastapi.testclient import TestClient

    client = TestClient(create_app(api_viewer), raise_server_exceptions=False)
    for body in (b"[" * 3000 + b"]" * 3000, b'{"queries": ' + b"[" * 3000 + b"]" * 3000 + b"}"):
        r = client.post("/api/query", content=body, headers={"Content-Type": "application/json"})
        assert r.status_code == 400, r.text
        assert set(r.json()) == {"error"} and "nested" in r.json()["error"]


@pytest.mark.parametrize("body", [
    {"queries": ["mug"], "camera": {"orbit": {"azimuth": 10 ** 400, "elevation": 0, "radius": 1}}},
    {"queries": ["mug"], "camera": {"orbit": {"azimuth": 0, "elevation": 0, "radius": 1e999}}},
])
def test_numbers_too_large_for_a_float_are_a_422(api_viewer, body):
    from fastapi.testclient import TestClient

    client = TestClient(create_app(api_viewer), raise_server_exceptions=False)
    payload = json.dumps(body).replace("Infinity", "1e999").encode()
    r = client.post("/api/query", content=payload, headers={"Content-Type": "application/json"})
    assert r.status_code == 422 and set(r.json()) == {"error"}
    r = client.post("/api/selection", content=json.dumps({"query": "mug", "threshold": 10 ** 400}).encode(),
                    headers={"Content-Type": "application/json"})
    assert r.status_code == 422 and "threshold" in r.json()["error"]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def api_url(api_viewer):
    """The JSON API as ``n2f2 view`` serves it (uvicorn with the JSON-error protocol)."""
    import threading

    from n2f2.viewer.server import api_server

    server = api_server(api_viewer, "127.0.0.1", _free_port())
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    deadline = time.time() + 30
    while not server.started:
        assert time.time() < deadline, "API server did not start"
        time.sleep(0.05)
    yield server.config.host, server.config.port
    server.should_exit = True
    thread.join(timeout=10)


def _raw_request(host: str, port: int, data: bytes) -> tuple[int, dict, bytes]:
    """Send bytes as they are, read the whole response -> (status, headers, body)."""
    with socket.create_connection((host, port), timeout=30) as s:
        s.sendall(data)
        chunks = []
        while True:
            chunk = s.recv(65536)
            if not chunk:
                break
            chunks.append(chunk)
            raw = b"".join(chunks)
            if b"\r\n\r\n" in raw:
                head, _, body = raw.partition(b"\r\n\r\n")
                length = [int(line.split(b":", 1)[1]) for line in head.split(b"\r\n")
                          if line.lower().startswith(b"content-length:")]
                if length and len(body) >= length[0]:
                    break
    head, _, body = b"".join(chunks).partition(b"\r\n\r\n")
    lines = head.decode("latin-1").split("\r\n")
    headers = {k.strip().lower(): v.strip() for k, v in (line.split(":", 1) for line in lines[1:])}
    return int(lines[0].split()[1]), headers, body


@pytest.mark.parametrize("request_bytes", [
    b"POST /api/query HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\nContent-Length: abc\r\n\r\n{}",
    b"POST /api/query HTTP/1.1\r\nHost: x\r\nContent-Length: -5\r\n\r\n{}",
    b"POST /api/query HTTP/1.1\r\nHost: x\r\nContent-Length: 2\r\nContent-Length: 3\r\n\r\n{}",
    b"GARBAGE\r\n\r\n",
    b"GET /api/scene HTTP/1.1\r\nbad header line\r\n\r\n",
], ids=["non-numeric-length", "negative-length", "conflicting-lengths", "bad-request-line", "bad-header"])
def test_requests_the_http_parser_refuses_get_json_errors(api_url, request_bytes):
    status, headers, body = _raw_request(*api_url, request_bytes)
    assert 400 <= status < 500
    assert headers.get("content-type") == "application/json"
    data = json.loads(body)
    assert set(data) == {"error"} and "Traceback" not in data["error"]


def test_a_well_formed_raw_request_still_works(api_url):
    status, _, body = _raw_request(*api_url, b"GET /api/scene HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n")
    assert status == 200 and "views" in json.loads(body)


# ----------------------------------------------------------------------------- the 3D viewer
@pytest.fixture(scope="module")
def running(trained_run, tmp_path_factory):
    """``n2f2 view`` as the CLI starts it (both servers, free ports), in this process."""
    from n2f2.viewer.commands import launch

    export = tmp_path_factory.mktemp("exports")
    r = launch(trained_run.run_dir, port=0, api_port=0, scene=str(trained_run.scene_dir), export_dir=export)
    assert r.splats.ready.wait(120), "per-Gaussian features were not computed"
    yield r
    r.stop()


def _set_query(running, text: str, mode: str | None = "composite") -> None:
    s = running.splats
    s.gui_text.value = text
    if mode is not None:
        s.gui_mode.value = mode  # a change re-runs the last query in the new mode
    s.gui_run.value = True  # a server-side click: runs the button's callback


def test_the_json_api_runs_beside_the_3d_viewer(running):
    import urllib.request

    assert running.api_url and running.url != running.api_url
    with urllib.request.urlopen(running.api_url + "/api/scene", timeout=30) as resp:
        assert len(json.loads(resp.read())["views"]) == len(running.viewer.scene.cameras)
    with urllib.request.urlopen(running.url, timeout=30) as resp:  # viser's page
        assert resp.status == 200


def test_splats_are_the_runs_gaussians(running):
    s = running.splats
    g = running.viewer.engine.gaussians
    assert s.num == g.num
    np.testing.assert_allclose(s.splats.centers, g.means.detach().numpy(), atol=0)
    # Colours as sent (uint8) are the DC colours: 0.282 dc + 0.5, clipped, in 0..255.
    dc = g.sh[:, 0].detach().numpy()
    want = np.clip(0.28209479177387814 * dc + 0.5, 0, 1) * 255
    assert np.abs(s.splats.rgbs.astype(float) - want).max() <= 1.0
    want_opacity = 255 / (1 + np.exp(-g.opacity_logits.detach().numpy()))
    assert np.abs(s.splats.opacities[:, 0].astype(float) - want_opacity).max() <= 1.0
    assert len(s.frustums) == len(running.viewer.scene.cameras)


def test_a_query_recolours_only_the_colour_words(running, trained_run):
    s = running.splats
    _set_query(running, f"{trained_run.part_query}; teapot")
    assert s.query is not None and s.query.texts == [trained_run.part_query, "teapot"]
    assert s.shown == "heatmap"
    buf = s.splats.buffer
    np.testing.assert_array_equal(buf[:, :7], s._base[:, :7])  # geometry as sent at start
    assert (buf[:, 7] != s._base[:, 7]).mean() > 0.5
    # The heat colours are turbo of the engine's own 3D relevancy, normalised per query.
    from matplotlib import colormaps

    rel = running.viewer.engine.query_gaussians([trained_run.part_query, "teapot"]).relevancy.numpy()
    lo, hi = rel.min(1, keepdims=True), rel.max(1, keepdims=True)
    v = ((rel - lo) / (hi - lo)).max(0)
    # Sent colours are 8-bit; float32 rounding may put a value on the next of turbo's 256 entries.
    err = np.min([np.abs(s.splats.rgbs.astype(float) - colormaps["turbo"](np.clip(v + d, 0, 1))[:, :3] * 255).max(1)
                  for d in (-1 / 256, 0.0, 1 / 256)], axis=0)
    assert np.median(err) <= 0.5
    assert err.max() <= 1.0
    np.testing.assert_array_equal(s.splats.opacities, s.base_rgba[:, 3:4])
    assert s.timing.bytes == 32 * s.num and s.timing.total > 0


def test_selection_display_dims_everything_else(running, trained_run):
    from n2f2.eval.protocol import normalized_for_threshold

    s = running.splats
    _set_query(running, trained_run.part_query)
    s.gui_threshold.value = 0.4
    s.gui_display.value = "selection"
    rel = running.viewer.engine.query_gaussians([trained_run.part_query]).relevancy.numpy()[0]
    keep = normalized_for_threshold(rel) > 0.4
    assert 0 < keep.sum() < s.num
    rgba = s.splats.buffer[:, 7:8].view(np.uint8).reshape(-1, 4)
    np.testing.assert_array_equal(rgba[keep], s.base_rgba[keep])
    np.testing.assert_array_equal(rgba[~keep, 3], (s.base_rgba[~keep, 3] * 0.15).astype(np.uint8))
    s.gui_threshold.value = 0.8  # a higher threshold keeps fewer
    rgba = s.splats.buffer[:, 7:8].view(np.uint8).reshape(-1, 4)
    kept = (rgba == s.base_rgba).all(1)
    assert kept.sum() == (normalized_for_threshold(rel) > 0.8).sum() < keep.sum()
    s.gui_display.value = "rgb"  # back to the Gaussians' own colours
    np.testing.assert_array_equal(s.splats.buffer, s._base)
    s.gui_display.value = "heatmap"


def test_explicit_mode_and_bad_queries(running):
    s = running.splats
    _set_query(running, "teapot", mode="explicit")
    assert s.query.mode == "explicit" and s.query.chosen[0] is not None
    before = s.query
    _set_query(running, " ; , ", mode=None)  # nothing to ask: an error in the GUI, the last answer stays
    assert s.query is before and "error" in s.gui_status.content
    _set_query(running, ", ".join(["mug"] * (running.viewer.limits.max_queries + 1)), mode=None)
    assert s.query is before and "too many" in s.gui_status.content
    s.gui_mode.value = "composite"


def test_export_writes_the_selection(running, trained_run):
    from n2f2.gaussians import read_ply

    s = running.splats
    _set_query(running, trained_run.part_query)
    s.gui_threshold.value = 0.4
    s.gui_export.value = True
    path = s.last_export
    assert path is not None and path.parent == s.export_dir and path.suffix == ".ply"
    want = selection_mask(s.query.relevancy, 0.4)
    g = read_ply(path)
    assert g.num == int(want.sum()) > 0
    np.testing.assert_allclose(g.means.detach().numpy(), running.viewer.engine.gaussians.means.detach().numpy()[want])
    meta = json.loads(path.with_suffix(".json").read_text())
    assert meta["selected"] == g.num and meta["queries"] == [trained_run.part_query]
    assert str(path) in s.gui_export_status.content


def test_render_view_of_a_browser_camera(running, trained_run):
    s = running.splats
    _set_query(running, f"{trained_run.part_query}, teapot")
    cam = running.viewer.scene.cameras[2]
    wxyz, pos = pose_of(cam)
    fake = SimpleNamespace(camera=SimpleNamespace(wxyz=wxyz, position=pos, aspect=cam.width / cam.height,
                                                  fov=2 * math.atan(0.5 * cam.height / cam.fy)))
    image = s.render_view(fake)
    assert image.shape == (2 * cam.height, 2 * cam.width, 3) and image.dtype == np.uint8
    assert image.std() > 5
    assert trained_run.part_query in s.gui_numbers.content and "localisation" in s.gui_numbers.content
    # The same camera through the JSON API's path: the same relevancy in the shown heatmap.
    from n2f2.query.outputs import heatmap_overlay

    view, result = running.viewer.query_view("check", s.render_camera(fake), [trained_run.part_query], "composite")
    heat = heatmap_overlay(view.rgb.numpy(), result.relevancy[0].numpy())
    want = (np.clip(heat, 0, 1) * 255 + 0.5).astype(np.uint8)
    diff = np.abs(image[: cam.height, : cam.width].astype(int) - want.astype(int))
    # Float rounding between the two paths may put a value on the other side of a boundary of
    # turbo's 256-entry colour table: at most one table step (times the overlay's opacity) plus
    # 1 for rounding to uint8, at a few pixels; everywhere else at most the rounding.
    from matplotlib import colormaps

    from n2f2.query.outputs import HEATMAP_ALPHA

    table = colormaps["turbo"](np.linspace(0.0, 1.0, 256))[:, :3]
    one_step = np.abs(np.diff(table, axis=0)).max() * 255 * HEATMAP_ALPHA + 1
    assert diff.max() <= one_step and (diff.max(axis=-1) > 1).mean() < 0.01


# ----------------------------------------------------------------------------- browser
def _png(data: bytes) -> np.ndarray:
    from PIL import Image

    return np.asarray(Image.open(io.BytesIO(data)).convert("RGB"), dtype=float)


@pytest.mark.skipif(not Path(CHROMIUM_PATH).exists(),
                    reason="Debian chromium is not installed (apt-get install chromium); .ci/run installs it")
def test_browser_sees_splats_moves_and_recolours(running, trained_run, tmp_path, wait, viewer_page):
    shot_dir = Path(os.environ.get("N2F2_SCREENSHOT_DIR", tmp_path))
    shot_dir.mkdir(parents=True, exist_ok=True)
    s = running.splats
    s.gui_display.value = "rgb"
    with viewer_page(running, 640, 420, "Queries") as (page, client):
        # The view region left of the GUI panel.
        clip = {"x": 0, "y": 0, "width": 300, "height": 420}

        def shot(name: str) -> np.ndarray:
            data = page.screenshot(clip=clip)
            (shot_dir / f"{name}.png").write_bytes(data)
            return _png(data)

        # Splats arrive: the view is no longer one flat colour.
        wait(lambda: shot("viewer3d_0_start").std(axis=(0, 1)).mean() > 15, 90, "splats on screen")
        first = shot("viewer3d_0_start")

        # Move the camera to a training view (what clicking its frustum does).
        s.move_to_view(client, 3)
        target = pose_of(running.viewer.scene.cameras[3])[1]
        wait(lambda: np.allclose(client.camera.position, target, atol=1e-3), 30, "the camera move")
        wait(lambda: np.abs(shot("viewer3d_1_view3") - first).mean() > 5, 30, "a new picture")
        moved = shot("viewer3d_1_view3")

        # Type a query in the page and press the Query button.
        s.query = None
        box = page.locator("div.mantine-Flex-root", has=page.locator("label", has_text="Queries"))
        box.locator("input").fill(trained_run.part_query)
        page.get_by_role("button", name="Query", exact=True).click()
        wait(lambda: s.query is not None and s.shown == "heatmap", 60, "the query's colours")
        assert s.query.texts == [trained_run.part_query]
        wait(lambda: np.abs(shot("viewer3d_2_query") - moved).mean() > 5, 30, "recoloured splats")
        page.screenshot(path=str(shot_dir / "viewer3d_page.png"))
    assert np.abs(_png((shot_dir / "viewer3d_2_query.png").read_bytes()) - moved).mean() > 5
