"""What building a segment bank needs besides the bank itself, from plain settings: the scene
(checked), the depth provider that lifts segments to 3D, and the segment source (segmenter +
encoder). ``n2f2 segments``, ``n2f2 segments-from-langsplat`` and the pipeline's segments stage
build them here; a Ray worker builds them once from :class:`SegmentsSetup`."""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Optional

from ..errors import InputError


def load_bank_scene(data: str | Path, downscale: float = 1.0, skip_missing: bool = False):
    """The scene a bank is built for (``load_scene``), refusing a bad downscale or no images."""
    from ..data import load_scene

    if downscale <= 0:
        raise InputError(None, f"--downscale must be > 0, got {downscale}")
    scene = load_scene(data, downscale=downscale, skip_missing=skip_missing)
    if len(scene) == 0:
        raise InputError(data, "scene has no images")
    return scene


def depth_provider(scene, depth_source: str, gaussians: Optional[str | Path], device: str = "cpu"):
    """The demo scene's exact depth (``depth_source="gt"``) or the expected depth rendered from
    ``gaussians`` (a PLY, or the folder holding ``gaussians.ply``)."""
    from .lifting import LiftSettings, gt_depth_provider, render_depth_provider

    if depth_source == "gt":
        return gt_depth_provider(scene)
    if not gaussians:
        raise InputError(
            None,
            "--gaussians PLY is needed to lift segments with rendered depth "
            "(or use --depth-source gt on the demo scene)",
        )
    from ..gaussians import read_ply

    path = Path(gaussians)
    if path.is_dir():
        path = path / "gaussians.ply"
    if not path.is_file():
        raise InputError(path, "Gaussians file does not exist (run `n2f2 fit-gaussians` first)")
    return render_depth_provider(read_ply(path, device=device), scene.cameras, min_alpha=LiftSettings().min_alpha)


@dataclass(frozen=True)
class SegmentsSetup:
    """The scene, the segment source (segmenter + encoder) and the depth provider of a bank,
    as settings. Built in this process, and once in every Ray worker (picklable and hashable, so
    a worker keeps what it built for its next images)."""

    data: str
    downscale: float
    skip_missing: bool
    depth_source: str
    gaussians: Optional[str]
    segmenter: str
    encoder: str
    model: Optional[str]
    sam_model: Optional[str]
    device: str

    def for_ray_worker(self) -> "SegmentsSetup":
        """A Ray task sees only the GPU Ray gave it, as device ``cuda``."""
        return replace(self, device="cuda") if self.device.startswith("cuda") else self

    def build(self) -> tuple:
        """(scene, source, depth provider), checking the inputs before loading models."""
        from .bank import SegmentAndEncode, check_pairing
        from .encoders import ENCODERS, get_encoder
        from .segmenters import get_segmenter

        kind = ENCODERS.get(self.encoder)
        check_pairing(self.segmenter, self.encoder, kind is not None and kind.requires_captions)  # no model loaded
        scene = load_bank_scene(self.data, self.downscale, self.skip_missing)
        depth = depth_provider(scene, self.depth_source, self.gaussians, self.device)  # a missing PLY: before models
        segmenter = get_segmenter(self.segmenter, scene=scene, model_id=self.sam_model, device=self.device)
        encoder = get_encoder({"name": self.encoder, "model_id": self.model}, device=self.device)
        return scene, SegmentAndEncode(segmenter, encoder), depth


def langsplat_source(features: str | Path, encoder: Optional[str], model: Optional[str]):
    """The :class:`~n2f2.segments.langsplat.LangSplatSource` of a ``language_features`` folder:
    its text encoder is ``encoder``, else the one an n2f2 export recorded beside the features
    (``encoder.json``), else clip; ``model`` (a CLIP id), else the recorded one for clip."""
    from .langsplat import LangSplatSource, langsplat_encoder_spec, recorded_encoder

    features = Path(features)
    if not features.is_dir():
        raise InputError(features, "LangSplat features folder does not exist")
    recorded = recorded_encoder(features)
    encoder = encoder or (recorded["name"] if recorded else "clip")
    model = model or (recorded.get("model_id") if recorded and recorded["name"] == encoder == "clip" else None)
    return LangSplatSource(features, langsplat_encoder_spec(encoder, model))


def report_lines(report: dict) -> list[str]:
    """What ``build_bank``'s report says to a person: counts, timing, median scale and, on the
    demo scene, how the lifted scales rank against the true region extents."""
    c, t, s = report["counts"], report["timing"], report["scale_stats"]
    per = "" if t["seconds_per_image"] is None else f", {t['seconds_per_image']:.2f} s/image"
    lines = [
        f"segments: {c['images']} images, {c['segments']} segments ({c['valid']} lifted, "
        f"{c['dropped_degenerate']} degenerate dropped, {c['dropped_empty']} empty), "
        f"median scale {s['scale_median']:.4g}{per} -> {report['bank']}"
    ]
    parts = t.get("seconds_per_image_by_part") or {}
    if parts:
        lines.append("segments: seconds per image by part: " + ", ".join(f"{k} {v:.2f}" for k, v in parts.items()))
    check = report.get("ground_truth_check")
    if check:
        medians = ", ".join(f"{k} {v:.3g}" for k, v in check["median_scale_by_level"].items())
        lines.append(
            f"segments: lifted scale vs true region extent: Spearman "
            f"{check['spearman_scale_vs_true_extent']:.3f}; median scale by level: {medians}"
        )
    return lines
