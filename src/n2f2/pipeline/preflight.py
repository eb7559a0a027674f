"""What ``n2f2 run``, ``run-many`` and ``doctor`` check before the first heavy stage: every model
the stages that will run load, located without loading or downloading it (a missing CLIP used
to be found only after minutes of Gaussian fitting), and the output folder. Each problem is one
line with a command that works (:func:`n2f2.segments.encoders.download_advice`)."""

from __future__ import annotations

import os
import shutil
from pathlib import Path
from typing import Optional

from ..errors import InputError

STAGES = ("fit-gaussians", "segments", "train", "eval")  # in data-flow order


def needs_posing(data: Path) -> bool:
    """``data`` is a folder of photos without camera poses: ``run`` poses it (structure from
    motion) before anything else."""
    from ..data import detect_format
    from ..data.sfm import find_photo_folder

    try:
        detect_format(data)
        return False
    except InputError:
        return find_photo_folder(Path(data)) is not None


def encoder_model_id(opt) -> Optional[str]:
    """The model the run's encoder loads (None: its default): ``--clip-model``, else, for
    LangSplat features that an n2f2 export recorded with the same encoder, the recorded model."""
    if opt.model or opt.langsplat_features is None:
        return opt.model
    from ..segments.langsplat import recorded_encoder

    feats = Path(opt.langsplat_features)
    recorded = recorded_encoder(feats) if feats.is_dir() else None
    return recorded.get("model_id") if recorded and recorded["name"] == opt.encoder else None


def run_models(opt, stages) -> list:  # -> list[encoders.ModelLocation]
    """Every model the ``stages`` of a run with (resolved) options ``opt`` load, located: the
    segmenter's and the encoder's when the segments stage segments, the encoder's (its text
    model) when the evaluation runs."""
    from ..segments.encoders import locate_encoder_model
    from ..segments.segmenters import locate_segmenter_model

    segmenting = "segments" in stages and opt.langsplat_features is None
    found = []
    if segmenting:
        segmenter = locate_segmenter_model(opt.segmenter, opt.sam_model)
        found += [] if segmenter is None else [segmenter]
    if segmenting or "eval" in stages:
        found.append(locate_encoder_model(opt.encoder, encoder_model_id(opt)))
    return found


def check_run_models(opt, stages) -> None:
    """Refuse, in one line with its advice, the first model of :func:`run_models` that is missing."""
    for found in run_models(opt, stages):
        if found.problem:
            raise InputError(None, found.problem)


def model_line(found) -> str:
    """A located model for people: what, which, and where it was found."""
    if not found.where:
        return f"{found.what} model {found.model_id}: {found.how}"
    if found.where == found.model_id:
        return f"{found.what} model: {found.how} {found.where}"
    return f"{found.what} model {found.model_id}: {found.how} ({found.where})"


def output_folder_problem(out: Path) -> tuple[Optional[str], str]:
    """``(problem, description)`` of a run folder, without creating or writing anything (the
    run itself proves it writable with a file, :func:`n2f2.io.claim_out_dir`): the nearest
    existing folder must be a writable folder with room (:func:`n2f2.io.min_free_bytes`)."""
    from ..io import min_free_bytes

    out = Path(out)
    existing = next((p for p in (out, *out.parents) if p.exists()), Path("/"))
    if not existing.is_dir():
        return f"{existing} is not a folder", ""
    if not os.access(existing, os.W_OK | os.X_OK):
        return f"{existing} is not writable", ""
    free = shutil.disk_usage(existing).free
    state = "exists" if existing == out else f"will be created in {existing}"
    described = f"{out} {state}, writable, {free / 2**20:,.0f} MB free"
    if free < min_free_bytes():
        return f"{described}: below the {min_free_bytes() / 2**20:.0f} MB a run needs", described
    return None, described
