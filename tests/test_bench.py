"""``n2f2 bench``: a tiny bench end to end (tiny demo scene, 2 variants, a few steps) writes the
report with its tables and finite numbers and resumes on a rerun; the helpers are checked against
answers worked out by hand."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from n2f2.cli import main as cli_main
from n2f2.experiments.bench import BenchConfig, run_bench
from n2f2.experiments.claims import convergence, paired_difference
from n2f2.experiments.memory import ActivationMeter
from n2f2.experiments.variants import VARIANTS, run_name, scaled_step


def main(argv: list[str]) -> int:
    """``n2f2 bench ARGV``'s exit status (a refused option exits inside argparse)."""
    try:
        return cli_main(["bench", *argv])
    except SystemExit as e:
        return int(e.code or 0)


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    from n2f2.data import load_scene
    from n2f2.data.synthetic import generate_demo_scene
    from n2f2.gaussians import init_from_points, write_ply

    root = tmp_path_factory.mktemp("bench")
    scene_dir = generate_demo_scene(root / "scene", num_views=6, width=48, height=36, seed=0,
                                    labelled_views=[1, 4], supersample=1, num_points=600, show_progress=False)
    scene = load_scene(scene_dir)
    write_ply(root / "gaussians.ply", init_from_points(scene.points, scene.point_colors, sh_degree=0))
    config = BenchConfig(iterations=4, dim=12, pixels_per_step=256, variants=("nested", "flat", "levels", "lift"),
                         temperatures=(1.0, math.inf, 0.1), timing_repeats=1, progress=False)
    out = root / "out"
    result = run_bench(out, config, scene=scene_dir, gaussians=root / "gaussians.ply", log=lambda s: None)
    return {"root": root, "scene": scene_dir, "out": out, "config": config, "result": result}


def test_report_has_the_tables_and_finite_numbers(tiny):
    out = tiny["out"]
    md = (out / "bench.md").read_text()
    for heading in ("## Verdicts", "## Composite vs explicit vs oracle (paper Table 3)",
                    "## N2F2 vs the 3-level LangSplat-like field", "### Simple vs compound queries (paper Table 7)",
                    "## Nested vs non-nested", "## Composite temperature T", "## Query time breakdown (paper Table 4"):
        assert heading in md, heading
    assert "exact 30 px" in md and "scaled 1 px" in md  # both boxes, named with their sizes
    assert "segment scales: area measure, training scale jitter 0.03 (paper: eigenvalue, 0)" in md
    assert "with every covering segment, pixel balance 0.5 (paper 0: uniform pixels)" in md
    data = json.loads((out / "bench.json").read_text())
    bank = json.loads((out / "data" / "bank" / "bank.json").read_text())
    assert bank["lifting"]["scale_measure"] == data["data"]["scale_measure"] == "area"
    fields = [name for name, r in data["runs"].items() if not r["training_free"]]
    for name in fields:
        report = json.loads((out / "runs" / name / "train_report.json").read_text())
        assert report["train_config"]["scale_jitter"] == 0.03
        assert report["train_config"]["pixel_balance"] == 0.5
    assert set(data["runs"]) == {"nested-k1", "flat", "levels", "lift"}
    assert set(fields) == {"nested-k1", "flat", "levels"}
    for name in data["runs"]:
        assert (out / "runs" / name / "eval" / "eval.json").is_file()
    for name in fields:
        assert (out / "runs" / name / "field.pt").is_file()
        assert math.isfinite(data["runs"][name]["final_loss"])
    # Claims computed from paired (frame, query) differences are finite numbers.
    paired = [c for c in data["claims"] if c["pairs"]]
    assert {c["claim"] for c in paired} >= {"composite >= explicit (Table 3)",
                                           "N2F2 composite >= 3-level LangSplat-like",
                                           "composite T=1 (paper) >= T=0.1"}
    assert all(math.isfinite(c["delta"]) and -2 <= c["delta"] <= 2 for c in paired)
    for row in data["timing"]["rows"]:
        assert all(row[k] > 0 for k in ("render_s", "query_1_s", "per_query_s"))
    assert [r["mode"] for r in data["timing"]["rows"]] == ["composite", "explicit", "levels"]
    # The oracle picks, per pair, the best of the explicit mode's candidate scales.
    nested = data["evals"]["nested-k1"]["T1"]
    for box in ("exact", "scaled"):
        assert nested["scores"]["oracle"][box]["miou"] >= nested["scores"]["explicit"][box]["miou"] - 1e-9
    for png in ("methods.png", "loss_curves.png"):
        assert (out / png).stat().st_size > 0


def test_the_lift_row_is_what_the_loss_budget_scores(tiny):
    """The bench's lift (the nested run's RUN/lift.pt) scored as `n2f2 eval --budget` scores the
    lift of the same run, and its build time is what that run's training recorded."""
    from n2f2.eval.budget import loss_budget

    out = tiny["out"]
    data = json.loads((out / "bench.json").read_text())
    md = (out / "bench.md").read_text()
    assert "## Every method, with the time to build it" in md
    methods = {r["method"]: r for r in data["methods"]}
    assert list(methods) == ["N2F2 composite", "N2F2 composite, mean of normalised scale features (n2f2's default)",
                             "N2F2 composite, plain mean of scale features (T = infinity)",
                             "N2F2 composite, per-Gaussian render (paper)", "N2F2 soft",
                             "N2F2 explicit", "N2F2 explicit, per-Gaussian render (paper)", "N2F2 oracle",
                             "flat composite", "3-level", "3-level oracle", "lift (training-free)", "lift oracle"]
    # the paper's rendering is its own evaluation of the same nested run
    paper = data["evals"][methods["N2F2 composite"]["run"]]["gaussians"]
    assert paper["field"]["render"] == "gaussians" and set(paper["modes"]) == {"composite", "explicit"}
    assert data["evals"][methods["N2F2 composite"]["run"]]["T1"]["field"]["render"] == "deferred"
    # the composite rows name their weights: the paper's Eq. 6 at T = 1, and the uniform default
    evals = data["evals"][methods["N2F2 composite"]["run"]]
    assert evals["T1"]["field"]["composite_weights"] == "eq6" and evals["T1"]["field"]["composite_temperature"] == 1.0
    assert evals["Tuniform"]["field"]["composite_temperature"] == "uniform"
    assert evals["unit"]["field"]["composite_weights"] == "unit"
    assert data["config"]["temperatures"] == [1.0, "uniform", 0.1]  # JSON has no infinity
    for r in methods.values():
        assert r["build_time_s"] > 0
        assert f"| {r['method']} | {r['run']} |" in md
        for box in ("exact", "scaled"):
            for key in ("miou_pct", "loc_pct", "map_pct"):
                assert 0 <= r["scores"][box][key] <= 100
    lift = data["runs"]["lift"]
    assert lift["training_free"] and lift["lift"]["from"] == "training"
    assert lift["lift"]["lift_path"] == str(out / "runs" / "nested-k1" / "lift.pt")
    train = json.loads((out / "runs" / "nested-k1" / "train_report.json").read_text())
    assert lift["build_time_s"] == pytest.approx(train["blend_cache"]["build_s"] + train["lift"]["seconds"])
    assert data["runs"]["nested-k1"]["build_time_s"] == pytest.approx(train["train_time_s"])

    budget = loss_budget(out / "runs" / "nested-k1", tiny["scene"] / "label", scene=tiny["scene"],
                         bank=out / "data" / "bank")
    rows = {r["name"]: r for r in budget["rows"]}
    assert budget["lift"]["from"].startswith("RUN/lift.pt")
    ev = data["evals"]["lift"]["T1"]
    for method, row in (("lift (training-free)", "lift, 3 levels"), ("lift oracle", "lift, oracle level")):
        mode = methods[method]["mode"]
        for box in ("exact", "scaled"):
            want = rows[row]["scores"][box]
            got = methods[method]["scores"][box]
            assert got["miou_pct"] == pytest.approx(100 * want["miou"], abs=1e-9)
            assert got["loc_pct"] == pytest.approx(100 * want["loc_accuracy"], abs=1e-9)
            assert got["map_pct"] == pytest.approx(100 * want["map"], abs=1e-9)
            mine = {q: v["iou"] for q, v in ev["per_query"][mode][box].items()}
            assert mine and mine == pytest.approx({q: v["iou"] for q, v in rows[row]["per_query"][box].items()},
                                                  abs=1e-9)


def test_the_3d_protocol_scores_every_run_in_every_3d_mode(tiny):
    """Every run (nested, flat, levels and the lift) is scored under the 3D protocol on the labels
    the 2D tables use, in each mode it answers with a 3D query; bench.json and bench.md carry one
    row per (run, mode), and the nested run's numbers are those of evaluate_protocol3d called on
    that run directly."""
    from n2f2.data.labels import read_label_dir
    from n2f2.eval.protocol3d import Protocol3dConfig, evaluate_protocol3d
    from n2f2.query.engine import QueryEngine

    out = tiny["out"]
    data = json.loads((out / "bench.json").read_text())
    md = (out / "bench.md").read_text()
    p3 = data["protocol3d"]
    # Oracle is a 2D bound with no 3D query: every other mode of the prefix fields (flat has one
    # scale, so soft and explicit weigh it alone), and the level choice of the 3-level field and the lift.
    assert {n: list(m) for n, m in p3["runs"].items()} == {
        "nested-k1": ["composite", "explicit", "soft"], "flat": ["composite", "explicit", "soft"],
        "levels": ["levels"], "lift": ["levels"]}
    section = md.split("## 3D protocol (select Gaussians, render the selection)\n", 1)[1].split("\n## ", 1)[0]
    assert ("Selection rule (one per query, shared by every view): QueryEngine.select: min-max normalised "
            "Gaussian relevancy mapped to [-1, 1], clipped, > 0.4.") in section
    assert "| run | variant | mode | mIoU % | mAcc@0.25 % | mAcc@0.5 % | loc. % | pairs | empty selections |" in section
    variants = {"nested-k1": "nested", "flat": "flat", "levels": "levels", "lift": "lift"}
    for name, modes in p3["runs"].items():
        pairs_2d = data["evals"][name]["T1"]["scores"][data["evals"][name]["T1"]["modes"][0]]["exact"]["num_pairs"]
        for mode, r in modes.items():
            for key in ("miou_pct", "macc_0.25_pct", "macc_0.5_pct", "loc_pct"):
                assert 0 <= r[key] <= 100, (name, mode, key)
            assert r["macc_0.5_pct"] <= r["macc_0.25_pct"]  # IoU > 0.5 implies IoU > 0.25
            assert r["pairs"] == pairs_2d > 0  # the same (frame, query) pairs as the 2D protocol
            assert 0 <= r["empty_selections"] == len(r["empty_queries"]) <= r["queries"]
            assert (f"| {name} | {variants[name]} | {mode} | {r['miou_pct']:.1f} | {r['macc_0.25_pct']:.1f} | "
                    f"{r['macc_0.5_pct']:.1f} | {r['loc_pct']:.1f} | {r['pairs']} | "
                    f"{r['empty_selections']} of {r['queries']} |") in section
        assert (out / "runs" / name / "eval3d" / "eval.json").is_file()

    engine = QueryEngine.from_run(out / "runs" / "nested-k1", scene=tiny["scene"])
    direct = evaluate_protocol3d(engine, read_label_dir(tiny["scene"] / "label"), config=Protocol3dConfig(progress=False))
    assert direct.modes == list(p3["runs"]["nested-k1"])
    for mode, s in direct.scores.items():
        r = p3["runs"]["nested-k1"][mode]
        assert r["miou_pct"] == pytest.approx(100 * s.miou, abs=1e-6)
        assert r["macc_0.25_pct"] == pytest.approx(100 * s.acc["0.25"], abs=1e-6)
        assert r["macc_0.5_pct"] == pytest.approx(100 * s.acc["0.5"], abs=1e-6)
        assert r["loc_pct"] == pytest.approx(100 * s.loc_accuracy, abs=1e-6)
        assert (r["pairs"], r["empty_queries"]) == (s.num_pairs, s.empty_selections)


def test_the_lift_alone_builds_its_blending_weights(tiny, tmp_path, capsys):
    """`--variants lift` trains nothing: the bench builds the blending weights over the training
    views itself, and the lift is the one the nested run's training wrote from its cache."""
    from n2f2.field.lift import load_lift

    out = tmp_path / "alone"
    rc = main(["--out", str(out), "--variants", "lift", "--scene", str(tiny["scene"]),
               "--gaussians", str(tiny["root"] / "gaussians.ply"), "--bank", str(tiny["out"] / "data" / "bank"),
               "--quiet"])
    assert rc == 0, capsys.readouterr().err
    data = json.loads((out / "bench.json").read_text())
    assert set(data["runs"]) == {"lift"} and not (out / "runs" / "lift" / "field.pt").exists()
    lift = data["runs"]["lift"]
    assert lift["lift"]["from"] == "bench" and lift["build_time_s"] > 0
    assert lift["build_time_s"] == pytest.approx(lift["lift"]["blend_weights_s"] + lift["lift"]["lift_s"])
    assert "| lift (training-free) | lift |" in (out / "bench.md").read_text()
    mine = load_lift(out / "runs" / "lift" / "lift.pt")
    trained = load_lift(tiny["out"] / "runs" / "nested-k1" / "lift.pt")
    assert mine.views == trained.views
    torch.testing.assert_close(mine.features, trained.features)  # the same weights, computed twice
    full = {r["method"]: r["scores"] for r in json.loads((tiny["out"] / "bench.json").read_text())["methods"]}
    assert [r["method"] for r in data["methods"]] == ["lift (training-free)", "lift oracle"]
    for r in data["methods"]:
        for box in ("exact", "scaled"):
            assert r["scores"][box] == pytest.approx(full[r["method"]][box], abs=1e-6)


def test_gamma_sharpens_as_the_temperature_drops(tiny):
    gamma = {g["temperature"]: g for g in tiny["result"]["gamma"]}
    assert set(gamma) == {1.0, "uniform", 0.1}
    # T -> infinity: every Gaussian weighs its 12 scales equally
    assert gamma["uniform"]["max_gamma_x_scales_mean"] == pytest.approx(1.0, abs=1e-6)
    assert gamma["uniform"]["effective_scales_mean"] == pytest.approx(12.0, abs=1e-4)
    for g in gamma.values():
        assert g["scales"] == 12  # D = 12, k = 1
        assert g["max_gamma_mean"] >= 1.0 / g["scales"] - 1e-7  # a distribution's max is at least uniform
        assert 1.0 - 1e-5 <= g["effective_scales_mean"] * (1 + 1e-6) and g["effective_scales_mean"] <= 12 + 1e-4
        assert g["prefix_weight_at"]["1"] == pytest.approx(1.0, abs=1e-5)  # r_1 = sum of all gamma
    # The entropy of softmax(z / T) grows with T: fewer effective scales at T = 0.1.
    assert gamma[0.1]["effective_scales_mean"] <= gamma[1.0]["effective_scales_mean"] + 1e-6
    assert gamma[0.1]["max_gamma_mean"] >= gamma[1.0]["max_gamma_mean"] - 1e-7


def test_rerun_reuses_runs_and_evaluations(tiny):
    out = tiny["out"]
    fields = {p: p.stat().st_mtime_ns for p in (out / "runs").glob("*/field.pt")}
    evals = {p: p.stat().st_mtime_ns for p in (out / "runs").glob("*/eval*/eval.json")}
    # 2D: nested (T = 1, uniform and 0.1, unit weights, and the paper's per-Gaussian render), flat, levels
    # and the lift; 3D: one per run
    assert len(fields) == 3 and len(evals) == 8 + 4
    assert len([p for p in evals if p.parent.name == "eval3d"]) == 4
    again = run_bench(out, tiny["config"], scene=tiny["scene"], gaussians=tiny["root"] / "gaussians.ply",
                      log=lambda s: None)
    assert {p: p.stat().st_mtime_ns for p in (out / "runs").glob("*/field.pt")} == fields
    assert {p: p.stat().st_mtime_ns for p in (out / "runs").glob("*/eval*/eval.json")} == evals
    assert all(r["reused"] for r in again["runs"].values())
    assert again["protocol3d"] == tiny["result"]["protocol3d"]
    # Scores come from the reused evaluations, so their claims are the same; query timing is
    # measured anew on every run, so the speed claims are left out of the comparison.
    scored = lambda r: [c["delta"] for c in r["claims"] if c["metric"] != "time"]  # noqa: E731
    assert len(scored(again)) > 0
    assert scored(again) == pytest.approx(scored(tiny["result"]), nan_ok=True)
    assert [c["claim"] for c in again["claims"]] == [c["claim"] for c in tiny["result"]["claims"]]


def test_bad_input_is_one_clear_error(tmp_path, capsys):
    rc = main(["--out", str(tmp_path / "o"), "--scene", str(tmp_path / "missing"), "--quiet"])
    assert rc == 2
    assert "scene folder does not exist" in capsys.readouterr().err
    assert main(["--out", str(tmp_path / "o"), "--iterations", "0", "--quiet"]) == 2
    capsys.readouterr()
    assert main(["--out", str(tmp_path / "o"), "--scale-jitter", "-0.1", "--quiet"]) == 2
    assert "--scale-jitter must be" in capsys.readouterr().err


def test_scaled_step_keeps_the_number_of_scales():
    # Worked by hand: paper k -> floor(512 / k) scales; at D, k = floor(D / scales).
    assert [scaled_step(k, 128) for k in (1, 8, 32, 128, 170)] == [1, 2, 8, 32, 42]
    assert [scaled_step(k, 512) for k in (1, 8, 32, 128, 170)] == [1, 8, 32, 128, 170]
    assert [scaled_step(k, 32) for k in (1, 8, 32, 128, 170)] == [1, 1, 2, 8, 10]
    for k in (8, 32, 128, 170):
        assert 128 // scaled_step(k, 128) == 512 // k
    # Settings that map to the same k share a run.
    assert run_name(VARIANTS["k8"], 32) == run_name(VARIANTS["nested"], 32) == "nested-k1"
    assert run_name(VARIANTS["mlp"], 128) == "nested-k1-mlp"


def test_activation_meter_counts_saved_storages_once():
    a = torch.randn(1000, requires_grad=True)
    with ActivationMeter(exclude=[a]) as meter:
        b = a.exp()  # saves its result b (4000 bytes)
        (b * b).sum().backward()  # saves b twice: the same storage, counted once
        meter.end_step()
        c = a * 2.0  # saves nothing but the scalar; a itself is excluded
        c.sum().backward()
        meter.end_step()
    assert meter.steps[0] == 4000
    assert meter.steps[1] == 0
    assert meter.peak_bytes == 4000


def test_paired_difference_and_convergence_by_hand():
    def ev(ious, hits):
        pairs = [{"frame": "f", "category": q, "iou": i, "hit": h} for q, i, h in zip("abc", ious, hits)]
        return {"scores": {"m": {"exact": {"pairs": pairs}}}}

    d = paired_difference(ev([0.5, 0.2, 0.9], [1, 0, 1]), "m", ev([0.3, 0.2, 0.6], [0, 0, 1]), "m", "exact")
    diffs = np.array([0.2, 0.0, 0.3])
    assert d["delta"] == pytest.approx(diffs.mean())
    assert d["se"] == pytest.approx(diffs.std(ddof=1) / math.sqrt(3))
    assert d["pairs"] == 3
    assert paired_difference(ev([0.5, 0.2, 0.9], [1, 0, 1]), "m", ev([0.3, 0.2, 0.6], [0, 0, 1]), "m", "exact",
                             "hit")["delta"] == pytest.approx(1 / 3)
    curves = {"fast": {"step": [10, 20, 30], "loss": [0.5, 0.1, 0.05]},
              "slow": {"step": [10, 20, 30], "loss": [0.9, 0.5, 0.2]}}
    c = convergence(curves)
    assert c == {"target_loss": 0.2, "fast": 20, "slow": 30}


def test_a_longer_bench_continues_a_shorter_run_exactly(tiny, tmp_path):
    """4 steps then 2 more (the bench continues the checkpoint) = 6 steps at once."""
    from dataclasses import replace

    from n2f2.experiments.bench import BenchData
    from n2f2.experiments.training import train_variant
    from n2f2.field import load_field

    out, root = tiny["out"], tiny["root"]
    data = BenchData(tiny["scene"], root / "gaussians.ply", out / "data" / "bank", tiny["scene"] / "label")
    six = replace(tiny["config"], iterations=6)
    short = tmp_path / "short"
    train_variant(VARIANTS["nested"], data, short, tiny["config"], log=lambda s: None)
    continued = train_variant(VARIANTS["nested"], data, short, six, log=lambda s: None)
    fresh = train_variant(VARIANTS["nested"], data, tmp_path / "fresh", six, log=lambda s: None)
    assert continued["steps"] == fresh["steps"] == 6 and not continued["reused"]
    a, _ = load_field(short / "field.pt")
    b, _ = load_field(tmp_path / "fresh" / "field.pt")
    for (name, x), (_, y) in zip(a.state_dict().items(), b.state_dict().items()):
        torch.testing.assert_close(x, y, msg=name)
    # (The loss curves differ only in where points are logged: each session logs its last step.)
    assert continued["curve"]["step"][-1] == fresh["curve"]["step"][-1] == 6


def test_an_interrupted_extension_is_finished_not_reused(tiny, tmp_path):
    """A checkpoint with the longer run's settings beside the shorter run's field and report (what
    an interrupted extension leaves) is resumed to the full step count, never reported as done."""
    import shutil
    from dataclasses import replace

    from n2f2.experiments.bench import BenchData
    from n2f2.experiments.training import train_variant

    out, root = tiny["out"], tiny["root"]
    data = BenchData(tiny["scene"], root / "gaussians.ply", out / "data" / "bank", tiny["scene"] / "label")
    six = replace(tiny["config"], iterations=6)
    short, full = tmp_path / "short", tmp_path / "full"
    train_variant(VARIANTS["nested"], data, short, tiny["config"], log=lambda s: None)
    train_variant(VARIANTS["nested"], data, full, six, log=lambda s: None)
    shutil.copy(full / "checkpoint.pt", short / "checkpoint.pt")  # the 4-step field.pt stays
    again = train_variant(VARIANTS["nested"], data, short, six, log=lambda s: None)
    assert not again["reused"] and again["steps"] == 6
    assert json.loads((short / "train_report.json").read_text())["steps"] == 6
