"""The evaluation stage: LangSplat's LERF-OVS protocol (segmentation IoU and localization
accuracy), the 3D-OVS protocol, retrieval metrics, and Markdown / PNG reports."""

from .metrics import (QueryDeltas, RetrievalScores, per_query_scores, query_deltas, recall_at_k,
                      segment_mean_relevancy, segment_ranks)
from .ovs3d import Ovs3dLabels, Ovs3dScores, evaluate_ovs3d, read_ovs3d_segmentations
from .protocol import (LANGSPLAT_BOX_SIZE, LANGSPLAT_THRESHOLD, LERF_REFERENCE_WIDTH, PairRecord,
                       PairResult, ProtocolConfig, SceneScores, box_filter, evaluate_frame_category,
                       evaluate_label_dir, evaluate_scene, langsplat_relevancy, localization_hit,
                       majority_filter, resolve_box_size, resolve_majority_radius,
                       segmentation_mask, smoothed_relevancy)

__all__ = [
    "LANGSPLAT_BOX_SIZE", "LANGSPLAT_THRESHOLD", "LERF_REFERENCE_WIDTH", "PairRecord", "PairResult",
    "ProtocolConfig", "SceneScores", "box_filter", "evaluate_frame_category", "evaluate_label_dir",
    "evaluate_scene", "langsplat_relevancy", "localization_hit", "majority_filter",
    "resolve_box_size", "resolve_majority_radius", "segmentation_mask", "smoothed_relevancy",
    "Ovs3dLabels", "Ovs3dScores", "evaluate_ovs3d", "read_ovs3d_segmentations",
    "QueryDeltas", "RetrievalScores", "per_query_scores", "query_deltas", "recall_at_k",
    "segment_mean_relevancy", "segment_ranks",
]
