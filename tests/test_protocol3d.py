"""The 3D protocol (n2f2.eval.protocol3d) on a hand-built scene whose selections and masks are
worked out by hand, for every engine kind with 3D relevancy (nested composite / explicit / soft, flat,
a "levels" field, the lift), and ``n2f2 eval --protocol 3d|both`` on the tiny trained run."""

from __future__ import annotations

import json
import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from n2f2.cameras import Camera
from n2f2.cli import main as cli_main
from n2f2.data.labels import FrameLabels, LabelObject, polygon_to_mask
from n2f2.errors import InputError
from n2f2.eval.protocol3d import Protocol3dConfig, evaluate_protocol3d
from n2f2.gaussians import Gaussians
from n2f2.query.engine import QueryEngine

# Image 24 x 12, focal 24, principal point at the centre; three Gaussians at depth 2, each
# centred on a pixel centre: blob 0 on pixel (x=4, y=5), blob 1 on (12, 5), blob 2 on (19, 5).
W_PX, H_PX, FOCAL, DEPTH = 24, 12, 24.0, 2.0
CENTRES = [(4, 5), (12, 5), (19, 5)]
# Isotropic scale s with (FOCAL s / DEPTH)^2 = 0.8 px^2: with the rasterizer's 0.3 px^2 low-pass,
# sigma^2 = 1.1 px^2, so a pixel at distance d from the centre gets alpha 0.99 exp(-d^2 / 2.2)
# (opacity 0.999, clamped at 0.99): 0.99 at d = 0, 0.63 at d = 1, 0.40 at d = sqrt(2). The
# rendered selection is > 0.5 exactly on the 5-pixel plus around the centre, and the blobs'
# footprints (alpha >= 1/255 needs d < 3.5 px) do not overlap.
SCALE = math.sqrt(0.8) * DEPTH / FOCAL

E = 4  # text embedding size; e3 is where every phrase but the queries below points
TEXTS = {
    "red": [1.0, 0.0, 0.0, 0.0],  # blob 0's feature
    "green": [0.0, 1.0, 0.0, 0.0],  # blob 1's feature
    "red or green": [2.0, 1.0, 0.0, 0.0],  # cosine 0.894 with blob 0, 0.447 with blob 1, 0 with blob 2
    "purple": [0.0, 0.0, 0.0, 1.0],  # as relevant as the negatives everywhere: selects nothing
}


class HandEncoder:
    description = "hand-made embeddings"

    def encode_text(self, texts):  # -> [Q, E]
        return np.array([TEXTS.get(t, [0.0, 0.0, 0.0, 1.0]) for t in texts], dtype=np.float32)


class HandField(torch.nn.Module):
    """A field whose feature at each Gaussian centre is set by hand: ``theta[i]`` at ``means[i]``."""

    def __init__(self, W, means, theta):  # W [E, D], means [N, 3], theta [N, D]
        super().__init__()
        self.W = torch.nn.Parameter(W)
        self.register_buffer("means", means)
        self.register_buffer("theta", theta)

    def forward(self, xyz):  # [P, 3] -> [P, D]
        return self.theta[torch.cdist(xyz, self.means).argmin(dim=1)]


def _camera() -> Camera:
    return Camera(FOCAL, FOCAL, W_PX / 2, H_PX / 2, W_PX, H_PX)


def _gaussians() -> Gaussians:
    means = torch.tensor(
        [[(x + 0.5 - W_PX / 2) * DEPTH / FOCAL, (y + 0.5 - H_PX / 2) * DEPTH / FOCAL, DEPTH] for x, y in CENTRES]
    )
    n = len(CENTRES)
    return Gaussians(
        means,
        torch.tensor([[1.0, 0.0, 0.0, 0.0]] * n),
        torch.full((n, 3), math.log(SCALE)),
        torch.full((n,), math.log(0.999 / 0.001)),  # opacity 0.999
        torch.zeros(n, 1, 3),
    )


def _scene(tmp_path):
    return SimpleNamespace(cameras=[_camera()], image_names=["frame_00001"], root=tmp_path)


def _one_hot(dim: int) -> torch.Tensor:  # [3, dim]: blob k's feature is e_k
    theta = torch.zeros(len(CENTRES), dim)
    theta[torch.arange(3), torch.arange(3)] = 1.0
    return theta


def nested_engine(tmp_path) -> QueryEngine:
    """D = 8, k = 4: two scales (d = 4, 8); the features live in the first block, so both scales
    (and the composite blend, which weights block 0 by 1) see the same directions."""
    g = _gaussians()
    W = torch.cat([torch.eye(E), torch.randn(E, 4, generator=torch.Generator().manual_seed(0))], dim=1)
    field = HandField(W, g.means.detach(), _one_hot(8))
    meta = {"config": {"variant": "nested", "dim": 8, "step_size": 4}}
    return QueryEngine(field, g, HandEncoder(), meta, scene=_scene(tmp_path))


def flat_engine(tmp_path) -> QueryEngine:
    g = _gaussians()
    field = HandField(torch.eye(E), g.means.detach(), _one_hot(E))
    return QueryEngine(field, g, HandEncoder(), {"config": {"variant": "flat", "dim": E}}, scene=_scene(tmp_path))


class HandLevelsField(HandField):
    """A 3-level field by hand: theta holds the part / object / group features as three E-blocks."""

    def level_features(self, theta):  # [..., 3E] -> [..., 3, E]
        return theta.reshape(*theta.shape[:-1], 3, E) @ self.W[:, :E].T


def levels_engine(tmp_path) -> QueryEngine:
    """A "levels" field whose object block holds e_k (part and group empty), through the generic
    linear score cache."""
    g = _gaussians()
    theta = torch.zeros(len(CENTRES), 3 * E)
    theta[:, E : 2 * E] = _one_hot(E)
    field = HandLevelsField(torch.cat([torch.eye(E)] * 3, dim=1), g.means.detach(), theta)
    meta = {"config": {"variant": "levels", "dim": 3 * E}}
    return QueryEngine(field, g, HandEncoder(), meta, scene=_scene(tmp_path))


def lift_engine_by_hand(tmp_path):
    """The lift's engine over hand-set level blocks: the object level holds e_k, part and group
    are empty (relevancy 0.5 everywhere), so levels mode answers at the object level."""
    from n2f2.field.lift import Lift
    from n2f2.query.lifted import lift_engine

    features = torch.zeros(len(CENTRES), 3, E)
    features[:, 1, :] = _one_hot(E)
    lift = Lift(features, torch.ones(len(CENTRES), 3), [0], "layers")
    return lift_engine(lift, _gaussians(), HandEncoder(), {}, scene=_scene(tmp_path))


def _diamond(x: int, y: int) -> list[list[float]]:  # filled with its boundary: the 5-pixel plus
    return [[x, y - 1], [x + 1, y], [x, y + 1], [x - 1, y]]


def _labels() -> list[FrameLabels]:
    red = LabelObject("red", (3, 4, 5, 6), _diamond(4, 5))
    # A 3 x 3 square around blob 1, and a box that does not hold blob 1's centre.
    green = LabelObject("green", (14, 0, 23, 11), [[11, 4], [13, 4], [13, 6], [11, 6]])
    both = LabelObject("red or green", (3, 4, 5, 6), _diamond(4, 5))
    purple = LabelObject("purple", (17, 3, 21, 7), _diamond(19, 5))
    return [FrameLabels("frame_00001", H_PX, W_PX, [red, green, both, purple])]


# Hand-worked answers: selections, mask pixels, IoU, hit, localization pixel.
EXPECTED = {
    "red": dict(count=1, mask_px=5, iou=1.0, hit=True, loc=[4, 5]),  # the selection is the label
    "green": dict(count=1, mask_px=5, iou=5 / 9, hit=False, loc=[12, 5]),  # plus in a 3x3 square; box misses
    "red or green": dict(count=2, mask_px=10, iou=5 / 10, hit=True, loc=[4, 5]),  # two pluses, one labelled
    "purple": dict(count=0, mask_px=0, iou=0.0, hit=False, loc=None),  # nothing selected
}


def test_label_masks_are_the_hand_drawn_shapes():
    plus = np.zeros((H_PX, W_PX), bool)
    plus[5, 3:6] = True
    plus[4:7, 4] = True
    assert np.array_equal(polygon_to_mask(_diamond(4, 5), H_PX, W_PX), plus)
    square = polygon_to_mask([[11, 4], [13, 4], [13, 6], [11, 6]], H_PX, W_PX)
    assert square.sum() == 9 and square[4:7, 11:14].all()


@pytest.mark.parametrize(
    "make, modes",
    [
        (nested_engine, ["composite", "explicit", "soft"]),
        (flat_engine, ["composite", "explicit", "soft"]),
        (levels_engine, ["levels"]),
        (lift_engine_by_hand, ["levels"]),
    ],
)
def test_hand_built_scene_scores(tmp_path, make, modes):
    engine = make(tmp_path)
    res = evaluate_protocol3d(engine, _labels(), config=Protocol3dConfig(progress=False))
    assert res.modes == modes  # every 3D mode of the engine; oracle has no 3D query
    for m in modes:
        s = res.scores[m]
        got = {p.category: p for p in s.pairs}
        assert set(got) == set(EXPECTED)
        for q, want in EXPECTED.items():
            p = got[q]
            assert s.selections[q]["count"] == want["count"], (m, q)
            assert p.mask_px == want["mask_px"], (m, q)
            assert p.iou == pytest.approx(want["iou"], abs=1e-12), (m, q)
            assert p.hit is want["hit"] and p.loc == want["loc"], (m, q)
        ious = [want["iou"] for want in EXPECTED.values()]
        assert s.miou == pytest.approx(np.mean(ious), abs=1e-12)
        assert s.acc["0.25"] == pytest.approx(3 / 4) and s.acc["0.5"] == pytest.approx(2 / 4)  # strictly above
        assert s.loc_accuracy == pytest.approx(2 / 4)
        assert s.empty_selections == ["purple"]
    if "levels" in modes:
        assert res.scores["levels"].selections["red"]["scale"] == "object"


def test_selection_is_the_query_rule_and_threshold_option(tmp_path):
    engine = flat_engine(tmp_path)
    # The selection is QueryEngine.select's: the mask pixels equal render_selection > 0.5.
    res = evaluate_protocol3d(engine, _labels(), modes=["composite"], config=Protocol3dConfig(progress=False))
    cover = engine.render_selection(engine.select("red or green"), 0).numpy()
    assert res.scores["composite"].pairs[2].mask_px == int((cover > 0.5).sum()) == 10
    # An absolute threshold above blob 1's relevancy sigmoid(10 * 0.447) = 0.9887 keeps blob 0 only.
    res = evaluate_protocol3d(
        engine, _labels(), modes=["composite"], config=Protocol3dConfig(threshold=0.995, progress=False)
    )
    both = {p.category: p for p in res.scores["composite"].pairs}["red or green"]
    assert res.scores["composite"].selections["red or green"]["count"] == 1 and both.iou == pytest.approx(1.0)
    assert "0.995" in res.rules["selection"]


def test_bad_input(tmp_path):
    engine = flat_engine(tmp_path)
    with pytest.raises(InputError, match="oracle"):
        evaluate_protocol3d(engine, _labels(), modes=["oracle"], config=Protocol3dConfig(progress=False))
    wrong = [FrameLabels("frame_00001", H_PX + 1, W_PX, _labels()[0].objects)]
    with pytest.raises(InputError, match="rescale"):
        evaluate_protocol3d(engine, wrong, config=Protocol3dConfig(progress=False))
    outside = [FrameLabels("frame_00005", H_PX, W_PX, _labels()[0].objects)]
    with pytest.raises(InputError, match="views"):
        evaluate_protocol3d(engine, outside, config=Protocol3dConfig(progress=False))
    res = evaluate_protocol3d(
        engine, outside + _labels(), config=Protocol3dConfig(missing_frames="skip", progress=False)
    )
    assert res.skipped_frames == ["frame_00005"] and res.scores["composite"].num_pairs == 4


# ------------------------------------------------------------------------------ n2f2 eval
def test_cli_both_and_3d(trained_run, tmp_path, capsys):
    labels = trained_run.scene_dir / "label"
    out = tmp_path / "both"
    base = ["eval", str(trained_run.run_dir), "--labels", str(labels), "--quiet", "--no-relevancy"]
    assert cli_main(base + ["--out", str(out), "--mode", "composite", "explicit", "--protocol", "both"]) == 0
    printed = capsys.readouterr().out
    assert "eval composite:" in printed and "eval 3D composite:" in printed and "eval 3D explicit:" in printed
    data = json.loads((out / "eval.json").read_text())
    assert data["format"] == "n2f2-eval-v1" and data["scores"]["composite"]["exact"]["num_pairs"] > 0
    p3 = data["protocol3d"]
    assert p3["modes"] == ["composite", "explicit"]
    n_pairs = data["scores"]["composite"]["exact"]["num_pairs"]
    for m in p3["modes"]:
        s = p3["scores"][m]
        assert s["num_pairs"] == n_pairs  # the same (frame, category) pairs as the 2D protocol
        assert 0.0 <= s["miou"] <= 1.0 and 0.0 <= s["loc_accuracy"] <= 1.0
        assert all(0.0 <= p["iou"] <= 1.0 for p in s["pairs"])
    assert "## 3D protocol" in (out / "eval.md").read_text()

    # The 3D protocol alone: its own eval.json format, the same numbers.
    out3 = tmp_path / "3d"
    assert cli_main(base + ["--out", str(out3), "--mode", "composite", "--protocol", "3d"]) == 0
    alone = json.loads((out3 / "eval.json").read_text())
    assert alone["format"] == "n2f2-eval3d-v1" and "scores" in alone and alone["modes"] == ["composite"]
    assert alone["scores"]["composite"]["miou"] == p3["scores"]["composite"]["miou"]
    assert "3D protocol" in (out3 / "eval.md").read_text()

    # Flags the 3D protocol does not use are refused, as is oracle alone.
    assert cli_main(base + ["--out", str(tmp_path / "x"), "--protocol", "3d", "--budget"]) == 2
    assert "--budget" in capsys.readouterr().err
    assert cli_main(base + ["--out", str(tmp_path / "x"), "--protocol", "3d", "--mode", "oracle"]) == 2
    assert "oracle" in capsys.readouterr().err


def test_default_eval_json_has_no_3d_key(trained_run, tmp_path):
    out = tmp_path / "2d"
    argv = ["eval", str(trained_run.run_dir), "--labels", str(trained_run.scene_dir / "label"), "--out", str(out)]
    assert cli_main(argv + ["--mode", "composite", "--quiet", "--no-relevancy"]) == 0
    data = json.loads((out / "eval.json").read_text())
    assert "protocol3d" not in data and "3D protocol" not in (out / "eval.md").read_text()
