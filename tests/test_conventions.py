"""Camera conventions end to end: the demo scene written to disk and read back through both
loaders must reproject what the ray tracer hit onto the pixel centre it came from."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from n2f2.data import load_scene
from n2f2.data.synthetic import build_demo_scene, demo_cameras, generate_demo_scene, render_view

NUM_VIEWS, WIDTH, HEIGHT, SEED = 6, 64, 48, 3
# The contract is "within half a pixel"; every step is exact up to float rounding, so any
# convention slip (a flipped axis, a missing +0.5, distance vs z-depth) shows up far above this.
TOL_PX = 0.5
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
    assert max(errs) < TIGHT_PX < TOL_PX, max(errs)


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


def test_ids_written_are_the_traced_ids(traced, scene_dir):
    for view, render in enumerate(traced):
        stored = np.load(scene_dir / "regions" / f"frame_{view + 1:05d}.npy")
        assert (stored == render.regions).all()


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
