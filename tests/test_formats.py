"""Scene formats: COLMAP (binary, text), nerfstudio transforms.json, downscaling, bad input.

Expected values come from hand-built files (struct-packed binaries, hand-written text/JSON
with known projections) or from the synthetic cameras the files were written from."""

from __future__ import annotations

import json
import math
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from n2f2.cameras import Camera, look_at
from n2f2.data import load_scene
from n2f2.data.colmap import (read_colmap_model, read_colmap_scene, write_colmap_binary,
                              write_colmap_text)
from n2f2.data.nerfstudio import read_ply_points, read_transforms, write_ply_points, write_transforms
from n2f2.errors import InputError
from n2f2.io import write_png

W, H = 32, 24


def make_cameras(n: int = 4, per_camera_intrinsics: bool = False) -> list[Camera]:
    cams = []
    for k in range(n):
        a = 2 * math.pi * k / n
        R, t = look_at([3 * math.cos(a), 3 * math.sin(a), 1.0 + 0.1 * k], [0.1, -0.2, 0.3])
        f = 40.0 + (3.5 * k if per_camera_intrinsics else 0.0)
        cams.append(Camera(f, f * 1.01, W / 2 + 0.25, H / 2 - 0.5, W, H, R=R, t=t))
    return cams


def names(n: int) -> list[str]:
    return [f"frame_{k + 1:05d}.png" for k in range(n)]


def write_images(root: Path, n: int, seed: int = 0, folder: str = "images", size=(W, H)) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    images = []
    for name in names(n):
        img = rng.integers(0, 256, size=(size[1], size[0], 3), dtype=np.uint8)
        write_png(root / folder / name, img)
        images.append(img)
    return images


def assert_same_camera(a: Camera, b: Camera, tol: float = 1e-9) -> None:
    assert (a.width, a.height) == (b.width, b.height)
    np.testing.assert_allclose(a.K, b.K, atol=tol, rtol=0)
    np.testing.assert_allclose(a.R, b.R, atol=tol, rtol=0)
    np.testing.assert_allclose(a.t, b.t, atol=tol, rtol=0)


@pytest.fixture
def scene_dir(tmp_path: Path) -> Path:
    """Both formats describing the same 4 cameras, points and images."""
    cams = make_cameras(4)
    write_images(tmp_path, 4)
    pts = np.random.default_rng(1).normal(size=(20, 3))
    cols = np.random.default_rng(2).integers(0, 256, size=(20, 3), dtype=np.uint8)
    write_colmap_binary(tmp_path / "sparse" / "0", cams, names(4), pts, cols)
    write_transforms(tmp_path, cams, [f"images/{n}" for n in names(4)], pts, cols)
    return tmp_path


# ===================================================================== COLMAP round trips
@pytest.mark.parametrize("per_camera", [False, True])
def test_colmap_binary_and_text_round_trip(tmp_path: Path, per_camera: bool) -> None:
    cams = make_cameras(5, per_camera_intrinsics=per_camera)
    pts = np.random.default_rng(0).normal(size=(50, 3))
    cols = np.random.default_rng(1).integers(0, 256, size=(50, 3), dtype=np.uint8)
    write_colmap_binary(tmp_path / "bin", cams, names(5), pts, cols)
    write_colmap_text(tmp_path / "txt", cams, names(5), pts, cols)
    scenes = [read_colmap_scene(tmp_path / d) for d in ("bin", "txt")]
    assert [s.kind for s in scenes] == ["binary", "text"]
    for s in scenes:
        assert s.image_names == names(5)
        for got, want in zip(s.cameras, cams):
            assert_same_camera(got, want)
        np.testing.assert_array_equal(s.points, pts)
        np.testing.assert_array_equal(s.colors, cols)
    raw_bin, raw_txt = read_colmap_model(tmp_path / "bin"), read_colmap_model(tmp_path / "txt")
    assert raw_bin[0] == raw_txt[0] and raw_bin[1] == raw_txt[1]  # cameras, images identical
    # One COLMAP camera per distinct intrinsics.
    assert len(raw_bin[0]) == (5 if per_camera else 1)


def test_colmap_without_points(tmp_path: Path) -> None:
    write_colmap_text(tmp_path, make_cameras(2), names(2))
    assert read_colmap_scene(tmp_path).points is None


def test_colmap_binary_layout_known_answer(tmp_path: Path) -> None:
    """Hand-packed COLMAP binaries: SIMPLE_PINHOLE, identity rotation, known translation."""
    (tmp_path / "cameras.bin").write_bytes(
        struct.pack("<Q", 1) + struct.pack("<iiQQddd", 7, 0, 100, 80, 90.0, 50.0, 40.0))
    img = struct.pack("<idddddddi", 3, 1.0, 0.0, 0.0, 0.0, 1.0, 2.0, 3.0, 7) + b"a.png\x00"
    img += struct.pack("<Q", 2) + struct.pack("<ddq", 1.0, 2.0, -1) * 2  # 2D points are skipped
    (tmp_path / "images.bin").write_bytes(struct.pack("<Q", 1) + img)
    pt = struct.pack("<QdddBBBd", 1, 0.5, -0.5, 2.0, 10, 20, 30, 0.1) + struct.pack("<Q", 2) + struct.pack("<ii", 3, 0) * 2
    (tmp_path / "points3D.bin").write_bytes(struct.pack("<Q", 1) + pt)
    s = read_colmap_scene(tmp_path)
    c = s.cameras[0]
    assert (c.fx, c.fy, c.cx, c.cy, c.width, c.height) == (90.0, 90.0, 50.0, 40.0, 100, 80)
    np.testing.assert_array_equal(c.R, np.eye(3))
    np.testing.assert_array_equal(c.center, [-1.0, -2.0, -3.0])
    np.testing.assert_array_equal(s.points, [[0.5, -0.5, 2.0]])
    np.testing.assert_array_equal(s.colors, [[10, 20, 30]])


def test_colmap_text_quaternion_is_world_to_camera(tmp_path: Path) -> None:
    """A 90 degree rotation about z, written by hand: world +x must map to camera +y."""
    (tmp_path / "cameras.txt").write_text("# comment\n1 PINHOLE 64 48 100 100 32 24\n")
    h = math.sqrt(0.5)
    (tmp_path / "images.txt").write_text(f"# c\n1 {h} 0 0 {h} 0 0 5 1 x.png\n\n")
    c = read_colmap_scene(tmp_path).cameras[0]
    np.testing.assert_allclose(c.world_to_cam_points([1.0, 0.0, 0.0]), [0.0, 1.0, 5.0], atol=1e-12)
    uv, z = c.project(np.array([1.0, 0.0, 0.0]))
    np.testing.assert_allclose(uv, [32.0, 24.0 + 100.0 / 5.0], atol=1e-12)
    assert z == pytest.approx(5.0)


def test_colmap_zero_distortion_model_is_accepted(tmp_path: Path) -> None:
    (tmp_path / "cameras.txt").write_text("1 OPENCV 64 48 100 110 32 24 0 0 0 0\n")
    (tmp_path / "images.txt").write_text("1 1 0 0 0 0 0 0 1 x.png\n\n")
    c = read_colmap_scene(tmp_path).cameras[0]
    assert (c.fx, c.fy, c.cx, c.cy) == (100.0, 110.0, 32.0, 24.0)


@pytest.mark.parametrize("line, kind, coeffs", [
    # OpenCV's distCoeffs order is (k1, k2, p1, p2, k3, k4, k5, k6); cv2.fisheye's (k1..k4).
    ("1 OPENCV 64 48 100 110 32 24 0.1 0 0.01 0.02", "perspective", (0.1, 0, 0.01, 0.02, 0, 0, 0, 0)),
    ("1 SIMPLE_RADIAL 64 48 100 32 24 -0.02", "perspective", (-0.02, 0, 0, 0, 0, 0, 0, 0)),
    ("1 FULL_OPENCV 64 48 100 110 32 24 1 2 3 4 5 6 7 8", "perspective", (1, 2, 3, 4, 5, 6, 7, 8)),
    ("1 OPENCV_FISHEYE 64 48 100 110 32 24 0 0 0 0", "fisheye", (0, 0, 0, 0)),
    ("1 RADIAL_FISHEYE 64 48 100 32 24 0.1 0.2", "fisheye", (0.1, 0.2, 0, 0)),
])
def test_colmap_distorted_model_reads_its_lens(tmp_path: Path, line: str, kind: str, coeffs: tuple) -> None:
    (tmp_path / "cameras.txt").write_text(line + "\n")
    (tmp_path / "images.txt").write_text("1 1 0 0 0 0 0 0 1 x.png\n\n")
    s = read_colmap_scene(tmp_path)
    c, lens = s.cameras[0], s.lenses[0]
    assert (c.fx, c.cx, c.cy) == (100.0, 32.0, 24.0)
    assert (lens.kind, lens.coeffs) == (kind, coeffs)
    assert lens.name == "COLMAP " + line.split()[1]


@pytest.mark.parametrize("line", ["1 FOV 64 48 100 110 32 24 0.3",
                                  "1 THIN_PRISM_FISHEYE 64 48 100 110 32 24 0 0 0 0 0 0 0 0"])
def test_colmap_unsupported_model_is_rejected(tmp_path: Path, line: str) -> None:
    (tmp_path / "cameras.txt").write_text(line + "\n")
    (tmp_path / "images.txt").write_text("1 1 0 0 0 0 0 0 1 x.png\n\n")
    with pytest.raises(InputError, match="image_undistorter") as e:
        read_colmap_scene(tmp_path)
    assert e.value.path.name == "cameras.txt"


# ===================================================================== nerfstudio
def test_transforms_round_trip_global_intrinsics(scene_dir: Path) -> None:
    meta = json.loads((scene_dir / "transforms.json").read_text())
    assert meta["fl_x"] == 40.0 and "fl_x" not in meta["frames"][0]
    data = read_transforms(scene_dir)
    for got, want in zip(data.cameras, make_cameras(4)):
        assert_same_camera(got, want)
    assert [p.name for p in data.image_paths] == names(4)
    np.testing.assert_array_equal(data.points, np.random.default_rng(1).normal(size=(20, 3)))


def test_transforms_round_trip_per_frame_intrinsics(tmp_path: Path) -> None:
    cams = make_cameras(3, per_camera_intrinsics=True)
    write_transforms(tmp_path / "transforms.json", cams, names(3))
    meta = json.loads((tmp_path / "transforms.json").read_text())
    assert "fl_x" not in meta and [f["fl_x"] for f in meta["frames"]] == [40.0, 43.5, 47.0]
    for got, want in zip(read_transforms(tmp_path).cameras, cams):
        assert_same_camera(got, want)


def test_transforms_opengl_known_answer(tmp_path: Path) -> None:
    """Identity OpenGL c2w: the camera sits at the origin looking down world -z, world +y is
    image-up. Per-frame fl_x overrides the global one."""
    meta = {"fl_x": 10.0, "fl_y": 20.0, "cx": 16.0, "cy": 12.0, "w": 32, "h": 24,
            "frames": [{"file_path": "a.png", "fl_x": 30.0, "transform_matrix": np.eye(4).tolist()}]}
    (tmp_path / "transforms.json").write_text(json.dumps(meta))
    c = read_transforms(tmp_path).cameras[0]
    assert (c.fx, c.fy) == (30.0, 20.0)
    uv, z = c.project(np.array([[0.0, 0.0, -2.0], [1.0, 0.0, -2.0], [0.0, 1.0, -2.0]]))
    np.testing.assert_allclose(z, [2.0, 2.0, 2.0])
    np.testing.assert_allclose(uv, [[16.0, 12.0], [16.0 + 15.0, 12.0], [16.0, 12.0 - 10.0]])


def test_transforms_blender_camera_angle(tmp_path: Path) -> None:
    write_images(tmp_path, 1, folder="train")
    angle = 2 * math.atan(16.0 / 40.0)  # 32 px wide, focal 40 px
    meta = {"camera_angle_x": angle,
            "frames": [{"file_path": "./train/frame_00001", "transform_matrix": np.eye(4).tolist()}]}
    (tmp_path / "transforms.json").write_text(json.dumps(meta))
    scene = load_scene(tmp_path)
    c = scene.cameras[0]
    assert (c.width, c.height) == (W, H)
    assert c.fx == pytest.approx(40.0) and c.fy == pytest.approx(40.0)
    assert (c.cx, c.cy) == (16.0, 12.0)
    assert scene.image_paths[0].name == "frame_00001.png"


def test_ply_ascii_and_binary(tmp_path: Path) -> None:
    (tmp_path / "a.ply").write_text(
        "ply\nformat ascii 1.0\ncomment hi\nelement vertex 2\nproperty float x\nproperty float y\n"
        "property float z\nproperty uchar red\nproperty uchar green\nproperty uchar blue\n"
        "element face 0\nproperty list uchar int vertex_indices\nend_header\n"
        "1 2 3 255 0 7\n-1.5 0 0.25 1 2 3\n")
    pts, cols = read_ply_points(tmp_path / "a.ply")
    np.testing.assert_array_equal(pts, [[1, 2, 3], [-1.5, 0, 0.25]])
    np.testing.assert_array_equal(cols, [[255, 0, 7], [1, 2, 3]])
    write_ply_points(tmp_path / "b.ply", pts, cols)
    pts2, cols2 = read_ply_points(tmp_path / "b.ply")
    np.testing.assert_array_equal(pts2, pts)
    np.testing.assert_array_equal(cols2, cols)


# ===================================================================== load_scene
def test_both_formats_give_the_same_scene(scene_dir: Path) -> None:
    ns = load_scene(scene_dir)
    cm = load_scene(scene_dir, format="colmap")
    assert (ns.source_format, cm.source_format) == ("nerfstudio", "colmap-binary")
    assert ns.image_paths == cm.image_paths
    for a, b in zip(ns.cameras, cm.cameras):
        assert_same_camera(a, b)
    np.testing.assert_array_equal(ns.points, cm.points)
    assert ns.ground_truth is None
    (scene_dir / "regions.json").write_text("{}")
    assert load_scene(scene_dir).ground_truth.image_names == [n[:-4] for n in names(4)]


def test_colmap_text_and_sparse_dir_layouts(tmp_path: Path) -> None:
    cams = make_cameras(3)
    write_images(tmp_path, 3)
    write_colmap_text(tmp_path / "sparse", cams, names(3))  # sparse/ directly, text
    s = load_scene(tmp_path)
    assert s.source_format == "colmap-text" and len(s) == 3
    s2 = load_scene(tmp_path / "sparse")  # the model folder itself
    assert s2.image_paths == s.image_paths


def test_views_are_sorted_by_file_name(tmp_path: Path) -> None:
    cams = make_cameras(4)
    write_images(tmp_path, 4)
    order = [2, 0, 3, 1]
    write_transforms(tmp_path, [cams[i] for i in order], [f"images/{names(4)[i]}" for i in order])
    write_colmap_binary(tmp_path / "sparse" / "0", [cams[i] for i in order], [names(4)[i] for i in order])
    for fmt in ("nerfstudio", "colmap"):
        s = load_scene(tmp_path, format=fmt)
        assert [p.name for p in s.image_paths] == names(4)
        for got, want in zip(s.cameras, cams):
            assert_same_camera(got, want)


def test_downscale_halves_intrinsics_and_images(scene_dir: Path) -> None:
    full = load_scene(scene_dir)
    half = load_scene(scene_dir, downscale=2)
    pts = np.random.default_rng(3).normal(size=(30, 3)) * 0.3
    for a, b in zip(full.cameras, half.cameras):
        assert (b.width, b.height) == (W // 2, H // 2)
        assert (b.fx, b.fy, b.cx, b.cy) == pytest.approx((a.fx / 2, a.fy / 2, a.cx / 2, a.cy / 2))
        # Pixel centres at +0.5: a continuous position scales exactly by the factor.
        np.testing.assert_allclose(b.project(pts)[0], a.project(pts)[0] / 2, atol=1e-9)
    assert half.image(0).shape == (H // 2, W // 2, 3)
    assert full.image(0).shape == (H, W, 3)


def test_downscale_keeps_edges_in_place(tmp_path: Path) -> None:
    """Left 12 columns black, rest white: after /2 the edge sits at column 6 (pixel-centre
    convention), and a non-integer factor keeps camera and image sizes consistent."""
    img = np.full((H, W, 3), 255, np.uint8)
    img[:, :12] = 0
    write_png(tmp_path / "images" / "frame_00001.png", img)
    write_transforms(tmp_path, make_cameras(1), ["images/frame_00001.png"])
    half = load_scene(tmp_path, downscale=2).image(0)
    assert half[:, :5].max() < 0.05 and half[:, 7:].min() > 0.95
    assert 0.2 < half[:, 5:7].mean() < 0.8
    third = load_scene(tmp_path, downscale=3)
    c = third.cameras[0]
    assert (c.width, c.height) == (round(W / 3), round(H / 3))
    assert third.image(0).shape == (c.height, c.width, 3)
    assert c.fx == pytest.approx(40.0 * c.width / W)


def test_downscale_uses_predownscaled_folder(scene_dir: Path) -> None:
    small = write_images(scene_dir, 4, seed=9, folder="images_2", size=(W // 2, H // 2))
    s = load_scene(scene_dir, downscale=2)
    assert all(p.parent.name == "images_2" for p in s.image_paths)
    np.testing.assert_allclose(s.image(1), small[1] / 255.0, atol=1e-6)
    (scene_dir / "images_2" / names(4)[3]).unlink()  # incomplete folder: fall back
    assert all(p.parent.name == "images" for p in load_scene(scene_dir, downscale=2).image_paths)


def test_downscaled_camera_rounding_is_not_an_aspect_ratio_error(scene_dir: Path, tmp_path: Path) -> None:
    """A 739x492 photo at downscale 8: the camera is round(92.4) x round(61.5) = 92 x 62,
    whose aspect differs from the photo's by the rounding of one camera pixel (6 photo pixels)."""
    from n2f2.cameras import Camera
    from n2f2.data import _check_aspect_ratios

    photo = tmp_path / "photo.png"
    write_png(photo, np.zeros((492, 739, 3), np.uint8))
    _check_aspect_ratios([Camera(80.0, 80.0, 46.0, 31.0, 92, 62)], [photo], tmp_path / "images.bin")
    with pytest.raises(InputError, match="aspect ratio"):  # 92 x 70 is another shape
        _check_aspect_ratios([Camera(80.0, 80.0, 46.0, 35.0, 92, 70)], [photo], tmp_path / "images.bin")


def test_image_with_wrong_aspect_ratio(scene_dir: Path) -> None:
    write_png(scene_dir / "images" / names(4)[2], np.zeros((H, H, 3), np.uint8))
    with pytest.raises(InputError, match="aspect ratio") as e:
        load_scene(scene_dir)
    assert e.value.path.name == names(4)[2]


# ===================================================================== bad input via the CLI
def run_inspect(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "n2f2.cli", "inspect", *map(str, args)],
                          capture_output=True, text=True, timeout=120)


def assert_clean_error(result: subprocess.CompletedProcess, *fragments: str) -> None:
    assert result.returncode == 2, result.stderr
    assert "Traceback" not in result.stderr and "Traceback" not in result.stdout
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    for fragment in fragments:
        assert fragment in lines[0], lines[0]


def test_cli_inspect_prints_summary(scene_dir: Path, capsys: pytest.CaptureFixture) -> None:
    r = run_inspect(scene_dir, "--downscale", "2", "--json")
    assert r.returncode == 0, r.stderr
    info = json.loads(r.stdout)
    assert info["views"] == 4 and info["image_sizes"] == [[W // 2, H // 2]]
    assert info["fx"] == [20.0, 20.0] and info["points"] == 20 and info["format"] == "nerfstudio"
    from n2f2.cli import main  # the text summary, in-process (each subprocess costs ~1.5 s)

    assert main(["inspect", str(scene_dir), "--format", "colmap"]) == 0
    out = capsys.readouterr().out
    assert "colmap-binary" in out and "20 (with colours)" in out and "ground truth no" in out


def test_cli_missing_transforms(tmp_path: Path) -> None:
    assert_clean_error(run_inspect(tmp_path, "--format", "nerfstudio"), "transforms.json", "does not exist")
    assert_clean_error(run_inspect(tmp_path), "transforms.json", "no scene found")
    assert_clean_error(run_inspect(tmp_path / "nothing"), "nothing", "does not exist")


@pytest.mark.parametrize("name", ["cameras.bin", "images.bin", "points3D.bin"])
def test_cli_truncated_colmap_binary(scene_dir: Path, name: str) -> None:
    f = scene_dir / "sparse" / "0" / name
    f.write_bytes(f.read_bytes()[:-5])
    assert_clean_error(run_inspect(scene_dir, "--format", "colmap"), name, "truncated", "expected")


@pytest.mark.parametrize("fmt", ["nerfstudio", "colmap"])
def test_cli_image_listed_but_absent(scene_dir: Path, fmt: str) -> None:
    (scene_dir / "images" / names(4)[1]).unlink()
    assert_clean_error(run_inspect(scene_dir, "--format", fmt), names(4)[1], "does not exist")


def edit_transforms(root: Path, edit) -> None:
    meta = json.loads((root / "transforms.json").read_text())
    edit(meta)
    (root / "transforms.json").write_text(json.dumps(meta))


def test_cli_nan_pose(scene_dir: Path) -> None:
    def nan(meta):
        meta["frames"][2]["transform_matrix"][1][3] = float("nan")  # json writes NaN
    edit_transforms(scene_dir, nan)
    assert_clean_error(run_inspect(scene_dir), "transforms.json", "frame 2", "NaN")


def test_cli_nan_pose_colmap(tmp_path: Path) -> None:
    write_images(tmp_path, 2)
    write_colmap_text(tmp_path / "sparse" / "0", make_cameras(2), names(2))
    f = tmp_path / "sparse" / "0" / "images.txt"
    lines = f.read_text().splitlines()
    i = next(k for k, line in enumerate(lines) if line.startswith("2 "))
    parts = lines[i].split()
    parts[6] = "nan"
    lines[i] = " ".join(parts)
    f.write_text("\n".join(lines) + "\n")
    assert_clean_error(run_inspect(tmp_path), "images.txt", names(2)[1], "NaN")


def test_cli_wrong_shape_matrix(scene_dir: Path) -> None:
    def shape(meta):
        meta["frames"][0]["transform_matrix"] = np.eye(3).tolist()
    edit_transforms(scene_dir, shape)
    assert_clean_error(run_inspect(scene_dir), "transforms.json", "frame 0", "4x4", "3x3")


def test_cli_missing_file_path_and_bad_json(scene_dir: Path) -> None:
    edit_transforms(scene_dir, lambda meta: meta["frames"][3].pop("file_path"))
    assert_clean_error(run_inspect(scene_dir), "transforms.json", "frame 3", "file_path")
    (scene_dir / "transforms.json").write_text('{"frames": [')
    assert_clean_error(run_inspect(scene_dir), "transforms.json", "not valid JSON")


def test_cli_unsupported_camera_model(tmp_path: Path) -> None:
    write_images(tmp_path, 1)
    (tmp_path / "sparse").mkdir()
    (tmp_path / "sparse" / "cameras.txt").write_text("1 FOV 32 24 40 40 16 12 0.3\n")
    (tmp_path / "sparse" / "images.txt").write_text("1 1 0 0 0 0 0 0 1 frame_00001.png\n\n")
    assert_clean_error(run_inspect(tmp_path), "cameras.txt", "FOV", "colmap image_undistorter")
