"""Data files never run code when loaded: a pickle that would execute a command is refused."""

from __future__ import annotations

import os

import pytest
import torch

from n2f2.cli import main as cli_main
from n2f2.errors import InputError
from n2f2.field.model import load_field
from n2f2.gaussians.fit import load_checkpoint


class _RunsCode:
    def __init__(self, marker: str) -> None:
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


def _crafted(path, marker) -> None:
    torch.save({"format": "anything", "payload": _RunsCode(str(marker))}, path)


def test_crafted_checkpoint_and_field_do_not_run_code(tmp_path):
    marker = tmp_path / "ran"
    _crafted(tmp_path / "checkpoint.pt", marker)
    _crafted(tmp_path / "field.pt", marker)
    with pytest.raises(InputError):
        load_checkpoint(tmp_path / "checkpoint.pt")
    with pytest.raises(InputError):
        load_field(tmp_path / "field.pt")
    assert not marker.exists()


def test_crafted_field_through_the_cli_is_one_clear_error(tmp_path, capsys):
    marker = tmp_path / "ran"
    run = tmp_path / "run"
    run.mkdir()
    _crafted(run / "field.pt", marker)
    assert cli_main(["eval-field", str(run)]) == 2
    assert "field.pt" in capsys.readouterr().err
    assert not marker.exists()


def _copy_run(src, dst):
    import shutil

    shutil.copytree(src, dst)
    return dst


def _assert_refused(argv, marker, capsys) -> None:
    rc = cli_main([str(a) for a in argv])
    err = capsys.readouterr().err.strip()
    assert rc == 2, f"n2f2 {' '.join(map(str, argv))} exited {rc}: {err}"
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    assert not marker.exists(), "the crafted file ran code"


@pytest.mark.parametrize("command", ["query", "eval", "view", "train --resume"])
def test_crafted_run_files_run_no_code_in_any_command(command, trained_run, tmp_path, capsys):
    """A shared run folder whose field.pt / checkpoint.pt is a malicious pickle: every command
    that loads it refuses with one line, and the payload never runs."""
    marker = tmp_path / "ran"
    run = _copy_run(trained_run.run_dir, tmp_path / "run")
    _crafted(run / "field.pt", marker)
    _crafted(run / "checkpoint.pt", marker)
    scene, bank = trained_run.scene_dir, trained_run.bank_dir
    argv = {
        "query": ["query", run, "teapot", "--out", tmp_path / "q", "--scene", scene],
        "eval": ["eval", run, "--labels", scene / "label", "--scene", scene, "--bank", bank, "--out", tmp_path / "e"],
        "view": ["view", run, "--port", 0, "--scene", scene],
        "train --resume": ["train", scene, "--gaussians", run / "gaussians.ply", "--segments", bank, "--out", run,
                           "--resume", "--iterations", 2],
    }[command]
    _assert_refused(argv, marker, capsys)


def test_crafted_fit_checkpoint_runs_no_code_on_resume(trained_run, tmp_path, capsys):
    marker = tmp_path / "ran"
    out = tmp_path / "fit"
    out.mkdir()
    _crafted(out / "checkpoint.pt", marker)
    _assert_refused(["fit-gaussians", trained_run.scene_dir, "--out", out, "--resume", "--steps", 2], marker, capsys)
