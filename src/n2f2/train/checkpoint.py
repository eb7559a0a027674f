"""Reading a training checkpoint (``RUN/checkpoint.pt``): its format tags, the upgrade of a
v1 checkpoint's optimiser state, and the configs a run was started with."""

from __future__ import annotations

from pathlib import Path
from typing import Optional, Union

import torch

from ..errors import InputError
from ..field.model import FieldConfig
from ..io import load_torch
from .config import CHECKPOINT_NAME, TrainConfig

# v2: the TriPlane's parameter is texels [3, R, R, C]; v1 (read too) held planes [3, C, R, R].
CHECKPOINT_FORMAT = "n2f2-field-checkpoint-v2"
CHECKPOINT_V1 = "n2f2-field-checkpoint-v1"


def load_checkpoint(path: Path) -> dict:
    """The checkpoint at ``path`` (InputError when it is not one), a v1 one's TriPlane moments
    permuted to the v2 layout."""
    ck = load_torch(path, "checkpoint")
    if not isinstance(ck, dict) or ck.get("format") not in (CHECKPOINT_FORMAT, CHECKPOINT_V1):
        raise InputError(path, "not an n2f2 train checkpoint")
    if ck["format"] == CHECKPOINT_V1:  # the field state loads as is (TriPlane reads "planes")
        for state in ck["optimizer"]["state"].values():
            for key, value in state.items():
                if torch.is_tensor(value) and value.dim() == 4:  # the planes' moments: the one 4-D parameter
                    state[key] = value.permute(0, 2, 3, 1).contiguous()
    return ck


def saved_configs(out_dir: Union[str, Path]) -> Optional[tuple[FieldConfig, TrainConfig]]:
    """(field config, train config) of the checkpoint in ``out_dir``, or None when there is none."""
    path = Path(out_dir) / CHECKPOINT_NAME
    if not path.is_file():
        return None
    ck = load_checkpoint(path)
    return FieldConfig.from_dict(ck["field_meta"]["config"]), TrainConfig.from_dict(ck["train_config"])
