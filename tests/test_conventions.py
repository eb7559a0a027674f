"""Camera conventions end to end: the demo scene written to disk and read back through both
loaders must reproject what the ray tracer hit onto the pixel centre it came from."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from n2f2.data import load_scene
from n2f2.data.synthetic import build_demo_scene, demo_cameras, generate_demo_scene, intersect, render_view

NUM_VIEWS, WIDTH, HEIGHT, SEED = 6, 64, 48, 3
# The contract is "within half a pixel", but every step is exact up to float rounding, so the
# tests ask for far less: any convention slip (a flipped axis, a missing +0.5, distance vs
# z-depth) moves a point by a sizeable fraction of a pixel or more.
TIGHT_PX = 1e-3


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("conventions") / "scene"
    generate_demo_scene(out, num_views=NUM_VIEWS, width=WIDTH, height=HEIGHT, seed=SEED,
                        labelled_views=[], num_points=300, show_progress=False)
    return out


@pytest.fixture(scope="module")
def traced() -> list:
    """Ray-tracer hits at the pixel centres, recomputed from the scene description."""
    scene = build_demo_scene(SEED)
    return [render_view(scene, cam, supersample=1) for cam in demo_cameras(NUM_VIEWS, WIDTH, HEIGHT, SEED)]


@pytest.fixture(scope="module", params=["colmap", "nerfstudio"])
def loaded(request, scene_dir):
    scene = load_scene(scene_dir, format=request.param)
    assert scene.source_format.startswith(request.param)
    return scene


def _pixel_centres() -> np.ndarray:  # [H, W, 2]
    rows, cols = np.mgrid[0:HEIGHT, 0:WIDTH]
    return np.stack([cols + 0.5, rows + 0.5], axis=-1)


def test_sparse_points_project_to_their_source_pixel(loaded, scene_dir):
    src = np.load(scene_dir / "points_source.npy")
    assert loaded.points is not None and len(loaded.points) == len(src) == 300
    assert loaded.point_colors is not None
    errs = []
    for view in np.unique(src[:, 0]):
        sel = src[:, 0] == view
        uv, z = loaded.cameras[view].project(loaded.points[sel])
        want = np.stack([src[sel, 2] + 0.5, src[sel, 1] + 0.5], axis=-1)
        errs.append(np.abs(uv - want).max())
        depth = np.load(scene_dir / "depth" / f"frame_{view + 1:05d}.npy")
        np.testing.assert_allclose(z, depth[src[sel, 1], src[sel, 2]], rtol=1e-6)
        # the point's colour is the image's colour at that pixel
        img = (loaded.image(int(view)) * 255 + 0.5).astype(np.uint8)
        assert (loaded.point_colors[sel] == img[src[sel, 1], src[sel, 2]]).all()
    assert max(errs) < TIGHT_PX, max(errs)


def test_ray_tracer_hits_project_to_pixel_centres(loaded, traced, scene_dir):
    centres = _pixel_centres()
    for view, render in enumerate(traced):
        cam = loaded.cameras[view]
        uv, z = cam.project(render.points)
        assert np.abs(uv - centres).max() < TIGHT_PX
        depth = np.load(scene_dir / "depth" / f"frame_{view + 1:05d}.npy")
        np.testing.assert_allclose(z, depth, rtol=1e-6)
        # and back: the stored z-depth unprojected through the loaded camera is the hit point
        back = cam.unproject(centres, depth.astype(np.float64))
        assert np.abs(back - render.points).max() < 1e-5


def reference_ids(scene, camera) -> tuple[np.ndarray, np.ndarray]:
    """Region ids [3, H, W] (part, object, group) at every pixel centre, cast here without
    render_view, trace or the scene's id table: one ray per pixel centre (pinhole, +0.5) against
    every primitive (no culling), the nearest hit's own ids. Also [H, W] bool: pixels whose two
    nearest surfaces with different ids are within float rounding of each other (ambiguous)."""
    rows, cols = np.mgrid[0:camera.height, 0:camera.width]
    d_cam = np.stack([(cols + 0.5 - camera.cx) / camera.fx, (rows + 0.5 - camera.cy) / camera.fy,
                      np.ones(rows.shape)], axis=-1).reshape(-1, 3)
    dirs = d_cam @ camera.R  # world directions with camera-z component 1: t is z-depth
    t = np.stack([intersect(p, camera.center[None], dirs) for p in scene.primitives])  # [P, N]
    ids = np.array([(p.part, p.object, p.group) for p in scene.primitives])  # [P, 3]
    order = np.argsort(t, axis=0, kind="stable")
    first, second = order[0], order[1]
    n = np.arange(t.shape[1])
    assert np.isfinite(t[first, n]).all()  # the room is closed: every ray hits something
    ambiguous = (t[second, n] - t[first, n] < 1e-9 * t[first, n]) & (ids[first] != ids[second]).any(axis=1)
    shape = (camera.height, camera.width)
    return ids[first].T.reshape(3, *shape), ambiguous.reshape(shape)


def test_ids_written_are_the_nearest_surfaces_ids(scene_dir):
    """The region maps on disk against an independent cast from the cameras on disk."""
    scene = build_demo_scene(SEED)
    loaded = load_scene(scene_dir, format="colmap")
    for view, camera in enumerate(loaded.cameras):
        stored = np.load(scene_dir / "regions" / f"frame_{view + 1:05d}.npy")
        want, ambiguous = reference_ids(scene, camera)
        assert stored.shape == want.shape == (3, HEIGHT, WIDTH)
        assert ambiguous.mean() < 1e-3
        wrong = (stored != want).any(axis=0) & ~ambiguous
        assert not wrong.any(), f"view {view}: {wrong.sum()} pixels, first at {np.argwhere(wrong)[0]}"
        assert len(np.unique(want[1])) > 3  # several objects in view: the check is not vacuous


def test_downscaled_cameras_keep_pixel_centres(scene_dir, traced):
    """Halving the image: a hit at full-res pixel centre (u, v) lands at (u / 2, v / 2)."""
    scene = load_scene(scene_dir, downscale=2, format="colmap")
    cam = scene.cameras[1]
    assert (cam.width, cam.height) == (WIDTH // 2, HEIGHT // 2)
    uv, _ = cam.project(traced[1].points)
    assert np.abs(uv - _pixel_centres() / 2).max() < TIGHT_PX


def test_colmap_and_nerfstudio_agree(scene_dir):
    a = load_scene(scene_dir, format="colmap")
    b = load_scene(scene_dir, format="nerfstudio")
    assert a.image_names == b.image_names == [f"frame_{i + 1:05d}" for i in range(NUM_VIEWS)]
    truth = demo_cameras(NUM_VIEWS, WIDTH, HEIGHT, SEED)
    for ca, cb, ct in zip(a.cameras, b.cameras, truth):
        for c in (ca, cb):
            np.testing.assert_allclose(c.K, ct.K, atol=1e-9)
            np.testing.assert_allclose(c.R, ct.R, atol=1e-9)
            np.testing.assert_allclose(c.t, ct.t, atol=1e-9)
            assert (c.width, c.height) == (WIDTH, HEIGHT)
    np.testing.assert_allclose(a.points, b.points, atol=1e-6)
    assert (a.point_colors == b.point_colors).all()
    assert a.ground_truth is not None and b.ground_truth is not None


def test_cameras_look_at_the_table(traced):
    """Independent sanity check of the camera set-up: the table is in every view, centred."""
    scene = build_demo_scene(SEED)
    table = scene.region("table").id
    for render in traced:
        ys, xs = np.nonzero(render.regions[1] == table)
        assert len(xs) > 0.2 * WIDTH * HEIGHT
        assert abs(xs.mean() + 0.5 - WIDTH / 2) < WIDTH / 4
