"""The variants of the ablation bench: which field each trains (variant, backbone, the paper's
step size k) and what is evaluated on it, and how a paper step size maps to a smaller D.

One variant trains nothing: ``lift`` (``training_free``), the segment bank's features averaged
onto the bench's Gaussians with the training views' blending weights (:mod:`n2f2.field.lift`),
answered as the 3-level field is (modes ``levels`` and ``oracle``); see
:func:`n2f2.experiments.training.lift_variant` for where it comes from.

The paper uses D = 512 and k in {1, 8, 32, 128, 170}. With a smaller D the bench keeps the
*number of scales* ``floor(512 / k)`` of each paper setting: ``k_used = max(1, floor(D /
floor(512 / k)))`` (:func:`scaled_step`); at D = 128 that is k in {1, 2, 8, 32, 42} (= round(k D /
512), with k = 170 -> 42 so that it keeps its 3 scales)."""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

from ..field.variants import FieldVariant, get_variant

if TYPE_CHECKING:
    from ..field.model import FieldConfig

PAPER_DIM = 512
PAPER_STEPS = (1, 8, 32, 128, 170)  # paper Table 6


@dataclass(frozen=True)
class VariantSpec:
    """One bench variant: a field configuration and what to evaluate on it."""

    name: str  # user-facing name (--variants)
    title: str  # row label in the report
    variant: str  # FieldConfig.variant: nested | flat | levels (training-free: the variant it answers as)
    backbone: str = "triplane"  # FieldConfig.backbone
    paper_step: int = 1  # k of paper Table 6 (scaled to D by scaled_step)
    modes: tuple[str, ...] = ("composite", "explicit", "oracle")
    cosine: bool = True  # per-level cosine to the teacher on held-out views
    training_free: bool = False  # no field: the lift of the bench's Gaussians (experiments/training.py)

    @property
    def kind(self) -> FieldVariant:
        """The field variant it trains (:mod:`n2f2.field.variants`)."""
        return get_variant(self.variant)


VARIANTS: dict[str, VariantSpec] = {
    "nested": VariantSpec(
        "nested", "N2F2 (nested, TriPlane+MLP, k=1)", "nested", modes=("composite", "explicit", "soft", "oracle")
    ),
    "flat": VariantSpec("flat", "non-nested (flat)", "flat"),
    "levels": VariantSpec("levels", "3-level (LangSplat-like)", "levels", modes=("levels", "oracle")),
    "lift": VariantSpec(
        "lift",
        "lift (training-free, blending-weight average)",
        "levels",
        modes=("levels", "oracle"),
        cosine=False,
        training_free=True,
    ),
    **{f"k{k}": VariantSpec(f"k{k}", f"N2F2, k={k}", "nested", paper_step=k, cosine=False) for k in PAPER_STEPS[1:]},
    "mlp": VariantSpec("mlp", "N2F2 with MLP backbone (PE+MLP)", "nested", backbone="mlp", modes=("composite",)),
}
DEFAULT_VARIANTS = tuple(VARIANTS)


def scaled_step(paper_k: int, dim: int) -> int:
    """The step size at ``dim`` dimensions that keeps paper setting ``paper_k``'s number of scales
    ``floor(512 / paper_k)`` (at least 1, at most ``dim``)."""
    if paper_k < 1 or paper_k > PAPER_DIM:
        raise ValueError(f"paper step size must be in [1, {PAPER_DIM}], got {paper_k}")
    if dim == PAPER_DIM:
        return paper_k
    return int(min(dim, max(1, dim // (PAPER_DIM // paper_k))))


def run_name(spec: VariantSpec, dim: int) -> str:
    """Run folder of a variant, named by what is trained (paper k values that map to the same
    k at this D share one run); a training-free variant's folder is its name."""
    if spec.training_free:
        return spec.name
    backbone = "" if spec.backbone == "triplane" else f"-{spec.backbone}"
    if not spec.kind.uses_step:
        return spec.variant + backbone
    return f"{spec.variant}-k{scaled_step(spec.paper_step, dim)}" + backbone


def variant_field_config(spec: VariantSpec, dim: int) -> "FieldConfig":
    """The cpu preset's field with the variant's shape, D = ``dim`` and its step size scaled
    to ``dim``."""
    from ..pipeline.presets import get_preset

    if spec.training_free:
        raise ValueError(f"variant {spec.name!r} trains no field")

    step = spec.kind.step_size(scaled_step(spec.paper_step, dim))
    return replace(get_preset("cpu").field, dim=dim, variant=spec.variant, backbone=spec.backbone, step_size=step)
