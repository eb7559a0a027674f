"""The LangSplat LERF-OVS protocol and the 3D-OVS protocol, against slow literal references
(written here from LangSplat's eval/evaluate_iou_loc.py and eval/utils.py) and hand-built maps
with known answers."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
import torch
from PIL import Image

from n2f2.data.labels import FrameLabels, LabelObject
from n2f2.errors import InputError
from n2f2.eval import ovs3d
from n2f2.eval.protocol import (ProtocolConfig, box_filter, evaluate_frame_category,
                                evaluate_label_dir, evaluate_scene, frame_targets,
                                localization_hit, majority_filter, mask_from_smoothed,
                                pixels_in_boxes, points_in_boxes,
                                resolve_box_size, resolve_majority_radius, segmentation_mask,
                                smoothed_relevancy)


# ------------------------------------------------------------------------- slow references
def ref_box_filter(r: np.ndarray, size: int) -> np.ndarray:
    """Mean over rows i - size//2 .. i - size//2 + size - 1 (OpenCV's default anchor), with
    reflect-101 borders (numpy's 'reflect' mode), summed in float64."""
    a = size // 2
    pad = np.pad(r.astype(np.float64), ((a, size - 1 - a), (a, size - 1 - a)), mode="reflect")
    return np.lib.stride_tricks.sliding_window_view(pad, (size, size)).mean(axis=(2, 3))


def ref_smooth(mask: np.ndarray, scale: int = 3) -> np.ndarray:
    """Literal port of LangSplat's utils.smooth (per-pixel loop; ``scale`` is its half-window)."""
    h, w = mask.shape[:2]
    out = mask.copy()
    for i in range(h):
        for j in range(w):
            square = mask[max(0, i - scale): min(i + scale + 1, h - 1),
                          max(0, j - scale): min(j + scale + 1, w - 1)]
            out[i, j] = np.argmax(np.bincount(square.reshape(-1)))
    return out


def ref_pair(rel: np.ndarray, gt: np.ndarray, boxes: np.ndarray, size: int = 30, thresh: float = 0.4):
    """LangSplat's activate_stream + lerf_localization for one category, in loops."""
    kernel = np.ones((size, size)) / (size ** 2)
    n_head = rel.shape[0]
    ious, scores = [], []
    for i in range(n_head):
        avg = cv2.filter2D(rel[i], -1, kernel)
        v = 0.5 * (torch.from_numpy(avg) + torch.from_numpy(rel[i]))
        scores.append(float(v.max()))
        out = v - torch.min(v)
        out = out / (torch.max(out) + 1e-9)
        out = out * (1.0 - (-1.0)) + (-1.0)
        out = torch.clip(out, 0, 1)
        pred = ref_smooth((out.numpy() > thresh).astype(np.uint8))
        inter = np.sum(np.logical_and(gt, pred))
        union = np.sum(np.logical_or(gt, pred))
        ious.append(inter / union)
    seg_level = int(torch.argmax(torch.tensor(scores)))
    avg = cv2.filter2D(rel.transpose(1, 2, 0), -1, kernel)
    if avg.ndim == 2:
        avg = avg[..., None]
    lvl_scores, coords = [], []
    for i in range(n_head):
        s = avg[..., i].max()
        lvl_scores.append(s)
        coords.append(np.asarray(np.nonzero(avg[..., i] == s)).transpose(1, 0)[..., ::-1])
    loc_level = int(np.argmax(lvl_scores))
    hit = False
    for box in boxes.reshape(-1, 4):
        x1, y1, x2, y2 = box
        for c in coords[loc_level]:
            if min(x1, x2) <= c[0] <= max(x1, x2) and min(y1, y2) <= c[1] <= max(y1, y2):
                hit = True
                break
        if hit:
            break
    return ious[seg_level], hit, seg_level, loc_level


def blobs(rng: np.random.Generator, n: int, h: int, w: int, k: int = 3) -> np.ndarray:
    """[n, h, w] float32 relevancy-like maps: a few Gaussian bumps on a noisy floor."""
    yy, xx = np.mgrid[0:h, 0:w]
    out = np.empty((n, h, w), dtype=np.float32)
    for i in range(n):
        m = 0.3 + 0.05 * rng.random((h, w))
        for _ in range(k):
            cy, cx = rng.uniform(0, h), rng.uniform(0, w)
            s = rng.uniform(2, 8)
            m += rng.uniform(0.1, 0.6) * np.exp(-((yy - cy) ** 2 + (xx - cx) ** 2) / (2 * s * s))
        out[i] = np.clip(m, 0, 1)
    return out


# ------------------------------------------------------------------------- box filter
@pytest.mark.parametrize("shape,size", [((40, 52), 30), ((33, 31), 30), ((12, 9), 30), ((20, 24), 5),
                                        ((16, 16), 4)])
def test_box_filter_matches_reflect101_reference(shape, size):
    r = np.random.default_rng(1).random(shape).astype(np.float32)
    out = box_filter(r, size)
    assert out.dtype == np.float32 and out.shape == shape
    np.testing.assert_allclose(out, ref_box_filter(r, size), atol=2e-6)


def test_box_filter_anchor_of_even_kernel():
    # An impulse at (40, 40) spreads to rows/cols 26..55: output (i, j) averages rows i-15..i+14.
    r = np.zeros((80, 90), dtype=np.float32)
    r[40, 40] = 900.0
    out = box_filter(r, 30)
    support = np.abs(out) > 0.5
    rows, cols = np.nonzero(support)
    assert (rows.min(), rows.max(), cols.min(), cols.max()) == (26, 55, 26, 55)
    np.testing.assert_allclose(out[support], 1.0, atol=1e-4)


@pytest.mark.parametrize("size", [30, 5, 4])
def test_box_filter_stack_equals_per_map_and_multichannel_bitwise(size):
    # LangSplat filters per level for segmentation and the [H, W, L] stack (one multi-channel
    # filter2D call) for localization; both must equal box_filter's stack bit for bit.
    r = np.random.default_rng(size).random((6, 37, 41)).astype(np.float32)
    kernel = np.ones((size, size)) / size**2
    stacked = box_filter(r.reshape(3, 2, 37, 41), size).reshape(6, 37, 41)
    multichannel = cv2.filter2D(np.ascontiguousarray(r.transpose(1, 2, 0)), -1, kernel).transpose(2, 0, 1)
    assert np.array_equal(stacked, multichannel)
    for i in range(6):
        assert np.array_equal(stacked[i], cv2.filter2D(r[i], -1, kernel))


@pytest.mark.parametrize("threads", [1, 2, 3])
def test_box_filter_stack_on_threads_equals_per_map_bitwise(threads):
    # 40 maps at 30 px (the DFT filter): on 2 or 3 threads the stack is split in chunks, each map
    # still filtered alone, so every map equals its own filter2D call bit for bit.
    import torch

    r = np.random.default_rng(threads).random((40, 37, 41)).astype(np.float32)
    kernel = np.ones((30, 30)) / 900
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(threads)
        stacked = box_filter(r, 30)
    finally:
        torch.set_num_threads(before)
    for i in range(40):
        assert np.array_equal(stacked[i], cv2.filter2D(r[i], -1, kernel)), i


# ------------------------------------------------------------------------- majority filter
@pytest.mark.parametrize("seed,density", [(0, 0.5), (1, 0.3), (2, 0.7), (3, 0.5)])
def test_majority_filter_matches_loop_port(seed, density):
    m = (np.random.default_rng(seed).random((12, 9)) < density).astype(np.uint8)
    assert np.array_equal(majority_filter(m), ref_smooth(m))


@pytest.mark.parametrize("radius", [1, 2, 5, 9])
def test_majority_filter_stack_and_radii_match_loop_port(radius):
    # A stack is filtered map by map; windows larger than the image clip at its edges.
    rng = np.random.default_rng(radius)
    stack = (rng.random((3, 2, 13, 10)) < 0.5).astype(np.uint8)
    out = majority_filter(stack.astype(bool), radius)
    assert out.shape == stack.shape and out.dtype == np.uint8
    for idx in np.ndindex(3, 2):
        assert np.array_equal(out[idx], ref_smooth(stack[idx], radius))


def test_majority_filter_far_edge_is_excluded_and_ties_go_to_zero():
    # Ones only in the last row and column: LangSplat's windows stop at H-1 / W-1, so no
    # window ever sees them and everything becomes 0.
    m = np.zeros((10, 8), dtype=np.uint8)
    m[-1, :] = 1
    m[:, -1] = 1
    assert majority_filter(m).sum() == 0
    assert ref_smooth(m).sum() == 0
    # 2 x 9 image: every window is row 0 only; pixel (0, 0) sees cols 0..3.
    m = np.zeros((2, 9), dtype=np.uint8)
    m[0, :2] = 1  # 2 ones of 4: a tie -> 0
    assert majority_filter(m)[0, 0] == 0
    m[0, 2] = 1  # 3 of 4 -> 1
    assert majority_filter(m)[0, 0] == 1
    assert majority_filter(m)[1, 0] == 1  # row 1 also only sees row 0


def test_majority_filter_radius_zero_keeps_all_but_the_far_edge():
    m = (np.random.default_rng(7).random((8, 11)) < 0.5).astype(np.uint8)
    expected = m.copy()
    expected[-1, :] = 0  # the far-edge rule leaves those windows empty
    expected[:, -1] = 0
    assert np.array_equal(majority_filter(m, radius=0), expected)


def test_majority_filter_rejects_degenerate_images():
    with pytest.raises(ValueError):
        majority_filter(np.ones((1, 5), dtype=np.uint8))


# ------------------------------------------------------------------------- threshold rule
def test_threshold_rule_on_a_ramp():
    # box size 1 leaves R' = R; normalised value 2 j / 39 - 1 > 0.4  <=>  j >= 28.
    r = np.tile(np.arange(40, dtype=np.float32) / 39, (20, 1))
    mask = segmentation_mask(r, threshold=0.4, box_size=1)
    expected = np.zeros((20, 40), dtype=np.uint8)
    expected[:, 28:] = 1
    assert np.array_equal(mask, expected)
    # threshold 0: 2 j / 39 - 1 > 0  <=>  j >= 20
    expected[:, 20:] = 1
    assert np.array_equal(segmentation_mask(r, threshold=0.0, box_size=1), expected)


def test_threshold_rule_is_invariant_to_affine_rescaling():
    yy, xx = np.mgrid[0:36, 0:44]
    noise = 0.05 * np.random.default_rng(4).random((36, 44))
    r = (np.exp(-((yy - 18) ** 2 + (xx - 20) ** 2) / 200.0) + noise).astype(np.float32)
    a = segmentation_mask(r)
    b = segmentation_mask(np.float32(0.5) * r + np.float32(0.25))
    assert (a != b).mean() < 0.002  # only float rounding at the threshold may differ
    assert a.any() and not a.all()


def test_smoothed_relevancy_is_half_mix():
    r = blobs(np.random.default_rng(5), 1, 30, 30)[0]
    np.testing.assert_allclose(smoothed_relevancy(r, 30), 0.5 * (ref_box_filter(r, 30) + r), atol=2e-6)


# ------------------------------------------------------------------------- IoU / hit by hand
def test_iou_of_a_hand_drawn_square():
    # R = 1 on a 10x10 square, box size 1: the mask is the square minus 5 pixels at each corner
    # (the 7x7 majority filter: the corner pixel sees 16 of 49 ones, its neighbours 20 and 24).
    r = np.zeros((40, 50), dtype=np.float32)
    r[10:20, 10:20] = 1.0
    gt = np.zeros((40, 50), dtype=bool)
    gt[10:20, 10:30] = True  # contains the square; 200 pixels
    res = evaluate_frame_category(r[None], gt, np.array([[0, 0, 5, 5]]), box_size=1)
    assert res.iou == pytest.approx((100 - 20) / 200)
    mask = segmentation_mask(r, box_size=1)
    assert mask.sum() == 80 and mask[10, 10] == 0 and mask[10, 13] == 1 and mask[11, 11] == 1


def test_localization_hit_is_edge_inclusive():
    r = np.zeros((30, 40), dtype=np.float32)
    r[5, 10] = 1.0  # the maximum at x = 10, y = 5
    assert localization_hit(r, np.array([[10, 5, 20, 20]]), box_size=1)
    assert not localization_hit(r, np.array([[11, 5, 20, 20]]), box_size=1)
    assert not localization_hit(r, np.array([[0, 6, 20, 20]]), box_size=1)
    assert localization_hit(r, np.array([[20, 20, 10, 5]]), box_size=1)  # corners in any order
    assert localization_hit(r, np.array([[9.5, 4.5, 10.0, 5.0]]), box_size=1)
    # any of several boxes
    assert localization_hit(r, np.array([[30, 20, 39, 29], [0, 0, 10, 5]]), box_size=1)


def test_localization_uses_the_box_filtered_maximum():
    # A 30x30 patch of ones at rows/cols 20..49: box(R) peaks where its window (rows i-15..i+14)
    # covers the patch exactly, at (x, y) = (35, 35); a lone brighter pixel elsewhere is averaged away.
    r = np.zeros((80, 90), dtype=np.float32)
    r[20:50, 20:50] = 0.5
    r[70, 80] = 1.0
    assert localization_hit(r, np.array([[35, 35, 35, 35]]), box_size=30)
    assert not localization_hit(r, np.array([[34, 34, 34, 34]]), box_size=30)
    assert not localization_hit(r, np.array([[75, 65, 85, 75]]), box_size=30)
    assert localization_hit(r, np.array([[75, 65, 85, 75]]), box_size=1)  # raw max is the pixel


def test_level_choice_differs_between_segmentation_and_localization():
    h, w = 60, 70
    rel = np.zeros((2, h, w), dtype=np.float32)
    rel[0, 5, 5] = 1.0  # R' max = 0.5 (1 + 1/900): highest for segmentation
    rel[1, 20:40, 20:45] = 0.4  # box(R) max 0.4 * 500/900 > 1/900: highest for localization
    gt = np.zeros((h, w), dtype=bool)
    gt[20:40, 20:45] = True
    res = evaluate_frame_category(rel, gt, np.array([[20, 20, 44, 39]]))
    assert (res.seg_level, res.loc_level) == (0, 1)
    assert res.hit
    assert res.iou == res.iou_per_level[0] < res.iou_per_level[1]


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("size", [30, 5])
def test_pair_matches_literal_langsplat_port(seed, size):
    rng = np.random.default_rng(seed)
    h, w = 36, 48
    rel = blobs(rng, 3, h, w)
    # ground truth: the brightest part of one level, shifted a little (so IoUs are neither 0 nor 1)
    lvl = rng.integers(0, 3)
    gt = np.roll(rel[lvl] > np.quantile(rel[lvl], 0.85), rng.integers(-3, 4), axis=1)
    ys, xs = np.nonzero(gt)
    boxes = np.array([[xs.min(), ys.min(), xs.max(), ys.max()], rng.uniform(0, 30, 4)])
    res = evaluate_frame_category(rel, gt, boxes, box_size=size)
    iou, hit, seg_level, loc_level = ref_pair(rel, gt.astype(np.uint8), boxes, size=size)
    assert res.iou == pytest.approx(iou, abs=1e-12)
    assert (res.hit, res.seg_level, res.loc_level) == (hit, seg_level, loc_level)


def test_pixels_in_boxes_is_points_in_boxes_pixel_by_pixel():
    # Float corners in either order, a box on the image edge, one partly outside.
    boxes = np.array([[3.5, 2.0, 1.0, 6.2], [8, 0, 8, 3], [10.4, 5.5, 14.0, 20.0]])
    inside = pixels_in_boxes(boxes, 9, 12)
    assert inside.shape == (9, 12)
    for y in range(9):
        for x in range(12):
            assert inside[y, x] == points_in_boxes(np.array([[x, y]]), boxes)
    assert inside[2, 1] and inside[6, 3] and not inside[7, 2]  # rows 2..6, cols 1..3
    assert inside[3, 8] and not inside[4, 8]
    assert not pixels_in_boxes(np.zeros((0, 4)), 4, 4).any()


@pytest.mark.parametrize("seed", range(3))
def test_every_level_of_a_pair_matches_the_port_level_by_level(seed):
    """The stacked masks, IoUs and hits of all levels equal the literal port run on each level
    alone (the oracle reads these per-level values)."""
    rng = np.random.default_rng(10 + seed)
    h, w = 30, 40
    rel = blobs(rng, 5, h, w)
    gt = np.roll(rel[2] > np.quantile(rel[2], 0.8), 2, axis=0)
    ys, xs = np.nonzero(gt)
    boxes = np.array([[xs.min(), ys.min(), xs.max(), ys.max()]])
    res = evaluate_frame_category(rel, gt, boxes, box_size=7)
    for lvl in range(5):
        iou, hit, _, _ = ref_pair(rel[lvl:lvl + 1], gt.astype(np.uint8), boxes, size=7)
        assert res.iou_per_level[lvl] == pytest.approx(iou, abs=1e-12)
        assert res.hit_per_level[lvl] == hit
    smoothed = smoothed_relevancy(rel, 7)
    stacked = mask_from_smoothed(smoothed, 0.4, 3)
    for lvl in range(5):
        np.testing.assert_array_equal(stacked[lvl], mask_from_smoothed(smoothed[lvl], 0.4, 3))
    assert len(set(res.hit_per_level)) == 2 or len(set(np.round(res.iou_per_level, 6))) > 1  # levels differ


# ------------------------------------------------------------------------- relevancy
def test_relevancy_is_langsplats_softmax_argmin_on_normalised_features():
    """n2f2's one relevancy (field.relevancy) against a literal port of LangSplat's
    OpenCLIPNetwork.get_relevancy, applied to the unit-normalised features it scores."""
    from n2f2.field.relevancy import relevancy
    g = torch.Generator().manual_seed(0)
    f = torch.randn(50, 16, generator=g, dtype=torch.float64) * 0.3  # unnormalised, as rendered
    pos = torch.randn(3, 16, generator=g, dtype=torch.float64)
    neg = torch.randn(4, 16, generator=g, dtype=torch.float64)
    pn, nn_ = pos / pos.norm(dim=-1, keepdim=True), neg / neg.norm(dim=-1, keepdim=True)
    fn = f / f.norm(dim=-1, keepdim=True)
    expected = torch.empty(50, 3, dtype=torch.float64)
    for k in range(3):  # OpenCLIPNetwork.get_relevancy, one positive at a time
        out = fn @ torch.cat([pn, nn_]).T
        sims = torch.stack((out[:, k:k + 1].repeat(1, 4), out[:, 3:]), dim=-1)
        soft = torch.softmax(10 * sims, dim=-1)
        best = soft[..., 0].argmin(dim=1)
        expected[:, k] = torch.gather(soft, 1, best[:, None, None].expand(50, 4, 2))[:, 0, 0]
    torch.testing.assert_close(relevancy(f, pn, nn_), expected, rtol=0, atol=1e-12)
    # the scale of a rendered feature does not change its relevancy
    torch.testing.assert_close(relevancy(3 * f, pn, nn_), expected, rtol=0, atol=1e-12)


# ------------------------------------------------------------------------- box size option
def test_resolve_box_size():
    assert resolve_box_size(30, 160) == 30
    assert resolve_box_size("scaled", 986) == 30
    assert resolve_box_size("scaled", 160) == 5  # 4.87
    assert resolve_box_size("scaled", 320) == 10  # 9.74
    assert resolve_box_size("scaled", 10) == 1  # never 0
    assert resolve_box_size("scaled", 200, ref_width=400) == 15
    assert resolve_majority_radius(3, 160) == 3
    assert resolve_majority_radius("scaled", 986) == 3
    assert resolve_majority_radius("scaled", 160) == 0  # 0.49
    assert resolve_majority_radius("scaled", 320) == 1  # 0.97
    cfg = ProtocolConfig.scaled()
    assert (cfg.box_size, cfg.majority_radius, cfg.box_ref_width) == ("scaled", "scaled", 986)
    with pytest.raises(ValueError):
        ProtocolConfig(majority_radius=-1)
    with pytest.raises(ValueError):
        ProtocolConfig(box_size=0)
    with pytest.raises(ValueError):
        ProtocolConfig(box_size="big")


# ------------------------------------------------------------------------- scenes
def square(x0, y0, x1, y1):
    return [[x0, y0], [x1, y0], [x1, y1], [x0, y1]]


def obj(cat, x0, y0, x1, y1):
    return LabelObject(cat, (x0, y0, x1, y1), square(x0, y0, x1, y1))


def test_union_over_repeated_categories_keeps_all_boxes():
    frame = FrameLabels("frame_00001", 40, 60, [obj("mug", 2, 2, 9, 9), obj("plate", 20, 20, 30, 30),
                                                obj("mug", 40, 10, 49, 19)])
    targets, dropped = frame_targets(frame)
    assert dropped == 0 and [t.category for t in targets] == ["mug", "plate"]
    mug = targets[0]
    expected = np.zeros((40, 60), dtype=bool)
    expected[2:10, 2:10] = True  # fillPoly includes the boundary
    expected[10:20, 40:50] = True
    assert np.array_equal(mug.mask, expected)
    np.testing.assert_array_equal(mug.boxes, [[2, 2, 9, 9], [40, 10, 49, 19]])

    # A map peaking only in the second mug: IoU uses the union, the hit uses the second box.
    rel = np.zeros((40, 60), dtype=np.float32)
    rel[10:20, 40:50] = 1.0
    res = evaluate_frame_category(rel, mug.mask, mug.boxes, box_size=1)
    assert res.hit
    assert res.iou == pytest.approx((100 - 20) / 164)  # corners eroded by the majority filter


def _relevancy_fn(maps):
    """(view, categories) -> [1, K, H, W] from a dict (view, category) -> [H, W]."""
    def fn(view, cats):
        return np.stack([maps[(view, c)] for c in cats])[None]
    return fn


def test_scene_scores_are_means_over_pairs():
    h, w = 40, 60
    frames = [FrameLabels("frame_00001", h, w, [obj("mug", 8, 8, 17, 17), obj("plate", 30, 20, 49, 35)]),
              FrameLabels("frame_00003", h, w, [obj("mug", 40, 10, 49, 19)])]
    maps = {}
    good = np.zeros((h, w), np.float32)
    good[8:18, 8:18] = 1.0  # exactly the mug: IoU 80/100, hit
    maps[(0, "mug")] = good
    bad = np.zeros((h, w), np.float32)
    bad[8:18, 8:18] = 1.0  # not the plate: IoU 0, miss
    maps[(0, "plate")] = bad
    third = np.zeros((h, w), np.float32)
    third[10:20, 40:50] = 1.0
    maps[(2, "mug")] = third  # IoU 80/100, hit
    s = evaluate_scene(_relevancy_fn(maps), frames, num_views=3,
                       config=ProtocolConfig(box_size=1), progress=False)
    assert s.num_pairs == 3 and s.num_frames == 2
    assert s.miou == pytest.approx((0.8 + 0.0 + 0.8) / 3)
    assert s.loc_accuracy == pytest.approx(2 / 3)
    assert [(p.frame, p.view_index, p.category, p.hit) for p in s.pairs] == [
        ("frame_00001", 0, "mug", True), ("frame_00001", 0, "plate", False), ("frame_00003", 2, "mug", True)]
    assert s.box_sizes == [1]
    d = json.loads(json.dumps(s.to_dict()))
    assert d["miou"] == pytest.approx(s.miou) and len(d["pairs"]) == 3


def test_scene_default_box_is_exact_30_and_scaled_is_recorded():
    h, w = 40, 60
    frames = [FrameLabels("frame_00001", h, w, [obj("mug", 8, 8, 17, 17)])]
    m = np.zeros((h, w), np.float32)
    m[8:18, 8:18] = 1.0
    fn = _relevancy_fn({(0, "mug"): m})
    assert evaluate_scene(fn, frames, 1, progress=False).box_sizes == [30]
    s = evaluate_scene(fn, frames, 1, ProtocolConfig(box_size="scaled"), progress=False)
    assert s.box_sizes == [2] and s.pairs[0].box_size == 2  # round(30 * 60 / 986) = 2
    assert s.majority_radii == [3] and s.config["box_size"] == "scaled"
    s = evaluate_scene(fn, frames, 1, ProtocolConfig.scaled(ref_width=60), progress=False)
    assert (s.box_sizes, s.majority_radii) == ([30], [3])


def test_bad_inputs_error_or_count():
    h, w = 30, 40
    m = np.zeros((h, w), np.float32)
    m[8:18, 8:18] = 1.0
    fn = lambda view, cats: np.stack([m] * len(cats))[None]  # noqa: E731
    with pytest.raises(InputError, match="empty"):
        evaluate_scene(fn, [], 5, progress=False)
    # a frame beyond the scene: an error by default, a counted skip on request
    frames = [FrameLabels("frame_00001", h, w, [obj("mug", 8, 8, 17, 17)]),
              FrameLabels("frame_00009", h, w, [obj("mug", 8, 8, 17, 17)])]
    with pytest.raises(InputError, match="view 8"):
        evaluate_scene(fn, frames, 5, progress=False)
    s = evaluate_scene(fn, frames, 5, ProtocolConfig(missing_frames="skip"), progress=False)
    assert s.skipped_frames == ["frame_00009"] and s.num_pairs == 1
    # a polygon entirely outside is dropped and counted; partly outside is clipped
    frames = [FrameLabels("frame_00001", h, w, [obj("mug", 8, 8, 17, 17), obj("ghost", 50, 50, 60, 60),
                                                obj("edge", 35, 25, 45, 35)])]
    s = evaluate_scene(fn, frames, 5, progress=False)
    assert s.skipped_objects == 1 and s.skipped_categories == 1
    assert [p.category for p in s.pairs] == ["mug", "edge"]
    targets, _ = frame_targets(frames[0])
    assert targets[1].mask.sum() == 5 * 5  # rows 25..29, cols 35..39
    # only unscoreable pairs left: a clear error, not a silent 0
    frames = [FrameLabels("frame_00001", h, w, [obj("ghost", 50, 50, 60, 60)])]
    with pytest.raises(InputError, match="no \\(frame, category\\) pair"):
        evaluate_scene(fn, frames, 5, progress=False)
    # maps of another size than the labels
    frames = [FrameLabels("frame_00001", 2 * h, 2 * w, [obj("mug", 16, 16, 35, 35)])]
    with pytest.raises(InputError, match="80x60"):
        evaluate_scene(fn, frames, 5, progress=False)
    s = evaluate_scene(fn, frames, 5, ProtocolConfig(rescale_labels=True, box_size=1), progress=False)
    assert s.pairs[0].iou == pytest.approx(80 / 100)  # the square, scaled by 1/2, is rows 8..17
    # two labels for one view
    frames = [FrameLabels("frame_00001", h, w, [obj("mug", 8, 8, 17, 17)]),
              FrameLabels("frame_1", h, w, [obj("mug", 8, 8, 17, 17)])]
    with pytest.raises(InputError, match="both view 0"):
        evaluate_scene(fn, frames, 5, progress=False)


def test_evaluate_label_dir_reads_files(tmp_path):
    from n2f2.data.labels import write_label_dir

    with pytest.raises(InputError):
        evaluate_label_dir(tmp_path, lambda v, c: None, 3, progress=False)
    m = np.zeros((30, 40), np.float32)
    m[8:18, 8:18] = 1.0
    write_label_dir(tmp_path, [FrameLabels("frame_00002", 30, 40, [obj("mug", 8, 8, 17, 17)])])
    s = evaluate_label_dir(tmp_path, lambda v, c: np.stack([m] * len(c))[None], 3,
                           ProtocolConfig(box_size=1), progress=False)
    assert s.pairs[0].view_index == 1 and s.pairs[0].iou == pytest.approx(0.8)


# ------------------------------------------------------------------------- 3D-OVS
def _write_ovs(root, classes, views):
    seg = root / "segmentations"
    seg.mkdir(parents=True)
    (seg / "classes.txt").write_text("\n".join(classes) + "\n\n")
    for name, masks in views.items():
        (seg / name).mkdir()
        for c, m in masks.items():
            Image.fromarray((m * 255).astype(np.uint8)).save(seg / name / f"{c}.png")


def test_ovs3d_argmax_protocol(tmp_path):
    h, w = 20, 30
    a = np.zeros((h, w), bool)
    a[:, :10] = True
    b = np.zeros((h, w), bool)
    b[:, 10:] = True
    absent = np.zeros((h, w), bool)
    _write_ovs(tmp_path, ["zebra", "apple", "ball"], {"00": {"apple": a, "ball": b, "zebra": absent},
                                                      "02": {"apple": a, "ball": b, "zebra": absent}})
    labels = ovs3d.read_ovs3d_segmentations(tmp_path)
    assert labels.classes == ["apple", "ball", "zebra"]  # sorted, blank line ignored
    assert [v.view_index for v in labels.views] == [0, 2]

    def scores(view, classes):
        s = np.zeros((3, h, w), np.float32)
        s[0, :, :12] = 1.0  # apple predicted on cols 0..11 (2 columns too many)
        s[1, :, 12:] = 1.0
        s[2] = 0.5 if view == 0 else 0.0  # zebra wins nowhere... except view 0's ties? no: 0.5 < 1
        s[2, 0, 0] = 2.0 if view == 2 else 0.0  # view 2: one wrong zebra pixel
        return s

    res = ovs3d.evaluate_ovs3d(scores, labels, num_views=3, progress=False)
    apple0, ball0 = 10 / 12, 18 / 20
    # view 0: zebra absent in both -> IoU 0 (sklearn); view 2: zebra predicted on 1 pixel -> 0
    apple2 = (10 * 20 - 1) / (12 * 20)
    assert res.per_view[0]["iou"] == pytest.approx([apple0, ball0, 0.0])
    assert res.per_view[1]["iou"] == pytest.approx([apple2, ball0, 0.0])
    assert res.miou == pytest.approx(np.mean([apple0, ball0, 0, apple2, ball0, 0]))
    assert res.empty_unions == 1
    assert res.accuracy == pytest.approx(np.mean([(600 - 40) / 600, (600 - 41) / 600]))
    skip = ovs3d.evaluate_ovs3d(scores, labels, num_views=3, empty_union="skip", progress=False)
    assert skip.miou == pytest.approx(np.mean([apple0, ball0, apple2, ball0, 0]))


def test_ovs3d_threshold_mode_and_bad_input(tmp_path):
    h, w = 30, 30
    a = np.zeros((h, w), bool)
    a[8:18, 8:18] = True  # off the borders: the majority filter erodes 5 pixels per corner
    _write_ovs(tmp_path / "s", ["mug"], {"01": {"mug": a}})
    labels = ovs3d.read_ovs3d_segmentations(tmp_path / "s" / "segmentations")
    fn = lambda v, c: a.astype(np.float32)[None]  # noqa: E731
    res = ovs3d.evaluate_ovs3d(fn, labels, 2, mode="threshold", config=ProtocolConfig(box_size=1),
                               progress=False)
    assert res.miou == pytest.approx(0.8) and res.accuracy is None
    with pytest.raises(InputError, match="not in the scene"):
        ovs3d.evaluate_ovs3d(fn, labels, 1, progress=False)
    half = ovs3d.read_ovs3d_segmentations(tmp_path / "s", size=(15, 15))
    assert half.views[0].masks.shape == (1, 15, 15) and half.views[0].masks.sum() == 25
    with pytest.raises(InputError, match="15x15"):
        ovs3d.evaluate_ovs3d(fn, half, 2, progress=False)
    # only grey value 255 is "in the class" (3D-OVS: (v / 255).astype(int8))
    grey = np.zeros((h, w), np.uint8)
    grey[0, :5] = 254
    grey[1, :3] = 255
    Image.fromarray(grey).save(tmp_path / "s" / "segmentations" / "01" / "mug.png")
    assert ovs3d.read_ovs3d_segmentations(tmp_path / "s").views[0].masks.sum() == 3
    (tmp_path / "s" / "segmentations" / "01" / "mug.png").unlink()
    with pytest.raises(InputError, match="missing"):
        ovs3d.read_ovs3d_segmentations(tmp_path / "s")
    with pytest.raises(InputError, match="classes.txt"):
        ovs3d.read_ovs3d_segmentations(tmp_path)
