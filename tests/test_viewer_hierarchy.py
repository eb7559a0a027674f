"""The scene's hierarchy in ``n2f2 view``: the 3D viewer colours the Gaussians by their node at a
level, shows a clicked Gaussian's path up to the root and exports a node; the JSON API answers
mode node only when the run has a hierarchy. Built on the shared demo run, decomposed here."""

from __future__ import annotations

import json
import os
import shutil
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

pytest.importorskip("viser")
pytest.importorskip("fastapi")

from n2f2.errors import InputError  # noqa: E402
from n2f2.hierarchy.views import palette  # noqa: E402
from n2f2.viewer.browser import CHROMIUM_PATH  # noqa: E402
from n2f2.viewer.hierarchy import path_records, pick_gaussian, whitening  # noqa: E402

VOCABULARY = ("teapot", "lid of the teapot", "red mug", "bag of cookies", "plate")


def _copy_run(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst, ignore=shutil.ignore_patterns("decomposition"))
    return dst


@pytest.fixture(scope="module")
def decomposed_run(trained_run, tmp_path_factory) -> Path:
    """A copy of the shared demo run with its hierarchy in RUN/decomposition (texts from a vocabulary)."""
    from n2f2.cli import main

    root = tmp_path_factory.mktemp("viewer_hierarchy")
    run = _copy_run(trained_run.run_dir, root / "run")
    vocab = root / "vocab.txt"
    vocab.write_text("\n".join(VOCABULARY) + "\n")
    assert main(["decompose", str(run), "--vocabulary", str(vocab), "--quiet"]) == 0
    assert (run / "decomposition" / "tree.json").is_file()
    return run


@pytest.fixture(scope="module")
def bare_run(trained_run, tmp_path_factory) -> Path:
    """A copy of the shared demo run without a hierarchy."""
    return _copy_run(trained_run.run_dir, tmp_path_factory.mktemp("viewer_bare") / "run")


@pytest.fixture(scope="module")
def running(decomposed_run, trained_run, tmp_path_factory):
    from n2f2.viewer.commands import launch

    export = tmp_path_factory.mktemp("node_exports")
    r = launch(decomposed_run, port=0, api_port=None, scene=str(trained_run.scene_dir), export_dir=export, warm=False)
    yield r
    r.stop()


def _rgba(running) -> np.ndarray:  # [N, 4] uint8 colours as sent
    return running.splats.splats.buffer[:, 7:8].view(np.uint8).reshape(-1, 4)


def _by_hand(nodes: np.ndarray) -> np.ndarray:  # [N] node ids -> [N, 3] palette colour of each, one at a time
    table = {int(k): palette(np.array([k]))[0] for k in np.unique(nodes)}
    return np.stack([table[int(k)] for k in nodes])


# ----------------------------------------------------------------------------- picking
def test_a_click_picks_the_gaussian_that_gives_the_pixel_its_colour():
    # Three round Gaussians on the z axis (sigma 0.1), the camera at the origin looking along +z.
    centers = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 2.0], [0.0, 0.0, 3.0]])
    quats = np.tile([1.0, 0.0, 0.0, 0.0], (3, 1))
    A = whitening(quats, np.full((3, 3), 0.1))
    np.testing.assert_allclose(A, np.tile(np.eye(3) * 10.0, (3, 1, 1)), atol=1e-6)
    o, d = np.zeros(3), np.array([0.0, 0.0, 1.0])
    assert pick_gaussian(centers, A, np.array([0.9, 0.9, 0.9]), o, d) == 0  # the front one covers the rest
    assert pick_gaussian(centers, A, np.array([0.01, 0.9, 0.9]), o, d) == 1  # nearly transparent: seen through
    assert pick_gaussian(centers, A, np.array([0.9, 0.9, 0.9]), o, -d) is None  # behind the camera
    # 0.25 off the axis is 2.5 sigma of a round Gaussian: hit; an elongated one (sigma 0.5 along
    # x, quaternion given unnormalised) reaches a ray 1.0 off its centre along x.
    assert pick_gaussian(centers[:1], A[:1], np.array([0.9]), [0.25, 0.0, 0.0], d) == 0
    assert pick_gaussian(centers[:1], A[:1], np.array([0.9]), [0.35, 0.0, 0.0], d) is None
    long = whitening(np.array([[2.0, 0.0, 0.0, 0.0]]), np.array([[0.5, 0.1, 0.1]]))
    assert pick_gaussian(centers[:1], long, np.array([0.9]), [1.0, 0.0, 0.0], d) == 0
    assert pick_gaussian(centers[:1], long, np.array([0.9]), [0.0, 1.0, 0.0], d) is None


# ----------------------------------------------------------------------------- colours per level
def test_each_level_colours_every_gaussian_by_its_node(running):
    s, h = running.splats, running.splats.hierarchy
    assert h is not None and "node" in s.modes
    s.query = None
    h.select(None)
    nodes = h.tree.gaussian_nodes
    assert nodes.shape == (s.num, h.tree.num_levels) and h.tree.num_levels >= 2
    for level in range(h.tree.num_levels):
        if level == 0:
            h.set_level(0)
        else:
            h.gui_level.value = level  # as the slider sets it: its callback recolours
        assert h.showing and s.shown == "nodes" and h.level == level
        rgba = _rgba(running)
        np.testing.assert_array_equal(rgba[:, :3], _by_hand(nodes[:, level]))
        np.testing.assert_array_equal(rgba[:, 3], s.base_rgba[:, 3])  # opacities as they were
        np.testing.assert_array_equal(s.splats.buffer[:, :7], s._base[:, :7])  # geometry as sent
        assert f"level {level} of" in h.gui_level_text.content
    assert len(np.unique(_rgba(running)[:, :3], axis=0)) > len(np.unique(nodes[:, 0]))  # finer: more colours
    h.gui_show.value = False  # back to the usual colours
    assert s.shown == "rgb"
    np.testing.assert_array_equal(s.splats.buffer, s._base)


# ----------------------------------------------------------------------------- click and path
def _click_at(running, i: int, target: np.ndarray) -> None:
    """A scene click from training view ``i``'s camera through ``target`` (as viser reports one)."""
    cam = running.viewer.scene.cameras[i]
    event = SimpleNamespace(client=None, ray_origin=tuple(cam.center), ray_direction=tuple(target - cam.center))
    running.splats.hierarchy._on_click(event)


def test_a_clicked_gaussian_shows_its_path_to_the_root(running):
    s, h = running.splats, running.splats.hierarchy
    tree, g = h.tree, running.viewer.engine.gaussians
    finest = tree.num_levels - 1
    h.set_level(finest)
    means = g.means.detach().numpy()
    target = means[int(np.argmax(g.opacities.detach().numpy()))]
    _click_at(running, 0, target)
    cam = running.viewer.scene.cameras[0]
    want = pick_gaussian(
        means, whitening(g.quats.detach().numpy(), g.scales.detach().numpy()), g.opacities.detach().numpy(),
        cam.center, target - cam.center,
    )
    assert want is not None and h.gaussian == want
    node = int(tree.gaussian_nodes[want, finest])
    path = tree.path(node)
    # One node per distinct id of its row: a node spanning several levels is one step of the path.
    assert path == list(dict.fromkeys(tree.gaussian_nodes[want, ::-1].tolist())) and h.node == node
    assert [r["node"] for r in path_records(tree, node)] == path
    text = h.gui_path.content
    assert f"Gaussian {want:,}" in text
    lines = [line for line in text.splitlines() if line.startswith("- ")]
    assert len(lines) == len(path)
    for line, k in zip(lines, path):
        rec = tree.tree["nodes"][k]
        span = f"level {rec['level']} "
        if rec["last_level"] != rec["level"]:
            span = f"levels {rec['level']}–{rec['last_level']} ("
        assert f"node **{k}**" in line and span in line
        assert rec["text"] in VOCABULARY and f"“{rec['text']}”" in line
    # While the node colours show, the clicked node keeps its colour and the rest is dimmed.
    inside = tree.gaussian_nodes[:, finest] == node
    rgba = _rgba(running)
    np.testing.assert_array_equal(rgba[inside, :3], _by_hand(tree.gaussian_nodes[inside, finest]))
    assert (rgba[~inside, 3] < s.base_rgba[~inside, 3]).mean() > 0.9
    # A coarser level: the same Gaussian, the path from its coarser node.
    h.gui_level.value = 1
    assert [f"node **{k}**" in h.gui_path.content for k in tree.path(int(tree.gaussian_nodes[want, 1]))] == [True] * 2
    # A click into empty space clears the selection.
    _click_at(running, 0, cam.center - 5.0 * (target - cam.center))
    assert h.gaussian is None and "Click a Gaussian" in h.gui_path.content


# ----------------------------------------------------------------------------- export
def test_export_node_writes_its_gaussians(running):
    from n2f2.gaussians import read_ply

    s, h = running.splats, running.splats.hierarchy
    tree = h.tree
    h.select(None)
    h.gui_export.value = True  # nothing clicked: an error in the status, no file
    assert "click a Gaussian first" in s.gui_status.content and h.last_export is None
    level = tree.num_levels - 1
    h.set_level(level)
    h.select(int(np.argmax(running.viewer.engine.gaussians.opacities.detach().numpy())))
    node = h.node
    h.gui_export.value = True  # the button, clicked on the server
    path = h.last_export
    first = tree.tree["nodes"][node]["level"]  # the file is named by the node's first level
    assert first <= level <= tree.tree["nodes"][node]["last_level"]
    assert path == s.export_dir / f"node_{node}_level_{first}.ply"
    written = read_ply(path)
    assert written.num == tree.tree["nodes"][node]["gaussians"] > 0
    mask = tree.gaussian_nodes[:, level] == node
    means = running.viewer.engine.gaussians.means.detach().numpy()
    np.testing.assert_allclose(written.means.detach().numpy(), means[mask])
    meta = json.loads(path.with_suffix(".json").read_text())
    assert meta["node"] == node and meta["path"] == tree.path(node)
    assert (meta["level"], meta["last_level"]) == (first, tree.tree["nodes"][node]["last_level"])
    assert meta["gaussians"] == written.num and str(path) in h.gui_export_status.content


def test_a_query_shows_its_answer_not_the_nodes(running):
    s, h = running.splats, running.splats.hierarchy
    h.set_level(0)
    assert s.shown == "nodes"
    s.gui_text.value = "teapot"
    s.gui_mode.value = "node"
    s.gui_run.value = True
    assert s.query is not None and s.query.mode == "node"
    assert not h.showing and s.shown == "heatmap"
    answer = running.viewer.engine.node_answers(["teapot"])[0]
    want = np.isin(h.tree.gaussian_nodes[:, answer.level], answer.nodes)
    np.testing.assert_array_equal(s.query.relevancy[0] > 0.5, want)


# ----------------------------------------------------------------------------- the JSON API
def test_the_api_answers_mode_node_with_a_map(running):
    import base64
    import io

    from fastapi.testclient import TestClient
    from PIL import Image

    from n2f2.viewer.server import create_app

    client = TestClient(create_app(running.viewer), raise_server_exceptions=False)
    assert "node" in client.get("/api/scene").json()["modes"]
    # "table": a large answer on the test's short-trained field (its "teapot" nodes are too small
    # for the protocol's smoothing box at this size).
    r = client.post("/api/query", json={"queries": ["table"], "mode": "node", "camera": {"view": 1}})
    assert r.status_code == 200, r.text
    data = r.json()
    res = data["results"][0]
    answer = running.viewer.engine.node_answers(["table"])[0]
    assert data["mode"] == "node" and res["nodes"] == answer.nodes and res["level"] == answer.level
    labels = [lv["scale_label"] for lv in running.splats.hierarchy.tree.tree["levels"]]
    assert res["chosen_scale"] == labels[answer.level]
    heat = np.asarray(Image.open(io.BytesIO(base64.b64decode(res["relevancy_png"]))))
    mask = np.asarray(Image.open(io.BytesIO(base64.b64decode(res["mask_png"]))))
    assert heat.shape[:2] == mask.shape[:2] == (data["height"], data["width"])
    assert 0 < res["mask_area"] < data["height"] * data["width"] and res["max_relevancy"] > 0.5
    # The 3D selection of mode node: the answer's Gaussians.
    r = client.post("/api/selection", json={"query": "table", "mode": "node", "threshold": None})
    assert r.status_code == 200, r.text
    want = np.isin(running.splats.hierarchy.tree.gaussian_nodes[:, answer.level], answer.nodes)
    assert int(r.headers["X-Selected-Gaussians"]) == int(want.sum())


def test_a_run_without_a_hierarchy_does_not_offer_node(bare_run, decomposed_run, trained_run, tmp_path):
    from fastapi.testclient import TestClient

    from n2f2.query.engine import QueryConfig, QueryEngine
    from n2f2.viewer.commands import launch
    from n2f2.viewer.server import Viewer, create_app

    viewer = Viewer(QueryEngine.from_run(bare_run, scene=trained_run.scene_dir))
    assert viewer.tree is None and viewer.tree_error is None and "node" not in viewer.modes
    client = TestClient(create_app(viewer), raise_server_exceptions=False)
    assert "node" not in client.get("/api/scene").json()["modes"]
    r = client.post("/api/query", json={"queries": ["teapot"], "mode": "node", "camera": {"view": 0}})
    assert r.status_code == 422 and "n2f2 decompose" in r.json()["error"]

    r3d = launch(bare_run, port=0, api_port=None, scene=str(trained_run.scene_dir), warm=False)
    try:
        assert r3d.splats.hierarchy is None and "node" not in r3d.splats.gui_mode.options
    finally:
        r3d.stop()
    with pytest.raises(InputError, match="decompose"):  # asked for, and missing: the viewer does not start
        launch(bare_run, port=0, api_port=None, scene=str(trained_run.scene_dir), decomposition=tmp_path / "none")

    # A stale hierarchy (another run's Gaussians): not offered, and the API says why.
    stale = tmp_path / "stale"
    shutil.copytree(decomposed_run / "decomposition", stale)
    np.save(stale / "gaussian_nodes.npy", np.load(stale / "gaussian_nodes.npy")[:-1])
    engine = QueryEngine.from_run(bare_run, scene=trained_run.scene_dir, config=QueryConfig(decomposition=str(stale)))
    viewer = Viewer(engine)
    assert viewer.tree is None and "decompose it again" in viewer.tree_error and "node" not in viewer.modes
    r = TestClient(create_app(viewer), raise_server_exceptions=False).post(
        "/api/query", json={"queries": ["teapot"], "mode": "node"})
    assert r.status_code == 422 and "decompose it again" in r.json()["error"]


def test_view_takes_a_decomposition_folder(decomposed_run, trained_run, tmp_path):
    from n2f2.cli import build_parser
    from n2f2.viewer.commands import launch

    args = build_parser().parse_args(["view", "RUN", "--decomposition", "DIR"])
    assert args.decomposition == "DIR"
    assert build_parser().parse_args(["view", "RUN"]).decomposition is None
    moved = tmp_path / "elsewhere"
    shutil.copytree(decomposed_run / "decomposition", moved)
    bare = _copy_run(decomposed_run, tmp_path / "run")  # without RUN/decomposition
    r = launch(bare, port=0, api_port=None, scene=str(trained_run.scene_dir), warm=False, decomposition=moved)
    try:
        assert r.splats.hierarchy is not None and r.splats.hierarchy.tree.root == moved
        assert "node" in r.viewer.modes
    finally:
        r.stop()


# ----------------------------------------------------------------------------- browser
@pytest.mark.skipif(not Path(CHROMIUM_PATH).exists(),
                    reason="Debian chromium is not installed (apt-get install chromium); .ci/run installs it")
def test_browser_shows_levels_and_a_clicked_path(running, tmp_path, wait, viewer_page):
    """In a real page: two levels look different, and a click on the splats (viser's scene
    click, a ray) selects a Gaussian and shows its path in the panel."""
    from io import BytesIO

    from PIL import Image

    shot_dir = Path(os.environ.get("N2F2_SCREENSHOT_DIR", tmp_path))
    shot_dir.mkdir(parents=True, exist_ok=True)
    s, h = running.splats, running.splats.hierarchy
    h.select(None)
    with viewer_page(running, 800, 640, "Granularity") as (page, client):
        s.move_to_view(client, 0)
        view = {"x": 0, "y": 0, "width": 400, "height": 640}  # left of the GUI panel

        def shot(name: str, clip=view) -> np.ndarray:
            data = page.screenshot(clip=clip) if clip else page.screenshot()
            (shot_dir / f"{name}.png").write_bytes(data)
            return np.asarray(Image.open(BytesIO(data)).convert("RGB"), dtype=float)

        h.set_level(0)
        wait(lambda: shot("hierarchy_level_0").std(axis=(0, 1)).mean() > 15, 90, "splats on screen")
        time.sleep(1.0)
        coarse = shot("hierarchy_level_0", None)
        h.gui_level.value = h.tree.num_levels - 1
        wait(lambda: np.abs(shot("hierarchy_level_finest", None) - coarse).mean() > 2, 30, "the finer colours")
        time.sleep(1.0)
        shot("hierarchy_level_finest", None)
        page.mouse.click(200, 320)  # the middle of the view: the scene
        wait(lambda: h.gaussian is not None, 30, "a picked Gaussian")
        page.get_by_text(f"Gaussian {h.gaussian:,}").wait_for(timeout=30_000)  # the path, in the page
        page.get_by_role("button", name="Export node").scroll_into_view_if_needed()  # all of it on screen
        time.sleep(1.0)
        shot("hierarchy_path", None)
    assert h.node is not None and f"node **{h.node}**" in h.gui_path.content
