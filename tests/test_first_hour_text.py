"""What a newcomer reads in the first hour: the README's offline advice, flag names, help
defaults and progress text (issue "A newcomer's first hour", items 2 and 6)."""

from __future__ import annotations

import argparse
import re
import shlex
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch

from n2f2.cli import build_parser

README = Path(__file__).resolve().parents[1] / "README.md"


def _subparser(name: str) -> argparse.ArgumentParser:
    parser = build_parser()
    (sub,) = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    return sub.choices[name]


def _help(name: str) -> str:
    return " ".join(_subparser(name).format_help().split())  # unwrapped


def _offline_section() -> str:
    text = README.read_text(encoding="utf-8")
    match = re.search(r"^### No internet on the machine\?\n(.*?)(?=^#)", text, re.S | re.M)
    assert match, "README has no 'No internet on the machine?' section"
    return match.group(1)


def _code_lines(section: str) -> list[str]:
    """The lines of the section's fenced code blocks."""
    lines, inside = [], False
    for line in section.splitlines():
        if line.strip().startswith("```"):
            inside = not inside
        elif inside and line.strip():
            lines.append(line.strip())
    return lines


def test_the_advised_download_command_exists():
    hf = Path(sys.executable).parent / "hf"
    assert hf.is_file(), f"{hf} missing: the README advises `hf download`"
    done = subprocess.run([str(hf), "download", "--help"], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    assert "--local-dir" in done.stdout


def test_sfm_documents_force_and_still_accepts_overwrite():
    text = _help("sfm")
    assert "--force" in text
    assert "--overwrite" not in text
    parser = build_parser()
    plain = parser.parse_args(["sfm", "photos", "--out", "data"])
    force = parser.parse_args(["sfm", "photos", "--out", "data", "--force"])
    old = parser.parse_args(["sfm", "photos", "--out", "data", "--overwrite"])
    assert plain.overwrite is False
    assert force.overwrite is True and old.overwrite is True


def test_render_size_states_its_default():
    assert "--size W H" in _help("render")
    assert re.search(r"--size W H [^-]*\(default 512 384\)", _help("render"))
    assert build_parser().parse_args(["render", "x.ply", "--out", "d"]).size == (512, 384)


def test_offline_section_downloads_the_default_models():
    from n2f2.segments.encoders import DEFAULT_CLIP_MODEL
    from n2f2.segments.sam import DEFAULT_SAM_MODEL

    downloads = [shlex.split(line) for line in _code_lines(_offline_section()) if line.startswith("hf ")]
    ids = {words[2] for words in downloads}
    assert {DEFAULT_CLIP_MODEL, DEFAULT_SAM_MODEL} <= ids
    for words in downloads:
        assert words[:2] == ["hf", "download"] and "--local-dir" in words


def _placeholder(word: str, root: Path) -> str:
    """A dummy path for a placeholder (PHOTOS, RUN, models/clip, GAUSSIANS/gaussians.ply)."""
    if word.startswith("-") or not (word.isupper() or "/" in word):
        return word
    path = root / word
    if path.suffix:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.touch()
    else:
        path.mkdir(parents=True, exist_ok=True)
    return str(path)


def test_every_n2f2_command_of_the_offline_section_parses(tmp_path):
    section = _offline_section()
    commands = [line for line in _code_lines(section) if line.startswith("n2f2 ")]
    inline = re.findall(r"`(n2f2 [^`]*)`", section)
    flags = re.findall(r"`(--[a-z-]+(?: [a-z0-9-]+)?)`", section)
    assert len(commands) >= 5 and any("--clip-model" in c for c in commands)
    assert any("--sam-model" in c and c.startswith("n2f2 run-many") for c in commands)
    parser = build_parser()
    names = set(next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices)
    for line in commands + inline:
        words = shlex.split(line)[1:]
        assert words[0] in names, line
        if len(words) == 1:
            continue  # a command named in prose, without arguments
        args = parser.parse_args([_placeholder(w, tmp_path) for w in words])
        assert callable(args.func), line
    for flag in flags:  # flags named in prose are `n2f2 run`'s
        if flag.startswith("--local-dir"):
            continue
        parser.parse_args(["run", str(tmp_path), "--out", str(tmp_path / "run"), *flag.split()])


def test_run_and_run_many_take_both_model_folders(tmp_path):
    parser = build_parser()
    for command in (["run", "photos", "--out", "run"], ["run-many", "a", "b", "--out", "dir"]):
        args = parser.parse_args([*command, "--clip-model", "models/clip", "--sam-model", "models/sam"])
        assert "models/clip" in vars(args).values() and "models/sam" in vars(args).values()


def test_classical_sentence_says_the_encoder_needs_clip():
    text = " ".join(README.read_text(encoding="utf-8").split())
    assert "works on real photos without any weights" not in text
    assert re.search(r"`--segmenter classical`[^*]*needs the CLIP weights", text)


def test_sfm_map_text():
    from n2f2.data.sfm import _models_text

    assert _models_text([]) == "no model"
    assert _models_text([84]) == "1 model, 84 photos registered"
    assert _models_text([1]) == "1 model, 1 photo registered"
    assert _models_text([84, 2]) == "2 models, 84 and 2 photos registered (the largest is kept)"
    assert _models_text([84, 5, 2]) == "3 models, 84, 5 and 2 photos registered (the largest is kept)"


def test_sfm_bars_name_their_unit(capsys):
    from n2f2.data.sfm import _Stages

    stages = object.__new__(_Stages)  # _bar needs no pycolmap
    stages.progress = True
    with stages._bar(10, "sfm: extracting features", "photo") as bar:
        slow = {**bar.format_dict, "n": 3, "elapsed": 3.06}  # one photo a second: the rate reads s/unit
        line = bar.format_meter(**slow)
    assert "1.02s/photo]" in line and "s/]" not in line


def _fake_blend(monkeypatch):
    import n2f2.train.blend as blend

    def weights(geometry, cam):
        pix = torch.arange(cam.width * cam.height)
        return pix, torch.zeros_like(pix), torch.ones(pix.numel())

    monkeypatch.setattr(blend, "view_blend_weights", weights)
    return blend.build_blend_cache, {"means": torch.zeros(2, 3)}, [SimpleNamespace(width=4, height=3)] * 3


def test_blend_bar_is_not_left_at_zero_when_the_cache_does_not_fit(monkeypatch, capsys):
    build, geometry, cams = _fake_blend(monkeypatch)
    with pytest.raises(MemoryError):
        build(geometry, cams, max_bytes=100, progress=True)
    assert "blend weights" not in capsys.readouterr().err


def test_blend_bar_starts_at_the_first_view(monkeypatch, capsys):
    build, geometry, cams = _fake_blend(monkeypatch)
    cache = build(geometry, cams, progress=True)
    assert cache.offsets == [0, 12, 24]
    err = capsys.readouterr().err
    assert "blend weights" in err and "1/3" in err and "0/3" not in err
