"""Querying features stored as 3 level blocks (part, object, group): the ``lift`` baseline
(:mod:`n2f2.field.lift`, per-Gaussian features averaged from the segment bank, no network)
through the same query engine and evaluation code as the 3-level ``levels`` field.

* :class:`LiftEngine` is a :class:`~n2f2.query.engine.QueryEngine` whose per-Gaussian features
  are the lift's ``[N, 3E]`` blocks: modes ``levels`` (LangSplat's level choice) and ``oracle``,
  2D (the blocks rasterized like any field's features) and 3D (on the Gaussians).
* Its score caches compute each level's norm and negatives on its own block
  (:func:`level_block_cache`): the generic linear cache would form ``[3E, 3E]`` Gram products
  (3E = 1152 for MiniLM).
* :func:`build_lift` computes the blending weights the lift needs when no cache is at hand;
  :func:`run_lift` prefers the ``RUN/lift.pt`` that training writes from its own cache.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import TYPE_CHECKING, Any, Sequence, Union

import torch
from torch import Tensor

from ..field.lift import LIFT_LEVELS, LevelBlocks, Lift, lift_features, load_lift
from ..field.relevancy import inverse_norm
from ..field.variants import NUM_LEVELS, LevelsVariant
from .caches import LinearCache
from .engine import QueryEngine

if TYPE_CHECKING:
    from ..data.scene import Scene
    from ..gaussians.model import Gaussians
    from ..segments.bank import SegmentBank


class LevelBlockCache(LinearCache):
    """A ``levels`` score cache of block features: margins per block, no ``[S, E, 3E]`` product."""

    def margins(self, texts: Tensor) -> Tensor:  # [Q, E] -> [S, Q, P]
        S, E = self.maps.shape[0], texts.shape[1]
        raw = torch.stack([texts @ self.features[:, s * E : (s + 1) * E].T for s in range(S)])  # [S, Q, P]
        return raw.mul_(self.inv_norm).sub_(self.neg_max)


def level_block_cache(
    features: Tensor,  # [P, 3E] level blocks side by side (part first)
    negatives: Tensor,  # [C, E] unit embeddings of the negative phrases
    labels: Sequence[str] = LIFT_LEVELS,
    chunk: int = 65536,
) -> LevelBlockCache:
    """The score cache of block features (per block: ``1 / |phi|`` and ``max_c phi^ . c``)."""
    P = features.shape[0]
    E = negatives.shape[1]
    S = features.shape[1] // E
    inv = features.new_empty(S, 1, P)
    neg = features.new_empty(S, 1, P)
    step = max(1, min(chunk, (1 << 22) // max(1, E)))
    for a in range(0, P, step):
        for s in range(S):
            phi = features[a : a + step, s * E : (s + 1) * E]  # [p, E]
            i = inverse_norm(phi)  # [p, 1]
            inv[s, 0, a : a + step] = i[:, 0]
            neg[s, 0, a : a + step] = ((phi @ negatives.T) * i).amax(dim=-1)
    maps = LevelBlocks(E, features.device).selectors()
    return LevelBlockCache(features.contiguous(), maps, inv, neg, labels=list(labels))


class LevelBlockEngine(QueryEngine):
    """A query engine over features stored as 3 level blocks: a 3-level field without a network
    (modes ``levels`` and ``oracle``). Subclasses say where the features come from."""

    def __init__(
        self,
        embed_dim: int,
        gaussians: Any,
        encoder: Any,
        meta: dict,
        config: Any = None,
        device: Any = "cpu",
        scene: Any = None,
        run_dir: Any = None,
    ) -> None:
        levels = LevelsVariant.name  # answered as the 3-level field is
        meta = {**meta, "config": {"variant": levels, "dim": NUM_LEVELS * int(embed_dim)}, "variant": levels}
        super().__init__(LevelBlocks(embed_dim, device), gaussians, encoder, meta, config, device, scene, run_dir)

    def level_maps(self) -> Tensor:  # [3, E, 3E]
        return self.field.selectors()

    def _build_cache(self, kind: str, points: Tensor) -> Any:
        return level_block_cache(points, self.encode(self.config.negatives), chunk=self.config.chunk)


class LiftEngine(LevelBlockEngine):
    """The lift's per-Gaussian features (``engine.lift``), queried as a 3-level field."""

    def __init__(
        self,
        lift: Lift,
        gaussians: Any,
        encoder: Any,
        meta: dict,
        config: Any = None,
        device: Any = "cpu",
        scene: Any = None,
        run_dir: Any = None,
    ) -> None:
        super().__init__(int(lift.features.shape[-1]), gaussians, encoder, meta, config, device, scene, run_dir)
        self.lift = lift
        self._theta = lift.flat.to(self.device)


def lift_engine(
    lift: Lift,
    gaussians: Any,
    encoder: Any,
    meta: dict,
    config: Any = None,
    device: Any = "cpu",
    scene: Any = None,
    run_dir: Any = None,
) -> LiftEngine:
    """A query engine over ``lift`` (``meta``: the run's field metadata, for the encoder spec,
    scene and bank paths, and the held-out views)."""
    return LiftEngine(lift, gaussians, encoder, meta, config, device, scene, run_dir)


def build_lift(
    gaussians: Union[Gaussians, dict[str, Tensor]],  # or frozen geometry {"means", "quats", "scales", "opacities"}
    scene: Scene,  # its cameras
    bank: SegmentBank,
    views: Sequence[int],  # scene views to lift from (the training views)
    *,
    cache: Any = None,  # n2f2.train.blend.BlendCache of exactly `views` at the bank's size, if at hand
    progress: bool = False,
) -> Lift:
    """:func:`n2f2.field.lift.lift_features`, computing the views' blending weights first when
    no cache is given (``seconds``: "blend", "lift", "total")."""
    from ..train.blend import build_blend_cache
    from ..train.geometry import bank_cameras, frozen_geometry

    t0 = time.perf_counter()
    bank.validate_against(scene)
    geometry = gaussians if isinstance(gaussians, dict) else frozen_geometry(gaussians, "cpu")
    if cache is None:
        cameras = bank_cameras(scene, bank)
        cache = build_blend_cache(geometry, [cameras[int(v)] for v in views], progress=progress)
    t1 = time.perf_counter()
    lift = lift_features(cache, views, bank, int(geometry["means"].shape[0]))
    lift.seconds = {"blend": t1 - t0, "lift": lift.seconds["lift"], "total": time.perf_counter() - t0}
    return lift


def run_lift(run_dir: Any, engine: QueryEngine, bank: Any, progress: bool = False) -> tuple[Lift, bool]:
    """(the lift of a run, read from a file?): ``RUN/lift.pt`` when training wrote it (from its
    cached blending weights), else built now over the run's training views."""
    path = Path(run_dir) / "lift.pt"
    N = int(engine.gaussians.means.shape[0])
    if path.is_file():
        return load_lift(path, num_gaussians=N), True
    views = engine.meta.get("train_views") or list(range(len(engine.scene.cameras)))
    return build_lift(engine.gaussians, engine.scene, bank, views, progress=progress), False
