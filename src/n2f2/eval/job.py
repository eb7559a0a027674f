"""What one evaluation asks for (:class:`EvalJob`): read by the runner (:mod:`.stage`) and by
each protocol (:mod:`.protocols`)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, Optional, Sequence


@dataclass
class EvalJob:
    """One evaluation: what ``n2f2 eval`` takes on its command line."""

    run_dir: Path  # trained run folder (field.pt + gaussians.ply)
    labels: Path  # LangSplat-format label folder, or a scene in the 3D-OVS layout
    out: Optional[Path] = None  # None: RUN_DIR/eval
    protocol: Optional[str] = None  # a name in protocols.PROTOCOLS; None: from the labels' layout
    ovs_prediction: Literal["argmax", "threshold"] = "argmax"  # 3D-OVS: each pixel's best class, or per class
    modes: Optional[Sequence[str]] = None  # None: every mode the field supports
    scene: Optional[Path] = None  # None: the run's
    bank: Optional[Path] = None  # None: the run's (R@K segment pool, the budget's teacher)
    compare: Optional[Path] = None  # another run's eval.json: per-query deltas
    query_types: Optional[Path] = None  # None: SCENE/queries.json
    skip_missing_frames: bool = False
    rescale_labels: bool = False
    query_config: Any = None  # n2f2.query.QueryConfig; None: its defaults
    relevancy: bool = True  # write the relevancy .npy files
    budget: bool = False  # also the loss budget from the teacher to the answers
    force: bool = False  # replace the evaluation in OUT once the inputs are checked
    device: str = "cpu"
    encoder: Any = None  # a text encoder instead of the run's (the bench's memo)
    engine: Any = None  # a query engine instead of the run's (the bench's training-free lift)
    notes: tuple[str, ...] = ()  # added to the report's notes (the bench names its settings)
    progress: bool = True
