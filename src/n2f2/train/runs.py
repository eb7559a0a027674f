"""Reading a trained run folder (``field.pt`` beside ``gaussians.ply``): the scene it was trained
on, at the downscale it was trained at. Query engines and the hierarchy open runs through it."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Optional, Union

from ..errors import InputError


def load_run_scene(run_dir: Path, meta: dict, scene: Optional[Union[str, Path]], full_res: bool = False) -> Any:
    """The scene a run was trained on: ``scene`` if given, else the path its metadata records;
    at the downscale the training recorded (runs from before it was recorded: 1), or 1 with
    ``full_res``; without its missing images when the training went without them."""
    from ..data import load_scene

    if scene is None:
        candidates: list[Optional[str]] = [meta.get("scene"), meta.get("scene_path")]  # recorded folders
        report = run_dir / "train_report.json"
        if report.is_file():
            try:
                r = json.loads(report.read_text())
                candidates += [r.get("scene"), r.get("scene_path")]
            except (json.JSONDecodeError, OSError):
                pass
        recorded = next((c for c in candidates if c), None)
        # A recorded folder that has moved is not an error until a view index needs it.
        if recorded is None or not Path(recorded).is_dir():
            return None
        scene = recorded
    path = Path(scene)
    if not path.is_dir():
        raise InputError(path, "scene folder does not exist")
    downscale = 1.0 if full_res else float(meta.get("downscale", 1.0) or 1.0)
    # A run trained with --skip-missing renders the views it was trained on.
    return load_scene(path, downscale=downscale, skip_missing=bool(meta.get("skip_missing", False)))
