"""A trained run renders RGB as its Gaussian fit did: over the fit's learned background (copied
into the run as ``background.json``), bit for bit the fit's own test-view render at the same
camera, and at the downscale the run was trained at unless ``--full-res`` is asked for."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from n2f2.cli import main
from n2f2.gaussians.fit import BACKGROUND_NAME, TEST_RENDERS_DIR, Environment
from n2f2.io import write_json
from n2f2.query.engine import QueryEngine

TRAIN = (
    "--iterations",
    3,
    "--pixels-per-step",
    256,
    "--dim",
    32,
    "--plane-resolution",
    32,
    "--plane-channels",
    8,
    "--hidden",
    64,
    "--train-on-all",
    "--quiet",
)  # a few steps: the field's quality is not in question here


def _cli(*argv) -> None:
    assert main([str(a) for a in argv]) == 0, f"n2f2 {' '.join(map(str, argv))} failed"


def _fit_dir(trained_run) -> Path:
    fit = trained_run.run_dir.parent / "fit"  # where conftest's trained_run fits its Gaussians
    assert (fit / "gaussians.ply").is_file()
    return fit


def _train(trained_run, gaussians: Path, out: Path, *extra) -> Path:
    _cli(
        "train",
        trained_run.scene_dir,
        "--gaussians",
        gaussians,
        "--segments",
        trained_run.bank_dir,
        "--out",
        out,
        *TRAIN,
        *extra,
    )
    return out


def _test_views(fit: Path, engine: QueryEngine) -> dict[int, np.ndarray]:
    """The fit's held-out renders (``test_views/<stem>.npy``) by scene view index."""
    stems = [Path(n).stem for n in engine.scene.image_names]
    renders = {stems.index(p.stem): np.load(p) for p in sorted((fit / TEST_RENDERS_DIR).glob("*.npy"))}
    assert renders, "the fit held out no view"
    return renders


def test_a_run_renders_the_fits_test_views_bit_for_bit(trained_run):
    fit = _fit_dir(trained_run)
    engine = QueryEngine.from_run(trained_run.run_dir)
    # The demo scene's sparse points cover its walls: the fit learned no background (black).
    assert not (fit / BACKGROUND_NAME).exists() and not (trained_run.run_dir / BACKGROUND_NAME).exists()
    assert engine.background is None
    for i, render in _test_views(fit, engine).items():
        rgb = engine.render_view(i, rgb=True).rgb
        assert rgb is not None and np.array_equal(rgb.numpy(), render), engine.scene.image_names[i]


@pytest.fixture(scope="module")
def background_run(trained_run, tmp_path_factory):
    """A copy of the demo fit with a learned background (a colour varying over ray directions:
    SH degree 2) written beside its PLY, and a run trained on it."""
    root = tmp_path_factory.mktemp("background_run")
    fit = root / "fit"
    shutil.copytree(_fit_dir(trained_run), fit)
    env = Environment(2, (0.2, 0.5, 0.8))
    with torch.no_grad():
        env.sh[1:] = torch.linspace(-0.3, 0.3, 24).reshape(8, 3)
    write_json(fit / BACKGROUND_NAME, env.to_dict())
    return fit, _train(trained_run, fit / "gaussians.ply", root / "run")


def test_training_copies_the_fits_background_and_renders_use_it(trained_run, background_run):
    from n2f2.data import load_scene
    from n2f2.gaussians import read_ply
    from n2f2.gaussians.fit import FitConfig, evaluate, read_background

    fit, run = background_run
    assert (run / BACKGROUND_NAME).read_bytes() == (fit / BACKGROUND_NAME).read_bytes()
    engine = QueryEngine.from_run(run)
    assert engine.background is not None
    # The fit's own evaluation render of its held-out views over that background ...
    scene = load_scene(trained_run.scene_dir)
    views = sorted(_test_views(_fit_dir(trained_run), engine))
    renders = fit / "renders"
    evaluate(
        read_ply(fit / "gaussians.ply"),
        scene,
        views,
        views,
        FitConfig(),
        float(scene.extent()),
        renders_dir=renders,
        env=read_background(fit),
    )
    black = QueryEngine.from_run(trained_run.run_dir)
    for i in views:
        expected = np.load(renders / f"{Path(scene.image_names[i]).stem}.npy")
        rgb = engine.render_view(i, rgb=True).rgb
        assert rgb is not None and np.array_equal(rgb.numpy(), expected), scene.image_names[i]
        # ... which shows where the Gaussians leave the view uncovered (black before).
        assert not np.array_equal(rgb.numpy(), black.render_view(i, rgb=True).rgb.numpy())


def test_the_viewer_renders_over_the_runs_background(background_run):
    pytest.importorskip("fastapi")
    from n2f2.viewer.server import Viewer

    _, run = background_run
    engine = QueryEngine.from_run(run)
    view, _ = Viewer(engine).render("view:0", 0)
    assert torch.equal(view.rgb, engine.render_view(0, rgb=True).rgb)


def test_retraining_on_gaussians_without_a_background_drops_the_copied_one(trained_run, background_run, tmp_path):
    fit, run = background_run
    again = tmp_path / "run"
    shutil.copytree(run, again)
    _train(trained_run, _fit_dir(trained_run) / "gaussians.ply", again, "--force")
    assert not (again / BACKGROUND_NAME).exists()
    assert QueryEngine.from_run(again).background is None
    # Trained on its own copy of the Gaussians, a run keeps the background beside it.
    _train(trained_run, run / "gaussians.ply", again, "--force")
    assert (again / BACKGROUND_NAME).read_bytes() == (fit / BACKGROUND_NAME).read_bytes()


# ------------------------------------------------------------------------------------ downscale
@pytest.fixture(scope="module")
def downscaled_run(trained_run, tmp_path_factory):
    """A run trained at ``--downscale 2`` (its segment bank made at that size too)."""
    root = tmp_path_factory.mktemp("downscaled_run")
    bank = root / "bank"
    _cli(
        "segments",
        trained_run.scene_dir,
        "--gaussians",
        _fit_dir(trained_run) / "gaussians.ply",
        "--segmenter",
        "ground-truth",
        "--encoder",
        "captions",
        "--out",
        bank,
        "--downscale",
        2,
        "--quiet",
    )
    run = root / "run"
    _cli(
        "train",
        trained_run.scene_dir,
        "--gaussians",
        _fit_dir(trained_run) / "gaussians.ply",
        "--segments",
        bank,
        "--out",
        run,
        "--downscale",
        2,
        *TRAIN,
    )
    return run


def test_a_run_renders_at_the_downscale_it_was_trained_at(trained_run, downscaled_run):
    from n2f2.field import load_field

    assert load_field(downscaled_run / "field.pt")[1]["downscale"] == 2.0
    full = QueryEngine.from_run(trained_run.run_dir).scene.cameras[0]
    engine = QueryEngine.from_run(downscaled_run)
    assert engine.scene.downscale == 2.0
    assert engine.render_view(0, rgb=True).rgb.shape == (full.height // 2, full.width // 2, 3)
    # The same with the scene folder named (--scene); --full-res: the images' size.
    assert QueryEngine.from_run(downscaled_run, scene=trained_run.scene_dir).scene.downscale == 2.0
    at_full = QueryEngine.from_run(downscaled_run, full_res=True)
    assert at_full.render_view(0, rgb=True).rgb.shape == (full.height, full.width, 3)


def test_query_and_view_commands_take_full_res(trained_run, downscaled_run, tmp_path, monkeypatch):
    from PIL import Image

    full = QueryEngine.from_run(trained_run.run_dir).scene.cameras[0]
    for flags, size in (((), (full.width // 2, full.height // 2)), (("--full-res",), (full.width, full.height))):
        out = tmp_path / f"query{len(flags)}"
        _cli("query", downscaled_run, "teapot", "--views", 0, "--out", out, "--quiet", *flags)
        view = json.loads((out / "query.json").read_text())["views"][0]["view"]
        assert Image.open(out / f"{view}_rgb.png").size == size, flags

    pytest.importorskip("viser")
    from n2f2.cli import build_parser
    from n2f2.viewer import commands

    assert build_parser().parse_args(["view", str(downscaled_run), "--full-res"]).full_res
    assert not build_parser().parse_args(["view", str(downscaled_run)]).full_res
    seen = {}

    def from_run(run_dir, **kw):
        seen.update(kw)
        raise KeyboardInterrupt  # stop before any server starts

    monkeypatch.setattr(QueryEngine, "from_run", staticmethod(from_run))
    for full_res in (False, True):
        with pytest.raises(KeyboardInterrupt):
            commands.launch(downscaled_run, full_res=full_res)
        assert seen["full_res"] is full_res


def test_a_run_trained_without_missing_images_renders_its_own_views(trained_run, tmp_path):
    """A run trained with --skip-missing records it, so its query engine (and the hierarchy)
    load the scene the same way instead of refusing the missing image."""
    from n2f2.errors import InputError
    from n2f2.train.runs import load_run_scene

    scene = tmp_path / "scene"
    shutil.copytree(trained_run.scene_dir, scene)
    missing = sorted((scene / "images").iterdir())[0]
    missing.unlink()
    run, bank, ply = tmp_path / "run", tmp_path / "bank", _fit_dir(trained_run) / "gaussians.ply"
    assert main(["segments", str(scene), "--gaussians", str(ply), "--segmenter", "ground-truth",
                 "--encoder", "captions", "--out", str(bank), "--skip-missing", "--quiet"]) == 0
    assert main(["train", str(scene), "--gaussians", str(ply),
                 "--segments", str(bank), "--out", str(run), "--iterations", "2",
                 "--dim", "8", "--plane-resolution", "8", "--plane-channels", "4", "--hidden", "16",
                 "--skip-missing", "--quiet"]) == 0
    meta = torch.load(run / "field.pt", weights_only=False, map_location="cpu")["meta"]
    assert meta["skip_missing"] is True
    loaded = load_run_scene(run, meta, None)
    assert len(loaded.cameras) == trained_run.num_views - 1
    with pytest.raises(InputError):
        load_run_scene(run, {**meta, "skip_missing": False}, None)
