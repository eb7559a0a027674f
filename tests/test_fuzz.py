"""Corrupted inputs and meaningless numbers for every command: each must end in one clear line
on stderr and exit status 2, with no traceback, and leave every watched folder exactly as it was
(file by file, by content hash). Also: nothing non-finite is ever written, reruns never replace
finished work without --force, training stops after MAX_BAD_STEPS non-finite steps in a row,
and temporary files that a killed write left behind are removed by the next run.

Valid bases come from the session's ``trained_run`` (tests/conftest.py) and are copied before
they are corrupted. The CLI runs in-process (``n2f2.cli.main``)."""

from __future__ import annotations

import hashlib
import json
import shutil
import struct
import zlib
from pathlib import Path
from typing import Callable

import numpy as np
import pytest
import torch

from n2f2.cli import build_parser, main
from n2f2.validate import MAX_BAD_STEPS, OPTION_TYPES, NonFiniteError

# A numpy overflow or invalid-value warning means a bad value went through unchecked.
pytestmark = pytest.mark.filterwarnings("error::RuntimeWarning")


# ------------------------------------------------------------------------------------ helpers
def folder_state(folder: Path) -> dict[str, str]:
    """relative path -> sha256 of every file under ``folder`` (empty when it does not exist)."""
    folder = Path(folder)
    if not folder.exists():
        return {}
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def run_cli(argv: list) -> int:
    try:
        return main([str(a) for a in argv])
    except SystemExit as e:  # argparse errors
        return int(e.code or 0)


def assert_refused(capsys, argv: list, watch: list[Path], *fragments: str) -> str:
    """Run ``argv``: exit 2, exactly one line on stderr holding ``fragments``, no traceback, and
    no file under any ``watch`` folder created, changed or removed. Returns the line."""
    before = [folder_state(w) for w in watch]
    capsys.readouterr()
    rc = run_cli(argv)
    out, err = capsys.readouterr()
    assert rc == 2, (rc, err)
    assert "Traceback" not in err + out
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    for fragment in fragments:
        assert fragment in lines[0], lines[0]
    assert [folder_state(w) for w in watch] == before, "a watched folder changed"
    return lines[0]


def assert_all_finite(folder: Path) -> None:
    """Every array n2f2 wrote under ``folder`` (.npy, .pt, .ply) is finite."""
    from n2f2.gaussians.ply import _read_vertices
    from n2f2.io import load_torch
    from n2f2.validate import _non_finite

    for p in Path(folder).rglob("*"):
        if p.suffix == ".npy":
            assert _non_finite(np.load(p)) is None, p
        elif p.suffix == ".pt":
            assert _non_finite(load_torch(p)) is None, p
        elif p.suffix == ".ply":
            v = _read_vertices(p)
            assert all(np.isfinite(v[name]).all() for name in v.dtype.names), p


@pytest.fixture(scope="module")
def base(trained_run, tmp_path_factory) -> dict[str, Path]:
    """Valid inputs to corrupt: the scene (COLMAP text + nerfstudio), its COLMAP model as binary,
    the fitted Gaussians, LangSplat features exported from the bank, and the labels."""
    from n2f2.data.colmap import read_colmap_scene, write_colmap_binary
    from n2f2.segments.langsplat import export_langsplat

    root = tmp_path_factory.mktemp("fuzz_base")
    scene = root / "scene"
    shutil.copytree(trained_run.scene_dir, scene)
    binary = root / "binary"
    shutil.copytree(trained_run.scene_dir, binary)
    model = read_colmap_scene(binary / "sparse" / "0")
    write_colmap_binary(binary / "sparse" / "0", model.cameras, model.image_names, model.points, model.colors)
    for name in ("cameras", "images", "points3D"):
        (binary / "sparse" / "0" / f"{name}.txt").unlink()
    features = root / "features"
    export_langsplat(trained_run.bank_dir, features, progress=False)
    return {"scene": scene, "binary": binary, "features": features,
            "ply": trained_run.run_dir.parent / "fit" / "gaussians.ply",
            "fit": trained_run.run_dir.parent / "fit", "run": trained_run.run_dir, "bank": trained_run.bank_dir}


def copy(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst) if src.is_dir() else shutil.copyfile(src, dst)
    return dst


def edit_json(path: Path, fn: Callable[[dict], None]) -> None:
    data = json.loads(path.read_text())
    fn(data)
    path.write_text(json.dumps(data))  # NaN and Infinity are written as JSON's extensions


def replace_text(path: Path, old: str, new: str, count: int = 1) -> None:
    text = path.read_text()
    assert old in text, (path, old)
    path.write_text(text.replace(old, new, count))


def replace_line(path: Path, index: int, fn: Callable[[list[str]], list[str]]) -> None:
    """Apply ``fn`` to the words of the ``index``-th data line (comments skipped)."""
    lines = path.read_text().splitlines()
    data = [i for i, line in enumerate(lines) if line.strip() and not line.startswith("#")]
    k = data[index]
    lines[k] = " ".join(fn(lines[k].split()))
    path.write_text("\n".join(lines) + "\n")


def patch_bytes(path: Path, offset: int, fmt: str, *values) -> None:
    data = bytearray(path.read_bytes())
    struct.pack_into(fmt, data, offset, *values)
    path.write_bytes(bytes(data))


def png_bytes(width: int, height: int, bit_depth: int = 8, color_type: int = 2, idat: bytes = b"") -> bytes:
    """A PNG with the given header and raw IDAT payload (for malformed images)."""
    def chunk(kind: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))
    ihdr = struct.pack(">IIBBBBB", width, height, bit_depth, color_type, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", idat) + chunk(b"IEND", b"")


# ------------------------------------------------------------------------------------ numbers
def _numeric_cases() -> list[tuple[str, str, int, str]]:
    """(command, flag, nargs, bad value) for every numeric option of every command, found by
    walking the parser: an option with a plain int/float type fails the test below."""
    cases, raw = [], []
    subparsers = next(a for a in build_parser()._actions if a.__class__.__name__ == "_SubParsersAction")
    for command, parser in subparsers.choices.items():
        for action in parser._actions:
            if action.type in (int, float):
                raw.append(f"{command} {action.option_strings}")
            if action.type not in OPTION_TYPES or not action.option_strings:
                continue
            nargs = action.nargs if isinstance(action.nargs, int) else 1
            for value in action.type.invalid_examples:
                cases.append((command, "/".join(action.option_strings), nargs, value))
    assert not raw, f"numeric options without a validating type: {raw}"
    return cases


NUMERIC_CASES = _numeric_cases()


def test_every_numeric_option_is_validated():
    commands = {c for c, *_ in NUMERIC_CASES}
    assert {"train", "fit-gaussians", "query", "render", "run", "demo", "view", "bench"} <= commands
    flags = {(c, o) for c, f, *_ in NUMERIC_CASES for o in f.split("/")}
    for needed in [("train", "--render-downscale"), ("train", "--plane-resolution"), ("train", "--cos-weight"),
                   ("train", "--pixels-per-step"), ("fit-gaussians", "--depth-spread"), ("query", "--threshold")]:
        assert needed in flags


@pytest.mark.parametrize("command,flag,nargs,value", NUMERIC_CASES,
                         ids=[f"{c} {f} {v}" for c, f, _, v in NUMERIC_CASES])
def test_bad_number_is_one_line(command, flag, nargs, value, tmp_path, capsys):
    for option in flag.split("/"):  # every spelling (--downscale, -r)
        if nargs == 1:  # "--flag=-inf": a value starting with "-" is not read as an option
            line = assert_refused(capsys, [command, f"{option}={value}"], [tmp_path], repr(value))
            assert line.startswith(f"n2f2 {command}: error: {flag} must be"), line
        else:
            assert_refused(capsys, [command, option, *([value] * nargs)], [tmp_path], flag)


# ------------------------------------------------------------------------------------ nerfstudio
def _frames(fn):
    return lambda d: d["frames"][1].update(fn(d["frames"][1]))


NERFSTUDIO = {
    "not-json": lambda p: p.write_text("{not json"),
    "not-utf8": lambda p: p.write_bytes(b"\xff\xfe\x00{"),
    "top-level-list": lambda p: p.write_text("[]"),
    "no-frames": lambda p: edit_json(p, lambda d: d.pop("frames")),
    "empty-frames": lambda p: edit_json(p, lambda d: d.update(frames=[])),
    "frame-not-object": lambda p: edit_json(p, lambda d: d["frames"].__setitem__(2, 7)),
    "no-file-path": lambda p: edit_json(p, lambda d: d["frames"][1].pop("file_path")),
    "missing-image": lambda p: edit_json(p, lambda d: d["frames"][1].update(file_path="images/nope.png")),
    "listed-twice": lambda p: edit_json(p, lambda d: d["frames"][2].update(file_path=d["frames"][1]["file_path"])),
    "no-matrix": lambda p: edit_json(p, lambda d: d["frames"][1].pop("transform_matrix")),
    "matrix-3x3": lambda p: edit_json(p, lambda d: d["frames"][1].update(transform_matrix=[[1, 0, 0]] * 3)),
    "matrix-nan": lambda p: edit_json(p, lambda d: d["frames"][1]["transform_matrix"][0].__setitem__(3, float("nan"))),
    "matrix-inf": lambda p: edit_json(p, lambda d: d["frames"][1]["transform_matrix"][1].__setitem__(0, float("inf"))),
    "matrix-text": lambda p: edit_json(p, lambda d: d["frames"][1]["transform_matrix"][1].__setitem__(0, "x")),
    "matrix-scaled": lambda p: edit_json(p, lambda d: d["frames"][1].update(
        transform_matrix=(2 * np.asarray(d["frames"][1]["transform_matrix"])).tolist())),
    "fl_x-text": lambda p: edit_json(p, lambda d: d.update(fl_x="70")),
    "fl_x-nan": lambda p: edit_json(p, lambda d: d.update(fl_x=float("nan"))),
    "fl_x-zero": lambda p: edit_json(p, lambda d: d.update(fl_x=0)),
    "fl_y-negative": lambda p: edit_json(p, lambda d: d.update(fl_y=-5.0)),
    "w-zero": lambda p: edit_json(p, lambda d: d.update(w=0)),
    "w-fraction": lambda p: edit_json(p, lambda d: d.update(w=80.5)),
    "w-bool": lambda p: edit_json(p, lambda d: d.update(w=True)),
    "h-negative": lambda p: edit_json(p, lambda d: d.update(h=-60)),
    "aspect-ratio": lambda p: edit_json(p, lambda d: d.update(w=120)),
    "angle-zero": lambda p: edit_json(p, lambda d: (d.pop("fl_x"), d.pop("fl_y"), d.update(camera_angle_x=0))),
    "angle-too-wide": lambda p: edit_json(p, lambda d: (d.pop("fl_x"), d.pop("fl_y"), d.update(camera_angle_x=4.0))),
    "cx-inf": lambda p: edit_json(p, lambda d: d.update(cx=float("inf"))),
    "unknown-lens": lambda p: edit_json(p, lambda d: d.update(camera_model="EQUIRECTANGULAR")),
    "latlong": lambda p: edit_json(p, lambda d: d.update(latlong=True)),
    "k4": lambda p: edit_json(p, lambda d: d.update(k4=0.1)),
    "fisheye-p1": lambda p: edit_json(p, lambda d: d.update(camera_model="OPENCV_FISHEYE", p1=0.01)),
    "k1-nan": lambda p: edit_json(p, lambda d: d.update(k1=float("nan"))),
    "applied-transform": lambda p: edit_json(p, lambda d: d.update(applied_transform=[[1, 0], [0, 1]])),
    "ply-missing": lambda p: edit_json(p, lambda d: d.update(ply_file_path="nope.ply")),
}

POINTS_PLY = {  # the scene's sparse_pc.ply (ply_file_path), binary with double x y z + uchar rgb
    "count-not-integer": lambda p: _ply_header(p, "element vertex 4000", "element vertex 12.5"),
    "count-negative": lambda p: _ply_header(p, "element vertex 4000", "element vertex -3"),
    "count-huge": lambda p: _ply_header(p, "element vertex 4000", "element vertex 100000000000"),
    "not-ply": lambda p: p.write_bytes(b"hello"),
    "no-end-header": lambda p: p.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 1\n"),
    "bad-property": lambda p: _ply_header(p, "property double x", "property double"),
    "list-property": lambda p: _ply_header(p, "property double x", "property list uchar int x"),
    "first-element-face": lambda p: _ply_header(p, "element vertex 4000", "element face 4000"),
    "unknown-format": lambda p: _ply_header(p, "format binary_little_endian 1.0", "format zip 1.0"),
    "truncated": lambda p: p.write_bytes(p.read_bytes()[:-7]),
    "nan-point": lambda p: _ply_body(p, 8, "<d", float("nan")),
    "ascii-text": lambda p: p.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\n"
                                          b"property float y\nproperty float z\nend_header\n1 2 3\n4 five 6\n"),
    "ascii-short": lambda p: p.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\n"
                                           b"property float y\nproperty float z\nend_header\n1 2 3\n4 5\n"),
    "ascii-count-huge": lambda p: p.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 99999999999\n"
                                                b"property float x\nproperty float y\nproperty float z\n"
                                                b"end_header\n1 2 3\n"),
}


def _ply_header(path: Path, old: str, new: str) -> None:
    data = path.read_bytes()
    end = data.index(b"end_header")
    head = data[:end].decode("ascii")
    assert old in head, (path, old, head)
    path.write_bytes(head.replace(old, new, 1).encode("ascii") + data[end:])


def _ply_body(path: Path, offset: int, fmt: str, *values) -> None:
    """Patch the body of a binary PLY at ``offset`` bytes past the header."""
    data = path.read_bytes()
    start = data.index(b"end_header\n") + len(b"end_header\n")
    patch_bytes(path, start + offset, fmt, *values)


@pytest.mark.parametrize("case", sorted(NERFSTUDIO))
def test_corrupt_transforms_json(case, base, tmp_path, capsys):
    scene = copy(base["scene"], tmp_path / "scene")
    NERFSTUDIO[case](scene / "transforms.json")
    line = assert_refused(capsys, ["inspect", scene, "--format", "nerfstudio"], [scene])
    assert "transforms.json" in line or "images" in line or ".ply" in line, line


@pytest.mark.parametrize("case", sorted(POINTS_PLY))
def test_corrupt_points_ply(case, base, tmp_path, capsys):
    scene = copy(base["scene"], tmp_path / "scene")
    POINTS_PLY[case](scene / "sparse_pc.ply")
    assert_refused(capsys, ["inspect", scene, "--format", "nerfstudio"], [scene], "sparse_pc.ply")


# ------------------------------------------------------------------------------------ COLMAP
COLMAP_TEXT = {  # file -> corruption; the error must name that file
    "cameras-unknown-model": ("cameras.txt", lambda p: replace_line(p, 0, lambda w: [w[0], "FANCY", *w[2:]])),
    "cameras-param-count": ("cameras.txt", lambda p: replace_line(p, 0, lambda w: w[:-1])),
    "cameras-width-zero": ("cameras.txt", lambda p: replace_line(p, 0, lambda w: [w[0], w[1], "0", *w[3:]])),
    "cameras-height-negative": ("cameras.txt", lambda p: replace_line(p, 0, lambda w: [*w[:3], "-60", *w[4:]])),
    "cameras-width-text": ("cameras.txt", lambda p: replace_line(p, 0, lambda w: [w[0], w[1], "wide", *w[3:]])),
    "cameras-fx-nan": ("cameras.txt", lambda p: replace_line(p, 0, lambda w: [*w[:4], "nan", *w[5:]])),
    "cameras-fx-zero": ("cameras.txt", lambda p: replace_line(p, 0, lambda w: [*w[:4], "0", *w[5:]])),
    "cameras-fov-omega": ("cameras.txt", lambda p: replace_line(p, 0, lambda w: [w[0], "FOV", *w[2:], "0.3"])),
    "cameras-binary-bytes": ("cameras.txt", lambda p: p.write_bytes(b"\x00\xff\x10\x80")),
    "images-qvec-nan": ("images.txt", lambda p: replace_line(p, 0, lambda w: [w[0], "nan", *w[2:]])),
    "images-zero-quaternion": ("images.txt", lambda p: replace_line(p, 0, lambda w: [w[0], "0", "0", "0", "0", *w[5:]])),
    "images-short-line": ("images.txt", lambda p: replace_line(p, 0, lambda w: w[:5])),
    "images-unknown-camera": ("images.txt", lambda p: replace_line(p, 0, lambda w: [*w[:8], "9", *w[9:]])),
    "images-tvec-inf": ("images.txt", lambda p: replace_line(p, 0, lambda w: [*w[:5], "inf", *w[6:]])),
    "images-empty": ("images.txt", lambda p: p.write_text("# nothing\n")),
    "points-nan": ("points3D.txt", lambda p: replace_line(p, 5, lambda w: [w[0], "nan", *w[2:]])),
    "points-inf": ("points3D.txt", lambda p: replace_line(p, 3, lambda w: [*w[:3], "-inf", *w[4:]])),
    "points-colour-300": ("points3D.txt", lambda p: replace_line(p, 0, lambda w: [*w[:4], "300", *w[5:]])),
    "points-short-line": ("points3D.txt", lambda p: replace_line(p, 0, lambda w: w[:3])),
}

_POINT = struct.calcsize("<QdddBBBdQ")
COLMAP_BINARY = {
    "cameras-truncated": ("cameras.bin", lambda p: p.write_bytes(p.read_bytes()[:-5])),
    "cameras-model-id": ("cameras.bin", lambda p: patch_bytes(p, 12, "<i", 99)),
    "cameras-width-zero": ("cameras.bin", lambda p: patch_bytes(p, 16, "<Q", 0)),
    "cameras-count-huge": ("cameras.bin", lambda p: patch_bytes(p, 0, "<Q", 2**62)),
    "images-count-huge": ("images.bin", lambda p: patch_bytes(p, 0, "<Q", 2**62)),
    "images-truncated": ("images.bin", lambda p: p.write_bytes(p.read_bytes()[:40])),
    "images-qvec-nan": ("images.bin", lambda p: patch_bytes(p, 12, "<d", float("nan"))),
    "images-points2d-huge": ("images.bin", lambda p: patch_bytes(
        p, 8 + 64 + len("frame_00001.png") + 1, "<Q", 2**61)),
    "images-name-unterminated": ("images.bin", lambda p: p.write_bytes(p.read_bytes()[:8 + 64 + 5])),
    "points-count-huge": ("points3D.bin", lambda p: patch_bytes(p, 0, "<Q", 2**62)),
    "points-nan": ("points3D.bin", lambda p: patch_bytes(p, 8 + 8, "<d", float("nan"))),
    "points-inf": ("points3D.bin", lambda p: patch_bytes(p, 8 + 3 * _POINT + 16, "<d", float("inf"))),
    "points-track-huge": ("points3D.bin", lambda p: patch_bytes(p, 8 + _POINT - 8, "<Q", 2**61)),
    "points-truncated": ("points3D.bin", lambda p: p.write_bytes(p.read_bytes()[:-3])),
}


@pytest.mark.parametrize("case", sorted(COLMAP_TEXT))
def test_corrupt_colmap_text(case, base, tmp_path, capsys):
    name, corrupt = COLMAP_TEXT[case]
    scene = copy(base["scene"], tmp_path / "scene")
    corrupt(scene / "sparse" / "0" / name)
    assert_refused(capsys, ["inspect", scene, "--format", "colmap"], [scene], name)


@pytest.mark.parametrize("case", sorted(COLMAP_BINARY))
def test_corrupt_colmap_binary(case, base, tmp_path, capsys):
    name, corrupt = COLMAP_BINARY[case]
    scene = copy(base["binary"], tmp_path / "scene")
    corrupt(scene / "sparse" / "0" / name)
    assert_refused(capsys, ["inspect", scene, "--format", "colmap"], [scene], name)


def test_nan_point_is_refused_not_printed(base, tmp_path, capsys):
    scene = copy(base["scene"], tmp_path / "scene")
    replace_line(scene / "sparse" / "0" / "points3D.txt", 16, lambda w: [w[0], w[1], "nan", *w[3:]])
    line = assert_refused(capsys, ["inspect", scene, "--format", "colmap", "--json"], [scene],
                          "points3D.txt", "line ")
    assert "NaN" in line and "bounds" not in line


# ------------------------------------------------------------------------------------ images
IMAGES = {  # frame_00002.png is a training view (view 0 is held out)
    "garbage": lambda p: p.write_bytes(b"definitely not a png"),
    "empty-file": lambda p: p.write_bytes(b""),
    "truncated": lambda p: p.write_bytes(p.read_bytes()[:120]),
    "bad-idat": lambda p: p.write_bytes(png_bytes(80, 60, idat=b"\x00" * 40)),
    "bad-crc": lambda p: p.write_bytes(p.read_bytes()[:-20] + bytes(b ^ 0xFF for b in p.read_bytes()[-20:-12])
                                       + p.read_bytes()[-12:]),
    "decompression-bomb": lambda p: p.write_bytes(png_bytes(40000, 30000, idat=zlib.compress(b"\x00" * 64))),
    "wrong-aspect": lambda p: p.write_bytes(png_bytes(60, 60, idat=zlib.compress(b"\x00" * (61 * 60)))),
    "zero-size-header": lambda p: p.write_bytes(png_bytes(0, 0)),
}


@pytest.mark.parametrize("case", sorted(IMAGES))
def test_corrupt_image(case, base, tmp_path, capsys):
    scene = copy(base["scene"], tmp_path / "scene")
    IMAGES[case](scene / "images" / "frame_00002.png")
    out = tmp_path / "fit"
    assert_refused(capsys, ["fit-gaussians", scene, "--out", out, "--steps", 1, "--quiet"], [scene, out],
                   "frame_00002.png")


def test_sixteen_bit_images_load_scaled_by_65535(base, tmp_path):
    import cv2

    from n2f2.data import load_scene
    from n2f2.data.scene import load_image

    rng = np.random.default_rng(0)
    gray = rng.integers(0, 65536, size=(60, 80), dtype=np.uint16)
    y, x = np.mgrid[0:60, 0:80] / 80.0  # smooth colours, so resizing them is comparable at 8 bits
    rgb = np.round(65535 * np.stack([0.5 + 0.4 * np.sin(3 * x), 0.5 + 0.4 * np.cos(2 * y), 0.5 + 0.3 * np.sin(x + y)],
                                    axis=2)).astype(np.uint16)
    rgb[7, 9] = (65535, 0, 1)  # and exact extremes
    cv2.imwrite(str(tmp_path / "gray16.png"), gray)
    cv2.imwrite(str(tmp_path / "rgb16.png"), rgb[..., ::-1])  # OpenCV writes BGR
    got = load_image(tmp_path / "gray16.png", 80, 60)
    np.testing.assert_allclose(got, np.repeat(gray[..., None] / 65535.0, 3, axis=2), atol=1e-6)
    np.testing.assert_allclose(load_image(tmp_path / "rgb16.png", 80, 60), rgb / 65535.0, atol=1e-6)
    # Resized: the same as the 8-bit image of the same content resized, to 8-bit precision.
    cv2.imwrite(str(tmp_path / "rgb8.png"), np.round(rgb[..., ::-1] / 257.0).astype(np.uint8))
    half16 = load_image(tmp_path / "rgb16.png", 40, 30)
    half8 = load_image(tmp_path / "rgb8.png", 40, 30)
    assert half16.shape == (30, 40, 3) and np.abs(half16 - half8).max() < 2.5 / 255
    # Through a scene: a 16-bit grayscale view is not white.
    scene_dir = copy(base["scene"], tmp_path / "scene")
    cv2.imwrite(str(scene_dir / "images" / "frame_00002.png"), gray)
    image = load_scene(scene_dir).image(1)
    np.testing.assert_allclose(image[..., 0], gray / 65535.0, atol=1e-6)


def test_sixteen_bit_tiffs_load_scaled_by_65535(tmp_path):
    import cv2
    from PIL import Image

    from n2f2.data.scene import load_image

    rng = np.random.default_rng(1)
    rgb = rng.integers(0, 65536, size=(60, 80, 3), dtype=np.uint16)
    rgb[7, 9] = (65535, 0, 1)
    cv2.imwrite(str(tmp_path / "rgb16.tif"), rgb[..., ::-1])  # OpenCV writes BGR
    Image.fromarray(rgb[..., 1]).save(tmp_path / "gray16.tif")  # PIL: mode I;16
    # atol far below one 8-bit step: a file read as 8 bits (the low byte dropped) fails.
    np.testing.assert_allclose(load_image(tmp_path / "rgb16.tif", 80, 60), rgb / 65535.0, atol=1e-6)
    np.testing.assert_allclose(load_image(tmp_path / "gray16.tif", 80, 60),
                               np.repeat(rgb[..., 1:2] / 65535.0, 3, axis=2), atol=1e-6)
    rgb8 = (rgb >> 8).astype(np.uint8)  # an 8-bit TIFF is still divided by 255
    Image.fromarray(rgb8).save(tmp_path / "rgb8.tif")
    np.testing.assert_allclose(load_image(tmp_path / "rgb8.tif", 80, 60), rgb8 / 255.0, atol=1e-6)


def test_sixteen_bit_tiff_big_endian_with_alpha(tmp_path):
    tifffile = pytest.importorskip("tifffile")
    from n2f2.data.scene import load_image

    rgba = np.random.default_rng(2).integers(0, 65536, size=(30, 40, 4), dtype=np.uint16)
    tifffile.imwrite(tmp_path / "be.tif", rgba, byteorder=">", photometric="rgb", extrasamples=["unassalpha"])
    np.testing.assert_allclose(load_image(tmp_path / "be.tif", 40, 30), rgba[..., :3] / 65535.0, atol=1e-6)


OVS3D_MASKS = {
    "decompression-bomb": (lambda p: p.write_bytes(png_bytes(40000, 30000, color_type=0,
                                                             idat=zlib.compress(b"\x00" * 64))), "too large"),
    "bad-idat": (lambda p: p.write_bytes(png_bytes(8, 6, color_type=0, idat=b"\x00" * 40)), "cannot read mask"),
    "not-an-image": (lambda p: p.write_bytes(b"mask"), "cannot read"),
}


@pytest.mark.parametrize("case", sorted(OVS3D_MASKS))
def test_corrupt_ovs3d_mask_is_one_line(case, tmp_path):
    from n2f2.errors import InputError
    from n2f2.eval.ovs3d import read_ovs3d_segmentations
    from n2f2.io import write_png

    seg = tmp_path / "segmentations"
    (seg / "00").mkdir(parents=True)
    (seg / "classes.txt").write_text("cup\nplate\n")
    write_png(seg / "00" / "cup.png", np.full((6, 8), 255, np.uint8))
    corrupt, fragment = OVS3D_MASKS[case]
    corrupt(seg / "00" / "plate.png")
    with pytest.raises(InputError) as e:
        read_ovs3d_segmentations(tmp_path)
    message = str(e.value)
    assert "plate.png" in message and fragment in message and "\n" not in message, message


# ------------------------------------------------------------------------------------ Gaussians PLY
_PROPS = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
          "rot_0", "rot_1", "rot_2", "rot_3"]


def _inria_ascii(rows: list[str], props: list[str] | None = None, count: int | None = None) -> bytes:
    props = props or _PROPS
    head = ["ply", "format ascii 1.0", f"element vertex {len(rows) if count is None else count}"]
    head += [f"property float {p}" for p in props] + ["end_header"]
    return ("\n".join(head + rows) + "\n").encode("ascii")


_ROW = "0 0 0 0.5 0.5 0.5 0 -3 -3 -3 1 0 0 0"
GAUSSIANS_PLY = {
    "count-1e11": lambda p: _ply_header(p, _vertex_line(p), "element vertex 100000000000"),
    "count-not-integer": lambda p: _ply_header(p, _vertex_line(p), "element vertex 1.5"),
    "count-negative": lambda p: _ply_header(p, _vertex_line(p), "element vertex -1"),
    "zero-vertices": lambda p: p.write_bytes(_inria_ascii([])),
    "ascii-text": lambda p: p.write_bytes(_inria_ascii([_ROW, _ROW.replace("0.5", "half", 1)])),
    "ascii-short-row": lambda p: p.write_bytes(_inria_ascii([_ROW, "0 0 0"])),
    "ascii-count-huge": lambda p: p.write_bytes(_inria_ascii([_ROW], count=10**11)),
    "ascii-nan": lambda p: p.write_bytes(_inria_ascii([_ROW, "nan" + _ROW[1:]])),
    "ascii-inf-opacity": lambda p: p.write_bytes(_inria_ascii([_ROW.replace(" 0 -3", " inf -3")])),
    "ascii-zero-quaternion": lambda p: p.write_bytes(_inria_ascii([_ROW[:-7] + "0 0 0 0"])),
    "ascii-zero-linear-scales": lambda p: p.write_bytes(_inria_ascii([_ROW.replace("-3 -3 -3", "0 0 0")])),
    "ascii-rest-count": lambda p: p.write_bytes(_inria_ascii(
        [_ROW + " 0 0 0 0"], props=[*_PROPS, "f_rest_0", "f_rest_1", "f_rest_2", "f_rest_3"])),
    "missing-opacity": lambda p: _ply_header(p, "property float opacity", "property float opacity_x"),
    "duplicate-property": lambda p: _ply_header(p, "property float opacity", "property float x"),
    "list-property": lambda p: _ply_header(p, "property float opacity", "property list uchar int opacity"),
    "bad-format": lambda p: _ply_header(p, "format binary_little_endian 1.0", "format binary_middle_endian 1.0"),
    "unknown-header-line": lambda p: _ply_header(p, "format binary_little_endian 1.0",
                                                 "format binary_little_endian 1.0\nvertices please"),
    "no-end-header": lambda p: p.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\n"),
    "not-ply": lambda p: p.write_bytes(b"\x89PNG\r\n"),
    "truncated": lambda p: p.write_bytes(p.read_bytes()[:-9]),
    "nan-mean": lambda p: _ply_body(p, 0, "<f", float("nan")),
    "inf-scale": lambda p: _ply_body(p, 4 * (_n_props(p) - 5), "<f", float("inf")),
    "zero-quaternion": lambda p: _ply_body(p, 4 * (_n_props(p) - 4), "<4f", 0.0, 0.0, 0.0, 0.0),
}


def _vertex_line(path: Path) -> str:
    head = path.read_bytes()[:4096].decode("ascii", "replace")
    return next(line for line in head.splitlines() if line.startswith("element vertex"))


def _n_props(path: Path) -> int:
    head = path.read_bytes()[:8192].decode("ascii", "replace").split("end_header")[0]
    return sum(line.startswith("property") for line in head.splitlines())


@pytest.mark.parametrize("case", sorted(GAUSSIANS_PLY))
def test_corrupt_gaussians_ply(case, base, tmp_path, capsys):
    ply = copy(base["ply"], tmp_path / "gaussians.ply")
    GAUSSIANS_PLY[case](ply)
    out = tmp_path / "render"
    assert_refused(capsys, ["render", ply, "--out", out, "--views", 1, "--size", 8, 8], [out, tmp_path],
                   "gaussians.ply")


# ------------------------------------------------------------------------------------ LangSplat
def _feats(stem: str = "frame_00003") -> str:
    return f"{stem}_f.npy"


def _segs(stem: str = "frame_00003") -> str:
    return f"{stem}_s.npy"


def _edit_npy(path: Path, fn) -> None:
    np.save(path, fn(np.load(path)))


def _nan_row(a: np.ndarray) -> np.ndarray:
    a = a.copy()
    a[min(17, len(a) - 1), 3] = np.nan
    return a


LANGSPLAT = {  # file -> corruption, fragment of the error
    "f-nan-row": (_feats(), lambda p: _edit_npy(p, _nan_row), "is not finite"),
    "f-inf": (_feats(), lambda p: _edit_npy(p, lambda a: np.where(np.arange(a.size).reshape(a.shape) == 5,
                                                                  np.inf, a).astype(a.dtype)), "is not finite"),
    "f-beyond-float16": (_feats(), lambda p: _edit_npy(p, lambda a: (a.astype(np.float64) * 1e6)), "float16"),
    "f-1d": (_feats(), lambda p: _edit_npy(p, lambda a: a.ravel()), "[N, E]"),
    "f-integers": (_feats(), lambda p: _edit_npy(p, lambda a: (a * 100).astype(np.int32)), "float"),
    "f-no-columns": (_feats(), lambda p: _edit_npy(p, lambda a: a[:, :0]), "no dimensions"),
    "f-other-width": (_feats(), lambda p: _edit_npy(p, lambda a: np.pad(a, ((0, 0), (0, 1)))), "-d"),
    "f-garbage": (_feats(), lambda p: p.write_bytes(b"\x93NUMPY garbage"), "cannot read"),
    "f-pickle": (_feats(), lambda p: np.save(p, np.array([{"a": 1}], dtype=object), allow_pickle=True), "cannot read"),
    "f-missing": (_feats(), lambda p: p.unlink(), "does not exist"),
    "s-fraction": (_segs(), lambda p: _edit_npy(p, lambda a: a + 0.5), "non-integer"),
    "s-nan": (_segs(), lambda p: _edit_npy(p, lambda a: np.where(a == a.max(), np.nan, a)), "non-integer"),
    "s-index-too-big": (_segs(), lambda p: _edit_npy(p, lambda a: np.where(a == a.max(), 10**6, a)), "outside"),
    "s-index-huge-float": (_segs(), lambda p: _edit_npy(p, lambda a: np.where(a == a.max(), 1e30, a)), "outside"),
    "s-index-below": (_segs(), lambda p: _edit_npy(p, lambda a: np.where(a == a.max(), -2, a)), "outside"),
    "s-wrong-size": (_segs(), lambda p: _edit_npy(p, lambda a: a[:, :-1]), "but the image is"),
    "s-strings": (_segs(), lambda p: np.save(p, np.full((4, 60, 80), "a")), "integer"),
    "s-4d": (_segs(), lambda p: _edit_npy(p, lambda a: a[None]), "[levels, H, W]"),
    "s-row-in-two-levels": (_segs(), lambda p: _edit_npy(p, _same_row_twice), "level layout"),
    "s-missing": (_segs(), lambda p: p.unlink(), "does not exist"),
    "encoder-json": ("encoder.json", lambda p: p.write_text("{"), "encoder"),
}


def _same_row_twice(a: np.ndarray) -> np.ndarray:
    a = a.copy()
    row = a[2][a[2] >= 0].flat[0]
    a[3][a[3] == a[3].max()] = row  # level l now reuses one of level m's rows
    return a


@pytest.mark.parametrize("case", sorted(LANGSPLAT))
def test_corrupt_langsplat_features(case, base, tmp_path, capsys):
    name, corrupt, fragment = LANGSPLAT[case]
    feats = copy(base["features"], tmp_path / "features")
    corrupt(feats / name)
    bank = tmp_path / "bank"
    line = assert_refused(capsys, ["segments-from-langsplat", base["scene"], "--features", feats, "--depth-source",
                                   "gt", "--out", bank, "--quiet"], [bank, feats, base["scene"]], name, fragment)
    if case == "f-nan-row":
        assert "row 17 of frame_00003_f.npy is not finite" in line


# ------------------------------------------------------------------------------------ labels
def _label(fn) -> Callable[[Path], None]:
    return lambda p: edit_json(p, fn)


def _seg(fn):
    return _label(lambda d: fn(d["objects"][0]["segmentation"]))


LABELS = {
    "not-json": lambda p: p.write_text("{"),
    "list": lambda p: p.write_text("[]"),
    "no-info": _label(lambda d: d.pop("info")),
    "height-zero": _label(lambda d: d["info"].update(height=0)),
    "width-fraction": _label(lambda d: d["info"].update(width=80.5)),
    "width-text": _label(lambda d: d["info"].update(width="80")),
    "size-absurd": _label(lambda d: d["info"].update(width=10**6, height=10**6)),
    "name-number": _label(lambda d: d["info"].update(name=5)),
    "objects-not-list": _label(lambda d: d.update(objects={})),
    "object-not-dict": _label(lambda d: d["objects"].__setitem__(0, "mug")),
    "no-segmentation": _label(lambda d: d["objects"][0].pop("segmentation")),
    "empty-segmentation": _label(lambda d: d["objects"][0].update(segmentation=[])),
    "vertex-text": _seg(lambda s: s[0].__setitem__(0, "x")),
    "vertex-nan": _seg(lambda s: s[0].__setitem__(0, float("nan"))),
    "vertex-inf": _seg(lambda s: s[1].__setitem__(1, float("-inf"))),
    "vertex-huge-integer": _seg(lambda s: s[0].__setitem__(0, 10**400)),
    "vertex-three-numbers": _seg(lambda s: s[0].append(1)),
    "empty-category": _label(lambda d: d["objects"][0].update(category=" ")),
    "bbox-short": _label(lambda d: d["objects"][0].update(bbox=[1, 2, 3])),
    "bbox-nan": _label(lambda d: d["objects"][0]["bbox"].__setitem__(0, float("nan"))),
}


@pytest.mark.parametrize("case", sorted(LABELS))
def test_corrupt_labels(case, base, tmp_path, capsys):
    labels = copy(base["scene"] / "label", tmp_path / "label")
    LABELS[case](labels / "frame_00005.json")
    out = tmp_path / "eval"
    assert_refused(capsys, ["eval", base["run"], "--labels", labels, "--out", out, "--quiet"],
                   [out, labels, base["run"]], "frame_00005.json")


def test_label_file_names_and_frames(base, tmp_path, capsys):
    labels = copy(base["scene"] / "label", tmp_path / "label")
    shutil.copyfile(labels / "frame_00005.json", labels / "frame_0000x.json")
    out = tmp_path / "eval"
    assert_refused(capsys, ["eval", base["run"], "--labels", labels, "--out", out, "--quiet"],
                   [out, labels, base["run"]], "frame_0000x.json")
    (labels / "frame_0000x.json").unlink()
    shutil.copyfile(labels / "frame_00005.json", labels / "frame_00099.json")  # the scene has 6 views
    assert_refused(capsys, ["eval", base["run"], "--labels", labels, "--out", out, "--quiet"],
                   [out, labels, base["run"]], "frame_00099")


def test_huge_polygon_coordinates_are_clipped():
    from n2f2.data.labels import clip_polygon, polygon_to_mask

    import cv2

    H, W = 60, 80
    mask = polygon_to_mask([[10, 10], [1e12, 20], [30, 50]], H, W)
    # Worked by hand: inside the image the edges to (1e12, 20) are the rows y = 10 and y = 50 (to
    # within 1e-9 px), so the triangle is the quadrilateral (10, 10) (79, 10) (79, 50) (30, 50).
    reference = np.zeros((H, W), np.uint8)
    cv2.fillPoly(reference, [np.array([[10, 10], [79, 10], [79, 50], [30, 50]], np.int32)], 1)
    assert (mask != reference.astype(bool)).sum() <= W  # at most the boundary row y = 50 differs
    assert mask[30, 40] and mask[10, 70] and not mask[55, 40] and not mask[30, 5]
    # Clipping keeps every point inside the box inside (a square clipped to itself is itself).
    square = np.array([[0, 0], [10, 0], [10, 10], [0, 10]], float)
    np.testing.assert_array_equal(clip_polygon(square, (-1, -1, 11, 11)), square)
    np.testing.assert_allclose(clip_polygon(square, (5, -1, 11, 11)), [[5, 0], [10, 0], [10, 10], [5, 10]])


# ------------------------------------------------------------------------------------ NaN never written
def test_nan_langsplat_features_are_refused_on_import(base, tmp_path, capsys):
    feats = copy(base["features"], tmp_path / "features")
    _edit_npy(feats / "frame_00003_f.npy", _nan_row)
    bank = tmp_path / "bank"
    assert_refused(capsys, ["segments-from-langsplat", base["scene"], "--features", feats, "--depth-source", "gt",
                            "--out", bank, "--quiet"], [bank], "row 17 of frame_00003_f.npy is not finite")
    assert not bank.exists()


def _train_args(base: dict, out: Path, *extra) -> list:
    return ["train", base["scene"], "--gaussians", base["ply"], "--segments", base["bank"], "--out", out,
            "--iterations", 3, "--pixels-per-step", 256, "--dim", 16, "--plane-resolution", 16,
            "--plane-channels", 4, "--hidden", 32, "--quiet", *extra]


@pytest.mark.parametrize("extra", [("--cos-weight", "nan"), ("--pixels-per-step", "0"), ("--cos-weight", "inf")])
def test_nan_training_options_are_refused(extra, base, tmp_path, capsys):
    out = tmp_path / "run"
    assert_refused(capsys, _train_args(base, out, *extra), [out], extra[0])
    assert not out.exists()


def test_infinite_depth_spread_is_refused(base, tmp_path, capsys):
    out = tmp_path / "fit"
    assert_refused(capsys, ["fit-gaussians", base["scene"], "--out", out, "--steps", 2, "--depth-spread", "inf",
                            "--quiet"], [out], "--depth-spread")
    assert not out.exists()


def test_bank_with_nan_embedding_is_refused_by_train(base, tmp_path, capsys):
    bank = copy(base["bank"], tmp_path / "bank")
    emb = bank / "frame_00003" / "embeddings.npy"
    _edit_npy(emb, _nan_row)
    out = tmp_path / "run"
    assert_refused(capsys, [*_train_args(base, out)[:5], bank, *_train_args(base, out)[6:]], [out, bank],
                   "frame_00003/embeddings.npy", "not finite")
    assert_all_finite(out)


@pytest.mark.parametrize("command", ["query", "eval"])
def test_nan_field_from_an_older_version_is_refused(command, base, tmp_path, capsys):
    run = copy(base["run"], tmp_path / "run")
    blob = torch.load(run / "field.pt", weights_only=True)
    blob["state_dict"]["W"][3, 1] = float("nan")
    torch.save(blob, run / "field.pt")  # as written before saves were checked
    out = tmp_path / "out"
    argv = {"query": ["query", run, "teapot", "--out", out, "--quiet"],
            "eval": ["eval", run, "--labels", base["scene"] / "label", "--out", out, "--quiet"]}[command]
    line = assert_refused(capsys, argv, [out, run], "field.pt", "NaN or infinite", "W (1 of ")
    assert "Traceback" not in line


# ------------------------------------------------------------------------------------ non-finite steps
@pytest.fixture(scope="module")
def train_inputs(base):
    from n2f2.data import load_scene
    from n2f2.gaussians import read_ply
    from n2f2.segments import SegmentBank

    return load_scene(base["scene"]), read_ply(base["ply"]), SegmentBank.open(base["bank"])


def _tiny_train(**over):
    from n2f2.field import FieldConfig
    from n2f2.train.config import TrainConfig

    field = FieldConfig(dim=12, plane_resolution=16, plane_channels=4, hidden=32)
    config = TrainConfig(iterations=over.pop("iterations", 12), pixels_per_step=128, blend_cache=True,
                         checkpoint_every=over.pop("checkpoint_every", 4), log_every=2, **over)
    return field, config


def _flaky_loss(monkeypatch, bad: Callable[[int], bool]) -> dict:
    import n2f2.train.trainer as trainer

    calls = {"n": 0}

    def flaky(real):  # both losses (the cpu preset's every-segment one too), one step count
        def loss(*args):
            calls["n"] += 1
            total, l2, cos = real(*args)
            return (total * float("nan") if bad(calls["n"]) else total), l2, cos

        return loss

    monkeypatch.setattr(trainer, "projected_loss", flaky(trainer.projected_loss))
    monkeypatch.setattr(trainer, "prefix_projected_loss", flaky(trainer.prefix_projected_loss))
    return calls


def test_non_finite_steps_are_skipped(train_inputs, tmp_path, monkeypatch):
    from n2f2.train.trainer import train_field

    scene, gaussians, bank = train_inputs
    field_config, config = _tiny_train()
    _flaky_loss(monkeypatch, lambda n: n in (3, 4, 9))
    report = train_field(scene, gaussians, bank, tmp_path, field_config=field_config, config=config, progress=False)
    assert report["steps"] == 12 and report["skipped_steps"] == 3
    # log_every = 2: steps 3 and 4 were both skipped, so the curve has no point at step 4.
    assert report["curve"]["step"] == [2, 6, 8, 10, 12] and all(np.isfinite(report["curve"]["loss"]))
    assert_all_finite(tmp_path)
    assert (tmp_path / "field.pt").is_file()


def test_training_stops_after_max_bad_steps(base, train_inputs, tmp_path, monkeypatch, capsys):
    from n2f2.train.trainer import train_field

    scene, gaussians, bank = train_inputs
    field_config, config = _tiny_train(iterations=60)
    calls = _flaky_loss(monkeypatch, lambda n: n >= 6)  # steps 6, 7, ... are all non-finite
    with pytest.raises(NonFiniteError, match=f"stopped at step {5 + MAX_BAD_STEPS}: the last {MAX_BAD_STEPS} steps"):
        train_field(scene, gaussians, bank, tmp_path, field_config=field_config, config=config, progress=False)
    assert calls["n"] == 5 + MAX_BAD_STEPS
    assert not (tmp_path / "field.pt").exists()
    assert_all_finite(tmp_path)  # the checkpoints before and during the bad run hold the good state
    # The same through the CLI: one line, exit 2, no field.
    _flaky_loss(monkeypatch, lambda n: True)
    out = tmp_path / "cli"
    line = assert_refused(capsys, _train_args(base, out, "--iterations", 40), [], "training stopped at step")
    assert f"the last {MAX_BAD_STEPS} steps" in line and not (out / "field.pt").exists()
    assert_all_finite(out)


def test_fit_stops_after_max_bad_steps(base, tmp_path, monkeypatch):
    import n2f2.gaussians.fit as fit_mod
    from n2f2.data import load_scene
    from n2f2.gaussians.fit import FitConfig, fit_gaussians

    real = fit_mod.photometric_loss
    monkeypatch.setattr(fit_mod, "photometric_loss", lambda *a, **k: real(*a, **k) * float("nan"))
    config = FitConfig.preset("cpu").sized_for(load_scene(base["scene"]), steps=50)
    with pytest.raises(NonFiniteError, match=f"stopped at step {MAX_BAD_STEPS}"):
        fit_gaussians(load_scene(base["scene"]), config, tmp_path, progress=False)
    assert not (tmp_path / "gaussians.ply").exists()
    assert_all_finite(tmp_path)


def test_saves_refuse_non_finite_tensors(tmp_path):
    from n2f2.gaussians.model import Gaussians
    from n2f2.gaussians.ply import write_ply
    from n2f2.validate import check_finite

    g = Gaussians(torch.zeros(2, 3), torch.tensor([[1.0, 0, 0, 0]] * 2), torch.zeros(2, 3), torch.zeros(2),
                  torch.zeros(2, 1, 3))
    with torch.no_grad():
        g.means[1, 0] = float("nan")
    with pytest.raises(NonFiniteError, match="1 of 2 Gaussians"):
        write_ply(tmp_path / "g.ply", g)
    with pytest.raises(NonFiniteError, match=r"state.*\[1\].*exp_avg"):
        check_finite(tmp_path / "c.pt", {"state": {1: {"exp_avg": torch.tensor([0.0, float("inf")])}}})
    assert list(tmp_path.iterdir()) == []


# ------------------------------------------------------------------------------------ no silent overwrite
def test_train_rerun_needs_resume_or_force(base, tmp_path, capsys):
    run = copy(base["run"], tmp_path / "run")
    assert_refused(capsys, _train_args(base, run), [run], str(run), "--resume", "--force")
    half = tmp_path / "half"  # a run killed after its first checkpoint
    half.mkdir()
    shutil.copyfile(run / "checkpoint.pt", half / "checkpoint.pt")
    assert_refused(capsys, _train_args(base, half), [half], "checkpoint.pt", "--resume")
    assert_refused(capsys, _train_args(base, run, "--resume", "--force"), [run], "--resume", "--force")
    old = folder_state(run)
    assert run_cli(_train_args(base, run, "--force")) == 0
    new = folder_state(run)
    assert new["field.pt"] != old["field.pt"] and new["checkpoint.pt"] != old["checkpoint.pt"]
    assert json.loads((run / "train_report.json").read_text())["steps"] == 3
    assert_all_finite(run)


def test_fit_rerun_needs_resume_or_force(base, tmp_path, capsys):
    fit = copy(base["fit"], tmp_path / "fit")
    args = ["fit-gaussians", base["scene"], "--out", fit, "--steps", 2, "--quiet"]
    assert_refused(capsys, args, [fit], str(fit), "gaussians.ply", "--resume", "--force")
    half = tmp_path / "half"
    half.mkdir()
    shutil.copyfile(fit / "checkpoint.pt", half / "checkpoint.pt")
    assert_refused(capsys, ["fit-gaussians", base["scene"], "--out", half, "--steps", 2, "--quiet"], [half],
                   "checkpoint.pt")
    old = folder_state(fit)
    assert run_cli([*args, "--force"]) == 0
    new = folder_state(fit)
    assert new["gaussians.ply"] != old["gaussians.ply"]
    assert json.loads((fit / "fit_report.json").read_text())["steps"] == 2
    assert_all_finite(fit)


def test_segments_rerun_needs_resume_or_force(base, tmp_path, capsys):
    bank = copy(base["bank"], tmp_path / "bank")
    args = ["segments", base["scene"], "--segmenter", "ground-truth", "--encoder", "captions", "--depth-source", "gt",
            "--out", bank, "--quiet"]
    assert_refused(capsys, args, [bank], str(bank), "bank.json", "--resume", "--force")
    (bank / "bank.json").unlink()  # an interrupted bank: records but no bank.json
    assert_refused(capsys, args, [bank], "frame_0000")
    assert run_cli([*args, "--force"]) == 0
    assert json.loads((bank / "bank.json").read_text())["complete"] is True
    assert json.loads((bank / "bank.json").read_text())["lifting"]["depth_source"] == "gt"


def test_export_never_overwrites(base, tmp_path, capsys):
    out = copy(base["features"], tmp_path / "features")
    np.save(out / "frame_00001_f.npy", np.zeros((2, 3), np.float32))  # not what the export would write
    args = ["segments-export-langsplat", base["bank"], "--out", out, "--quiet"]
    assert_refused(capsys, args, [out], str(out), "frame_00001", "--force")
    assert run_cli([*args, "--force"]) == 0
    assert folder_state(out) == folder_state(base["features"])


def test_langsplat_import_notices_changed_features(base, tmp_path, capsys):
    feats = copy(base["features"], tmp_path / "features")
    bank = tmp_path / "bank"
    args = ["segments-from-langsplat", base["scene"], "--features", feats, "--depth-source", "gt", "--out", bank,
            "--quiet"]
    assert run_cli(args) == 0
    assert_refused(capsys, args, [bank], "--resume", "--force")  # a plain rerun
    assert run_cli([*args, "--resume"]) == 0  # same features: nothing to do
    _edit_npy(feats / "frame_00002_f.npy", lambda a: -a)  # other, still valid features
    assert_refused(capsys, [*args, "--resume"], [bank], "bank.json", "changed", "--force")
    assert run_cli([*args, "--force"]) == 0
    from n2f2.segments import SegmentBank

    rec = SegmentBank.open(bank).record(1)  # LangSplat row r is bank segment r
    np.testing.assert_allclose(rec.embeddings, -np.load(base["features"] / "frame_00002_f.npy"), atol=1e-3)


def test_query_rerun_needs_force(base, tmp_path, capsys):
    out = tmp_path / "query"
    args = ["query", base["run"], "teapot", "red mug", "--views", 1, "--out", out, "--quiet"]
    assert run_cli(args) == 0
    line = assert_refused(capsys, args, [out], str(out), "query.json", "--force")
    assert "--resume" not in line
    (out / "notes.txt").write_text("not a query result")
    # --force with another question replaces the whole previous answer, and only it.
    other = ["query", base["run"], "cookies", "--views", 1, "--out", out, "--quiet"]
    assert run_cli([*other, "--force"]) == 0
    summary = json.loads((out / "query.json").read_text())
    (view,) = summary["views"]
    assert [r["query"] for r in view["queries"]] == ["cookies"]
    listed = {"query.json", "notes.txt", f"{view['view']}_rgb.png", *view["queries"][0]["files"].values()}
    assert {p.name for p in out.iterdir()} == listed
    # An interrupted query (files but no query.json) is refused too, naming what is there.
    (out / "query.json").unlink()
    assert_refused(capsys, other, [out], f"{view['view']}_cookies.npy", "--force")


def test_render_rerun_needs_force(base, tmp_path, capsys):
    out = tmp_path / "render"
    args = ["render", base["ply"], "--out", out, "--size", 8, 8]
    assert run_cli([*args, "--views", 2]) == 0
    line = assert_refused(capsys, [*args, "--views", 2], [out], str(out), "cameras.json", "orbit_00", "--force")
    assert "--resume" not in line
    assert run_cli([*args, "--views", 1, "--force"]) == 0  # the renders of the earlier, longer orbit go too
    assert sorted(p.name for p in out.iterdir()) == ["cameras.json", "orbit_00.npy", "orbit_00.png"]
    assert len(json.loads((out / "cameras.json").read_text())) == 1


def test_eval_rerun_needs_force(base, tmp_path, capsys):
    out = tmp_path / "eval"
    labels = base["scene"] / "label"
    args = ["eval", base["run"], "--labels", labels, "--out", out, "--mode", "composite", "--quiet"]
    assert run_cli(args) == 0
    names = set(folder_state(out))
    line = assert_refused(capsys, args, [out], str(out), "eval.json", "--force")
    assert "--resume" not in line
    # With --force, bad inputs still leave the previous evaluation as it was.
    bad = copy(labels, tmp_path / "label")
    LABELS["not-json"](bad / "frame_00005.json")
    assert_refused(capsys, [*args[:3], bad, *args[4:], "--force"], [out, bad], "frame_00005.json")
    assert_refused(capsys, [*args, "--force", "--compare", out / "eval.json"], [out], "--compare", "copy it")
    (out / "delta_composite_exact.png").write_bytes(b"a plot of an earlier --compare")
    assert run_cli([*args, "--force"]) == 0
    assert set(folder_state(out)) == names


def test_fit_resume_without_checkpoint(base, tmp_path, capsys):
    fit = copy(base["fit"], tmp_path / "fit")
    (fit / "checkpoint.pt").unlink()  # finished results, but nothing to continue from
    args = ["fit-gaussians", base["scene"], "--steps", 2, "--resume"]
    assert_refused(capsys, [*args, "--out", fit, "--quiet"], [fit], str(fit), "no checkpoint.pt", "gaussians.ply",
                   "--force")
    empty = tmp_path / "empty"  # nothing there: --resume starts from scratch and says so
    capsys.readouterr()
    assert run_cli([*args, "--out", empty]) == 0
    assert "starting from scratch" in capsys.readouterr().out
    assert json.loads((empty / "fit_report.json").read_text())["steps"] == 2


def test_bank_resume_with_other_settings_offers_force(base, tmp_path):
    from n2f2.errors import InputError
    from n2f2.segments.bank import _check_resume

    bank = copy(base["bank"], tmp_path / "bank")  # built with rendered depth
    header = json.loads((bank / "bank.json").read_text())
    header["lifting"] = {**header["lifting"], "depth_source": "gt"}
    with pytest.raises(InputError, match="different lifting settings; pass --force to replace it") as e:
        _check_resume(bank / "bank.json", header)
    assert "delete" not in str(e.value)
    (bank / "bank.json").write_text("{")
    with pytest.raises(InputError, match="cannot read existing bank.json .*; pass --force") as e:
        _check_resume(bank / "bank.json", header)
    assert "delete" not in str(e.value)


def test_run_reruns_evaluation_into_its_own_folder(base, tmp_path, capsys):
    """`n2f2 run` passes --force to a stage its cache decided to rerun: new labels re-evaluate."""
    labels = copy(base["scene"] / "label", tmp_path / "label")
    run = tmp_path / "run"
    args = ["run", base["scene"], "--out", run, "--gaussians", base["ply"], "--labels", labels, "--train-steps", 2,
            "--dim", 16, "--modes", "composite", "--quiet"]
    assert run_cli(args) == 0
    (labels / "frame_00002.json").unlink()
    capsys.readouterr()
    assert run_cli(args) == 0
    out = capsys.readouterr().out
    assert "[train] up to date" in out and "[eval] running" in out
    frames = json.loads((run / "eval" / "eval.json").read_text())["relevancy_files"]
    assert sorted(frames) == ["frame_00005"]


# ------------------------------------------------------------------------------------ temp files
def test_atomic_temp_file_names_are_recognised(tmp_path):
    from n2f2.io import _TEMP_NAME, atomic_path

    with atomic_path(tmp_path / "checkpoint.pt") as tmp:
        assert _TEMP_NAME.match(tmp.name), tmp.name
        tmp.write_bytes(b"x")
    for name in ("checkpoint.pt", "notes.tmp", ".hidden", "a.tmp.txt"):
        assert not _TEMP_NAME.match(name), name


def test_orphaned_temp_files_are_removed_on_the_next_run(base, tmp_path, capsys):
    import subprocess
    import sys

    out = copy(base["features"], tmp_path / "features")
    orphans = [out / ".frame_00001_f.npy.k2j4h8q1.tmp.npy", out / ".encoder.json.a_b9c0d1.tmp.json"]
    keep = [out / "notes.tmp", out / ".hidden"]
    for p in orphans + keep:
        p.write_bytes(b"partial")
    assert run_cli(["segments-export-langsplat", base["bank"], "--out", out, "--force", "--quiet"]) == 0
    assert not any(p.exists() for p in orphans) and all(p.exists() for p in keep)
    # A process killed (SIGKILL) in the middle of an atomic checkpoint write leaves its temp file;
    # the next command in that folder removes it, even one that then refuses to run.
    run = copy(base["run"], tmp_path / "run")
    killed = ("import os, signal, sys\nfrom n2f2.io import atomic_path\n"
              "with atomic_path(sys.argv[1]) as tmp:\n    tmp.write_bytes(b'partial')\n"
              "    os.kill(os.getpid(), signal.SIGKILL)\n")
    proc = subprocess.run([sys.executable, "-c", killed, str(run / "checkpoint.pt")], capture_output=True)
    assert proc.returncode == -9
    left = list(run.glob(".checkpoint.pt.*.tmp.pt"))
    assert len(left) == 1
    capsys.readouterr()
    assert run_cli(_train_args(base, run)) == 2
    assert not left[0].exists() and (run / "checkpoint.pt").is_file()
    # One level down too: a held-out render of a fit.
    fit = copy(base["fit"], tmp_path / "fit")
    orphan = fit / "test_views" / ".frame_00001.png.q0w9e8r7.tmp.png"
    orphan.write_bytes(b"partial")
    assert run_cli(["fit-gaussians", base["scene"], "--out", fit, "--quiet"]) == 2
    assert not orphan.exists()
