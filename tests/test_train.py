"""Feature-field training: sampling, loss, deferred rendering, checkpoints / resume, bad input,
CLI and the per-level cosine evaluation, on a tiny demo scene with a hash "teacher"."""

from __future__ import annotations

import hashlib
import json
from dataclasses import replace

import numpy as np
import pytest
import torch

from n2f2.cli import main as cli_main
from n2f2.data import Scene, load_scene
from n2f2.data.synthetic import generate_demo_scene
from n2f2.errors import InputError
from n2f2.field import FieldConfig, load_field
from n2f2.gaussians import init_from_points, write_ply
from n2f2.segments.bank import SegmentAndEncode, SegmentBank, build_bank
from n2f2.segments.bins import scale_to_dims
from n2f2.segments.lifting import gt_depth_provider
from n2f2.segments.segmenters import GroundTruthSegmenter
from n2f2.train.config import CHECKPOINT_NAME, FIELD_NAME, REPORT_NAME, TrainConfig
from n2f2.train.evaluate import evaluate_cosine_by_level, match_regions_to_segments
from n2f2.train.geometry import bank_cameras, frozen_geometry, render_features
from n2f2.train.losses import hierarchical_loss, prefix_projected_loss, projected_loss
from n2f2.train.sampling import SegmentPool, ViewSegments, covering_probabilities, sample_segments, segment_weights
from n2f2.train.trainer import jitter_scales, train_field

FIELD = FieldConfig(dim=12, plane_resolution=16, plane_channels=4, hidden=32)


class HashEncoder:
    """A deterministic stand-in teacher: each caption -> a fixed random unit vector."""

    name = "hash"
    requires_captions = True
    description = "test teacher"

    def __init__(self, dim: int) -> None:
        self.dim = dim

    @property
    def spec(self) -> dict:
        return {"name": "hash", "embed_dim": self.dim}

    def encode_text(self, texts):
        out = []
        for t in texts:
            seed = int(hashlib.md5(f"{self.dim}:{t}".encode()).hexdigest()[:8], 16)
            v = np.random.default_rng(seed).standard_normal(self.dim)
            out.append(v / np.linalg.norm(v))
        return torch.tensor(np.array(out), dtype=torch.float32)

    def encode_segments(self, image, masks, captions=None):
        return self.encode_text(captions)


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    root = tmp_path_factory.mktemp("train")
    scene_dir = generate_demo_scene(root / "scene", num_views=4, width=32, height=24, num_points=160,
                                    supersample=1, show_progress=False)
    scene = load_scene(scene_dir)
    gaussians = init_from_points(scene.points, scene.point_colors, sh_degree=0)
    write_ply(root / "gaussians.ply", gaussians)
    banks = {}
    for E in (16, 8):
        source = SegmentAndEncode(GroundTruthSegmenter(scene), HashEncoder(E))
        build_bank(scene, source, gt_depth_provider(scene), root / f"bank{E}", progress=False)
        banks[E] = SegmentBank.open(root / f"bank{E}")
    return {"root": root, "scene_dir": scene_dir, "scene": scene, "gaussians": gaussians, "banks": banks}


def tiny_config(**kw) -> TrainConfig:
    base = dict(iterations=6, pixels_per_step=128, log_every=1, checkpoint_every=3, seed=0)
    base.update(kw)
    return TrainConfig(**base)


# ---------------------------------------------------------------------------------- sampling
def test_segment_probabilities_follow_inverse_log_area():
    areas = torch.tensor([10, 100, 1000, 50, 1])
    valid = torch.tensor([True, True, True, False, True])
    w = segment_weights(areas, valid)
    candidates = torch.tensor([[0, 1, 2], [2, 3, -1], [4, -1, 1]])  # [P, L], -1 = none
    p = covering_probabilities(candidates, w)
    ref0 = np.array([1 / np.log(10), 1 / np.log(100), 1 / np.log(1000)])
    np.testing.assert_allclose(p[0].numpy(), ref0 / ref0.sum(), rtol=1e-12)
    np.testing.assert_allclose(p[1].numpy(), [1.0, 0.0, 0.0])  # segment 3 is invalid
    ref2 = np.array([1 / np.log(2), 0.0, 1 / np.log(100)])  # area 1 is clamped to log(2)
    np.testing.assert_allclose(p[2].numpy(), ref2 / ref2.sum(), rtol=1e-12)

    # Empirical frequencies of the sampler match (4 sigma).
    n = 40000
    g = torch.Generator().manual_seed(0)
    chosen = sample_segments(candidates[:1].expand(n, 3), w, g)
    freq = np.bincount(chosen.numpy(), minlength=3)[:3] / n
    sigma = np.sqrt(ref0 / ref0.sum() * (1 - ref0 / ref0.sum()) / n)
    assert np.all(np.abs(freq - ref0 / ref0.sum()) < 4 * sigma)


class _Record:
    def __init__(self, layers, areas, valid, E=4):
        S = len(areas)
        self.layers, self.areas, self.valid = layers, np.asarray(areas), np.asarray(valid)
        self.quantized = np.linspace(0.1, 0.9, S).astype(np.float32)
        self.embeddings = np.eye(S, E, dtype=np.float16)


def test_pixels_uniform_over_covered_pixels_of_views():
    # View a: 2x3 image, 4 pixels covered (one only by an invalid segment -> not covered).
    la = np.array([[[0, 0, -1], [1, 2, -1]]], np.int32)
    lb = np.full((1, 2, 3), 0, np.int32)  # view b: all 6 pixels covered by segment 0
    va = ViewSegments.from_record(0, _Record(la, [2, 1, 1], [True, True, False]))
    vb = ViewSegments.from_record(1, _Record(lb, [6], [True]))
    assert va.covered.tolist() == [0, 1, 3] and len(vb.covered) == 6
    pool = SegmentPool.from_views([va, vb])
    batch = pool.sample(27000, torch.Generator().manual_seed(1))
    counts = np.bincount((batch.slot * 6 + batch.pixel).numpy(), minlength=12)
    covered = [0, 1, 3] + [6 + i for i in range(6)]
    assert set(np.nonzero(counts)[0]) == set(covered)  # never an uncovered pixel
    assert np.all(np.abs(counts[covered] / 27000 - 1 / 9) < 4 * np.sqrt((1 / 9) * (8 / 9) / 27000))
    # Each pixel's segment covers it, and targets / scales are that segment's.
    seg_of = {0: 0, 1: 0, 3: 1}
    a = batch.slot == 0
    assert all(seg_of[p] == s for p, s in zip(batch.pixel[a].tolist(), batch.segment[a].tolist()))
    torch.testing.assert_close(pool.embeddings[batch.pooled[a]], torch.eye(3, 4)[batch.segment[a]])


def test_pool_of_views_with_different_layer_counts():
    """Views whose records have 1 and 2 layers pool together; every sampled segment covers
    its pixel in its own view, and both layers of the 2-layer view get sampled."""
    la = np.array([[[0, 0, -1], [1, 1, -1]]], np.int32)  # 1 layer, 2 segments
    lb = np.stack([np.full((2, 3), 0, np.int32), np.array([[1, -1, 2], [1, -1, 2]], np.int32)])  # 2 layers
    va = ViewSegments.from_record(0, _Record(la, [2, 2], [True, True]))
    vb = ViewSegments.from_record(1, _Record(lb, [6, 2, 2], [True, True, True]))
    pool = SegmentPool.from_views([va, vb])
    batch = pool.sample(4000, torch.Generator().manual_seed(3))
    layers = [la.reshape(1, -1), lb.reshape(2, -1)]
    for slot, pixel, seg in zip(batch.slot.tolist(), batch.pixel.tolist(), batch.segment.tolist()):
        assert seg in layers[slot][:, pixel]
    b = batch.slot == 1
    assert set(batch.segment[b].tolist()) == {0, 1, 2}
    torch.testing.assert_close(pool.embeddings[batch.pooled[b]], torch.eye(3, 4)[batch.segment[b]])


def test_every_segment_rows_are_each_covering_segment_with_its_draw_probability():
    """Hand-built view: 2 layers over a 2x3 image; segment areas 4, 16, 2, 9 -> weights 1/log(area)
    (area 2 stays 2: MIN_AREA). Each sampled pixel gets one row per covering segment, in layer
    order, weighted by its share of the pixel's weights; the pixels are those `sample` draws."""
    import math

    layers = np.stack([np.array([[0, 0, 1], [1, 1, -1]], np.int32), np.array([[2, -1, 3], [3, -1, -1]], np.int32)])
    areas = [4, 16, 2, 9]
    view = ViewSegments.from_record(0, _Record(layers, areas, [True] * 4))
    pool = SegmentPool.from_views([view])
    batch = pool.sample_every_segment(200, torch.Generator().manual_seed(5))
    assert torch.equal(batch.pixel, pool.sample(200, torch.Generator().manual_seed(5)).pixel)
    w = [1 / math.log(a) for a in areas]
    expected = {0: [(0, w[0]), (2, w[2])], 1: [(0, w[0])], 2: [(1, w[1]), (3, w[3])], 3: [(1, w[1]), (3, w[3])],
                4: [(1, w[1])]}
    for i, pixel in enumerate(batch.pixel.tolist()):
        rows = torch.nonzero(batch.row == i).squeeze(1)
        total = sum(x for _, x in expected[pixel])
        assert batch.segment[rows].tolist() == [seg for seg, _ in expected[pixel]]
        assert batch.weight[rows].tolist() == pytest.approx([x / total for _, x in expected[pixel]], rel=1e-6)
        assert batch.scale[rows].tolist() == pytest.approx(view.quantized[batch.segment[rows]].tolist())
    assert torch.equal(batch.pooled, batch.segment)  # one view: pooled ids are its own


def test_balanced_pixels_follow_the_smallest_covering_area():
    """The view of the test above: pixels 0-4 are covered, their smallest covering segments have
    areas 2, 4, 9, 9, 16 (pixel 5 is uncovered). With balance b a pixel is drawn with probability
    area^-b / sum; b = 0 keeps the uniform draw and its random stream."""
    from n2f2.train.sampling import pixel_probabilities

    layers = np.stack([np.array([[0, 0, 1], [1, 1, -1]], np.int32), np.array([[2, -1, 3], [3, -1, -1]], np.int32)])
    view = ViewSegments.from_record(0, _Record(layers, [4, 16, 2, 9], [True] * 4))
    assert view.covered.tolist() == [0, 1, 2, 3, 4]
    finest = np.array([2.0, 4.0, 9.0, 9.0, 16.0])
    for b in (0.5, 1.0):
        ref = finest**-b / (finest**-b).sum()
        pool = SegmentPool.from_views([view], balance=b)
        np.testing.assert_allclose(pixel_probabilities(pool.candidates, view.areas, b).numpy(), ref, rtol=1e-12)
    n = 40000
    batch = SegmentPool.from_views([view], balance=1.0).sample(n, torch.Generator().manual_seed(2))
    freq = np.bincount(batch.pixel.numpy(), minlength=6) / n
    ref = finest**-1.0 / (finest**-1.0).sum()
    assert freq[5] == 0 and np.all(np.abs(freq[:5] - ref) < 4 * np.sqrt(ref * (1 - ref) / n))
    # b = 0: the paper's uniform draw, the same pixels as torch.randint from the same seed.
    uniform = SegmentPool.from_views([view], balance=0.0).sample(300, torch.Generator().manual_seed(4))
    assert uniform.pixel.tolist() == torch.randint(5, (300,), generator=torch.Generator().manual_seed(4)).tolist()
    balanced = SegmentPool.from_views([view], balance=1.0)
    every = balanced.sample_every_segment(300, torch.Generator().manual_seed(4))
    assert torch.equal(every.pixel, balanced.sample(300, torch.Generator().manual_seed(4)).pixel)
    with pytest.raises(ValueError, match="balance"):
        SegmentPool.from_views([view], balance=-1.0)


def test_weighted_projected_loss_is_the_expected_one_segment_loss():
    """Pixel 0 is covered by segments a, b (draw probabilities 0.3, 0.7), pixel 1 by c, d, e
    (0.2, 0.5, 0.3). The weighted loss over all five rows equals the probability-weighted sum of
    the paper's one-segment loss (eq. 5 of phi = x W^T) over all 6 draws, value and gradients."""
    g = torch.Generator().manual_seed(7)
    D, E = 5, 8
    theta = torch.randn(2, D, generator=g, dtype=torch.float64)
    W0 = torch.randn(E, D, generator=g, dtype=torch.float64)
    targets = torch.randn(5, E, generator=g, dtype=torch.float64)  # segments a..e
    dims = [2, 5, 1, 3, 4]  # M(s) of each segment's prefix mask
    mask = (torch.arange(D)[None] < torch.tensor(dims)[:, None]).double()  # [5, D]
    row, prob = torch.tensor([0, 0, 1, 1, 1]), [0.3, 0.7, 0.2, 0.5, 0.3]

    def grads(fn):
        t, W = theta.clone().requires_grad_(), W0.clone().requires_grad_()
        loss = fn(t, W)
        return [loss.detach(), *torch.autograd.grad(loss, (t, W))]

    def expected(t, W):
        total = 0
        for a in (0, 1):
            for b in (2, 3, 4):
                phi = torch.stack([t[0] * mask[a], t[1] * mask[b]]) @ W.t()
                total = total + prob[a] * prob[b] * hierarchical_loss(phi, targets[[a, b]], 0.1)[0]
        return total

    def weighted(t, W):
        x = t.index_select(0, row) * mask
        return projected_loss(x, W, targets, torch.arange(5), 0.1, weight=torch.tensor(prob, dtype=torch.float64))[0]

    for a, b in zip(grads(weighted), grads(expected)):
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-9)


# ---------------------------------------------------------------------------------- loss
def test_hierarchical_loss_known_values():
    phi = torch.tensor([[1.0, 0.0], [0.0, 2.0]])
    target = torch.tensor([[0.0, 1.0], [0.0, 1.0]])
    loss, l2, cos = hierarchical_loss(phi, target, 0.001)
    assert l2.item() == pytest.approx((1 + 1 + 0 + 1) / 4)  # mean squared error
    assert cos.item() == pytest.approx((1.0 + 0.0) / 2)  # mean of 1 - cos
    assert loss.item() == pytest.approx(0.75 + 0.0005)


@pytest.mark.parametrize("mask_kind", ["prefix", "ones", "zero-rows"])
def test_projected_loss_equals_the_loss_of_the_projected_features(mask_kind):
    # The reference: phi = x W^T, targets gathered per pixel, hierarchical_loss (paper eq. 5).
    g = torch.Generator().manual_seed(3)
    P, D, E, T = 50, 6, 9, 7
    theta = torch.randn(P, D, generator=g, dtype=torch.float64)
    if mask_kind == "prefix":
        mask = (torch.arange(D) < torch.randint(1, D + 1, (P, 1), generator=g)).double()
    elif mask_kind == "ones":
        mask = torch.ones(P, D, dtype=torch.float64)
    else:  # some rows project to phi = 0 (cosine clamped, as F.cosine_similarity does)
        mask = torch.ones(P, D, dtype=torch.float64)
        mask[::4] = 0
    targets = torch.randn(T, E, generator=g, dtype=torch.float64)
    index = torch.randint(T, (P,), generator=g)
    W0 = torch.randn(E, D, generator=g, dtype=torch.float64)

    def grads(fn):
        x = (theta * mask).requires_grad_()
        W = W0.clone().requires_grad_()
        loss, l2, cos = fn(x, W)
        gx, gw = torch.autograd.grad(loss, (x, W))
        return [v.detach() for v in (loss, l2, cos, gx, gw)]

    ref = grads(lambda x, W: hierarchical_loss(x @ W.t(), targets[index], 0.1))
    got = grads(lambda x, W: projected_loss(x, W, targets, index, 0.1))
    for a, b in zip(got, ref):
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("weighted", [False, True])
def test_prefix_projected_loss_equals_the_loss_of_the_masked_rows(weighted):
    # The reference: each row's x = theta[row] * prefix mask of M dims through projected_loss (itself
    # checked against eq. 5 above). Rows repeat pixels, M spans 1 .. D, one target is all zeros.
    from n2f2.field.model import prefix_mask

    g = torch.Generator().manual_seed(11)
    P, R, D, E, T = 20, 55, 7, 10, 6
    theta0 = torch.randn(P, D, generator=g, dtype=torch.float64)
    W0 = torch.randn(E, D, generator=g, dtype=torch.float64)
    targets = torch.randn(T, E, generator=g, dtype=torch.float64)
    targets[2] = 0
    row = torch.randint(P, (R,), generator=g)
    dims = torch.randint(1, D + 1, (R,), generator=g)
    dims[:3] = torch.tensor([1, D, D])
    index = torch.randint(T, (R,), generator=g)
    weight = torch.rand(R, generator=g, dtype=torch.float64) if weighted else None

    def grads(fn):
        t, W = theta0.clone().requires_grad_(), W0.clone().requires_grad_()
        loss, l2, cos = fn(t, W)
        return [loss.detach(), l2.detach(), cos.detach(), *torch.autograd.grad(loss, (t, W))]

    ref = grads(lambda t, W: projected_loss(t[row] * prefix_mask(dims, D, torch.float64), W, targets, index, 0.1,
                                            weight))
    got = grads(lambda t, W: prefix_projected_loss(t, row, dims, W, targets, index, 0.1, weight))
    for a, b in zip(got, ref):
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-9)


def _projected_losses(x0, W0, targets, index, rows, dims, index3, weight, dtype=torch.float32):
    """(loss, dloss/dx, dloss/dW) of projected_loss, then of prefix_projected_loss."""
    out = ()
    for fn in (
        lambda x, W: projected_loss(x, W, targets.to(dtype), index, 0.001),
        lambda x, W: prefix_projected_loss(x, rows, dims, W, targets.to(dtype), index3, 0.001, weight.to(dtype)),
    ):
        x, W = x0.to(dtype).requires_grad_(), W0.to(dtype).requires_grad_()
        loss = fn(x, W)[0]
        out += (loss.detach(), *torch.autograd.grad(loss, (x, W)))
    return out


def test_projected_loss_on_one_and_two_threads_agrees_to_float32_rounding():
    # The guarantee across thread counts (serial runs and Ray workers with another
    # OMP_NUM_THREADS, docs/distributed.md): equal to float32 rounding, not bit for bit. The
    # matrix products' sums are ordered by the BLAS, which may split them by thread (MKL on an
    # AVX-512 Xeon does, so the gradients differ in the last bits there). On one thread count
    # the same inputs give the same bits.
    g = torch.Generator().manual_seed(0)
    x0, W0 = torch.randn(4096, 16, generator=g), torch.randn(384, 16, generator=g) * 0.01
    targets, index = torch.randn(300, 384, generator=g), torch.randint(300, (4096,), generator=g)
    rows, index3 = torch.arange(4096).repeat_interleave(3), torch.randint(300, (3 * 4096,), generator=g)
    dims, weight = torch.randint(1, 17, (3 * 4096,), generator=g), torch.rand(3 * 4096, generator=g)
    args = (x0, W0, targets, index, rows, dims, index3, weight)
    reference = _projected_losses(*args, dtype=torch.float64)  # independent of any float32 order
    threads, results = torch.get_num_threads(), {}
    try:
        for n in (1, 2, 1):
            torch.set_num_threads(n)
            got = _projected_losses(*args)
            if n in results:  # the same thread count again: bit for bit
                for a, b in zip(results[n], got):
                    assert torch.equal(a, b)
            results[n] = got
    finally:
        torch.set_num_threads(threads)
    for n, got in results.items():
        for a, ref in zip(got, reference):
            # float32 sums of a few thousand terms: within 1e-5 of the value's scale (measured on
            # a Zen 3: at most 5e-7 from float64; one pixel given another target moves the
            # gradients by 3e-2 to 5e-1 and the loss by 1.5e-5)
            scale = ref.abs().max().item()
            torch.testing.assert_close(a.double(), ref, rtol=0, atol=1e-5 * scale, msg=f"{n} thread(s)")
    for a, b in zip(results[1], results[2]):
        scale = b.abs().max().item()
        torch.testing.assert_close(a, b, rtol=0, atol=1e-5 * scale)


def test_projected_loss_at_zero_projection():
    # W = 0 (its initial value): phi = 0, so L2 = mean |t|^2 and 1 - cos = 1 for every pixel.
    targets = torch.tensor([[3.0, 4.0], [0.0, 1.0]])
    loss, l2, cos = projected_loss(torch.ones(3, 2), torch.zeros(2, 2), targets, torch.tensor([0, 1, 1]), 0.5)
    assert l2.item() == pytest.approx((25 + 1 + 1) / 6)
    assert cos.item() == pytest.approx(1.0)
    assert loss.item() == pytest.approx(27 / 6 + 0.5)


def test_scale_jitter_stays_in_range_and_spreads():
    s = torch.tensor([0.0, 0.5, 0.99]).repeat(4000)
    g = torch.Generator().manual_seed(0)
    assert jitter_scales(s, 0.0, g) is s  # off: nothing drawn
    assert torch.equal(g.get_state(), torch.Generator().manual_seed(0).get_state())
    out = jitter_scales(s, 0.05, g).view(4000, 3)
    assert out.min() >= 0 and out.max() < 1
    assert (out - s.view(4000, 3)).abs().max() <= 0.05 + 1e-7
    mid = out[:, 1]
    assert mid.min() < 0.46 and mid.max() > 0.54 and abs(mid.mean().item() - 0.5) < 0.005  # ~uniform
    with pytest.raises(ValueError, match="scale_jitter"):
        TrainConfig(scale_jitter=float("nan"))
    with pytest.raises(ValueError, match="scale_jitter"):
        TrainConfig(scale_jitter=-0.1)


# ---------------------------------------------------------------------------------- training
@pytest.mark.parametrize("every_segment", [False, True])
def test_short_training_lowers_loss(setup, tmp_path, every_segment):
    bank = setup["banks"][16]
    config = tiny_config(iterations=25, lr_mlp=0.01, checkpoint_every=0, every_segment=every_segment)
    report = train_field(setup["scene"], setup["gaussians"], bank, tmp_path, field_config=FIELD, config=config,
                         progress=False)
    loss = report["curve"]["loss"]
    assert len(loss) == 25
    # Zero-initialised W: phi = 0 at step 0, so the first loss is mean(target^2) = 1/E plus lambda.
    assert loss[0] == pytest.approx(1 / 16 + 0.001, rel=1e-4)
    assert np.mean(loss[-5:]) < 0.9 * loss[0]
    assert report["train_views"] == [1, 2, 3] and report["heldout_views"] == [0]
    for name in (FIELD_NAME, CHECKPOINT_NAME, REPORT_NAME):
        assert (tmp_path / name).is_file()
    field, meta = load_field(tmp_path / FIELD_NAME)
    assert meta["step"] == 25 and meta["embed_dim"] == 16 and meta["encoder_spec"]["name"] == "hash"
    assert meta["heldout_views"] == [0]


def test_resume_after_kill_matches_uninterrupted_run(setup, tmp_path):
    bank = setup["banks"][16]
    cfg = tiny_config(iterations=6, checkpoint_every=3)
    full = train_field(setup["scene"], setup["gaussians"], bank, tmp_path / "a", field_config=FIELD,
                       config=cfg, progress=False)
    field_a, _ = load_field(tmp_path / "a" / FIELD_NAME)

    class Killed(Exception):
        pass

    def kill_at_5(step, loss):
        if step == 5:
            raise Killed

    with pytest.raises(Killed):
        train_field(setup["scene"], setup["gaussians"], bank, tmp_path / "b", field_config=FIELD,
                    config=cfg, progress=False, callback=kill_at_5)
    ck = torch.load(tmp_path / "b" / CHECKPOINT_NAME, weights_only=True)
    assert ck["step"] == 3  # the last checkpoint before the kill
    assert not (tmp_path / "b" / FIELD_NAME).exists()

    seen = {}

    def first_step(step, loss):
        seen.setdefault("first", step)

    resumed = train_field(setup["scene"], setup["gaussians"], bank, tmp_path / "b", field_config=FIELD,
                          config=cfg, resume=True, progress=False, callback=first_step)
    assert seen["first"] == 4  # continued from the saved step
    field_b, _ = load_field(tmp_path / "b" / FIELD_NAME)
    for (name, a), (_, b) in zip(field_a.state_dict().items(), field_b.state_dict().items()):
        assert torch.equal(a, b), name
    assert resumed["curve"] == full["curve"]
    ck_a = torch.load(tmp_path / "a" / CHECKPOINT_NAME, weights_only=True)
    ck_b = torch.load(tmp_path / "b" / CHECKPOINT_NAME, weights_only=True)
    assert torch.equal(ck_a["rng"], ck_b["rng"])
    for sa, sb in zip(ck_a["optimizer"]["state"].values(), ck_b["optimizer"]["state"].values()):
        assert torch.equal(sa["exp_avg"], sb["exp_avg"]) and torch.equal(sa["exp_avg_sq"], sb["exp_avg_sq"])


def test_variants_and_non_deferred_train(setup, tmp_path):
    bank = setup["banks"][16]
    cases = [(replace(FIELD, variant="flat"), True, False),
             (replace(FIELD, variant="levels"), True, False),
             (replace(FIELD, backbone="mlp", pe_frequencies=2), True, False),
             (replace(FIELD, step_size=4), False, False),
             # every covering segment: prefix masks (flat, nested with a step size) and the 3 level blocks
             (replace(FIELD, variant="flat"), True, True),
             (replace(FIELD, variant="levels"), True, True),
             (replace(FIELD, step_size=4), False, True)]
    for i, (fc, deferred, every) in enumerate(cases):
        report = train_field(setup["scene"], setup["gaussians"], bank, tmp_path / str(i), field_config=fc,
                             config=tiny_config(iterations=2, checkpoint_every=0, deferred=deferred,
                                                every_segment=every),
                             progress=False)
        assert report["steps"] == 2 and np.isfinite(report["final_loss"])
        assert (report["rows_per_iteration"] > 128) == every  # 128 pixels; rows: one per covering segment


def test_deferred_gather_matches_full_render(setup):
    """The deferred path's per-pixel rows are the rendered backbone features at those pixels,
    whether rasterized each step or taken from the blend-weight cache."""
    from n2f2.field import NestedField
    from n2f2.train.blend import build_blend_cache
    from n2f2.train.geometry import pixel_theta
    from n2f2.train.sampling import PixelBatch

    scene, bank = setup["scene"], setup["banks"][16]
    torch.manual_seed(0)
    field = NestedField(FIELD, 16, [-3, -3, -3], [3, 3, 3])
    geometry = frozen_geometry(setup["gaussians"], "cpu")
    cams = [bank_cameras(scene, bank)[v] for v in (1, 2)]
    batch = PixelBatch(slot=torch.tensor([1, 0, 1, 0]), pixel=torch.tensor([5, 100, 700, 33]),
                       row=torch.arange(4), segment=torch.zeros(4, dtype=torch.long), scale=torch.zeros(4),
                       pooled=torch.zeros(4, dtype=torch.long), weight=torch.ones(4))
    with torch.no_grad():
        feats = field.encode(field.normalize(geometry["means"]))
        images = [render_features(geometry, feats, cam) for cam in cams]
        expected = field.decode(torch.stack([images[s][p] for s, p in zip(batch.slot.tolist(), batch.pixel.tolist())]))
    theta = pixel_theta(field, geometry, batch, deferred=True, cameras=cams)
    torch.testing.assert_close(theta.detach(), expected)
    cache = build_blend_cache(geometry, cams)
    theta_cached = pixel_theta(field, geometry, batch, deferred=True, cache=cache)
    torch.testing.assert_close(theta_cached.detach(), expected, rtol=1e-5, atol=1e-5)


def test_blend_cache_equals_rasterizer_with_gradients(setup):
    """Cached weights reproduce every pixel of the rasterizer, and the gradient it sends to
    the per-Gaussian features."""
    from n2f2.train.blend import build_blend_cache

    scene = setup["scene"]
    geometry = frozen_geometry(setup["gaussians"], "cpu")
    cams = [scene.cameras[0], scene.cameras[3]]
    cache = build_blend_cache(geometry, cams)
    N = geometry["means"].shape[0]
    g = torch.Generator().manual_seed(0)
    f1 = torch.randn(N, 5, generator=g, requires_grad=True)
    f2 = f1.detach().clone().requires_grad_(True)
    HW = cams[0].width * cams[0].height
    slot = torch.cat([torch.zeros(HW, dtype=torch.long), torch.ones(HW, dtype=torch.long)])
    pixel = torch.cat([torch.arange(HW), torch.arange(HW)])
    ref = torch.cat([render_features(geometry, f1, cam) for cam in cams])  # [2 HW, 5]
    got = cache.blend(f2, slot, pixel)
    torch.testing.assert_close(got, ref, rtol=1e-5, atol=1e-5)
    upstream = torch.randn(ref.shape, generator=g)
    (ref * upstream).sum().backward()
    (got * upstream).sum().backward()
    torch.testing.assert_close(f2.grad, f1.grad, rtol=1e-4, atol=1e-5)
    with pytest.raises(MemoryError):
        build_blend_cache(geometry, cams, max_bytes=100)


def test_blend_gradient_of_a_batch_with_repeated_pixels_equals_dense_reference(setup):
    """A training batch draws pixels with repeats and from both views in any order: the
    features' gradient (the backward's transposed entries, sorted by Gaussian) equals the dense
    product with the requested rows of the cached weights."""
    from n2f2.train.blend import build_blend_cache

    scene = setup["scene"]
    geometry = frozen_geometry(setup["gaussians"], "cpu")
    cams = [scene.cameras[1], scene.cameras[2]]
    cache = build_blend_cache(geometry, cams)
    N = geometry["means"].shape[0]
    HW = cams[0].width * cams[0].height
    g = torch.Generator().manual_seed(3)
    slot = torch.randint(0, 2, (300,), generator=g)
    pixel = torch.randint(0, HW, (300,), generator=g)
    pixel[150:] = pixel[:150]  # every pixel of the second half repeats one of the first
    slot[150:] = slot[:150]
    f = torch.randn(N, 4, generator=g, requires_grad=True)
    upstream = torch.randn(300, 4, generator=g)
    (cache.blend(f, slot, pixel) * upstream).sum().backward()
    dense = torch.zeros(300, N, dtype=torch.float64)  # the requested rows of the cache, written out
    for i, (k, p) in enumerate(zip(slot.tolist(), pixel.tolist())):
        r = cache.offsets[k] + p
        for e in range(int(cache.crow[r]), int(cache.crow[r + 1])):
            dense[i, int(cache.gid[e])] += float(cache.weight[e])
    assert dense.abs().sum() > 0
    expected = dense.t() @ upstream.double()
    torch.testing.assert_close(f.grad.double(), expected, rtol=1e-5, atol=1e-6)


def test_blend_cache_training_matches_rasterized_training(setup, tmp_path):
    """Same sampled pixels (one view per step, so both paths sample alike) -> same losses."""
    bank = setup["banks"][16]
    scene = Scene(root=setup["scene"].root, cameras=setup["scene"].cameras, image_paths=setup["scene"].image_paths)
    losses = []
    for cached in (False, True):
        cfg = tiny_config(iterations=3, checkpoint_every=0, holdout=True, blend_cache=cached)
        # A bank/scene with one training view makes both paths sample from the same view.
        r = train_field(_one_train_view(scene, tmp_path), setup["gaussians"], bank, tmp_path / str(cached),
                        field_config=FIELD, config=cfg, progress=False)
        losses.append(r["curve"]["loss"])
        assert r["blend_cache"]["used"] is cached
    np.testing.assert_allclose(losses[0], losses[1], rtol=1e-4)


def _one_train_view(scene: Scene, tmp_path) -> Scene:
    """The same scene with scene.json holding out all but view 2 (root is a temp copy of the
    listing only; images stay where they are)."""
    import shutil

    root = tmp_path / "one_view"
    if not root.exists():
        shutil.copytree(scene.root, root, ignore=shutil.ignore_patterns("images", "depth", "label"))
        meta = json.loads((root / "scene.json").read_text())
        meta["test_views"] = [0, 1, 3]
        (root / "scene.json").write_text(json.dumps(meta))
    return Scene(root=root, cameras=scene.cameras, image_paths=scene.image_paths, ground_truth=scene.ground_truth)


# ---------------------------------------------------------------------------------- bad input
def test_bank_from_another_scene_is_rejected(setup, tmp_path):
    scene, bank = setup["scene"], setup["banks"][16]
    fewer = Scene(root=scene.root, cameras=scene.cameras[:3], image_paths=scene.image_paths[:3])
    with pytest.raises(InputError, match="bank has 4 images, the scene has 3"):
        train_field(fewer, setup["gaussians"], bank, tmp_path, field_config=FIELD, config=tiny_config(), progress=False)
    smaller = load_scene(setup["scene_dir"], downscale=2)
    with pytest.raises(InputError, match="16x12 in the scene"):
        train_field(smaller, setup["gaussians"], bank, tmp_path, field_config=FIELD, config=tiny_config(), progress=False)


def test_resume_from_a_checkpoint_with_channels_first_planes_matches_uninterrupted_run(setup, tmp_path):
    """Checkpoints written before the TriPlane's texel layout (format v1) hold the planes and
    their Adam moments as [3, C, R, R]; such a checkpoint resumes to the field an uninterrupted
    run trains (fused Adam walks a parameter and its moments as flat memory, so a moment left in
    the old layout would mix texels and channels)."""
    bank = setup["banks"][16]
    cfg = tiny_config(iterations=6, checkpoint_every=3)
    train_field(setup["scene"], setup["gaussians"], bank, tmp_path / "a", field_config=FIELD, config=cfg,
                progress=False)
    field_a, _ = load_field(tmp_path / "a" / FIELD_NAME)

    train_field(setup["scene"], setup["gaussians"], bank, tmp_path / "b", field_config=FIELD,
                config=replace(cfg, iterations=3), progress=False)
    ck_path = tmp_path / "b" / CHECKPOINT_NAME
    ck = torch.load(ck_path, weights_only=True)
    assert ck["format"] == "n2f2-field-checkpoint-v2"
    ck["format"] = "n2f2-field-checkpoint-v1"  # rewritten as an older n2f2 wrote it
    ck["field_state"]["backbone.planes"] = ck["field_state"].pop("backbone.texels").permute(0, 3, 1, 2).contiguous()
    moments = 0
    for state in ck["optimizer"]["state"].values():
        for key, value in state.items():
            if torch.is_tensor(value) and value.dim() == 4:
                state[key] = value.permute(0, 3, 1, 2).contiguous()
                moments += 1
    assert moments == 2  # exp_avg and exp_avg_sq of the planes
    torch.save(ck, ck_path)
    train_field(setup["scene"], setup["gaussians"], bank, tmp_path / "b", field_config=FIELD, config=cfg,
                resume=True, progress=False)
    field_b, _ = load_field(tmp_path / "b" / FIELD_NAME)
    for (name, a), (_, b) in zip(field_a.state_dict().items(), field_b.state_dict().items()):
        assert torch.equal(a, b), name


def test_resume_with_other_embedding_dim_is_rejected(setup, tmp_path):
    train_field(setup["scene"], setup["gaussians"], setup["banks"][16], tmp_path, field_config=FIELD,
                config=tiny_config(iterations=2), progress=False)
    with pytest.raises(InputError, match="dim 8 .* E = 16"):
        train_field(setup["scene"], setup["gaussians"], setup["banks"][8], tmp_path, field_config=FIELD,
                    config=tiny_config(iterations=4), resume=True, progress=False)
    with pytest.raises(InputError, match="field config"):
        train_field(setup["scene"], setup["gaussians"], setup["banks"][16], tmp_path,
                    field_config=replace(FIELD, dim=24), config=tiny_config(iterations=4), resume=True, progress=False)
    with pytest.raises(InputError, match="no checkpoint"):
        train_field(setup["scene"], setup["gaussians"], setup["banks"][16], tmp_path / "none", field_config=FIELD,
                    config=tiny_config(), resume=True, progress=False)


# ---------------------------------------------------------------------------------- CLI
def test_cli_train_and_eval(setup, tmp_path, capsys):
    root = setup["root"]
    run = tmp_path / "run"
    common = [str(setup["scene_dir"]), "--gaussians", str(root / "gaussians.ply"), "--segments", str(root / "bank16"),
              "--out", str(run), "--quiet", "--dim", "12", "--plane-resolution", "16", "--plane-channels", "4",
              "--hidden", "32", "--pixels-per-step", "64"]
    assert cli_main(["train", *common, "--iterations", "2"]) == 0
    report = json.loads((run / REPORT_NAME).read_text())
    assert report["steps"] == 2 and report["deferred"] is True and report["peak_rss_mb"] > 0
    assert (run / "gaussians.ply").is_file() and (run / FIELD_NAME).is_file()
    assert cli_main(["train", *common, "--iterations", "3", "--resume"]) == 0
    assert json.loads((run / REPORT_NAME).read_text())["steps"] == 3
    assert cli_main(["eval-field", str(run)]) == 0
    result = json.loads((run / "eval_field.json").read_text())
    assert result["views"] == [0] and set(result["levels"]) == {"part", "object", "group"}
    capsys.readouterr()
    # A bank made at another resolution: one clear line, exit 2, and --force kept the results.
    before = (run / FIELD_NAME).read_bytes()
    assert cli_main(["train", *common, "--downscale", "2", "--iterations", "1", "--force"]) == 2
    err = capsys.readouterr().err
    assert "bank.json" in err and "Traceback" not in err
    assert (run / FIELD_NAME).read_bytes() == before
    with pytest.raises(SystemExit) as e:
        cli_main(["train", *common, "--scale-jitter", "nan", "--iterations", "1"])
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert "--scale-jitter must be" in err and "Traceback" not in err


# ---------------------------------------------------------------------------------- evaluation
def test_match_regions_to_segments_by_hand():
    regions = np.array([[0, 0, 1, 1], [0, 0, 1, 1], [2, 2, 2, -1]])
    layers = np.array([
        [[0, 0, 0, 1], [0, 0, 1, 1], [-1, -1, -1, -1]],  # seg 0 ~ region 0 (+1 px), seg 1 ~ region 1
        [[-1, -1, -1, -1], [-1, -1, -1, -1], [2, -1, -1, -1]],  # seg 2: 1 of region 2's 3 pixels
    ])
    ids, seg, iou = match_regions_to_segments(regions, layers, 3, min_iou=0.5)
    assert ids.tolist() == [0, 1, 2]
    assert seg.tolist() == [0, 1, -1]
    np.testing.assert_allclose(iou, [4 / 5, 3 / 4, 1 / 3])


def test_evaluate_cosine_matches_slow_reference(setup):
    scene, bank = setup["scene"], setup["banks"][16]
    torch.manual_seed(0)
    from n2f2.field import NestedField

    field = NestedField(FIELD, 16, [-3, -3, -3], [3, 3, 3])
    with torch.no_grad():
        field.W.normal_()
    res = evaluate_cosine_by_level(field, setup["gaussians"], scene, bank, [0, 2])

    # Reference: per region, boolean masks, best IoU, explicit W[:, :M] theta[:M].
    geometry = frozen_geometry(setup["gaussians"], "cpu")
    with torch.no_grad():
        theta_g = field(geometry["means"])
    W = field.W.detach().double()
    total = {0: [0.0, 0], 1: [0.0, 0], 2: [0.0, 0]}
    in_view = {}  # (view, level) -> [cos sum, pixels]
    for v in (0, 2):
        theta = render_features(geometry, theta_g, bank_cameras(scene, bank)[v]).detach().double()
        rec = bank.record(v)
        masks = rec.masks()  # [S, H, W]
        gt = np.asarray(scene.ground_truth.region_ids(v))
        for level in range(3):
            for r in np.unique(gt[level]):
                if r < 0:
                    continue
                R = gt[level] == r
                ious = [(R & m).sum() / (R | m).sum() for m in masks]
                s = int(np.argmax(ious))
                if ious[s] < 0.5 or not rec.valid[s]:
                    continue
                M = int(scale_to_dims(float(rec.quantized[s]), FIELD.dim))
                e = torch.tensor(np.asarray(rec.embeddings[s], dtype=np.float64))
                for p in np.flatnonzero(R.reshape(-1)):
                    phi = W[:, :M] @ theta[p, :M]
                    c = float(phi @ e / max(phi.norm() * e.norm(), 1e-8))
                    total[level][0] += c
                    total[level][1] += 1
                    acc = in_view.setdefault((v, level), [0.0, 0])
                    acc[0] += c
                    acc[1] += 1
    for level, name in enumerate(("part", "object", "group")):
        assert res["levels"][name]["pixels"] == total[level][1] > 0
        assert res["levels"][name]["cosine"] == pytest.approx(total[level][0] / total[level][1], abs=1e-5)
    assert [row["view"] for row in res["per_view"]] == [0, 2]
    for row in res["per_view"]:
        for level, name in enumerate(("part", "object", "group")):
            acc = in_view.get((row["view"], level))
            if acc is None:
                assert row[name] is None
            else:
                assert row[name] == pytest.approx(acc[0] / acc[1], abs=1e-5)


def test_compiled_blend_request_equals_the_torch_request():
    """The compiled row request (and its transpose) is the torch one array for array: rows with
    no entries, repeated rows, rows in any order, and a Gaussian no requested row reaches."""
    from n2f2.train import numba_blend
    from n2f2.train.blend import BlendCache

    if not numba_blend.available():
        pytest.skip("numba is not installed")
    g = torch.Generator().manual_seed(5)
    n, rows_total = 40, 60
    counts = torch.randint(0, 6, (rows_total,), generator=g)
    counts[[3, 17]] = 0
    crow = torch.cat([torch.zeros(1, dtype=torch.long), torch.cumsum(counts, 0)])
    nnz = int(crow[-1])
    gid = torch.randint(0, n - 1, (nnz,), generator=g).to(torch.int32)  # Gaussian n - 1 never appears
    cache = BlendCache(crow=crow, gid=gid, weight=torch.rand(nnz, generator=g), offsets=[0, 30], sizes=[(5, 6)] * 2)
    slot = torch.tensor([1, 0, 0, 1, 0, 1, 0])
    pixel = torch.tensor([4, 3, 17, 29, 3, 0, 12])  # row 3 twice, rows 3 and 17 empty
    for transpose in (False, True):
        got, got_t = cache.request(slot, pixel, n, transpose)
        want, want_t = cache.request_torch(slot, pixel, n, transpose)
        pairs = [(got, want)] + ([(got_t, want_t)] if transpose else [])
        assert (got_t is None) is (not transpose)
        for a, b in pairs:
            assert a.shape == b.shape
            for part in ("crow_indices", "col_indices", "values"):
                x, y = getattr(a, part)(), getattr(b, part)()
                assert x.dtype == y.dtype and torch.equal(x, y)
    dense = torch.zeros(7, n)  # the request written out by hand from the cache
    for i, r in enumerate((34, 3, 17, 59, 3, 30, 12)):
        for e in range(int(crow[r]), int(crow[r + 1])):
            dense[i, int(gid[e])] += float(cache.weight[e])
    torch.testing.assert_close(got.to_dense(), dense)
    torch.testing.assert_close(got_t.to_dense(), dense.t())


@pytest.mark.parametrize(("dtype", "rtol"), [(torch.float64, 1e-12), (torch.float32, 1e-5)])
def test_compiled_prefix_sums_match_the_tensor_reference_with_gradients(dtype, rtol):
    """The loss's per-row prefix sums, compiled, against the cumulative sums they replace: rows
    sharing a pixel or a target, the first and the last dim as a row's last."""
    from n2f2.train import numba_prefix

    if not numba_prefix.available():
        pytest.skip("numba is not installed")
    g = torch.Generator().manual_seed(6)
    P, T, D, R = 9, 4, 7, 30
    theta, u, a = (torch.randn(n, D, generator=g, dtype=dtype) for n in (P, T, P))
    row, index = torch.randint(0, P, (R,), generator=g), torch.randint(0, T, (R,), generator=g)
    last = torch.randint(0, D, (R,), generator=g)
    last[:2] = torch.tensor([0, D - 1])
    upstream = torch.randn(R, generator=g, dtype=dtype)
    results = []
    for compiled in (False, True):
        leaves = [t.clone().requires_grad_(True) for t in (theta, u, a)]
        with pytest.MonkeyPatch.context() as mp:
            if not compiled:
                mp.setattr(numba_prefix, "usable", lambda *t: False)
            dot = numba_prefix.prefix_dot(leaves[1], leaves[0], index, row, last)
            total = numba_prefix.prefix_sum(leaves[2], row, last)
        grads = torch.autograd.grad(((dot + 2 * total) * upstream).sum(), leaves)
        results.append((dot.detach(), total.detach(), grads))
    (dot_ref, sum_ref, grads_ref), (dot, total, grads) = results
    by_hand = torch.stack([(u[j, : k + 1] * theta[p, : k + 1]).sum() for j, p, k in zip(index, row, last)])
    torch.testing.assert_close(dot_ref, by_hand, rtol=rtol, atol=rtol)
    torch.testing.assert_close(dot, dot_ref, rtol=rtol, atol=rtol)
    torch.testing.assert_close(total, sum_ref, rtol=rtol, atol=rtol)
    for got, want in zip(grads, grads_ref):
        assert got.dtype == dtype
        torch.testing.assert_close(got, want, rtol=rtol, atol=rtol)


def test_compiled_prefix_sums_gradcheck():
    from n2f2.train import numba_prefix

    if not numba_prefix.available():
        pytest.skip("numba is not installed")
    g = torch.Generator().manual_seed(7)
    theta, u = torch.randn(3, 5, generator=g, dtype=torch.float64), torch.randn(2, 5, generator=g, dtype=torch.float64)
    row, index, last = torch.tensor([0, 2, 2, 1, 0]), torch.tensor([1, 0, 1, 1, 0]), torch.tensor([4, 0, 2, 3, 1])
    inputs = (u.requires_grad_(True), theta.requires_grad_(True))
    assert torch.autograd.gradcheck(lambda a, b: numba_prefix.prefix_dot(a, b, index, row, last), inputs)
    assert torch.autograd.gradcheck(lambda b: numba_prefix.prefix_sum(b, row, last), (theta,))
