"""The variants of the feature field (the paper's ablations) as objects, one class each, so that
code outside the field asks a field's variant what it needs instead of switching on its name.

``FieldConfig.variant`` and every file that records it (``field.pt``, ``train_report.json``,
``eval.json``, ``bench.json``) keep the name; :data:`VARIANTS` maps the name to the object
(``FieldConfig.kind``, ``NestedField.kind``, ``QueryEngine.kind``).

For a field of ``D`` dims configured with step size ``k`` (``FieldConfig.step_size``):

* :meth:`~FieldVariant.scales`: the theta dims ``[start, end)`` of each scale the variant
  supervises and answers with, in the order of :meth:`~FieldVariant.scale_labels` (their names in
  reports and query results);
* :meth:`~FieldVariant.step`: the step of its prefix scales (what the query engine and
  ``eval.json`` call the step); :meth:`~FieldVariant.step_size`: the ``step_size`` a field of it is
  trained with when step size ``k`` is asked for (the bench's step-size sweep);
* :meth:`~FieldVariant.dims_for_scale` and :meth:`~FieldVariant.supervision_mask`: what a segment
  of quantized scale ``s`` supervises, ``M(s)`` (prefix variants, :attr:`~FieldVariant.prefix`) and
  the ``[B, D]`` mask ``B(s)``;
* :attr:`~FieldVariant.modes`: the query modes it answers; :attr:`~FieldVariant.answers_with`:
  ``"prefix"`` or ``"levels"``, the score cache its per-query scale choice and its ``oracle`` run
  on, i.e. what the oracle picks among (prefixes or level blocks);
  :meth:`~FieldVariant.mode_for`: which of its modes plays the part of a nested field's mode.

    variant  scales at D = 12, k = 3   labels             step        modes
    nested   [0,3) [0,6) [0,9) [0,12)  d=3 d=6 d=9 d=12   k           composite explicit soft oracle
    flat     [0,12)                    d=12               D           composite explicit soft oracle
    levels   [8,12) [4,8) [0,4)        part object group  k (unused)  levels oracle

(``soft``, :mod:`n2f2.query.soft`, blends the prefix scales; on a flat field's one scale it is
its explicit map.)
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import TYPE_CHECKING, ClassVar, Optional

from ..segments.bins import scale_to_dims, supervised_dims, three_level_groups

if TYPE_CHECKING:
    import torch
    from torch import Tensor

NUM_LEVELS = 3  # part, object, group (fine to coarse), as the demo ground truth and LangSplat
LEVEL_NAMES = ("part", "object", "group")  # hierarchy level 0, 1, 2: the levels field's scale labels


def level_blocks(dim: int) -> list[tuple[int, int]]:
    """``[start, end)`` of the 3 contiguous blocks of the "levels" variant, block 0 first
    (sizes differ by at most one when 3 does not divide D)."""
    edges = [round(i * dim / NUM_LEVELS) for i in range(NUM_LEVELS + 1)]
    return [(edges[i], edges[i + 1]) for i in range(NUM_LEVELS)]


def level_to_block(level: Tensor | int) -> Tensor | int:
    """Hierarchy level (0 = part, finest .. 2 = group, coarsest) -> block (0 = first dims)."""
    return NUM_LEVELS - 1 - level


def prefix_mask(M: Tensor, dim: int, dtype: Optional[torch.dtype] = None) -> Tensor:
    """B(s): ``[B, D]`` mask with ones in the first ``M[b]`` columns of row b (float32 unless
    ``dtype``). M [B] integer."""
    import torch

    return (torch.arange(dim, device=M.device) < M.unsqueeze(-1)).to(dtype or torch.float32)


def level_mask(level: Tensor, dim: int) -> Tensor:  # level [B] in {0, 1, 2} -> [B, D] float
    """The "levels" variant's B: ones on the block of hierarchy level ``level`` (0 = part)."""
    import torch

    blocks = torch.tensor(level_blocks(dim), device=level.device)  # [3, 2]
    start_end = blocks[level_to_block(level)]  # [B, 2]
    d = torch.arange(dim, device=level.device)
    return ((d >= start_end[:, :1]) & (d < start_end[:, 1:])).float()


class FieldVariant(ABC):
    """What a field variant supervises and how it is queried (see the module docstring). The
    variants are stateless: one instance each, in :data:`VARIANTS`."""

    name: ClassVar[str]  # FieldConfig.variant, as stored in files
    description: ClassVar[str]  # one line for help texts
    modes: ClassVar[tuple[str, ...]] = ("composite", "explicit", "oracle")  # query modes it answers
    answers_with: ClassVar[str] = "prefix"  # "prefix" | "levels": what explicit choice / oracle pick among
    uses_step: ClassVar[bool] = False  # whether the step size k changes what it supervises
    prefix: ClassVar[bool] = False  # whether a segment of scale s supervises a prefix theta[:M(s)]
    other_modes_hint: ClassVar[str]  # the advice for a user who asks for a mode it does not answer

    @abstractmethod
    def scales(self, dim: int, step_size: int = 1) -> list[tuple[int, int]]:
        """``[start, end)`` of the theta dims each scale reads, in the order of :meth:`scale_labels`."""

    @abstractmethod
    def scale_labels(self, dim: int, step_size: int = 1) -> list[str]:
        """The names of its scales in reports and query results."""

    @abstractmethod
    def scale_values(self, dim: int, step_size: int = 1) -> list[float]:
        """The quantized segment scale ``s`` in [0, 1) at the middle of each scale's bin (larger:
        coarser), in the order of :meth:`scales`."""

    def coarse_to_fine(self, dim: int, step_size: int = 1) -> list[tuple[int, int]]:
        """:meth:`scales`, coarsest first (the hierarchy's level order)."""
        return self._coarse_first(self.scales(dim, step_size), dim, step_size)

    def coarse_to_fine_labels(self, dim: int, step_size: int = 1) -> list[str]:
        return self._coarse_first(self.scale_labels(dim, step_size), dim, step_size)

    def coarse_to_fine_values(self, dim: int, step_size: int = 1) -> list[float]:
        return self._coarse_first(self.scale_values(dim, step_size), dim, step_size)

    def _coarse_first(self, items: list, dim: int, step_size: int) -> list:
        values = self.scale_values(dim, step_size)
        return [items[i] for i in sorted(range(len(items)), key=lambda i: -values[i])]

    @abstractmethod
    def supervision_mask(self, s: Tensor, dim: int, step_size: int = 1) -> Tensor:  # s [B] -> [B, D] float
        """B(s): which of the ``dim`` dims a segment of quantized scale ``s`` supervises."""

    def dims_for_scale(self, s: Tensor, dim: int, step_size: int = 1) -> Tensor:  # s [B] -> M [B] long
        """M(s), the prefix a segment of quantized scale ``s`` supervises (ValueError for a variant
        whose scales are no prefixes)."""
        raise ValueError(f"the {self.name!r} variant has no prefix M(s); use supervision_mask / level_features")

    def step(self, dim: int, step_size: int) -> int:
        """The step of its prefix scales at ``dim`` dims, configured step size ``step_size``.
        ``step(dim, step(dim, k)) == step(dim, k)``, so it may be given either."""
        return int(step_size)

    def step_size(self, k: int) -> int:
        """``FieldConfig.step_size`` of a field of this variant asked for step size ``k``: ``k`` when
        the variant uses a step size, else 1 (the field would ignore it)."""
        return int(k) if self.uses_step else 1

    def mode_for(self, mode: str) -> Optional[str]:
        """Its mode that plays the part of ``mode`` (one of a nested field's modes: composite,
        explicit, oracle), or None when it has none."""
        return mode if mode in self.modes else None

    def __repr__(self) -> str:
        return f"<field variant {self.name!r}>"


class PrefixVariant(FieldVariant):
    """A variant whose scales are prefixes ``theta[:d]`` answered by ``W[:, :d]``."""

    modes = ("composite", "explicit", "soft", "oracle")
    prefix = True

    def supervision_mask(self, s: Tensor, dim: int, step_size: int = 1) -> Tensor:
        return prefix_mask(self.dims_for_scale(s, dim, step_size), dim)

    def scale_dims(self, dim: int, step_size: int = 1) -> list[int]:
        """The prefix lengths ``d`` of its scales, coarse (short) to fine."""
        return supervised_dims(dim, self.step(dim, step_size))

    def scales(self, dim: int, step_size: int = 1) -> list[tuple[int, int]]:
        return [(0, d) for d in self.scale_dims(dim, step_size)]

    def scale_labels(self, dim: int, step_size: int = 1) -> list[str]:
        return [f"d={d}" for d in self.scale_dims(dim, step_size)]

    def scale_values(self, dim: int, step_size: int = 1) -> list[float]:
        """Prefix ``d = k j`` of ``n`` scales serves ``s`` in ``[1 - j / n, 1 - (j - 1) / n)``."""
        n = len(self.scale_dims(dim, step_size))
        return [1.0 - (j - 0.5) / n for j in range(1, n + 1)]


class NestedVariant(PrefixVariant):
    """N2F2: a segment of quantized scale s supervises the first ``M(s)`` dims, so the scales are
    the prefixes ``k, 2k, ..., k floor(D / k)`` (:func:`n2f2.segments.bins.supervised_dims`)."""

    name = "nested"
    description = "nested (N2F2)"
    uses_step = True
    other_modes_hint = "mode 'levels' needs a field trained with variant 'levels'"

    def dims_for_scale(self, s: Tensor, dim: int, step_size: int = 1) -> Tensor:
        """``M(s) = k ceil(floor(D / k) (1 - s))`` (:func:`n2f2.segments.bins.scale_to_dims`)."""
        import torch

        return torch.as_tensor(scale_to_dims(s, dim, step_size), device=s.device).long()


class FlatVariant(PrefixVariant):
    """The non-nested ablation: every scale supervises all D dims (``B(s) = 1``), so there is one
    scale, the whole of theta, and the step is D whatever was configured."""

    name = "flat"
    description = "flat (non-nested ablation)"
    other_modes_hint = NestedVariant.other_modes_hint

    def step(self, dim: int, step_size: int) -> int:
        return int(dim)

    def dims_for_scale(self, s: Tensor, dim: int, step_size: int = 1) -> Tensor:
        """All ``D`` dims at every scale."""
        import torch

        return torch.full(s.shape, dim, dtype=torch.long, device=s.device)


class LevelsVariant(FieldVariant):
    """The LangSplat-like 3-level baseline: theta is split into 3 contiguous blocks
    (:func:`level_blocks`), each supervised by one tercile of the quantized scale; hierarchy level
    ``l`` (0 = part) lives in block ``2 - l``. It answers with its level blocks: ``levels`` mode
    (LangSplat's level choice) and ``oracle`` over the same 3 levels. Its step size is recorded as
    configured and not used."""

    name = "levels"
    description = "levels (3 scale groups, LangSplat-like)"
    modes = ("levels", "oracle")
    answers_with = "levels"
    other_modes_hint = "it was trained as the 3-level baseline: use --mode levels"

    def scales(self, dim: int, step_size: int = 1) -> list[tuple[int, int]]:
        blocks = level_blocks(dim)
        return [blocks[int(level_to_block(level))] for level in range(NUM_LEVELS)]

    def scale_labels(self, dim: int, step_size: int = 1) -> list[str]:
        return list(LEVEL_NAMES)

    def scale_values(self, dim: int, step_size: int = 1) -> list[float]:
        """The middles of the terciles of ``s`` (:func:`n2f2.segments.bins.three_level_groups`)."""
        return [(2 * level + 1) / (2 * NUM_LEVELS) for level in range(NUM_LEVELS)]

    def supervision_mask(self, s: Tensor, dim: int, step_size: int = 1) -> Tensor:
        """The block of the segment's level, one tercile of the quantized scale each
        (:func:`n2f2.segments.bins.three_level_groups`)."""
        import torch

        level = torch.as_tensor(three_level_groups(s), device=s.device).long()
        return level_mask(level, dim)

    def mode_for(self, mode: str) -> Optional[str]:
        """``explicit`` -> ``levels`` (its per-query scale choice); no ``composite``."""
        return super().mode_for("levels" if mode == "explicit" else mode)


# The registry: FieldConfig.variant -> its variant. Order = the order of help texts and choices.
VARIANTS: dict[str, FieldVariant] = {v.name: v for v in (NestedVariant(), FlatVariant(), LevelsVariant())}


def get_variant(name: str) -> FieldVariant:
    """The variant named ``name`` (ValueError naming the choices for an unknown one)."""
    try:
        return VARIANTS[name]
    except KeyError:
        raise ValueError(f"variant must be one of {tuple(VARIANTS)}, got {name!r}") from None
