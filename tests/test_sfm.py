"""``n2f2 sfm``: structure from motion with pycolmap on photos without poses.

The synthetic scene is rendered here by a small ray caster (a ground plane and two boxes
covered in smooth colour noise, which SIFT finds plenty of features on), so the true camera
centres are known independently of the code under test; the recovered ones are compared after
a similarity (Umeyama) alignment written here too."""

from __future__ import annotations

import json
import math
import os
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

WIDTH, HEIGHT, FOCAL = 320, 240, 280.0
BOXES = (((-0.5, -0.35, 0.0), (0.3, 0.35, 0.7)), ((0.45, -0.6, 0.0), (0.85, -0.1, 0.35)))


# ----------------------------------------------------------------------------- the toy scene
def _value_noise(grid: np.ndarray,  # [n, n, 3] random colours at the lattice points
                 u: np.ndarray, v: np.ndarray, cell: float) -> np.ndarray:  # u, v [N] -> [N, 3]
    n = grid.shape[0]
    x, y = u / cell, v / cell
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    x0, y0 = x0 % n, y0 % n
    x1, y1 = (x0 + 1) % n, (y0 + 1) % n
    return ((1 - fx) * (1 - fy) * grid[y0, x0] + fx * (1 - fy) * grid[y0, x1]
            + (1 - fx) * fy * grid[y1, x0] + fx * fy * grid[y1, x1])


def _texture(seed: int):
    rng = np.random.default_rng(seed)
    coarse, fine = rng.random((64, 64, 3)), rng.random((128, 128, 3))
    return lambda u, v: 0.5 * _value_noise(coarse, u, v, 0.16) + 0.5 * _value_noise(fine, u, v, 0.05)


def _look_at(eye: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:  # [3], [3] -> R [3, 3], t [3]
    forward = (target - eye) / np.linalg.norm(target - eye)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    R = np.stack([right, np.cross(forward, right), forward])  # OpenCV axes: x right, y down, z forward
    return R, -R @ eye


def _render(R: np.ndarray, t: np.ndarray) -> np.ndarray:  # R [3, 3], t [3] -> uint8 [H, W, 3]
    centre = -R.T @ t
    j, i = np.meshgrid(np.arange(WIDTH) + 0.5, np.arange(HEIGHT) + 0.5)
    rays = np.stack([(j - WIDTH / 2) / FOCAL, (i - HEIGHT / 2) / FOCAL, np.ones_like(j)], -1).reshape(-1, 3) @ R
    depth = np.full(len(rays), np.inf)
    colour = np.full((len(rays), 3), 0.5)  # grey sky: no features
    with np.errstate(divide="ignore", invalid="ignore"):
        s = -centre[2] / rays[:, 2]
        p = centre + s[:, None] * rays
        ground = (s > 0) & (np.abs(p[:, 0]) < 3) & (np.abs(p[:, 1]) < 3)
        depth[ground] = s[ground]
        colour[ground] = _texture(1)(p[ground, 0], p[ground, 1])
        for b, (lo, hi) in enumerate(BOXES):
            t1, t2 = (np.array(lo) - centre) / rays, (np.array(hi) - centre) / rays
            near, far = np.minimum(t1, t2).max(1), np.maximum(t1, t2).min(1)
            hit = (near < far) & (near > 0) & (near < depth)
            q = centre + near[:, None] * rays
            face_axis = np.argmax(np.minimum(t1, t2), 1)
            texture = _texture(10 + b)
            for axis in range(3):
                m = hit & (face_axis == axis)
                u_axis, v_axis = [k for k in range(3) if k != axis]
                colour[m] = texture(q[m, u_axis] + 3 * axis, q[m, v_axis])
            depth[hit] = near[hit]
    return (colour.reshape(HEIGHT, WIDTH, 3) * 255 + 0.5).astype(np.uint8)


def _write_toy_photos(folder: Path, num_views: int = 16) -> dict[str, np.ndarray]:
    """Photos on an orbit around the boxes; returns the true camera centre of each file name."""
    from PIL import Image

    folder.mkdir(parents=True)
    centres = {}
    for k in range(num_views):
        azimuth = 2 * math.pi * k / num_views
        elevation = math.radians(30 + 8 * math.sin(3 * azimuth))
        eye = 2.4 * np.array([math.cos(elevation) * math.cos(azimuth), math.cos(elevation) * math.sin(azimuth),
                              math.sin(elevation)])
        R, t = _look_at(eye, np.array([0.0, 0.0, 0.25]))
        name = f"view_{k:03d}.png"
        Image.fromarray(_render(R, t)).save(folder / name)
        centres[name] = eye
    return centres


def _umeyama(src: np.ndarray, dst: np.ndarray):  # src, dst [N, 3] -> scale, R [3, 3], t [3]
    """Similarity (scale, rotation, translation) minimising |dst - (s R src + t)|^2 (Umeyama 1991)."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    U, D, Vt = np.linalg.svd(xd.T @ xs / len(src))
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1.0
    R = U @ S @ Vt
    scale = np.trace(np.diag(D) @ S) / ((xs ** 2).sum() / len(src))
    return scale, R, mu_d - scale * R @ mu_s


def _cli(*argv) -> int:
    from n2f2.cli import main

    return main([str(a) for a in argv])


@dataclass(frozen=True)
class ToySfm:
    photos: Path
    out: Path
    centres: dict  # file name -> true camera centre [3]


@pytest.fixture(scope="module")
def toy_sfm(tmp_path_factory) -> ToySfm:
    root = tmp_path_factory.mktemp("sfm")
    photos = root / "toy" / "images"
    centres = _write_toy_photos(photos)
    out = root / "toy_sfm"
    assert _cli("sfm", photos, "--out", out, "--quiet") == 0
    return ToySfm(photos, out, centres)


# ----------------------------------------------------------------------------- tests
def test_sfm_recovers_the_true_camera_centres(toy_sfm):
    from n2f2.data import load_scene

    scene = load_scene(toy_sfm.out)  # the layout n2f2 reads: images/ + sparse/0 with PINHOLE cameras
    names = [p.name for p in scene.image_paths]
    assert len(names) >= 15, f"only {len(names)} of 16 views registered"
    estimated = np.array([-c.R.T @ c.t for c in scene.cameras])
    true = np.array([toy_sfm.centres[n] for n in names])
    scale, R, t = _umeyama(estimated, true)
    aligned = scale * estimated @ R.T + t
    rms = np.sqrt(((aligned - true) ** 2).sum(1).mean())
    extent = np.linalg.norm(true.max(0) - true.min(0))
    assert rms < 0.02 * extent, f"camera centres off by {rms:.4f} (RMS) in a {extent:.2f} extent"
    # Focal length is scale-free: the undistorted pinhole must match the renderer's.
    for cam in scene.cameras:
        assert cam.fx == pytest.approx(FOCAL, rel=0.03) and cam.fy == pytest.approx(FOCAL, rel=0.03)
        assert cam.cx == pytest.approx(cam.width / 2, abs=2) and cam.cy == pytest.approx(cam.height / 2, abs=2)


def test_sfm_report_counts_match_the_model(toy_sfm):
    from n2f2.data.colmap import read_colmap_model

    report = json.loads((toy_sfm.out / "sfm_report.json").read_text())
    cameras, images, points, _ = read_colmap_model(toy_sfm.out / "sparse" / "0")
    assert report["images_given"] == len(toy_sfm.centres)
    assert report["registered"] == len(images) == len(list((toy_sfm.out / "images").iterdir()))
    assert report["points"] == len(points)
    assert sorted(report["unregistered"]) == sorted(set(toy_sfm.centres) - {im.name for im in images})
    assert {c.model for c in cameras.values()} == {"PINHOLE"}
    assert len(cameras) == 1  # one shared camera by default
    assert report["models"][0] == report["registered"]
    assert set(report["timings_s"]) == {"extract", "match", "map", "undistort"}
    assert 0 < report["mean_reprojection_error_px"] < 2 and report["mean_track_length"] >= 2
    assert not toy_sfm.out.with_name(toy_sfm.out.name + ".partial").exists()


def test_rerun_reuses_the_result_and_other_inputs_are_refused(toy_sfm, tmp_path, capsys):
    report = toy_sfm.out / "sfm_report.json"
    before = report.stat().st_mtime_ns
    assert _cli("sfm", toy_sfm.photos, "--out", toy_sfm.out, "--quiet") == 0
    assert "up to date" in capsys.readouterr().out
    assert report.stat().st_mtime_ns == before

    # Other settings, or another set of photos, into the finished folder: refused, untouched.
    assert _cli("sfm", toy_sfm.photos, "--out", toy_sfm.out, "--matcher", "sequential", "--quiet") == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--force" in err[0]
    fewer = tmp_path / "fewer"
    fewer.mkdir()
    for name in sorted(toy_sfm.centres)[:8]:
        shutil.copy2(toy_sfm.photos / name, fewer / name)
    assert _cli("sfm", fewer, "--out", toy_sfm.out, "--quiet") == 2
    assert "--force" in capsys.readouterr().err
    assert report.stat().st_mtime_ns == before

    # A folder that is not an sfm result is never replaced, even with --overwrite.
    other = tmp_path / "other"
    other.mkdir()
    (other / "notes.txt").write_text("mine")
    assert _cli("sfm", toy_sfm.photos, "--out", other, "--overwrite", "--quiet") == 2
    assert (other / "notes.txt").read_text() == "mine"


def test_posed_scene_path(toy_sfm, tmp_path):
    from n2f2.data import load_scene
    from n2f2.data.sfm import posed_scene_path

    # A scene is returned unchanged, and nothing is written to the cache folder.
    assert posed_scene_path(toy_sfm.out, tmp_path / "unused", progress=False) == toy_sfm.out
    assert not (tmp_path / "unused").exists()

    # A plain folder of photos (here images/ without a model, with the same names, sizes and
    # modification times) becomes the sfm scene in the cache folder; the cache holds the
    # result made from these photos with the default settings, so it is reused, not rerun.
    plain = tmp_path / "plain"
    shutil.copytree(toy_sfm.photos, plain / "images")
    cache = tmp_path / "cache"
    shutil.copytree(toy_sfm.out, cache)
    logged = []
    assert posed_scene_path(plain, cache, progress=False, log=logged.append) == cache
    assert any("up to date" in line for line in logged)
    assert len(load_scene(cache)) == json.loads((cache / "sfm_report.json").read_text())["registered"]
    # The photos directly in a folder work the same way.
    assert posed_scene_path(plain / "images", cache, progress=False, log=logged.append) == cache

    # A folder that is neither a scene nor photos is returned for load_scene to report.
    empty = tmp_path / "empty"
    empty.mkdir()
    assert posed_scene_path(empty, tmp_path / "unused", progress=False) == empty


def test_photos_that_do_not_overlap_exit_2_with_one_line(tmp_path, capfd):
    from PIL import Image

    rng = np.random.default_rng(0)
    photos = tmp_path / "noise"
    photos.mkdir()
    for k in range(4):
        Image.fromarray((rng.random((72, 96, 3)) * 255).astype(np.uint8)).save(photos / f"noise_{k}.png")
    out = tmp_path / "out"
    assert _cli("sfm", photos, "--out", out, "--quiet") == 2
    err = capfd.readouterr().err.strip().splitlines()  # capfd: COLMAP's own log would land here too
    assert len(err) == 1, err
    assert "registered 0 of 4 photos" in err[0]
    assert not out.exists()  # nothing that looks like a result
    assert sorted(p.name for p in tmp_path.iterdir()) == ["noise"]  # and no working folder left
    # --keep-partial keeps the working files for a look; a rerun replaces them.
    assert _cli("sfm", photos, "--out", out, "--quiet", "--keep-partial") == 2
    assert "registered 0 of 4 photos" in capfd.readouterr().err
    assert (tmp_path / "out.partial" / "colmap" / "database.db").is_file()
    assert _cli("sfm", photos, "--out", out, "--quiet") == 2
    assert "registered 0 of 4 photos" in capfd.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["noise"]


def test_sequential_pairs_are_the_neighbours_and_powers_of_two():
    from n2f2.data.sfm import _pair_batches

    pairs = sorted(p for batch in _pair_batches(8, "sequential", 3) for p in batch)
    # overlap 3: i+1, i+2, i+3 and i+1, i+2, i+4 (COLMAP's quadratic overlap), up to index 7
    expected = sorted({(i, j) for i in range(8) for j in (i + 1, i + 2, i + 3, i + 4) if j < 8})
    assert pairs == expected
    exhaustive = [p for batch in _pair_batches(120, "exhaustive", 3) for p in batch]
    assert len(exhaustive) == len(set(exhaustive)) == 120 * 119 // 2


def test_bad_input_exits_2(tmp_path, capsys):
    empty = tmp_path / "empty"
    empty.mkdir()
    assert _cli("sfm", empty, "--out", tmp_path / "out") == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no images" in err[0]
    assert _cli("sfm", tmp_path / "missing", "--out", tmp_path / "out") == 2
    assert "does not exist" in capsys.readouterr().err
    assert _cli("sfm", empty, "--out", tmp_path / "out", "--max-image-size", "10") == 2
    assert "max image size" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_output_folder_holding_the_photos_is_refused(tmp_path, capsys):
    from PIL import Image

    scene = tmp_path / "scene"
    (scene / "images").mkdir(parents=True)
    for k in range(3):
        Image.new("RGB", (32, 24)).save(scene / "images" / f"{k}.png")
    assert _cli("sfm", scene / "images", "--out", scene, "--overwrite") == 2
    assert "contains the photos" in capsys.readouterr().err
    assert sorted(os.listdir(scene / "images")) == ["0.png", "1.png", "2.png"]


@pytest.mark.parametrize("bad", ["corrupt", "link"])
def test_an_unreadable_photo_is_one_line_and_leaves_no_working_folder(toy_sfm, tmp_path, capsys, bad):
    photos = tmp_path / "photos"
    shutil.copytree(toy_sfm.photos, photos)
    victim = photos / sorted(p.name for p in photos.iterdir())[3]
    victim.unlink()
    if bad == "corrupt":
        victim.write_bytes(b"\xff\xd8\xff\xe0 not a JPEG")
    else:  # a link to a file that is not an image
        (tmp_path / "notes.txt").write_text("not an image")
        victim.symlink_to(tmp_path / "notes.txt")
    out = tmp_path / "out"
    assert _cli("sfm", photos, "--out", out, "--quiet") == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and victim.name in err[0] and "cannot read image" in err[0], err
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(["photos", *(["notes.txt"] if bad == "link" else [])])
