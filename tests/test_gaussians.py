"""The Gaussian model, INRIA PLY input/output and initialisation."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from n2f2.cameras import Camera, look_at
from n2f2.errors import InputError
from n2f2.gaussians import Gaussians, init_from_points, init_random_in_frusta, read_ply, write_ply
from n2f2.gaussians.init import knn_scale
from n2f2.gaussians.model import SH_C0, rgb_to_sh, sh_to_rgb


def random_gaussians(n: int, degree: int, seed: int = 0) -> Gaussians:
    g = torch.Generator().manual_seed(seed)
    k = (degree + 1) ** 2
    return Gaussians(
        means=torch.randn(n, 3, generator=g),
        quats=torch.randn(n, 4, generator=g),
        log_scales=torch.randn(n, 3, generator=g) - 3.0,
        opacity_logits=torch.randn(n, generator=g),
        sh=torch.randn(n, k, 3, generator=g),
    )


def write_raw_ply(path, columns: dict[str, np.ndarray], fmt: str = "binary_little_endian",
                  extra_header: str = "", truncate: int = 0) -> None:
    """An independent PLY writer (one property per column, float32) for building test files."""
    names = list(columns)
    n = len(next(iter(columns.values())))
    header = f"ply\nformat {fmt} 1.0\n{extra_header}element vertex {n}\n"
    header += "".join(f"property float {name}\n" for name in names) + "end_header\n"
    data = np.stack([np.asarray(columns[c], np.float32) for c in names], axis=1)
    if fmt == "ascii":
        body = "".join(" ".join(repr(float(x)) for x in row) + "\n" for row in data).encode()
    else:
        body = data.astype("<f4" if fmt == "binary_little_endian" else ">f4").tobytes()
    if truncate:
        body = body[:-truncate]
    path.write_bytes(header.encode() + body)


def inria_columns(n: int, degree: int, seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    cols = {name: rng.normal(size=n).astype(np.float32) for name in ["x", "y", "z"]}
    cols.update({f"n{a}": np.zeros(n, np.float32) for a in "xyz"})
    cols.update({f"f_dc_{i}": rng.normal(size=n).astype(np.float32) for i in range(3)})
    cols.update({f"f_rest_{i}": rng.normal(size=n).astype(np.float32) for i in range(3 * ((degree + 1) ** 2 - 1))})
    cols["opacity"] = rng.normal(size=n).astype(np.float32)
    cols.update({f"scale_{i}": (rng.normal(size=n) - 4).astype(np.float32) for i in range(3)})
    cols.update({f"rot_{i}": rng.normal(size=n).astype(np.float32) for i in range(4)})
    return cols


# ------------------------------------------------------------------------------------ model
def test_model_shapes_and_activations():
    g = random_gaussians(5, 2)
    assert g.num == 5 and len(g) == 5
    assert g.max_sh_degree == 2 and g.sh_degree == 2
    assert g.sh.shape == (5, 9, 3)
    torch.testing.assert_close(g.scales, torch.exp(g.log_scales))
    torch.testing.assert_close(g.opacities, 1 / (1 + torch.exp(-g.opacity_logits)))
    assert {n for n, _ in g.named_parameters()} == {"means", "quats", "log_scales", "opacity_logits", "sh"}


def test_model_rejects_bad_shapes():
    with pytest.raises(ValueError):
        Gaussians(torch.zeros(3, 3), torch.zeros(3, 4), torch.zeros(3, 3), torch.zeros(3), torch.zeros(3, 5, 3))
    with pytest.raises(ValueError):
        Gaussians(torch.zeros(3, 3), torch.zeros(2, 4), torch.zeros(3, 3), torch.zeros(3), torch.zeros(3, 4, 3))


def test_subset_selects_rows_and_is_independent():
    g = random_gaussians(6, 1)
    g.sh_degree = 0
    mask = torch.tensor([True, False, True, False, False, True])
    s = g.subset(mask)
    assert s.num == 3 and s.sh_degree == 0 and s.max_sh_degree == 1
    for name in ["means", "quats", "log_scales", "opacity_logits", "sh"]:
        torch.testing.assert_close(getattr(s, name), getattr(g, name)[[0, 2, 5]], rtol=0, atol=0)
    with torch.no_grad():
        s.means.zero_()
    assert g.means.abs().sum() > 0


def test_sh_dc_colour_conversion():
    rgb = torch.tensor([[0.0, 0.5, 1.0]])
    torch.testing.assert_close(rgb_to_sh(rgb), torch.tensor([[-0.5, 0.0, 0.5]]) / SH_C0)
    torch.testing.assert_close(sh_to_rgb(rgb_to_sh(rgb)), rgb)


# ------------------------------------------------------------------------------------ PLY
@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_ply_round_trip_is_exact(tmp_path, degree):
    g = random_gaussians(17, degree, seed=degree)
    path = tmp_path / "g.ply"
    write_ply(path, g)
    r = read_ply(path)
    assert r.max_sh_degree == degree and r.num == 17
    for name in ["means", "quats", "log_scales", "opacity_logits", "sh"]:
        assert torch.equal(getattr(r, name), getattr(g, name)), name
    assert not list(tmp_path.glob(".*tmp*")), "atomic write left a temporary file"


def test_ply_header_is_inria_layout(tmp_path):
    path = tmp_path / "g.ply"
    write_ply(path, random_gaussians(2, 3))
    header = path.read_bytes().split(b"end_header\n")[0].decode()
    props = [line.split()[-1] for line in header.splitlines() if line.startswith("property")]
    expected = (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
                + [f"f_rest_{i}" for i in range(45)]
                + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])
    assert props == expected
    assert "format binary_little_endian 1.0" in header and "element vertex 2" in header
    assert all(line.startswith("property float ") for line in header.splitlines() if line.startswith("property"))


def test_ply_reads_hand_built_file_channel_major(tmp_path):
    # Build the file by hand: f_rest_{c * (K-1) + k} holds channel c of coefficient k + 1.
    n, degree = 4, 1
    cols = inria_columns(n, degree)
    for c in range(3):
        for k in range(3):
            cols[f"f_rest_{c * 3 + k}"] = np.full(n, 10 * c + k, np.float32)
    path = tmp_path / "hand.ply"
    write_raw_ply(path, cols)
    g = read_ply(path)
    assert g.max_sh_degree == 1
    for c in range(3):
        for k in range(3):
            assert torch.all(g.sh[:, 1 + k, c] == 10 * c + k)
    assert np.array_equal(g.means.detach().numpy(), np.stack([cols["x"], cols["y"], cols["z"]], 1))
    assert np.array_equal(g.sh[:, 0].detach().numpy(), np.stack([cols[f"f_dc_{i}"] for i in range(3)], 1))
    assert np.array_equal(g.opacity_logits.detach().numpy(), cols["opacity"])
    assert np.array_equal(g.log_scales.detach().numpy(), np.stack([cols[f"scale_{i}"] for i in range(3)], 1))
    assert np.array_equal(g.quats.detach().numpy(), np.stack([cols[f"rot_{i}"] for i in range(4)], 1))


def test_ply_tolerates_order_extra_props_ascii_and_big_endian(tmp_path):
    cols = inria_columns(3, 0)
    cols = dict(reversed(list(cols.items())))  # any property order
    cols["red"] = np.ones(3, np.float32)  # unknown extra property is ignored
    del cols["nx"], cols["ny"], cols["nz"]  # normals are optional (gsplat omits them)
    ref = None
    for fmt in ["binary_little_endian", "binary_big_endian", "ascii"]:
        path = tmp_path / f"{fmt}.ply"
        write_raw_ply(path, cols, fmt=fmt, extra_header="comment made by a test\n")
        g = read_ply(path)
        if ref is None:
            ref = g
        for name in ["means", "quats", "log_scales", "opacity_logits", "sh"]:
            torch.testing.assert_close(getattr(g, name), getattr(ref, name), rtol=0, atol=0)


def test_ply_missing_property_is_named(tmp_path):
    cols = inria_columns(3, 1)
    del cols["scale_1"], cols["f_rest_4"]
    path = tmp_path / "missing.ply"
    write_raw_ply(path, cols)
    with pytest.raises(InputError) as e:
        read_ply(path)
    assert "scale_1" in str(e.value) and "f_rest_4" in str(e.value) and "missing.ply" in str(e.value)


@pytest.mark.parametrize("prop,value,words", [
    ("x", np.nan, "NaN"),
    ("y", np.inf, "NaN or infinite"),
    ("scale_2", -np.inf, "zero scale"),
    ("f_rest_0", np.nan, "f_rest"),
    ("opacity", np.inf, "opacity"),
])
def test_ply_non_finite_values_are_rejected(tmp_path, prop, value, words):
    cols = inria_columns(5, 1)
    cols[prop][2] = value
    path = tmp_path / "bad.ply"
    write_raw_ply(path, cols)
    with pytest.raises(InputError) as e:
        read_ply(path)
    assert words in str(e.value) and "bad.ply" in str(e.value)


def test_ply_zero_linear_scales_are_rejected(tmp_path):
    cols = inria_columns(5, 0)
    for i in range(3):
        cols[f"scale_{i}"][1] = 0.0
    path = tmp_path / "linear.ply"
    write_raw_ply(path, cols)
    with pytest.raises(InputError, match="exactly 0"):
        read_ply(path)


def test_ply_zero_quaternion_is_rejected(tmp_path):
    cols = inria_columns(5, 0)
    for i in range(4):
        cols[f"rot_{i}"][0] = 0.0
    path = tmp_path / "q.ply"
    write_raw_ply(path, cols)
    with pytest.raises(InputError, match="quaternion"):
        read_ply(path)


def test_ply_truncated_and_not_ply(tmp_path):
    path = tmp_path / "trunc.ply"
    write_raw_ply(path, inria_columns(5, 1), truncate=7)
    with pytest.raises(InputError, match="truncated"):
        read_ply(path)
    path2 = tmp_path / "notply.ply"
    path2.write_bytes(b"hello\nworld\n")
    with pytest.raises(InputError, match="not a PLY"):
        read_ply(path2)
    path3 = tmp_path / "noend.ply"
    path3.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 3\n")
    with pytest.raises(InputError, match="end_header"):
        read_ply(path3)
    with pytest.raises(InputError, match="does not exist"):
        read_ply(tmp_path / "nothing.ply")


def test_ply_bad_rest_count(tmp_path):
    cols = inria_columns(2, 1)
    for i in range(6, 9):
        del cols[f"f_rest_{i}"]  # 6 f_rest: 2 coefficients per channel, not a square count - 1
    path = tmp_path / "rest.ply"
    write_raw_ply(path, cols)
    with pytest.raises(InputError, match="SH degree"):
        read_ply(path)


def test_write_ply_refuses_nan(tmp_path):
    g = random_gaussians(3, 0)
    with torch.no_grad():
        g.means[0, 0] = float("nan")
    with pytest.raises(ValueError):
        write_ply(tmp_path / "nan.ply", g)
    assert not (tmp_path / "nan.ply").exists()


# ------------------------------------------------------------------------------------ init
def test_knn_scale_matches_brute_force():
    rng = np.random.default_rng(1)
    pts = rng.normal(size=(50, 3))
    d2 = ((pts[:, None] - pts[None]) ** 2).sum(-1)
    np.fill_diagonal(d2, np.inf)
    expected = np.sqrt(np.sort(d2, axis=1)[:, :3].mean(axis=1))
    np.testing.assert_allclose(knn_scale(pts), expected, rtol=1e-10)


def test_init_from_points():
    pts = np.array([[0, 0, 0], [1, 0, 0], [0, 2, 0], [0, 0, 3], [1, 1, 1]], dtype=np.float64)
    colors = np.array([[255, 0, 0], [0, 255, 0], [0, 0, 255], [128, 128, 128], [0, 0, 0]], np.uint8)
    g = init_from_points(pts, colors, sh_degree=3)
    assert g.num == 5 and g.max_sh_degree == 3 and g.sh_degree == 0
    torch.testing.assert_close(g.means, torch.tensor(pts, dtype=torch.float32))
    torch.testing.assert_close(g.opacities, torch.full((5,), 0.1))
    assert torch.all(g.quats == torch.tensor([1.0, 0, 0, 0]))
    # point 0: neighbours at distances 1, sqrt(3), 2 -> sqrt((1 + 3 + 4) / 3)
    torch.testing.assert_close(g.scales[0], torch.full((3,), float(np.sqrt(8 / 3))))
    torch.testing.assert_close(g.sh[:, 0] * SH_C0 + 0.5, torch.tensor(colors / 255.0, dtype=torch.float32))
    assert torch.all(g.sh[:, 1:] == 0)


def test_init_from_duplicate_points_has_finite_scale():
    g = init_from_points(np.zeros((4, 3)), np.zeros((4, 3), np.uint8))
    assert torch.isfinite(g.log_scales).all()


def test_init_random_in_frusta_points_are_inside():
    R, t = look_at(np.array([0.0, -4.0, 1.0]), np.zeros(3))
    R2, t2 = look_at(np.array([4.0, 0.0, 1.0]), np.zeros(3))
    cams = [Camera(50, 50, 32, 24, 64, 48, R=R, t=t), Camera(50, 50, 32, 24, 64, 48, R=R2, t=t2)]
    g = init_random_in_frusta(cams, 500, near=1.0, far=6.0, seed=3, sh_degree=1)
    assert g.num == 500 and g.max_sh_degree == 1
    pts = g.means.detach().double().numpy()
    inside_some = np.zeros(len(pts), bool)
    for cam in cams:
        uv, z = cam.project(pts)
        inside = (z >= 1.0 - 1e-4) & (z <= 6.0 + 1e-4) & (uv[:, 0] >= -1e-3) & (uv[:, 0] <= 64 + 1e-3) \
            & (uv[:, 1] >= -1e-3) & (uv[:, 1] <= 48 + 1e-3)
        inside_some |= inside
    assert inside_some.all()
    g2 = init_random_in_frusta(cams, 500, near=1.0, far=6.0, seed=3, sh_degree=1)
    assert torch.equal(g.means, g2.means)


def test_quat_to_rotmat_matches_cameras_convention():
    from n2f2.cameras import qvec_to_rotmat
    from n2f2.gaussians.model import quat_to_rotmat

    q = np.random.default_rng(0).normal(size=(6, 4))
    got = quat_to_rotmat(torch.tensor(q)).numpy()
    for i in range(6):
        np.testing.assert_allclose(got[i], qvec_to_rotmat(q[i]), atol=1e-12)
