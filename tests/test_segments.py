"""Segment bank: layers, mask NMS, lifting, quantile bins, LangSplat import, resumable storage.

Reference values come from hand-worked examples or from slow, independent re-implementations
(Python loops transcribing LangSplat's NMS, ``cv2.erode`` per mask, ``np.cov`` per segment)."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from n2f2.cameras import Camera, look_at
from n2f2.data.scene import Scene
from n2f2.errors import InputError
from n2f2.io import write_png
from n2f2.segments.bank import SegmentBank, build_bank
from n2f2.segments.bins import QuantileScaleBins, scale_to_dims, three_level_groups
from n2f2.segments.langsplat import LangSplatSource, read_langsplat
from n2f2.segments.lifting import (LiftSettings, erode_layers, lift_view, segment_medians, segment_quantiles,
                                   segment_scales)
from n2f2.segments.segmenters import (SegmentSet, greedy_mask_nms, layers_to_masks, mask_nms, pack_layers,
                                      relabel_label_maps, segment_areas, segment_layers)


# ----------------------------------------------------------------------------- bins
def test_scale_to_dims_hand_values():
    s = np.array([0.0, 0.1, 0.5, 0.874, 0.875, 0.99])
    # ceil(8 (1 - s)) by hand: ceil(8) ceil(7.2) ceil(4) ceil(1.008) ceil(1.0) ceil(0.08)
    assert scale_to_dims(s, 8).tolist() == [8, 8, 4, 2, 1, 1]
    # k = 3, D = 10: floor(10/3) = 3 quantised values, dims {3, 6, 9}
    assert scale_to_dims(np.array([0.0, 0.5, 0.7, 0.99]), 10, k=3).tolist() == [9, 6, 3, 3]
    # paper: k = 170, D = 512 -> {170, 340, 510}
    got = scale_to_dims(np.linspace(0, 0.999, 1000), 512, k=170)
    assert sorted(set(got.tolist())) == [170, 340, 510]
    t = scale_to_dims(torch.tensor([0.0, 0.5, 0.7, 0.99]), 10, k=3)
    assert t.dtype == torch.long and t.tolist() == [9, 6, 3, 3]
    with pytest.raises(ValueError):
        scale_to_dims(s, 4, k=5)


def test_three_level_groups():
    got = three_level_groups(np.array([0.0, 0.33, 0.34, 0.67, 0.99, np.nan]))
    assert got.tolist() == [0, 0, 1, 2, 2, -1]
    assert three_level_groups(torch.tensor([0.1, 0.5, 0.9, float("nan")])).tolist() == [0, 1, 2, -1]


def test_quantile_bins_uniform_monotone_and_follow_k():
    rng = np.random.default_rng(0)
    raw = rng.lognormal(-5, 2, size=5000)
    bins = QuantileScaleBins.fit(np.concatenate([raw, [np.nan]]))
    s = bins.transform(raw)
    assert np.all((s >= 0) & (s < 1))
    order = np.argsort(raw)
    assert np.all(np.diff(s[order]) >= 0)  # monotone in the scale
    # uniform: deciles hold ~10 % each
    hist = np.histogram(s, bins=10, range=(0, 1))[0] / s.size
    assert np.allclose(hist, 0.1, atol=0.01)
    for k in (1, 8, 170):
        m = scale_to_dims(s, 512, k)
        assert np.all(m % k == 0) and m.min() >= k and m.max() <= k * (512 // k)
        assert np.all(np.diff(m[order]) <= 0)  # larger scale -> fewer dims
        assert len(np.unique(m)) <= 512 // k
    # round trip through bank.json and NaN handling
    again = QuantileScaleBins.from_dict(json.loads(json.dumps(bins.to_dict())))
    assert np.array_equal(again.transform(raw), s)
    assert np.isnan(bins.transform(np.array([np.nan])))[0]
    # below / above the data: clipped into [0, 1)
    assert bins.transform(np.array([0.0]))[0] == 0.0 and bins.transform(np.array([1e9]))[0] < 1.0


def test_quantile_bins_ties_and_single_value():
    bins = QuantileScaleBins.fit(np.array([1.0, 1.0, 1.0, 2.0, 3.0]))
    s = bins.transform(np.array([1.0, 2.0, 3.0]))
    assert s[0] < s[1] < s[2] and 0 < s[0] < 0.5  # tie maps to the middle of its range
    one = QuantileScaleBins.fit(np.array([0.5]))
    assert one.transform(np.array([0.1, 0.5, 2.0])).tolist() == [0.0, 0.0, 0.0]
    with pytest.raises(ValueError):
        QuantileScaleBins.fit(np.array([np.nan]))


# ----------------------------------------------------------------------------- layers
def _rect(H, W, y0, y1, x0, x1):
    m = np.zeros((H, W), bool)
    m[y0:y1, x0:x1] = True
    return m


def test_pack_layers_nested_and_disjoint():
    H, W = 12, 16
    masks = np.stack([_rect(H, W, 2, 6, 2, 6),  # part of 1
                      _rect(H, W, 0, 10, 0, 10),  # object
                      _rect(H, W, 0, 12, 0, 16),  # whole image
                      _rect(H, W, 0, 4, 12, 16),  # disjoint from 0 and 1
                      _rect(H, W, 3, 5, 3, 5)])  # part of the part
    layers = pack_layers(masks)
    assert layers.shape == (4, H, W)  # nesting depth 4 (image > object > part > sub-part)
    assert np.array_equal(layers_to_masks(layers, 5), masks)  # every segment exact
    lo = segment_layers(layers, 5)
    assert sorted(lo[[0, 1, 2, 4]].tolist()) == [0, 1, 2, 3]
    assert segment_areas(layers, 5).tolist() == [16, 100, 192, 16, 4]
    seg = SegmentSet.from_masks(masks)
    assert np.array_equal(seg.masks([4, 0]), masks[[4, 0]])


def test_segment_layers_rejects_duplicates_and_overflow():
    layers = np.array([[[0, 1]], [[1, -1]]], np.int32)
    with pytest.raises(ValueError, match="more than one layer"):
        segment_layers(layers, 2)
    with pytest.raises(ValueError, match="exceeds"):
        segment_layers(np.array([[[0, 3]]], np.int32), 2)


def test_relabel_label_maps():
    maps = np.array([[[5, 5, 7], [7, 7, -1]], [[2, 2, 2], [9, 9, 9]]])
    layers, src = relabel_label_maps(maps)
    assert layers.tolist() == [[[0, 0, 1], [1, 1, -1]], [[2, 2, 2], [3, 3, 3]]]
    assert src.tolist() == [5, 7, 2, 9]
    layers, src = relabel_label_maps(maps, min_area=3)
    assert layers.tolist() == [[[-1, -1, 0], [0, 0, -1]], [[1, 1, 1], [2, 2, 2]]]
    assert src.tolist() == [7, 2, 9]


# ----------------------------------------------------------------------------- NMS
def _langsplat_nms_reference(masks, scores, iou_thr, score_thr, inner_thr):
    """LangSplat's preprocess.py mask_nms, transcribed as its Python double loop."""
    scores, idx = scores.sort(dim=0, descending=True, stable=True)
    n = idx.shape[0]
    m = masks[idx]
    area = m.sum(dim=(1, 2)).float()
    iou_m = torch.zeros(n, n)
    inner_m = torch.zeros(n, n)
    for i in range(n):
        for j in range(i, n):
            inter = torch.logical_and(m[i], m[j]).sum().float()
            union = torch.logical_or(m[i], m[j]).sum().float()
            iou_m[i, j] = inter / union
            if inter / area[i] < 0.5 and inter / area[j] >= 0.85:
                inner_m[i, j] = 1 - (inter / area[j]) * (inter / area[i])
            if inter / area[i] >= 0.85 and inter / area[j] < 0.5:
                inner_m[j, i] = 1 - (inter / area[j]) * (inter / area[i])
    iou_m.triu_(diagonal=1)
    keep = iou_m.max(dim=0).values <= iou_thr
    conds = [scores > score_thr, torch.triu(inner_m, 1).max(0).values <= 1 - inner_thr,
             torch.tril(inner_m, 1).max(0).values <= 1 - inner_thr]
    for c in conds:
        if c.sum() == 0:
            c[scores.topk(min(3, n)).indices] = True
        keep &= c
    return idx[keep]


def _random_masks(rng, n, H=20, W=24):
    out = []
    for _ in range(n):
        y0, x0 = rng.integers(0, H - 3), rng.integers(0, W - 3)
        out.append(_rect(H, W, y0, rng.integers(y0 + 2, H + 1), x0, rng.integers(x0 + 2, W + 1)))
    base = out[0]
    out.append(base.copy())  # exact duplicate
    inner = np.zeros_like(base)
    ys, xs = np.nonzero(base)
    inner[ys.min():ys.min() + 2, xs.min():xs.min() + 2] = True  # small mask inside mask 0
    out.append(inner)
    return torch.from_numpy(np.stack(out))


@pytest.mark.parametrize("seed,thr", [(0, (0.7, 0.1, 0.2)), (1, (0.8, 0.7, 0.5)), (2, (0.5, 0.3, 0.9)),
                                      (3, (0.9, 0.95, 0.5))])
def test_mask_nms_matches_langsplat_loop(seed, thr):
    rng = np.random.default_rng(seed)
    masks = _random_masks(rng, 25)
    scores = torch.from_numpy(rng.uniform(0, 1, len(masks))).float()
    got = mask_nms(masks, scores, *thr)
    want = _langsplat_nms_reference(masks, scores.clone(), *thr)
    assert got.tolist() == want.tolist()


def test_greedy_mask_nms_matches_loop():
    rng = np.random.default_rng(4)
    masks = _random_masks(rng, 30)
    scores = torch.from_numpy(rng.uniform(0, 1, len(masks))).float()
    order = torch.argsort(scores, descending=True, stable=True).tolist()
    keep = []
    for i in order:
        a = masks[i]
        if all((a & masks[k]).sum() / (a | masks[k]).sum() <= 0.7 for k in keep):
            keep.append(i)
    assert greedy_mask_nms(masks, scores, 0.7).tolist() == keep
    assert greedy_mask_nms(masks[:0], scores[:0]).numel() == 0 and mask_nms(masks[:0], scores[:0]).numel() == 0


# ----------------------------------------------------------------------------- lifting
def test_erode_layers_equals_cv2_erode_per_mask():
    rng = np.random.default_rng(0)
    lab = cv2.resize(rng.integers(0, 6, (6, 8)).astype(np.uint8), (32, 24), interpolation=cv2.INTER_NEAREST)
    lab = lab.astype(np.int32)
    lab[lab == 5] = -1
    layers = np.stack([lab, np.where(lab == 0, 7, -1)])
    eroded = erode_layers(layers)
    kernel = np.ones((3, 3), np.uint8)
    for l in range(2):
        for i in range(8):
            want = cv2.erode((layers[l] == i).astype(np.uint8), kernel) > 0
            assert np.array_equal(eroded[l] == i, want)


def _brute_scales(layers, points, valid, S, min_points=10):
    """np.cov of each segment's (cv2-eroded, else un-eroded) valid points."""
    out = np.full(S, np.nan)
    kernel = np.ones((3, 3), np.uint8)
    for i in range(S):
        l = [k for k in range(len(layers)) if (layers[k] == i).any()]
        if not l:
            continue
        m = layers[l[0]] == i
        e = cv2.erode(m.astype(np.uint8), kernel) > 0
        pts = points[e & valid]
        if len(pts) < min_points:
            pts = points[m & valid]
        if len(pts) >= min_points:
            out[i] = np.linalg.eigvalsh(np.cov(pts.T, bias=True))[-1]
    return out


def test_segment_scales_match_brute_force():
    rng = np.random.default_rng(1)
    H, W = 30, 40
    lab = cv2.resize(rng.integers(0, 9, (5, 6)).astype(np.uint8), (W, H), interpolation=cv2.INTER_NEAREST)
    layers = np.stack([lab.astype(np.int32), np.full((H, W), -1, np.int32)])
    layers[1, 2:4, 5:30] = 9  # thin 2-pixel line: erosion empties it, falls back to the raw mask
    layers[1, 20, 30:35] = 10  # 5 pixels: degenerate (< 10 points)
    points = rng.normal(size=(H, W, 3)) + np.array([100.0, -50.0, 3.0])  # offset tests the centring
    valid = rng.uniform(size=(H, W)) > 0.1
    scales, npts = segment_scales(layers, points, valid, 11)
    want = _brute_scales(layers, points, valid, 11)
    assert np.isnan(scales[10]) and np.isnan(want[10])
    assert np.isfinite(scales[9])
    np.testing.assert_allclose(scales, want, rtol=1e-5, equal_nan=True)
    # erosion switched off: plain covariance of the raw masks
    plain, _ = segment_scales(layers, points, valid, 11, LiftSettings(erode=False))
    i = 0
    pts = points[(layers[0] == i) & valid]
    assert plain[i] == pytest.approx(np.linalg.eigvalsh(np.cov(pts.T, bias=True))[-1], rel=1e-6)


def test_lift_view_known_plane():
    """A fronto-parallel plane at depth 2 seen by a pinhole camera: a horizontal strip of
    pixels columns [x0, x1) lifts to x = (u - cx) / fx * 2 with u = column + 0.5, so its
    largest covariance eigenvalue is the variance of those x values (by hand)."""
    H, W, f = 20, 40, 20.0
    R, t = look_at(np.array([0.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0]))
    cam = Camera(f, f, W / 2, H / 2, W, H, R=R, t=t)
    depth = np.full((H, W), 2.0)
    layers = np.full((1, H, W), -1, np.int32)
    layers[0, 5:8, 4:36] = 0  # 3 rows x 32 columns
    scales, npts = lift_view(layers, depth, np.ones((H, W), bool), cam, 1, LiftSettings(erode=False))
    xs = (np.arange(4, 36) + 0.5 - W / 2) / f * 2.0
    ys = (np.arange(5, 8) + 0.5 - H / 2) / f * 2.0
    assert npts[0] == 96
    assert scales[0] == pytest.approx(xs.var(), rel=1e-6) and xs.var() > ys.var()
    # eroded: the strip shrinks to its middle row and columns 5..34
    scales_e, npts_e = lift_view(layers, depth, np.ones((H, W), bool), cam, 1)
    assert npts_e[0] == 30
    assert scales_e[0] == pytest.approx(((np.arange(5, 35) + 0.5 - W / 2) / f * 2.0).var(), rel=1e-6)
    # no valid depth -> degenerate
    scales_n, _ = lift_view(layers, np.zeros((H, W)), np.ones((H, W), bool), cam, 1)
    assert np.isnan(scales_n[0])


def test_segment_medians_match_numpy():
    rng = np.random.default_rng(2)
    ids = rng.integers(0, 7, 200)
    ids[ids == 3] = 4  # segment 3 has no samples
    vals = rng.normal(size=200)
    got = segment_medians(ids, vals, 8)
    want = [np.median(vals[ids == k]) if (ids == k).any() else np.nan for k in range(8)]
    np.testing.assert_allclose(got, want, equal_nan=True)
    for q in (0.0, 0.02, 0.37, 0.98, 1.0):
        got = segment_quantiles(ids, vals, 8, q)
        want = [np.quantile(vals[ids == k], q) if (ids == k).any() else np.nan for k in range(8)]
        np.testing.assert_allclose(got, want, equal_nan=True, rtol=1e-12)


def test_extent_scale_matches_brute_force():
    """scale_measure="extent": per segment, principal axes of its points' covariance, the
    [2, 98] percentile range of the points' coordinates along each, summed squares."""
    rng = np.random.default_rng(3)
    H, W = 30, 40
    lab = cv2.resize(rng.integers(0, 6, (5, 6)).astype(np.uint8), (W, H), interpolation=cv2.INTER_NEAREST)
    layers = np.stack([lab.astype(np.int32), np.full((H, W), -1, np.int32)])
    layers[1, 10:25, 5:35] = 6  # a segment overlapping the others (second layer)
    points = rng.normal(size=(H, W, 3)) * np.array([3.0, 1.0, 0.2]) + np.array([50.0, 7.0, -2.0])
    valid = rng.uniform(size=(H, W)) > 0.1
    settings = LiftSettings(erode=False, scale_measure="extent")
    scales, _ = segment_scales(layers, points, valid, 7, settings)
    for k in range(7):
        pts = points[(layers == k).any(axis=0) & valid]
        axes = np.linalg.eigh(np.cov(pts.T, bias=True))[1]
        proj = (pts - pts.mean(axis=0)) @ axes
        lo, hi = np.percentile(proj, [2, 98], axis=0)
        assert scales[k] == pytest.approx(((hi - lo) ** 2).sum(), rel=1e-5)


def test_extent_scale_known_plane():
    """A 3 x 32 pixel strip on a fronto-parallel plane at depth 2: with the percentile at 0 the
    extent is the squared diagonal of the strip's lifted rectangle (by hand)."""
    H, W, f = 20, 40, 20.0
    cam = Camera(f, f, W / 2, H / 2, W, H)
    layers = np.full((1, H, W), -1, np.int32)
    layers[0, 5:8, 4:36] = 0
    settings = LiftSettings(erode=False, scale_measure="extent", extent_percentile=0.0)
    scales, _ = lift_view(layers, np.full((H, W), 2.0), np.ones((H, W), bool), cam, 1, settings)
    width, height = 31 / f * 2.0, 2 / f * 2.0  # centre-to-centre spans of 32 columns and 3 rows
    assert scales[0] == pytest.approx(width ** 2 + height ** 2, rel=1e-5)


def test_area_scale_known_plane():
    """scale_measure="area": a 3 x 32 pixel strip on a fronto-parallel plane at depth 2 covers
    96 pixels of (2 / f)^2 each (by hand); a strip at depth 4 covers four times that; with
    erosion, its 30 inner pixels. A part inside its parent's mask never measures more."""
    H, W, f = 20, 40, 20.0
    cam = Camera(f, f, W / 2, H / 2, W, H)
    layers = np.full((2, H, W), -1, np.int32)
    layers[0, 5:8, 4:36] = 0
    layers[1, 6:8, 4:10] = 1  # a part: 2 x 6 pixels inside segment 0
    settings = LiftSettings(erode=False, scale_measure="area")
    scales, _ = lift_view(layers, np.full((H, W), 2.0), np.ones((H, W), bool), cam, 2, settings)
    assert scales[0] == pytest.approx(96 * (2.0 / f) ** 2, rel=1e-6)
    assert scales[1] == pytest.approx(12 * (2.0 / f) ** 2, rel=1e-6) and scales[1] < scales[0]
    far, _ = lift_view(layers[:1], np.full((H, W), 4.0), np.ones((H, W), bool), cam, 1, settings)
    assert far[0] == pytest.approx(4 * scales[0], rel=1e-6)
    eroded, _ = lift_view(layers[:1], np.full((H, W), 2.0), np.ones((H, W), bool), cam, 1,
                          LiftSettings(scale_measure="area"))
    assert eroded[0] == pytest.approx(30 * (2.0 / f) ** 2, rel=1e-6)
    with pytest.raises(ValueError, match="footprint"):
        segment_scales(layers, np.zeros((H, W, 3)), np.ones((H, W), bool), 2, settings)


def test_lift_settings_reject_unknown_measure():
    with pytest.raises(ValueError, match="scale_measure"):
        LiftSettings(scale_measure="diameter")
    with pytest.raises(ValueError, match="extent_percentile"):
        LiftSettings(extent_percentile=50.0)


def test_depth_outliers_are_rejected():
    """A segment on a plane at depth 2 whose mask leaks onto 4 background pixels at depth 9:
    with outlier rejection its scale is that of the plane pixels alone."""
    H, W, f = 20, 40, 20.0
    cam = Camera(f, f, W / 2, H / 2, W, H)
    depth = np.full((H, W), 9.0)
    depth[4:12, 6:30] = 2.0
    layers = np.full((1, H, W), -1, np.int32)
    layers[0, 4:12, 6:30] = 0
    layers[0, 12, 10:14] = 0  # leak: 4 background pixels below the plane
    valid = np.ones((H, W), bool)
    plain = LiftSettings(erode=False)
    robust, n_robust = lift_view(layers, depth, valid, cam, 1, plain)
    clean = layers.copy()
    clean[0, 12] = -1
    want, n_want = lift_view(clean, depth, valid, cam, 1, plain)
    assert n_robust[0] == n_want[0] == 8 * 24
    assert robust[0] == pytest.approx(want[0], rel=1e-9)
    leaky, _ = lift_view(layers, depth, valid, cam, 1, LiftSettings(erode=False, outlier_mads=None))
    assert leaky[0] > 2 * want[0]  # 4 leaked pixels out of 196 nearly triple the scale


# ----------------------------------------------------------------------------- fake scenes
def _scene(tmp_path: Path, n=4, H=12, W=16) -> Scene:
    rng = np.random.default_rng(0)
    paths, cams = [], []
    for i in range(n):
        p = tmp_path / "images" / f"frame_{i + 1:05d}.png"
        write_png(p, rng.uniform(size=(H, W, 3)))
        paths.append(p)
        R, t = look_at(np.array([0.0, -3.0 - i, 0.0]), np.zeros(3))
        cams.append(Camera(14.0, 14.0, W / 2, H / 2, W, H, R=R, t=t))
    return Scene(root=tmp_path, cameras=cams, image_paths=paths)


def _flat_depth(scene):
    return lambda i: (np.full((scene.cameras[i].height, scene.cameras[i].width), 2.0 + i),
                      np.ones((scene.cameras[i].height, scene.cameras[i].width), bool))


class _BlockSource:
    """Deterministic segments (3 blocks in 2 layers) and embeddings derived from the view."""

    segmenter_spec = {"name": "blocks"}
    encoder_spec = {"name": "fake", "embed_dim": 4, "description": "test"}

    def __init__(self, fail_at=None):
        self.calls = []
        self.fail_at = fail_at

    def prepare(self, stems):
        pass

    def extract(self, index, stem, image):
        if index == self.fail_at:
            raise KeyboardInterrupt
        self.calls.append(index)
        H, W = image.shape[:2]
        layers = np.full((2, H, W), -1, np.int32)
        layers[0, :, : W // 2] = 0
        layers[0, :, W // 2:] = 1
        layers[1, 2:8, 2:6 + index] = 2
        emb = np.eye(4, dtype=np.float32)[:3] * (index + 1)
        return SegmentSet(layers, np.ones(3, np.float32)), emb


def test_bank_round_trip_and_interrupted_resume(tmp_path):
    scene = _scene(tmp_path / "scene")
    out = tmp_path / "bank"
    with pytest.raises(KeyboardInterrupt):
        build_bank(scene, _BlockSource(fail_at=2), _flat_depth(scene), out, progress=False)
    assert {p.name for p in out.iterdir()} == {"bank.json", "frame_00001", "frame_00002"}
    with pytest.raises(InputError, match="incomplete"):
        SegmentBank.open(out)
    src = _BlockSource()
    report = build_bank(scene, src, _flat_depth(scene), out, progress=False)
    assert src.calls == [2, 3]  # finished images were skipped
    assert report["counts"]["segments"] == 12 and report["counts"]["valid"] == 12
    # The timing covers every image, also the two the interrupted run finished.
    assert report["timing"]["images_extracted_now"] == 2
    assert sorted(report["timing"]["per_image"]) == ["frame_00001", "frame_00002", "frame_00003", "frame_00004"]

    fresh = tmp_path / "fresh"
    build_bank(scene, _BlockSource(), _flat_depth(scene), fresh, progress=False)
    a, b = SegmentBank.open(out), SegmentBank.open(fresh)
    assert (a.num_images, a.height, a.width, a.embed_dim) == (4, 12, 16, 4)
    assert a.image_names == scene.image_names and a.encoder_spec["name"] == "fake"
    for i in range(4):
        ra, rb = a.record(i), b.record(i)
        for name in ("layers", "embeddings", "scales", "quantized", "areas", "valid"):
            np.testing.assert_array_equal(getattr(ra, name), getattr(rb, name))
        assert isinstance(ra.layers, np.memmap) and ra.embeddings.dtype == np.float16
        assert ra.layers.shape == (2, 12, 16) and ra.areas.tolist() == [96, 96, 6 * (4 + i)]
        np.testing.assert_array_equal(ra.embeddings, np.eye(4)[:3] * (i + 1))
        assert np.all((ra.quantized >= 0) & (ra.quantized < 1))
        np.testing.assert_array_equal(ra.quantized, a.quantized_scale(ra.scales).astype(np.float32))
    # quantized scale is monotone in the raw scale across the bank
    raw = np.concatenate([a.record(i).scales for i in range(4)])
    q = np.concatenate([a.record(i).quantized for i in range(4)])
    assert np.all(np.diff(q[np.argsort(raw)]) >= 0)
    a.validate_against(scene)


def test_resume_with_other_settings_and_validate_mismatch(tmp_path):
    scene = _scene(tmp_path / "scene")
    out = tmp_path / "bank"
    build_bank(scene, _BlockSource(), _flat_depth(scene), out, progress=False)
    other = _BlockSource()
    other.encoder_spec = {"name": "fake", "embed_dim": 4, "description": "other"}
    with pytest.raises(InputError, match="encoder") as e:
        build_bank(scene, other, _flat_depth(scene), out, progress=False)
    assert e.value.path == out / "bank.json"
    small = _scene(tmp_path / "small", n=3)
    with pytest.raises(InputError, match="3") as e:
        SegmentBank.open(out).validate_against(small)
    assert e.value.path == out / "bank.json"
    resized = _scene(tmp_path / "resized", H=6, W=8)
    with pytest.raises(InputError, match="downscale"):
        SegmentBank.open(out).validate_against(resized)


def test_bad_inputs_name_the_file(tmp_path):
    scene = _scene(tmp_path / "scene")
    scene.image_paths[1].write_bytes(b"")  # empty image file
    with pytest.raises(InputError) as e:
        build_bank(scene, _BlockSource(), _flat_depth(scene), tmp_path / "b1", progress=False)
    assert e.value.path == scene.image_paths[1]

    scene = _scene(tmp_path / "scene2")

    class WrongSize(_BlockSource):
        def extract(self, index, stem, image):
            segs, emb = super().extract(index, stem, image)
            return SegmentSet(segs.layers[:, :, :-1], segs.scores), emb

    with pytest.raises(InputError, match="15x12") as e:
        build_bank(scene, WrongSize(), _flat_depth(scene), tmp_path / "b2", progress=False)
    assert e.value.path == scene.image_paths[0]


# ----------------------------------------------------------------------------- LangSplat
def _langsplat_pair(H=6, W=8):
    """Hand-built LangSplat files: level sizes default 2, s 1, m 0, l 2 -> N = 5 rows.
    Global index = local index + rows of earlier levels (0, 2, 3, 3)."""
    s = -np.ones((4, H, W), np.float32)
    s[0, :, :4] = 0
    s[0, :, 4:] = 1
    s[1, 1:3, 1:3] = 0 + 2
    s[3, :3] = 0 + 3
    s[3, 3:, :5] = 1 + 3  # the rest stays -1
    f = np.arange(5 * 3, dtype=np.float32).reshape(5, 3) / 10.0
    return s, f


def test_langsplat_import_agrees_with_hand_built_pair(tmp_path):
    scene = _scene(tmp_path / "scene", n=2, H=6, W=8)
    feats = tmp_path / "language_features"
    feats.mkdir()
    s, f = _langsplat_pair()
    for stem in scene.image_names:
        np.save(feats / f"{stem}_s.npy", s)
        np.save(feats / f"{stem}_f.npy", f)
    layers, emb = read_langsplat(feats, scene.image_names[0], 6, 8)
    assert layers.dtype == np.int32 and np.array_equal(layers, s.astype(np.int32))
    out = tmp_path / "bank"
    build_bank(scene, LangSplatSource(feats), _flat_depth(scene), out, progress=False)
    bank = SegmentBank.open(out)
    assert bank.embed_dim == 3 and bank.encoder_spec["name"] == "clip"
    rec = bank.record(0)
    np.testing.assert_allclose(rec.embeddings, f, atol=1e-3)
    # segment k is exactly where _s == k, in the level LangSplat put it
    masks = rec.masks()
    for k in range(5):
        assert np.array_equal(masks[k], (s == k).any(axis=0))
    assert segment_layers(np.asarray(rec.layers), 5).tolist() == [0, 0, 1, 3, 3]
    assert rec.areas.tolist() == [24, 24, 4, 24, 15]
    assert rec.valid.tolist() == [True, True, False, True, True]  # 4 pixels < 10 points: degenerate
    assert bank.counts["dropped_degenerate"] == 2 and np.isnan(rec.quantized[2])


def test_langsplat_bad_files(tmp_path):
    feats = tmp_path / "lf"
    feats.mkdir()
    s, f = _langsplat_pair()
    np.save(feats / "a_s.npy", s)
    np.save(feats / "a_f.npy", f[:4])  # index 4 has no row
    with pytest.raises(InputError, match="only 4 rows") as e:
        read_langsplat(feats, "a", 6, 8)
    assert e.value.path == feats / "a_s.npy"
    np.save(feats / "a_f.npy", f)
    with pytest.raises(InputError, match="8x6 but the image is 16x12") as e:
        read_langsplat(feats, "a", 12, 16)
    assert e.value.path == feats / "a_s.npy"
    bad = s.copy()
    bad[0, 0, 0] = -2
    np.save(feats / "a_s.npy", bad)
    with pytest.raises(InputError, match="outside"):
        read_langsplat(feats, "a", 6, 8)
    with pytest.raises(InputError) as e:
        read_langsplat(feats, "missing", 6, 8)
    assert e.value.path == feats / "missing_s.npy"


def test_captions_encoder_beside_a_model_segmenter_is_refused_before_any_model_loads(tmp_path, monkeypatch):
    # --encoder captions needs the ground truth's captions: `segments --segmenter sam --encoder
    # captions` stops with one line before reading the scene or loading SAM or MiniLM.
    import n2f2.segments.encoders as encoders
    import n2f2.segments.segmenters as segmenters
    from n2f2.segments.setup import SegmentsSetup

    def never(*args, **kwargs):
        raise AssertionError("a model was loaded")

    monkeypatch.setattr(segmenters, "get_segmenter", never)
    monkeypatch.setattr(encoders, "get_encoder", never)
    setup = SegmentsSetup(data=str(tmp_path / "missing-scene"), downscale=1.0, skip_missing=False, depth_source="gt",
                          gaussians=None, segmenter="sam", encoder="captions", model=None, sam_model=None, device="cpu")
    with pytest.raises(InputError, match="--encoder captions embeds ground-truth captions"):
        setup.build()
