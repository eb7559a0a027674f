"""The evaluation stage: LangSplat's LERF-OVS protocol (segmentation IoU and localization
accuracy), the 3D-OVS protocol, retrieval metrics, and Markdown / PNG reports."""

from .._lazy import lazy_exports

__getattr__, __all__ = lazy_exports(
    __name__,
    {
        "QueryDeltas": "metrics",
        "average_precision": "metrics",
        "loss_budget": "budget",
        "RetrievalScores": "metrics",
        "per_query_scores": "metrics",
        "query_deltas": "metrics",
        "recall_at_k": "metrics",
        "segment_mean_relevancy": "metrics",
        "segment_ranks": "metrics",
        "Ovs3dLabels": "ovs3d",
        "Ovs3dScores": "ovs3d",
        "evaluate_ovs3d": "ovs3d",
        "read_ovs3d_segmentations": "ovs3d",
        "LANGSPLAT_BOX_SIZE": "protocol",
        "LANGSPLAT_THRESHOLD": "protocol",
        "LERF_REFERENCE_WIDTH": "protocol",
        "PairRecord": "protocol",
        "PairResult": "protocol",
        "ProtocolConfig": "protocol",
        "SceneScores": "protocol",
        "box_filter": "protocol",
        "evaluate_frame_category": "protocol",
        "evaluate_label_dir": "protocol",
        "evaluate_scene": "protocol",
        "localization_hit": "protocol",
        "localization_point": "protocol",
        "majority_filter": "protocol",
        "resolve_box_size": "protocol",
        "resolve_majority_radius": "protocol",
        "segmentation_mask": "protocol",
        "smoothed_relevancy": "protocol",
    },
)
