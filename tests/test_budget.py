"""mAP and query kinds in the evaluation runner, the teacher's features as a query engine, and
the loss budget (`n2f2 eval --budget`), on the session's tiny trained run."""

from __future__ import annotations

import json

import numpy as np
import pytest

from n2f2.cli import main as cli_main
from n2f2.data.labels import read_label_dir
from n2f2.eval.runner import EvalConfig, evaluate_run, read_query_kinds
from n2f2.query.outputs import unique_slugs


@pytest.fixture(scope="module")
def tiny(trained_run):
    return trained_run


@pytest.fixture(scope="module")
def evaluated(tiny, tmp_path_factory):
    out = tmp_path_factory.mktemp("budget_eval")
    result = evaluate_run(tiny.run_dir, tiny.scene_dir / "label", config=EvalConfig(progress=False),
                          relevancy_dir=out / "relevancy")
    return result, out


def _exact_mask(scene_dir, frame_name, query) -> np.ndarray:  # [H, W] bool, read off the region maps
    regions = json.loads((scene_dir / "regions.json").read_text())["regions"]
    level = {r["id"]: r["level"] for r in regions}
    ids = next(q["region_ids"] for q in json.loads((scene_dir / "queries.json").read_text())["queries"]
               if q["query"] == query)
    reg = np.load(scene_dir / "regions" / f"{frame_name}.npy")
    return np.any([reg[level[i]] == i for i in ids], axis=0)


def test_query_kinds_from_region_levels(tiny, tmp_path):
    kinds = read_query_kinds(tiny.scene_dir / "queries.json")
    assert kinds["lid of the teapot"] == "part" and kinds["teapot"] == "object" and kinds["tea set"] == "group"
    assert kinds["cookies"] == "mixed"  # the loose cookies (parts of the plate) and the bag (an object)
    path = tmp_path / "queries.json"
    path.write_text(json.dumps({"queries": [{"query": "a", "kind": "object"}, {"query": "b", "type": "simple"}]}))
    assert read_query_kinds(path) == {"a": "object"}


def test_ap_against_exact_masks_and_kind_split(tiny, evaluated):
    sklearn_metrics = pytest.importorskip("sklearn.metrics")
    result, out = evaluated
    labels = read_label_dir(tiny.scene_dir / "label")
    cats = list(dict.fromkeys(c for f in labels for c in f.categories))
    slug = dict(zip(cats, unique_slugs(cats)))
    ap = result.ap["composite"]["exact"]
    assert ap["num_pairs"] == result.scores["composite"]["exact"].num_pairs == ap["exact_masks"]
    for rec in ap["pairs"]:
        rel = np.load(out / "relevancy" / rec["frame"] / f"{slug[rec['query']]}.npy")
        mask = _exact_mask(tiny.scene_dir, rec["frame"], rec["query"])
        assert rec["ap"] == pytest.approx(sklearn_metrics.average_precision_score(mask.ravel(), rel.ravel()), abs=1e-9)
    assert ap["map"] == pytest.approx(np.mean([r["ap"] for r in ap["pairs"]]))
    assert result.ap["composite"]["scaled"]["map"] == ap["map"]  # one map, whatever the box
    kinds = read_query_kinds(tiny.scene_dir / "queries.json")
    for m in result.modes:
        for b, s in result.scores[m].items():
            kd = result.kinds[m][b]
            assert sum(v["pairs"] for v in kd.values()) == s.num_pairs
            for kind in ("part", "object", "group"):
                sel = [p for p in s.pairs if kinds.get(p.category) == kind]
                aps = [r["ap"] for r in result.ap[m][b]["pairs"] if kinds.get(r["query"]) == kind]
                assert kd[kind]["pairs"] == len(sel) == len(aps) > 0
                assert kd[kind]["miou"] == pytest.approx(np.mean([p.iou for p in sel]))
                assert kd[kind]["map"] == pytest.approx(np.mean(aps))


def test_teacher_engine_is_the_bank_features(tiny):
    """A labelled view's teacher relevancy at each level: the relevancy of the embedding of the
    segment covering the pixel at that level (ground-truth bank: layer l = level l; no segment:
    a zero feature, relevancy 0.5)."""
    import torch

    from n2f2.eval.budget import teacher_engine
    from n2f2.query.engine import QueryEngine
    from n2f2.segments.bank import SegmentBank

    base = QueryEngine.from_run(tiny.run_dir)
    bank = SegmentBank.open(tiny.bank_dir)
    teacher = teacher_engine(bank, base.encoder, dict(base.meta), base.config, scene=base.scene)
    frame = read_label_dir(tiny.scene_dir / "label")[0]
    view = teacher.render_view(frame.view_index, modes=["levels"])
    texts = frame.categories[:3]
    scored = []
    teacher.query(view, texts, mode="oracle", scorer=lambda rel, qi: scored.append(rel.clone()) or np.zeros(3))
    rec = bank.record(frame.view_index)
    emb = np.asarray(rec.embeddings, np.float64)
    t = base.encode(texts).double().numpy()
    negs = base.encode(base.config.negatives).double().numpy()
    layers = np.asarray(rec.layers)
    for qi in range(len(texts)):
        for level in range(3):
            ids = layers[level]
            ok = (ids >= 0) & np.asarray(rec.valid)[np.clip(ids, 0, None)]  # invalid segments: no feature
            e = np.where(ok[..., None], emb[np.clip(ids, 0, None)], 0.0)
            n = np.linalg.norm(e, axis=-1, keepdims=True)
            e = np.where(n > 0, e / np.maximum(n, 1e-30), 0.0)
            want = 1 / (1 + np.exp(-10 * (e @ t[qi] - (e @ negs.T).max(-1))))
            np.testing.assert_allclose(scored[qi][level].numpy(), want, atol=2e-5)
    assert torch.equal(view.alpha, torch.ones_like(view.alpha))


def test_loss_budget_and_cli(tiny, tmp_path, capsys):
    out = tmp_path / "out"
    rc = cli_main(["eval", str(tiny.run_dir), "--labels", str(tiny.scene_dir / "label"), "--out", str(out),
                   "--budget", "--quiet", "--no-relevancy"])
    assert rc == 0
    printed = capsys.readouterr().out
    assert "loss budget:" in printed and "teacher, 3 levels" in printed
    data = json.loads((out / "eval.json").read_text())
    budget = data["budget"]
    names = [r["name"] for r in budget["rows"]]
    assert names == ["teacher, 3 levels", "teacher, oracle level", "lift, 3 levels", "lift, oracle level",
                     "field, oracle scale", "composite", "explicit", "soft"]
    pairs = data["scores"]["composite"]["exact"]["num_pairs"]
    for r in budget["rows"]:
        for b in ("exact", "scaled"):
            s = r["scores"][b]
            assert s["num_pairs"] == pairs
            assert 0 <= s["miou"] <= 1 and 0 <= s["loc_accuracy"] <= 1 and 0 <= s["map"] <= 1
            assert sum(k["pairs"] for k in s["kinds"].values()) == pairs
    # the field's rows are the main evaluation's numbers
    by = {r["name"]: r for r in budget["rows"]}
    for name, mode in (("composite", "composite"), ("explicit", "explicit"), ("field, oracle scale", "oracle")):
        assert by[name]["scores"]["exact"]["miou"] == data["scores"][mode]["exact"]["miou"]
        assert by[name]["scores"]["exact"]["map"] == data["ap"][mode]["exact"]["map"]
    # the oracle level bounds the protocol's level choice, for the teacher and the lift
    for src in ("teacher", "lift"):
        for b in ("exact", "scaled"):
            assert by[f"{src}, oracle level"]["scores"][b]["miou"] >= by[f"{src}, 3 levels"]["scores"][b]["miou"] - 1e-12
    # training wrote the lift from its blend cache: the budget read it instead of building it
    assert budget["lift"]["from"].startswith("RUN/lift.pt") and budget["lift"]["seconds"]["lift"] > 0
    md = (out / "eval.md").read_text()
    assert "## Loss budget" in md and "lift, 3 levels" in md and "### By query kind" in md
    assert "mAP %" in md


def test_training_writes_the_lift_of_its_views(tiny):
    """RUN/lift.pt (written by `n2f2 train` from its cached blending weights) is the lift built
    from scratch over the same views."""
    import torch

    from n2f2.field.lift import load_lift
    from n2f2.query.engine import QueryEngine
    from n2f2.query.lifted import build_lift
    from n2f2.segments.bank import SegmentBank

    report = json.loads((tiny.run_dir / "train_report.json").read_text())
    assert report["lift"]["written"]
    base = QueryEngine.from_run(tiny.run_dir)
    saved = load_lift(tiny.run_dir / "lift.pt", num_gaussians=base.gaussians.means.shape[0])
    assert saved.views == report["train_views"]
    fresh = build_lift(base.gaussians, base.scene, SegmentBank.open(tiny.bank_dir), saved.views)
    torch.testing.assert_close(saved.features, fresh.features, atol=2e-3, rtol=0)  # float16 on disk


def test_budget_without_a_bank_is_one_line_before_any_work(tiny, tmp_path, capsys):
    out = tmp_path / "out"
    rc = cli_main(["eval", str(tiny.run_dir), "--labels", str(tiny.scene_dir / "label"), "--out", str(out),
                   "--budget", "--bank", str(tmp_path / "missing"), "--quiet"])
    assert rc == 2
    err = capsys.readouterr().err
    assert "--budget needs the run's segment bank" in err and len(err.strip().splitlines()) == 1
    assert not (out / "eval.json").exists()
