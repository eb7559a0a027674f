"""benchmarks/compare_outputs.py, the check that a refactor keeps every output: equal folders
pass with other timings and folder names; one changed number, tensor, pixel or file fails."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest
import torch

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "compare_outputs.py"


@pytest.fixture(scope="module")
def tool():
    spec = importlib.util.spec_from_file_location("compare_outputs", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _write(root: Path, seconds: float, value: float = 1.5, pixel: int = 7, extra: bool = False) -> Path:
    from PIL import Image

    (root / "run").mkdir(parents=True)
    (root / "run" / "report.json").write_text(json.dumps(
        {"psnr": value, "seconds": seconds, "paths": {"scene": str(root / "scene")}, "timing": {"per_image": seconds}}))
    (root / "stages.json").write_text(json.dumps({"fit": {"key": f"k{seconds}", "seconds": seconds, "outputs": ["a"]}}))
    np.save(root / "run" / "scales.npy", np.array([0.5, np.nan, value], dtype=np.float32))
    torch.save({"w": torch.full((2,), value), "meta": {"scene": str(root / "scene")}, "train_time": seconds},
               root / "run" / "field.pt")
    Image.fromarray(np.full((4, 4, 3), pixel, dtype=np.uint8)).save(root / "run" / "map.png")
    (root / "run" / "table.md").write_text(f"took {seconds} s\n")
    if extra:
        (root / "run" / "extra.txt").write_text("x")
    return root


def test_equal_outputs_with_other_timings_and_folders(tool, tmp_path):
    a, b = _write(tmp_path / "a", 1.0), _write(tmp_path / "b", 99.0)
    n, bad, lines = tool.compare_dirs(a, b)
    assert (n, bad) == (6, 0), lines
    assert lines == ["run/table.md: 1 lines differ (text: timings expected; not counted)"]


@pytest.mark.parametrize("change, where", [
    (dict(value=1.25), "run/report.json"),  # also the .npy and the tensor
    (dict(pixel=8), "run/map.png"),
    (dict(extra=True), "only in"),
])
def test_one_changed_output_is_found(tool, tmp_path, change, where):
    a, b = _write(tmp_path / "a", 1.0), _write(tmp_path / "b", 1.0, **change)
    n, bad, lines = tool.compare_dirs(a, b)
    assert bad >= 1 and any(where in line for line in lines), lines
    if "value" in change:
        assert bad == 3 and any(line.startswith("run/field.pt: /w") for line in lines)
