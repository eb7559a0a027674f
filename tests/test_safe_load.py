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
