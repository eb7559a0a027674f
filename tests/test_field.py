"""The nested feature field: TriPlane / PE backbones, scale-masked projection W, variants, files."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from n2f2.errors import InputError
from n2f2.field import (FieldConfig, NestedField, PositionalEncoding, TriPlane, bbox_from_points,
                        check_embed_dim, gaussian_features, level_blocks, load_field, save_field)


def small_field(variant: str = "nested", backbone: str = "triplane", dim: int = 12, embed: int = 5,
                step_size: int = 1, seed: int = 0) -> NestedField:
    torch.manual_seed(seed)
    cfg = FieldConfig(backbone=backbone, dim=dim, plane_resolution=8, plane_channels=4, hidden=16,
                      pe_frequencies=3, variant=variant, step_size=step_size)
    return NestedField(cfg, embed, np.array([-1.0, -2.0, 0.0]), np.array([1.0, 2.0, 4.0]))


def randomize_W(field: NestedField, seed: int = 1) -> None:
    with torch.no_grad():
        field.W.copy_(torch.randn(field.W.shape, generator=torch.Generator().manual_seed(seed)))


# ---------------------------------------------------------------------------------- masking
def test_mask_equals_explicit_slice_form():
    field = small_field(dim=12, embed=5)
    randomize_W(field)
    g = torch.Generator().manual_seed(3)
    theta = torch.randn(40, 12, generator=g)
    M = torch.randint(1, 13, (40,), generator=g)
    phi = field.scale_aware(theta, M)
    W = field.W.detach()
    # Paper eq. 4, literally: W_{1:M} theta_{1:M}, one row at a time.
    expected = torch.stack([W[:, :m] @ theta[b, :m] for b, m in enumerate(M.tolist())])
    torch.testing.assert_close(phi, expected, rtol=1e-5, atol=1e-5)


def test_nested_dims_follow_step_size():
    # D = 12, k = 4: floor(12/4) = 3 quantized scales -> M in {4, 8, 12}; by hand:
    # s=0 -> 4 ceil(3) = 12, s=0.4 -> 4 ceil(1.8) = 8, s=0.7 -> 4 ceil(0.9) = 4.
    field = small_field(dim=12, step_size=4)
    s = torch.tensor([0.0, 0.4, 0.7, 0.999])
    assert field.dims_for_scale(s).tolist() == [12, 8, 4, 4]
    mask = field.supervision_mask(s)
    assert mask.sum(1).tolist() == [12, 8, 4, 4]
    assert torch.equal(mask[1], torch.tensor([1.0] * 8 + [0.0] * 4))  # a prefix: coarse = first dims
    # k = 1 is the paper's ceil(D (1 - s)).
    assert small_field(dim=12).dims_for_scale(torch.tensor([0.0, 0.5, 0.95])).tolist() == [12, 6, 1]


def test_flat_variant_supervises_all_dims():
    field = small_field(variant="flat")
    randomize_W(field)
    s = torch.tensor([0.05, 0.5, 0.95])
    assert torch.equal(field.supervision_mask(s), torch.ones(3, 12))
    theta = torch.randn(1, 12).expand(3, 12)
    phi = field.project(theta, field.supervision_mask(s))
    torch.testing.assert_close(phi[0], phi[2])  # phi does not depend on s
    torch.testing.assert_close(phi[0], field.W.detach() @ theta[0])


def test_levels_variant_blocks():
    field = small_field(variant="levels", dim=12)
    randomize_W(field)
    assert level_blocks(12) == [(0, 4), (4, 8), (8, 12)]
    # three_level_groups: s < 1/3 -> part (0), >= 2/3 -> group (2); part lives in the last block.
    mask = field.supervision_mask(torch.tensor([0.1, 0.5, 0.9]))
    assert mask[0].nonzero().squeeze(1).tolist() == [8, 9, 10, 11]
    assert mask[1].nonzero().squeeze(1).tolist() == [4, 5, 6, 7]
    assert mask[2].nonzero().squeeze(1).tolist() == [0, 1, 2, 3]
    theta = torch.randn(6, 12)
    lf = field.level_features(theta)
    assert lf.shape == (6, 3, 5)
    W = field.W.detach()
    torch.testing.assert_close(lf[:, 0], theta[:, 8:] @ W[:, 8:].t())  # part
    torch.testing.assert_close(lf[:, 2], theta[:, :4] @ W[:, :4].t())  # group
    # The masked projection of a part-scale segment is the part level feature.
    torch.testing.assert_close(field.project(theta, mask[0].expand(6, 12)), lf[:, 0])
    assert [b - a for a, b in level_blocks(128)] == [43, 42, 43]  # all D dims used when 3 does not divide D
    with pytest.raises(ValueError):
        field.dims_for_scale(torch.tensor([0.5]))


def test_zero_init_W_gives_zero_output():
    for variant in ("nested", "flat", "levels"):
        field = small_field(variant=variant)
        x = torch.rand(30, 3) * 4 - 2
        theta = field(x)
        assert theta.abs().sum() > 0  # the backbone is not trivially zero ...
        phi = field.project(theta, field.supervision_mask(torch.rand(30)))
        assert torch.count_nonzero(phi) == 0  # ... but W is, so the output is exactly zero


def test_config_validation():
    with pytest.raises(ValueError):
        FieldConfig(dim=12, step_size=13)
    with pytest.raises(ValueError):
        FieldConfig(variant="deep")
    with pytest.raises(ValueError):
        FieldConfig(backbone="hashgrid")
    assert FieldConfig.paper().dim == 512 and FieldConfig.paper().plane_resolution == 512
    assert FieldConfig.paper().plane_channels == 64 and FieldConfig.paper().hidden == 256


# ---------------------------------------------------------------------------------- backbones
def test_triplane_bilinear_and_axes():
    """Plane values that are linear in (column, row) are reproduced exactly by bilinear
    sampling, which pins down which coordinate indexes which plane axis."""
    R, C = 5, 2
    tp = TriPlane(resolution=R, channels=C, reduce="sum")
    grid = torch.linspace(-1, 1, R)  # texel centres with align_corners=True
    with torch.no_grad():
        tp.planes.zero_()
        # plane 0 (xy): channel 0 = x (column coordinate), channel 1 = y (row coordinate)
        tp.planes[0, 0] = grid[None, :].expand(R, R)
        tp.planes[0, 1] = grid[:, None].expand(R, R)
        # plane 2 (yz): channel 0 = 10 z
        tp.planes[2, 0] = 10 * grid[:, None].expand(R, R)
    xyz = torch.tensor([[0.3, -0.7, 0.2], [-1.0, 1.0, -0.45], [2.0, 0.0, 0.0]])
    out = tp(xyz)
    x, y, z = xyz.clamp(-1, 1).unbind(1)  # outside the box: border texel
    torch.testing.assert_close(out[:, 0], x + 10 * z)
    torch.testing.assert_close(out[:, 1], y)


def test_triplane_product_reduce():
    tp = TriPlane(resolution=3, channels=1, reduce="product")
    with torch.no_grad():
        tp.planes.copy_(torch.tensor([2.0, 3.0, 5.0]).view(3, 1, 1, 1).expand(3, 1, 3, 3))
    torch.testing.assert_close(tp(torch.zeros(2, 3)), torch.full((2, 1), 30.0))


@pytest.mark.parametrize("reduce", ["sum", "product"])
def test_triplane_taps_equal_grid_sample_with_gradients(reduce):
    """The fixed-point fast path (precomputed bilinear taps, a gather per step) gives
    grid_sample's values and plane gradients, on the edges and outside the box too."""
    torch.manual_seed(0)
    tp = TriPlane(resolution=6, channels=3, reduce=reduce).double()
    xyz = torch.cat([torch.rand(40, 3, dtype=torch.float64) * 2 - 1,
                     torch.tensor([[1.0, 1.0, 1.0], [-1.0, -1.0, -1.0], [1.0, -1.0, 0.0],
                                   [1.7, 0.2, -3.0], [0.2, 0.6, 1.0]], dtype=torch.float64)])
    upstream = torch.randn(xyz.shape[0], 3, dtype=torch.float64)
    ref = tp(xyz)
    (g_ref,) = torch.autograd.grad((ref * upstream).sum(), tp.texels)
    fast = tp.sample(tp.taps(xyz))
    (g_fast,) = torch.autograd.grad((fast * upstream).sum(), tp.texels)
    torch.testing.assert_close(fast, ref, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(g_fast, g_ref, rtol=1e-12, atol=1e-12)


def test_triplane_loads_a_state_saved_as_channels_first_planes():
    """Fields saved before the texel layout hold ``planes [3, C, R, R]``; they load into
    ``texels [3, R, R, C]`` with every texel in its place."""
    tp = TriPlane(resolution=4, channels=3)
    planes = torch.arange(3 * 3 * 4 * 4, dtype=torch.float32).view(3, 3, 4, 4)  # [plane, channel, row, col]
    tp.load_state_dict({"planes": planes})
    assert tp.texels.shape == (3, 4, 4, 3) and tp.texels.is_contiguous()
    assert float(tp.texels.detach()[2, 1, 3, 0]) == float(planes[2, 0, 1, 3])
    torch.testing.assert_close(tp.planes, planes, rtol=0, atol=0)
    xyz = torch.rand(7, 3) * 2 - 1
    reference = TriPlane(resolution=4, channels=3)
    with torch.no_grad():
        reference.texels.copy_(planes.permute(0, 2, 3, 1))
    torch.testing.assert_close(tp(xyz), reference(xyz))


@pytest.mark.parametrize("backbone", ["triplane", "mlp"])
def test_fixed_point_encoder_equals_encode(backbone):
    field = small_field(backbone=backbone)
    x = torch.rand(9, 3) * 4 - 2  # some outside the bbox
    torch.testing.assert_close(field.fixed_point_encoder(x)(), field.encode(field.normalize(x)))


def test_positional_encoding():
    pe = PositionalEncoding(2)
    x = torch.tensor([[0.25, -0.5, 1.0]])
    out = pe(x)
    assert out.shape == (1, 3 + 12) and pe.out_dim == 15
    a = x[0, 0].item()
    # layout: [x, sin(pi x), sin(2 pi x) (per coordinate, frequency fastest), cos ...]
    assert out[0, 0].item() == pytest.approx(a)
    assert out[0, 3].item() == pytest.approx(math.sin(math.pi * a), abs=1e-6)
    assert out[0, 4].item() == pytest.approx(math.sin(2 * math.pi * a), abs=1e-6)
    assert out[0, 9].item() == pytest.approx(math.cos(math.pi * a), abs=1e-6)


def test_mlp_backbone_field():
    field = small_field(backbone="mlp")
    assert field.feature_dim == 3 + 6 * 3
    assert not any(g["name"] == "triplane" for g in field.param_groups(0.1, 0.01))
    assert field(torch.rand(4, 3)).shape == (4, 12)


def test_normalize_maps_bbox_and_clamps():
    field = small_field()
    x = torch.tensor([[-1.0, -2.0, 0.0], [1.0, 2.0, 4.0], [0.0, 0.0, 2.0], [5.0, -9.0, 1.0]])
    torch.testing.assert_close(field.normalize(x), torch.tensor(
        [[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0], [0.0, 0.0, 0.0], [1.0, -1.0, -0.5]]))


def test_deferred_decode_equals_forward_per_point():
    field = small_field()
    x = torch.rand(7, 3)
    torch.testing.assert_close(field.decode(field.encode(field.normalize(x))), field(x))


def test_gaussian_features_chunks():
    field = small_field()
    x = torch.rand(50, 3)
    full = gaussian_features(field, x, chunk=1000)
    torch.testing.assert_close(gaussian_features(field, x, chunk=7), full)
    torch.testing.assert_close(full, field(x).detach())
    assert gaussian_features(field, torch.zeros(0, 3)).shape == (0, 12)


def test_bbox_from_points_ignores_floaters():
    pts = np.random.default_rng(0).uniform(0, 1, size=(5000, 3))
    pts[0] = [100.0, 100.0, 100.0]
    lo, hi = bbox_from_points(pts, quantile=0.001, pad=0.0)
    assert np.all(hi < 1.01) and np.all(lo > -0.01)


# ---------------------------------------------------------------------------------- files
def test_save_load_roundtrip(tmp_path):
    field = small_field(variant="levels", backbone="triplane")
    randomize_W(field)
    save_field(tmp_path / "field.pt", field, {"encoder_spec": {"name": "x"}, "step": 3})
    loaded, meta = load_field(tmp_path / "field.pt")
    assert meta["step"] == 3 and meta["embed_dim"] == 5 and meta["variant"] == "levels"
    assert meta["config"]["dim"] == 12 and meta["bbox_min"] == [-1.0, -2.0, 0.0]
    x = torch.rand(9, 3)
    torch.testing.assert_close(loaded(x), field(x))
    torch.testing.assert_close(loaded.W, field.W)


def test_load_field_bad_input(tmp_path):
    with pytest.raises(InputError, match="does not exist"):
        load_field(tmp_path / "missing.pt")
    (tmp_path / "junk.pt").write_bytes(b"not a torch file")
    with pytest.raises(InputError, match="cannot read"):
        load_field(tmp_path / "junk.pt")
    torch.save({"something": 1}, tmp_path / "other.pt")
    with pytest.raises(InputError, match="not an n2f2 feature field"):
        load_field(tmp_path / "other.pt")


def test_check_embed_dim():
    meta = {"embed_dim": 512, "encoder_spec": {"name": "clip"}}
    check_embed_dim(meta, 512, "x")
    with pytest.raises(InputError, match="384 does not match"):
        check_embed_dim(meta, 384, "bank.json")
