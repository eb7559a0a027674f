"""Lens undistortion on load, and missing images.

References are independent of the loader: OpenCV's own forward models (``cv2.projectPoints``,
``cv2.fisheye.distortPoints``) with the coefficients written into the scene files, checked
once against COLMAP's (``pycolmap``) for the parameter orders and the half-pixel convention.
Scene images either encode their own pixel coordinates (16-bit), so the undistorted image
itself says where each of its pixels came from, or are renders of the demo scene distorted
by the test."""

from __future__ import annotations

import hashlib
import json
import math
import os
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from n2f2.cameras import Camera, look_at
from n2f2.cli import main
from n2f2.data import load_scene
from n2f2.data.colmap import write_colmap_text
from n2f2.data.nerfstudio import write_transforms
from n2f2.errors import InputError
from n2f2.io import write_png

W, H = 96, 72
FX, FY, CX, CY = 80.0, 82.0, 49.3, 35.1  # off-centre, non-integer principal point
FISHEYE_F = 45.0  # ~61 degrees at the edge midpoints, ~76 at the corners


# ============================================================================ references
def opencv_K(fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    # COLMAP, nerfstudio and n2f2 put the top-left pixel centre at (0.5, 0.5), OpenCV at (0, 0).
    return np.array([[fx, 0.0, cx - 0.5], [0.0, fy, cy - 0.5], [0.0, 0.0, 1.0]])


def reference_distort(points_cam: np.ndarray,  # [N, 3] camera space, z > 0
                      intrinsics: tuple, kind: str, D: tuple) -> np.ndarray:  # -> [N, 2] n2f2 pixels
    """Where OpenCV's model puts camera-space points in the distorted image."""
    K = opencv_K(*intrinsics)
    if kind == "fisheye":
        xy = (points_cam[:, :2] / points_cam[:, 2:]).reshape(-1, 1, 2)
        out = cv2.fisheye.distortPoints(xy, K, np.asarray(D, np.float64))
    else:
        out, _ = cv2.projectPoints(points_cam.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K,
                                   np.asarray(D, np.float64))
    return out.reshape(-1, 2) + 0.5


def reference_undistort(pixels: np.ndarray,  # [N, 2] n2f2 pixels of the distorted image
                        intrinsics: tuple, D: tuple) -> np.ndarray:  # -> [N, 2] normalised x/z, y/z
    """OpenCV's iterative inverse of the perspective model, run to convergence."""
    src = (pixels - 0.5).reshape(-1, 1, 2).astype(np.float64)
    K, D = opencv_K(*intrinsics), np.asarray(D, np.float64)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-14)
    if hasattr(cv2, "undistortPointsIter"):
        out = cv2.undistortPointsIter(src, K, D, None, None, criteria)
    else:
        out = cv2.undistortPoints(src, K, D, criteria=criteria)
    return out.reshape(-1, 2)


def bilinear(image: np.ndarray,  # [H, W, C] float
             uv: np.ndarray) -> np.ndarray:  # [N, 2] n2f2 pixels -> [N, C]
    """Plain bilinear interpolation with pixel centres at +0.5 (edge pixels replicated)."""
    h, w = image.shape[:2]
    x = np.clip(uv[:, 0] - 0.5, 0, w - 1)
    y = np.clip(uv[:, 1] - 0.5, 0, h - 1)
    x0 = np.minimum(np.floor(x).astype(int), w - 2)
    y0 = np.minimum(np.floor(y).astype(int), h - 2)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    return ((1 - fy) * ((1 - fx) * image[y0, x0] + fx * image[y0, x0 + 1])
            + fy * ((1 - fx) * image[y0 + 1, x0] + fx * image[y0 + 1, x0 + 1]))


def coordinate_image(w: int, h: int) -> np.ndarray:
    """uint16 [h, w, 3]: channel 0 encodes u / w, channel 1 v / h of each pixel centre.
    Bilinear resampling of a linear ramp is exact, so a resampled copy encodes where each of
    its pixels was taken from (to ~0.002 px)."""
    v, u = np.mgrid[0:h, 0:w] + 0.5
    img = np.zeros((h, w, 3), np.uint16)
    img[..., 0] = np.round(u / w * 65535)
    img[..., 1] = np.round(v / h * 65535)
    return img


def decode(image: np.ndarray, w: int, h: int) -> np.ndarray:  # [..., >=2] uint16 -> [..., 2] pixels
    return np.stack([image[..., 0] / 65535 * w, image[..., 1] / 65535 * h], axis=-1)


def tree_digest(folder: Path) -> dict[str, tuple[str, int]]:
    """Content hash and mtime of every file under ``folder``."""
    return {str(p.relative_to(folder)): (hashlib.sha256(p.read_bytes()).hexdigest(), p.stat().st_mtime_ns)
            for p in sorted(folder.rglob("*")) if p.is_file()}


def two_cameras(fx: float, fy: float, cx: float, cy: float) -> list[Camera]:
    cams = []
    for k in range(2):
        R, t = look_at([2.5 * math.cos(k), 2.5 * math.sin(k), 1.0], [0.1, -0.1, 0.2])
        cams.append(Camera(fx, fy, cx, cy, W, H, R=R, t=t))
    return cams


# ============================================================================ model cases
# (format, model, params after the intrinsics as the file writes them, reference kind,
#  reference OpenCV coefficients). OpenCV orders: perspective (k1, k2, p1, p2, k3, k4, k5, k6),
#  fisheye (k1, k2, k3, k4). COLMAP orders from src/colmap/sensor/models.h.
CASES = {
    "colmap-SIMPLE_RADIAL": ("colmap", "SIMPLE_RADIAL", [-0.18], "perspective", (-0.18, 0, 0, 0)),
    "colmap-RADIAL": ("colmap", "RADIAL", [-0.2, 0.05], "perspective", (-0.2, 0.05, 0, 0)),
    "colmap-OPENCV": ("colmap", "OPENCV", [-0.22, 0.06, 0.002, -0.003], "perspective",
                      (-0.22, 0.06, 0.002, -0.003)),
    "colmap-FULL_OPENCV": ("colmap", "FULL_OPENCV", [-0.22, 0.06, 0.002, -0.003, 0.01, 0.03, 0.005, 0.001],
                           "perspective", (-0.22, 0.06, 0.002, -0.003, 0.01, 0.03, 0.005, 0.001)),
    "colmap-OPENCV_FISHEYE": ("colmap", "OPENCV_FISHEYE", [0.04, -0.01, 0.002, -0.0005], "fisheye",
                              (0.04, -0.01, 0.002, -0.0005)),
    "colmap-RADIAL_FISHEYE": ("colmap", "RADIAL_FISHEYE", [0.04, -0.01], "fisheye", (0.04, -0.01, 0, 0)),
    "colmap-SIMPLE_RADIAL_FISHEYE": ("colmap", "SIMPLE_RADIAL_FISHEYE", [0.04], "fisheye", (0.04, 0, 0, 0)),
    # nerfstudio's perspective k3 is the r^6 term: OpenCV's fifth coefficient.
    "nerfstudio-OPENCV": ("nerfstudio", "OPENCV", {"k1": -0.22, "k2": 0.06, "k3": -0.01, "p1": 0.002,
                                                   "p2": -0.003},
                          "perspective", (-0.22, 0.06, 0.002, -0.003, -0.01)),
    "nerfstudio-OPENCV_FISHEYE": ("nerfstudio", "OPENCV_FISHEYE",
                                  {"k1": 0.04, "k2": -0.01, "k3": 0.002, "k4": -0.0005},
                                  "fisheye", (0.04, -0.01, 0.002, -0.0005)),
    "instant-ngp-fisheye": ("nerfstudio", None, {"is_fisheye": True, "k1": 0.04, "k2": -0.01},
                            "fisheye", (0.04, -0.01, 0, 0)),
}
SINGLE_FOCAL = {"SIMPLE_RADIAL", "RADIAL", "RADIAL_FISHEYE", "SIMPLE_RADIAL_FISHEYE"}


def case_intrinsics(model, kind) -> tuple[float, float, float, float]:
    f = FISHEYE_F if kind == "fisheye" else FX
    fy = f if model in SINGLE_FOCAL or model is None else f * FY / FX
    return f, fy, CX, CY


def write_case_scene(root: Path, case: str, images: list[np.ndarray], cameras: list[Camera]) -> None:
    """``images`` as images/frame_0000k.png and the cameras with the case's lens model."""
    fmt, model, params, kind, _ = CASES[case]
    names = [f"frame_{k + 1:05d}.png" for k in range(len(images))]
    for name, img in zip(names, images):
        (root / "images").mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(root / "images" / name), img)
    fx, fy, cx, cy = case_intrinsics(model, kind)
    if fmt == "colmap":
        write_colmap_text(root / "sparse" / "0", cameras, names)
        focal = [fx] if model in SINGLE_FOCAL else [fx, fy]
        values = " ".join(repr(float(v)) for v in [*focal, cx, cy, *params])
        (root / "sparse" / "0" / "cameras.txt").write_text(f"1 {model} {W} {H} {values}\n")
    else:
        write_transforms(root, cameras, [f"images/{n}" for n in names])
        meta = json.loads((root / "transforms.json").read_text())
        meta.pop("camera_model")
        if model is not None:
            meta["camera_model"] = model
        meta.update(params)
        (root / "transforms.json").write_text(json.dumps(meta))


# ============================================================================ geometry
@pytest.mark.parametrize("case", list(CASES))
def test_undistorted_pixels_come_from_where_opencv_distorts_them(tmp_path: Path, case: str) -> None:
    """Each loaded pinhole view, at the projection of a 3D point, holds the distorted pixel
    that OpenCV's model (with the file's coefficients) projects that point to."""
    fmt, model, _, kind, D = CASES[case]
    intr = case_intrinsics(model, kind)
    cams = two_cameras(*intr)
    write_case_scene(tmp_path / "scene", case, [coordinate_image(W, H)] * 2, cams)
    scene = load_scene(tmp_path / "scene", cache_dir=tmp_path / "cache")

    assert scene.undistorted_from.endswith(model or "OPENCV_FISHEYE")
    assert scene.num_undistorted == 2 and scene.image_names == ["frame_00001", "frame_00002"]
    assert all(p.is_relative_to(tmp_path / "cache" / "undistorted") and p.suffix == ".png"
               for p in scene.image_paths)
    rng = np.random.default_rng(0)
    for cam, orig, path in zip(scene.cameras, cams, scene.image_paths):
        assert (cam.width, cam.height) == (W, H)
        np.testing.assert_allclose(cam.R, orig.R, atol=1e-12)  # the pose does not change
        np.testing.assert_allclose(cam.t, orig.t, atol=1e-12)
        loaded = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        assert loaded.dtype == np.uint16 and loaded.shape == (H, W, 3)  # lossless, same depth

        uv = rng.uniform([1, 1], [W - 1, H - 1], size=(500, 2))
        X = cam.unproject(uv, rng.uniform(1.0, 3.0, size=500))  # world points seen at uv
        np.testing.assert_allclose(cam.project(X)[0], uv, atol=1e-9)
        came_from = decode(bilinear(loaded.astype(np.float64), uv), W, H)
        expected = reference_distort(orig.world_to_cam_points(X), intr, kind, D)
        err = np.linalg.norm(came_from - expected, axis=1)
        assert err.max() < 0.1, f"{case}: max error {err.max():.4f} px"

        # No invalid border: every output pixel comes from inside the photo (between the
        # outermost pixel centres) ...
        src = decode(loaded, W, H)
        assert src[..., 0].min() > 0.5 - 0.01 and src[..., 0].max() < W - 0.5 + 0.01
        assert src[..., 1].min() > 0.5 - 0.01 and src[..., 1].max() < H - 0.5 + 0.01
        # ... and the crop is no larger than needed: on one axis the output spans the photo.
        spans = [(src[..., a].min() < 0.5 + 0.05) and (src[..., a].max() > size - 0.5 - 0.05)
                 for a, size in ((0, W), (1, H))]
        assert any(spans), f"{case}: the crop could be wider"


def test_images_smaller_than_the_camera(tmp_path: Path) -> None:
    """Images stored at half the calibrated size (same aspect) are undistorted at their own
    size, with the camera scaled to it (pixel centres at +0.5)."""
    _, model, _, kind, D = CASES["colmap-OPENCV"]
    intr = case_intrinsics(model, kind)
    cams = two_cameras(*intr)
    write_case_scene(tmp_path / "scene", "colmap-OPENCV", [coordinate_image(W // 2, H // 2)] * 2, cams)
    scene = load_scene(tmp_path / "scene", cache_dir=tmp_path / "cache")
    cam, orig = scene.cameras[0], cams[0]
    assert (cam.width, cam.height) == (W, H) and scene.image(0).shape == (H, W, 3)
    loaded = cv2.imread(str(scene.image_paths[0]), cv2.IMREAD_UNCHANGED)
    assert loaded.shape == (H // 2, W // 2, 3)
    uv = np.random.default_rng(2).uniform([2, 2], [W - 2, H - 2], size=(300, 2))
    X = cam.unproject(uv, np.full(300, 2.0))
    came_from = 2 * decode(bilinear(loaded.astype(np.float64), uv / 2), W // 2, H // 2)
    expected = reference_distort(orig.world_to_cam_points(X), intr, kind, D)
    assert np.linalg.norm(came_from - expected, axis=1).max() < 0.1


def test_fisheye_wider_than_a_pinhole_can_show(tmp_path: Path) -> None:
    """A fisheye seeing 110 degrees off-axis at the edge midpoints: the pinhole view is
    cropped to 80 degrees off-axis and still maps exactly, with no pixel outside the photo."""
    intr, D = (25.0, 25.0, 48.0, 36.0), (0.01, 0.0, 0.0, 0.0)
    cams = two_cameras(*intr)
    write_case_scene(tmp_path / "scene", "colmap-SIMPLE_RADIAL_FISHEYE", [coordinate_image(W, H)] * 2, cams)
    (tmp_path / "scene" / "sparse" / "0" / "cameras.txt").write_text(
        f"1 SIMPLE_RADIAL_FISHEYE {W} {H} 25.0 48.0 36.0 0.01\n")
    scene = load_scene(tmp_path / "scene", cache_dir=tmp_path / "cache")
    cam = scene.cameras[0]
    half_angle = math.degrees(math.atan((W / 2) / cam.fx))
    assert 79.0 < half_angle < 80.5
    loaded = cv2.imread(str(scene.image_paths[0]), cv2.IMREAD_UNCHANGED)
    src = decode(loaded, W, H)
    assert src[..., 0].min() > 0.49 and src[..., 0].max() < W - 0.49
    assert src[..., 1].min() > 0.49 and src[..., 1].max() < H - 0.49
    uv = np.random.default_rng(3).uniform([1, 1], [W - 1, H - 1], size=(300, 2))
    X = cam.unproject(uv, np.full(300, 2.0))
    came_from = decode(bilinear(loaded.astype(np.float64), uv), W, H)
    expected = reference_distort(cams[0].world_to_cam_points(X), intr, "fisheye", D)
    assert np.linalg.norm(came_from - expected, axis=1).max() < 0.1


@pytest.mark.parametrize("case", [c for c in CASES if c.startswith("colmap-")])
def test_reference_matches_colmap(case: str) -> None:
    """The test's OpenCV reference (coefficient order and the half-pixel shift) is COLMAP's
    own projection for each COLMAP model."""
    pycolmap = pytest.importorskip("pycolmap")
    _, model, params, kind, D = CASES[case]
    fx, fy, cx, cy = case_intrinsics(model, kind)
    focal = [fx] if model in SINGLE_FOCAL else [fx, fy]
    camera = pycolmap.Camera(model=model, width=W, height=H, params=[*focal, cx, cy, *params])
    rng = np.random.default_rng(1)
    pts = np.concatenate([rng.uniform(-0.6, 0.6, size=(200, 2)), np.ones((200, 1))], axis=1)
    np.testing.assert_allclose(reference_distort(pts, (fx, fy, cx, cy), kind, D),
                               camera.img_from_cam(pts), atol=1e-6)


# ============================================================================ demo scene
@pytest.fixture(scope="module")
def demo(tmp_path_factory) -> Path:
    from n2f2.data.synthetic import generate_demo_scene

    return generate_demo_scene(tmp_path_factory.mktemp("demo") / "scene", num_views=3, width=W, height=H,
                               supersample=1, num_points=900, labelled_views=[], show_progress=False)


# Distorted camera: zoomed in and off-centre, so every distorted pixel sees the demo render.
DEMO_LENSES = {
    "nerfstudio-OPENCV": ("nerfstudio", {"k1": -0.2, "k2": 0.04, "p1": 0.003, "p2": -0.002},
                          (-0.2, 0.04, 0.003, -0.002)),
    "colmap-SIMPLE_RADIAL": ("colmap", ("SIMPLE_RADIAL", [-0.2]), (-0.2, 0, 0, 0)),
    "colmap-OPENCV": ("colmap", ("OPENCV", [-0.2, 0.04, 0.003, -0.002]), (-0.2, 0.04, 0.003, -0.002)),
}


def write_distorted_demo(demo: Path, out: Path, case: str) -> tuple[tuple, tuple, list[np.ndarray]]:
    """Distort the demo renders with the case's lens and write them as a scene of that format.
    Returns the distorted intrinsics, the OpenCV coefficients and the ideal renders."""
    fmt, spec, D = DEMO_LENSES[case]
    ideal = load_scene(demo)
    c0 = ideal.cameras[0]
    intr = (c0.fx * 1.2, c0.fx * 1.2, c0.cx + 1.3, c0.cy - 0.7)
    v, u = np.mgrid[0:H, 0:W] + 0.5
    normalized = reference_undistort(np.stack([u.ravel(), v.ravel()], 1), intr, D)
    from_ideal = normalized * [c0.fx, c0.fy] + [c0.cx, c0.cy]
    assert from_ideal.min() > 0.5 and (from_ideal < [W - 0.5, H - 0.5]).all()  # all real render
    renders = [ideal.image(i).astype(np.float64) for i in range(len(ideal))]
    for i, img in enumerate(renders):
        distorted = bilinear(img, from_ideal).reshape(H, W, 3)
        write_png(out / "images" / ideal.image_paths[i].name, distorted.astype(np.float32))
    if fmt == "nerfstudio":
        meta = json.loads((demo / "transforms.json").read_text())
        meta.update({"fl_x": intr[0], "fl_y": intr[1], "cx": intr[2], "cy": intr[3], **spec})
        (out / "transforms.json").write_text(json.dumps(meta))
        shutil.copy(demo / "sparse_pc.ply", out / "sparse_pc.ply")
    else:
        model, params = spec
        shutil.copytree(demo / "sparse", out / "sparse")
        focal = [intr[0]] if model == "SIMPLE_RADIAL" else [intr[0], intr[1]]
        values = " ".join(repr(float(x)) for x in [*focal, intr[2], intr[3], *params])
        (out / "sparse" / "0" / "cameras.txt").write_text(f"1 {model} {W} {H} {values}\n")
    return intr, D, renders


@pytest.mark.parametrize("case", list(DEMO_LENSES))
def test_demo_scene_round_trip(demo: Path, tmp_path: Path, case: str) -> None:
    """Distorted demo renders load back as pinhole views that agree with the ideal renders
    at the projections of the scene's own 3D points; the cache is reused and the user's
    folder is left as it was."""
    scene_dir, cache = tmp_path / "scene", tmp_path / "cache"
    intr, D, renders = write_distorted_demo(demo, scene_dir, case)
    before = tree_digest(scene_dir)
    scene = load_scene(scene_dir, cache_dir=cache)
    ideal = load_scene(demo)
    assert scene.root == scene_dir and scene.image_names == ideal.image_names
    assert scene.num_undistorted == 3
    np.testing.assert_array_equal(scene.points, ideal.points)  # sparse points stay as they are

    # Compared through a 1-pixel Gaussian blur, which takes out the difference between one
    # and two bilinear resamplings of the aliased renders but not a misplaced pixel.
    def blur(image: np.ndarray) -> np.ndarray:
        return cv2.GaussianBlur(image, (0, 0), 1.0)

    points_view = np.load(demo / "points_source.npy")[:, 0]
    for i in range(len(scene)):
        X = ideal.points[points_view == i]  # surface points visible in view i
        uv, _ = scene.cameras[i].project(X)
        inside = ((uv > 1.5) & (uv < [W - 1.5, H - 1.5])).all(axis=1)
        assert inside.mean() > 0.6
        uv, X = uv[inside], X[inside]
        want = bilinear(blur(renders[i]), ideal.cameras[i].project(X)[0])
        loaded = blur(scene.image(i).astype(np.float64))
        error = np.abs(bilinear(loaded, uv) - want).mean()
        # Controls: the same image half a pixel off, and the distorted photo used as pinhole.
        half_pixel_off = np.abs(bilinear(loaded, uv + [0.5, 0.0]) - want).mean()
        naive = Camera(*intr, W, H, R=scene.cameras[i].R, t=scene.cameras[i].t)
        raw = cv2.cvtColor(cv2.imread(str(scene.original_image_paths[i])), cv2.COLOR_BGR2RGB) / 255.0
        ignored = np.abs(bilinear(blur(raw), naive.project(X)[0]) - want).mean()
        assert error < 0.5 * half_pixel_off and error < 0.3 * ignored, (i, error, half_pixel_off, ignored)

    # Cache: a second load writes nothing and reads the same files.
    cached = tree_digest(cache)
    assert len(cached) == 3
    again = load_scene(scene_dir, cache_dir=cache)
    assert again.image_paths == scene.image_paths and tree_digest(cache) == cached
    for a, b in zip(again.cameras, scene.cameras):
        np.testing.assert_array_equal(a.K, b.K)
    # Downscaling applies after undistortion.
    half = load_scene(scene_dir, downscale=2, cache_dir=cache)
    assert tree_digest(cache) == cached and half.image_paths == scene.image_paths
    assert half.image(0).shape == (H // 2, W // 2, 3)
    assert half.cameras[0].fx == pytest.approx(scene.cameras[0].fx / 2)
    # A changed image is undistorted again.
    first = scene.original_image_paths[0]
    os.utime(first, ns=(first.stat().st_atime_ns, first.stat().st_mtime_ns + 10**9))
    before[str(first.relative_to(scene_dir))] = (before[str(first.relative_to(scene_dir))][0],
                                                 first.stat().st_mtime_ns)
    changed = load_scene(scene_dir, cache_dir=cache)
    assert changed.image_paths[0] != scene.image_paths[0] and changed.image_paths[1:] == scene.image_paths[1:]
    assert tree_digest(scene_dir) == before  # the user's folder: same files, same bytes


def test_cache_location_and_atomic_writes(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """``$N2F2_CACHE_DIR`` is the default cache; a write interrupted before its rename leaves
    nothing that a later load would take for a finished image."""
    write_case_scene(tmp_path / "scene", "colmap-OPENCV", [coordinate_image(W, H)] * 2,
                     two_cameras(*case_intrinsics("OPENCV", "perspective")))
    monkeypatch.setenv("N2F2_CACHE_DIR", str(tmp_path / "env-cache"))
    real_replace = os.replace

    def crash(src, dst):
        raise KeyboardInterrupt

    monkeypatch.setattr("n2f2.io.os.replace", crash)
    with pytest.raises(KeyboardInterrupt):
        load_scene(tmp_path / "scene")
    assert not [p for p in (tmp_path / "env-cache").rglob("*") if p.is_file()]
    monkeypatch.setattr("n2f2.io.os.replace", real_replace)
    scene = load_scene(tmp_path / "scene")
    assert all(p.is_relative_to(tmp_path / "env-cache" / "undistorted") and p.is_file() for p in scene.image_paths)


def test_unsupported_lenses_are_one_clear_error(tmp_path: Path) -> None:
    write_case_scene(tmp_path, "nerfstudio-OPENCV", [coordinate_image(W, H)] * 2,
                     two_cameras(*case_intrinsics("OPENCV", "perspective")))
    meta = json.loads((tmp_path / "transforms.json").read_text())
    for edit, fragment in (({"k4": 0.01}, "k4"), ({"camera_model": "EQUIRECTANGULAR"}, "EQUIRECTANGULAR"),
                           ({"camera_model": "OPENCV_FISHEYE", "p1": 0.01}, "p1")):
        (tmp_path / "transforms.json").write_text(json.dumps({**meta, **edit}))
        with pytest.raises(InputError, match=fragment) as e:
            load_scene(tmp_path, cache_dir=tmp_path / "cache")
        assert e.value.path.name == "transforms.json"
    # A strong barrel that folds over inside the image cannot be inverted there.
    (tmp_path / "transforms.json").write_text(json.dumps({**meta, "k1": -0.9, "k2": 0.0, "k3": 0.0}))
    with pytest.raises(InputError, match="cannot undistort"):
        load_scene(tmp_path, cache_dir=tmp_path / "cache")


# ============================================================================ missing images
@pytest.mark.parametrize("fmt", ["nerfstudio", "colmap"])
def test_missing_images(tmp_path: Path, fmt: str, capsys: pytest.CaptureFixture) -> None:
    n = 9
    cams = [Camera(40.0, 40.0, 16.0, 12.0, 32, 24, R=look_at([3 * math.cos(k), 3 * math.sin(k), 1.0],
                                                                [0, 0, 0])[0],
                   t=look_at([3 * math.cos(k), 3 * math.sin(k), 1.0], [0, 0, 0])[1]) for k in range(n)]
    names = [f"frame_{k + 1:05d}.png" for k in range(n)]
    for name in names:
        write_png(tmp_path / "images" / name, np.zeros((24, 32, 3), np.uint8))
    if fmt == "nerfstudio":
        write_transforms(tmp_path, cams, [f"images/{x}" for x in names])
    else:
        write_colmap_text(tmp_path / "sparse" / "0", cams, names)
    gone = [1, 2, 4, 5, 6, 7, 8]
    for k in gone:
        (tmp_path / "images" / names[k]).unlink()
    listing = "transforms.json" if fmt == "nerfstudio" else "images.txt"

    with pytest.raises(InputError) as e:
        load_scene(tmp_path, format=fmt)
    assert e.value.path.name == listing
    message = str(e.value)
    assert "7 of the 9 images" in message and "and 2 more" in message
    assert all(f"images/{names[k]}" in message for k in gone[:5])
    assert not any(names[k] in message for k in gone[5:]) and names[0] not in message

    scene = load_scene(tmp_path, format=fmt, skip_missing=True)
    assert scene.image_names == ["frame_00001", "frame_00004"]
    for got, k in zip(scene.cameras, [0, 3]):
        np.testing.assert_allclose(got.R, cams[k].R, atol=1e-9)
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "skipping 7 of 9 views" in err[0]

    assert main(["inspect", str(tmp_path), "--format", fmt, "--skip-missing"]) == 0
    assert main(["inspect", str(tmp_path), "--format", fmt]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and "skipping 7 of 9" in err[0]  # the warning of the first run
    assert "error" in err[1] and "7 of the 9 images" in err[1]


def test_inspect_reports_undistortion(tmp_path: Path, capsys: pytest.CaptureFixture,
                                      monkeypatch: pytest.MonkeyPatch) -> None:
    write_case_scene(tmp_path / "scene", "colmap-SIMPLE_RADIAL", [coordinate_image(W, H)] * 2,
                     two_cameras(*case_intrinsics("SIMPLE_RADIAL", "perspective")))
    monkeypatch.setenv("N2F2_CACHE_DIR", str(tmp_path / "cache"))
    assert main(["inspect", str(tmp_path / "scene"), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["undistorted_views"] == 2 and info["undistorted_from"] == "COLMAP SIMPLE_RADIAL"
    assert info["undistorted_cache"] == str(tmp_path / "cache" / "undistorted")
    assert info["image_folder"] == ["images"]
    assert main(["inspect", str(tmp_path / "scene")]) == 0
    assert "2 views from COLMAP SIMPLE_RADIAL" in capsys.readouterr().out
