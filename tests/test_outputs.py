"""Output folders on a bad disk, a second run and half-listed scenes: each ends in exit 2 and one
line on stderr, changes nothing outside ``--out`` and leaves nothing half-written inside it.

Full and read-only disks are real: a small ``tmpfs`` mounted in a private mount namespace
(``unshare -m``), which needs root; those tests are skipped otherwise. The commands run as child
processes there, on copies of the session's ``trained_run``."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from n2f2.cli import main
from n2f2.io import LOCK_NAME, MIN_FREE_BYTES

from test_fuzz import assert_refused, base, copy, folder_state, run_cli  # noqa: F401 (base: a fixture)


def _can_mount_tmpfs() -> bool:
    if os.geteuid() != 0 or shutil.which("unshare") is None:
        return False
    probe = subprocess.run(["unshare", "-m", "sh", "-c", "mount -t tmpfs -o size=64k tmpfs /mnt"],
                           capture_output=True)
    return probe.returncode == 0


# The n2f2 command in a child process.
N2F2 = [sys.executable, "-c", "import sys; from n2f2.cli import main; sys.exit(main())"]

needs_tmpfs = pytest.mark.skipif(not _can_mount_tmpfs(), reason="needs root and unshare -m to mount a tmpfs")

# The child: mounts a tmpfs of SIZE bytes on MOUNT (its own mount namespace), runs STEPS (each a
# list of n2f2 arguments, or a command: "fill" leaves FREE bytes free, "ro" remounts read-only),
# and prints one JSON line: per step its exit status, stderr, and the file hashes on the tmpfs.
_CHILD = textwrap.dedent("""
    import hashlib, json, os, subprocess, sys
    spec = json.loads(sys.argv[1])
    mount = spec["mount"]
    subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={spec['size']}", "tmpfs", mount], check=True)

    def state():
        return {os.path.relpath(os.path.join(d, f), mount):
                hashlib.sha256(open(os.path.join(d, f), "rb").read()).hexdigest()
                for d, _, files in os.walk(mount) for f in files}

    results = []
    for step in spec["steps"]:
        if step == "ro":
            subprocess.run(["mount", "-o", "remount,ro", mount], check=True)
            continue
        if isinstance(step, dict):  # fill the disk, leaving step["free"] bytes
            st = os.statvfs(mount)
            room = st.f_bavail * st.f_frsize - step["free"]
            with open(os.path.join(mount, "filler.bin"), "wb") as f:
                f.write(b"\\0" * max(room, 0))
            continue
        before = state()
        env = {**os.environ, "N2F2_MIN_FREE_MB": str(spec["min_free_mb"])}
        p = subprocess.run([*spec["n2f2"], *step], capture_output=True, text=True, env=env)
        results.append({"rc": p.returncode, "err": p.stderr, "out": p.stdout, "before": before, "after": state()})
    print(json.dumps(results))
""")


def in_tmpfs(mount: Path, size: int, steps: list, min_free_mb: float = MIN_FREE_BYTES / 2**20) -> list[dict]:
    mount.mkdir(parents=True, exist_ok=True)
    spec = json.dumps({"mount": str(mount), "size": size, "n2f2": N2F2, "min_free_mb": min_free_mb, "steps": [s if isinstance(s, (str, dict)) else
                                                                    [str(a) for a in s] for s in steps]})
    p = subprocess.run(["unshare", "-m", sys.executable, "-c", _CHILD, spec], capture_output=True, text=True,
                       timeout=900)
    assert p.returncode == 0, p.stderr
    return json.loads(p.stdout.strip().splitlines()[-1])


def one_line(result: dict, *fragments: str) -> str:
    """Exit 2, exactly one line on stderr (holding ``fragments``), no traceback."""
    lines = [line for line in result["err"].strip().splitlines() if line]
    assert result["rc"] == 2, result["err"]
    assert "Traceback" not in result["err"] + result["out"]
    assert len(lines) == 1, result["err"]
    for fragment in fragments:
        assert fragment in lines[0], lines[0]
    return lines[0]


def _fit(scene: Path, out: Path, *extra) -> list:
    return ["fit-gaussians", scene, "--out", out, "--steps", 4, "--quiet", *extra]


def _query(run: Path, out: Path, *extra) -> list:
    return ["query", run, "teapot", "lid of the teapot", "red mug", "--views", 0, 1, 2, 3, "--out", out, "--quiet",
            *extra]


# ------------------------------------------------------------------------------ before any work
def test_out_below_a_file_is_one_line(base, tmp_path, capsys):
    scene = copy(base["scene"], tmp_path / "scene")
    (scene / "o").write_text("a file")
    line = assert_refused(capsys, _fit(scene, scene / "o" / "sub"), [scene], "not a directory")
    assert str(scene / "o") in line


def test_a_refused_run_removes_the_folders_it_made(base, tmp_path, capsys):
    broken = copy(base["scene"], tmp_path / "scene")
    (broken / "transforms.json").write_text("{")
    out = tmp_path / "new" / "fit"
    assert_refused(capsys, _fit(broken, out), [broken], "transforms.json")
    assert not (tmp_path / "new").exists()


@needs_tmpfs
def test_read_only_and_full_output_folders_are_refused_up_front(base, tmp_path):
    mount = tmp_path / "disk"
    ro = in_tmpfs(mount, 32 << 20, ["ro", _fit(base["scene"], mount / "fit")])
    one_line(ro[0], str(mount / "fit"), "read-only")
    full = in_tmpfs(mount, 32 << 20, [{"free": MIN_FREE_BYTES // 2}, _fit(base["scene"], mount / "fit")])
    line = one_line(full[0], str(mount / "fit"), "no space left", "MB free", "MB needed")
    assert full[0]["after"] == full[0]["before"]
    assert line.count("MB") == 2


@needs_tmpfs
def test_a_disk_that_fills_during_the_fit_leaves_the_folder_as_it_was(base, tmp_path):
    # Room for the checks (a floor of 0.1 MB) but not for the checkpoint: torch's zip writer
    # fails mid-file.
    mount = tmp_path / "disk"
    res = in_tmpfs(mount, 32 << 20, [{"free": 256 << 10}, _fit(base["scene"], mount / "fit", "--checkpoint-every", 2)],
                   min_free_mb=0.1)
    one_line(res[0], "cannot write", "no space left")
    assert res[0]["after"] == res[0]["before"]  # no temporary file, no half result, no folder


@needs_tmpfs
def test_a_disk_that_fills_during_a_query_keeps_the_earlier_answer(base, tmp_path):
    mount = tmp_path / "disk"
    out = mount / "q"
    res = in_tmpfs(mount, 32 << 20, [_query(base["run"], out), {"free": 160 << 10}, _query(base["run"], out, "--force")],
                   min_free_mb=0.1)
    assert res[0]["rc"] == 0, res[0]["err"]
    one_line(res[1], "cannot write", "no space left")
    assert res[1]["after"] == res[1]["before"]  # the first answer, file for file
    assert any(name.endswith("query.json") for name in res[1]["after"])


# ------------------------------------------------------------------------------ one run at a time
def _train(base: dict, out: Path, iterations: int) -> list:
    return ["train", base["scene"], "--gaussians", base["ply"], "--segments", base["bank"], "--out", out,
            "--iterations", iterations, "--pixels-per-step", 256, "--dim", 16, "--plane-resolution", 16,
            "--plane-channels", 4, "--hidden", 32, "--checkpoint-every", 1, "--quiet"]


def test_a_second_run_into_a_busy_folder_is_refused_and_the_first_finishes(base, tmp_path):
    out = tmp_path / "run"
    cmd = [*N2F2, *map(str, _train(base, out, 150))]
    first = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 300
        while not (out / "checkpoint.pt").exists():  # the first is training and checkpointing
            assert first.poll() is None and time.monotonic() < deadline, first.communicate()
            time.sleep(0.05)
        # Paused while the second starts (however long its imports take), then let go on.
        os.kill(first.pid, signal.SIGSTOP)
        try:
            second = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
        finally:
            os.kill(first.pid, signal.SIGCONT)
        one_line({"rc": second.returncode, "err": second.stderr, "out": second.stdout},
                 str(out), f"PID {first.pid}", "another n2f2 run")
        _, err = first.communicate(timeout=600)
    finally:
        if first.poll() is None:
            first.kill()
    assert first.returncode == 0, err
    from n2f2.field.model import load_field

    field, meta = load_field(out / "field.pt")
    assert meta is not None and field is not None
    assert not (out / LOCK_NAME).exists()


def test_a_lock_left_by_a_dead_process_is_taken_over(base, tmp_path, capsys):
    out = tmp_path / "q"
    out.mkdir()
    dead = subprocess.Popen(["true"])
    dead.wait()
    (out / LOCK_NAME).write_text(f"{dead.pid}\n")
    assert run_cli(_query(base["run"], out)) == 0
    err = capsys.readouterr().err
    assert f"taking over the lock of PID {dead.pid}" in err
    assert (out / "query.json").is_file() and not (out / LOCK_NAME).exists()


def test_the_same_process_may_claim_a_folder_twice(tmp_path):
    from n2f2.io import claim_out_dir, command_outputs

    with command_outputs():
        claim_out_dir(tmp_path / "a", ())
        claim_out_dir(tmp_path / "a", ())  # n2f2 run claims RUN, then its stages their folders
        assert (tmp_path / "a" / LOCK_NAME).read_text().strip() == str(os.getpid())
    assert not (tmp_path / "a" / LOCK_NAME).exists()


# ------------------------------------------------------------------------------ the journal
def test_a_failing_command_restores_what_it_replaced_and_removes_what_it_wrote(tmp_path):
    from n2f2.io import command_outputs, remove_results, save_torch, write_json, write_text

    out = tmp_path / "out"
    out.mkdir()
    write_text(out / "old.txt", "old")
    write_text(out / "kept.txt", "kept")
    (out / "folder").mkdir()
    write_text(out / "folder" / "inside.txt", "inside")
    before = folder_state(out)
    with pytest.raises(RuntimeError, match="late"), command_outputs():
        remove_results(out, ["old.txt", "folder"])  # --force
        write_text(out / "old.txt", "new")
        write_text(out / "kept.txt", "replaced")
        write_json(out / "sub" / "new.json", {"a": 1})
        save_torch(out / "checkpoint.pt", {"step": 3}, keep=True)  # resumable state
        raise RuntimeError("late")
    after = folder_state(out)
    assert after.pop("checkpoint.pt") and after == before
    assert not (out / "sub").exists()
    assert sorted(p.name for p in out.iterdir()) == ["checkpoint.pt", "folder", "kept.txt", "old.txt"]
    # Success: the new files stay, the replaced ones are gone (no leftovers beside them).
    with command_outputs():
        remove_results(out, ["old.txt"])
        write_text(out / "old.txt", "new")
        write_text(out / "kept.txt", "replaced")
    assert (out / "old.txt").read_text() == "new" and (out / "kept.txt").read_text() == "replaced"
    assert sorted(p.name for p in out.iterdir()) == ["checkpoint.pt", "folder", "kept.txt", "old.txt"]


# ------------------------------------------------------------------------------ inputs checked at load
def test_an_image_listed_twice_through_an_alias_is_refused(base, tmp_path, capsys):
    scene = copy(base["scene"], tmp_path / "scene")
    meta = json.loads((scene / "transforms.json").read_text())
    name = meta["frames"][1]["file_path"]  # images/frame_00001.png
    meta["frames"].append({**meta["frames"][1], "file_path": "./images/../" + name})
    (scene / "transforms.json").write_text(json.dumps(meta))
    assert_refused(capsys, ["inspect", scene], [scene], "transforms.json", "listed twice", Path(name).name)


def test_missing_depth_of_a_held_out_view_is_one_warning(base, tmp_path, capsys):
    scene = copy(base["scene"], tmp_path / "scene")
    (scene / "depth" / "frame_00001.npy").unlink()  # view 0: held out by the fit
    out = tmp_path / "fit"
    assert run_cli(_fit(scene, out)) == 0
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(err) == 1 and "depth/frame_00001.npy" in err[0] and err[0].startswith("warning:"), err
    report = json.loads((out / "fit_report.json").read_text())
    assert report["test_psnr"] is not None
    # Lifting with the exact depth needs every view's: refused before any segmenting.
    bank = tmp_path / "bank"
    assert_refused(capsys, ["segments", scene, "--gaussians", base["ply"], "--segmenter", "ground-truth",
                            "--encoder", "captions", "--depth-source", "gt", "--out", bank, "--quiet"],
                   [scene], "frame_00001.npy", "--depth-source render")
    assert not bank.exists()


def test_long_query_texts_are_shortened_on_the_console_only(base, tmp_path, capsys):
    text = "teapot " * 2000
    out = tmp_path / "q"
    assert main(["query", str(base["run"]), text, "--views", "0", "--out", str(out), "--quiet"]) == 0
    printed = capsys.readouterr().out
    assert all(len(line) < 300 for line in printed.splitlines()), printed
    assert f"({len(text.strip())} characters)" in printed or f"({len(text)} characters)" in printed
    saved = json.loads((out / "query.json").read_text())
    assert saved["views"][0]["queries"][0]["query"] in (text, text.strip())


def test_results_a_killed_run_had_set_aside_are_put_back_by_the_next(tmp_path):
    from n2f2.io import claim_out_dir, command_outputs

    out = tmp_path / "out"
    out.mkdir()
    dead = subprocess.Popen(["true"])
    dead.wait()
    (out / f".field.pt.n2f2-old-{dead.pid}").write_text("the earlier field")  # nothing replaced it
    (out / "eval.json").write_text("new")
    (out / f".eval.json.n2f2-old-{dead.pid}").write_text("old")  # replaced: the new one stays
    (out / f".live.json.n2f2-old-{os.getpid()}").write_text("a live run's")
    with command_outputs():
        claim_out_dir(out, ())
    assert (out / "field.pt").read_text() == "the earlier field"
    assert (out / "eval.json").read_text() == "new"
    assert sorted(p.name for p in out.iterdir()) == [f".live.json.n2f2-old-{os.getpid()}", "eval.json", "field.pt"]


def test_n2f2_runs_segments_stage_finishes_an_interrupted_bank(base, tmp_path, monkeypatch):
    # The stage's bank, interrupted after two images, is finished by the next run: the images
    # done are not segmented again, and the bank equals one built in one go.
    from n2f2.segments.bank import SegmentAndEncode
    from n2f2.segments.lifting import LiftSettings
    from n2f2.segments.stage import BankJob, run_bank

    done, original = [], SegmentAndEncode.extract

    def extract(self, index, stem, image):
        if len(done) == 2 and stop:
            raise KeyboardInterrupt
        done.append(stem)
        return original(self, index, stem, image)

    def build(out, lift=LiftSettings()):
        job = BankJob(base["scene"], out, base["ply"], lift=lift, segmenter="ground-truth", encoder="captions",
                      force=True, keep_unfinished=True, progress=False)
        return run_bank(job, log=lambda m: None)

    monkeypatch.setattr(SegmentAndEncode, "extract", extract)
    stop = True
    with pytest.raises(KeyboardInterrupt):
        build(tmp_path / "bank")
    first = list(done)
    stop = False
    build(tmp_path / "bank")
    assert len(first) == 2 and set(done[2:]).isdisjoint(first) and len(done) == 6
    build(tmp_path / "whole")
    for name in ("layers.npy", "embeddings.npy", "scales.npy"):
        for stem in first + done[2:6]:
            a, b = np.load(tmp_path / "bank" / stem / name), np.load(tmp_path / "whole" / stem / name)
            assert np.array_equal(a, b, equal_nan=a.dtype.kind == "f"), (stem, name)
    # Other settings: the unfinished bank is replaced, not mixed in.
    stop, done[:] = True, []
    with pytest.raises(KeyboardInterrupt):
        build(tmp_path / "other")
    stop = False
    build(tmp_path / "other", LiftSettings(scale_measure="area"))
    assert len(done) == 2 + 6


def test_stage_cache_records_an_interrupted_stage_until_it_finishes(tmp_path):
    # A stage stopped in the middle is neither fresh nor forgotten: the next run with the same
    # key is told to continue it; another key starts afresh; a finished stage is skipped.
    from n2f2.io import command_outputs
    from n2f2.pipeline.cache import StageCache

    out = tmp_path / "run"
    out.mkdir()
    target = out / "result.txt"

    def fail():
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        with command_outputs():
            StageCache.open(out).run("stage", "k1", [target], fail, log=lambda m: None)
    cache = StageCache.open(out)
    assert cache.interrupted("stage", "k1") and not cache.interrupted("stage", "k2")
    assert not cache.fresh("stage", "k1", [target])
    target.write_text("done")  # a stage whose output exists but that never finished is not fresh
    assert not cache.fresh("stage", "k1", [target])
    with command_outputs():
        assert cache.run("stage", "k1", [target], lambda: None, log=lambda m: None)
    cache = StageCache.open(out)
    assert not cache.interrupted("stage", "k1") and cache.fresh("stage", "k1", [target])
    assert set(cache.records["stage"]) == {"key", "seconds", "outputs"}


def test_run_reads_its_labels_before_fitting(base, tmp_path, capsys):
    scene = copy(base["scene"], tmp_path / "scene")
    label = sorted((scene / "label").glob("frame_*.json"))[0]
    label.write_text("{ not json")
    out = tmp_path / "run"
    t = time.perf_counter()
    assert_refused(capsys, ["run", scene, "--out", out, "--fit-steps", 5, "--train-steps", 5, "--quiet"], [scene],
                   label.name)
    assert not out.exists() and time.perf_counter() - t < 60  # nothing fitted first


def test_bench_with_a_missing_input_leaves_no_folder(base, tmp_path, capsys):
    # The bench creates OUT/data before it checks --gaussians: a refused bench takes both back.
    out = tmp_path / "bench"
    missing = tmp_path / "nowhere.ply"
    assert_refused(capsys, ["bench", "--quick", "--out", out, "--scene", base["scene"], "--gaussians", missing,
                            "--quiet"], [base["scene"]], "nowhere.ply")
    assert not out.exists()


@pytest.mark.parametrize("command, module, func, argv, advice", [
    ("fit-gaussians", "n2f2.gaussians.commands", "run", ["DATA", "--out", "O"], "add --resume"),
    ("train", "n2f2.train.commands", "run_train", ["DATA", "--gaussians", "G", "--segments", "B", "--out", "O"],
     "add --resume"),
    ("segments", "n2f2.segments.commands", "run_segments", ["DATA", "--out", "B"], "add --resume"),
    ("run", "n2f2.pipeline.commands", "_cmd_run", ["DATA", "--out", "O"], "the same command continues"),
])
def test_ctrl_c_says_how_to_continue_and_the_advice_parses(monkeypatch, capsys, command, module, func, argv, advice):
    # Ctrl-C: exit 130 and one line saying how to go on; the flag it names is one the command takes.
    import importlib

    from n2f2.cli import build_parser, main

    def interrupted(args):
        raise KeyboardInterrupt

    monkeypatch.setattr(importlib.import_module(module), func, interrupted)
    assert main([command, *argv]) == 130
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"n2f2 {command}: interrupted;") and advice in err and "\n" not in err
    if "--resume" in advice:
        assert build_parser().parse_args([command, *argv, "--resume"]).resume is True
