"""The query engine: per-view caches, the five modes, and 3D queries on the Gaussians.

Modes (:mod:`n2f2.query.modes`; all scored by :mod:`n2f2.field.relevancy`, the one relevancy definition):

* ``composite`` (default, paper Sec. 3.3): one relevancy map per query from the composite
  embedding ``W Theta~``. ``Theta~`` (premultiplied by ``revcumsum(gamma^3D)``) is computed once
  per trained field; a view renders it once; a query is one pass over that cache.
* ``explicit``: relevancy at every scale of the nested field (the ``floor(D / k)`` supervised
  prefix lengths) and, per query, the scale with the highest selection score (LERF / LangSplat).
* ``levels``: the 3-level baseline field (variant ``"levels"``), explicit selection over its 3
  levels (part, object, group).
* ``soft`` ("soft explicit", :mod:`n2f2.query.soft`): per query, the relevancy at every scale
  averaged with weights ``softmax(peak / tau)`` of each scale's highest relevancy over the points
  (the view's pixels, or the Gaussians). Nested and flat fields.
* ``oracle``: the best scale per query given ground truth (a mask per query, or a scorer callback
  supplied by the evaluation stage): the upper bound of scale selection.

Fast path. Everything works on flat "points" (the pixels of a rendered view, or the Gaussians
for 3D queries) laid out points-last, so a batch of ``Q`` queries is a single matmul with the
cached features. Because the relevancy normalises features, each cache also holds, per point
(and per scale), ``1 / max(|phi|, eps)`` and the negatives' term ``max_c phi^ . c``. With
``q = W^T t`` a composite query is ``sigmoid(10 ((q^T theta~) / |phi| - negmax))``: one
``[Q, D] x [D, P]`` product plus elementwise work, nothing re-rendered. Explicit mode gets all
prefix dot products from block sums + a cumulative sum over scales (``P x D x Q``), and all prefix
norms once per view from ``G = W^T W`` (see :func:`n2f2.query.composite.prefix_sq_norms`).
3D queries on the Gaussians never form explicit mode's ``[S, Q, N]`` relevancy: per scale only the
largest margin over the Gaussians is kept (streamed; compiled with numba on CPU), and the
relevancy is computed once, at the chosen scale (:func:`select_scale`), with the same bits. Soft
mode takes its peaks from the same maxima and sums the weighted relevancy over windows of
Gaussians (:func:`soft_scales`).

Rendering a 2D view (``QueryConfig.render``). The field is trained with deferred rendering
(paper Sec. 3.2): a pixel's feature is the MLP of the blended backbone features,
``theta(p) = MLP(sum_i w_{p,i} f_i)``. The paper renders test views the other way, blending the
per-Gaussian ``Theta_i = MLP(f_i)`` (and, for composite, ``Theta~_i`` of Eq. 7 with gamma per
Gaussian). ``"deferred"`` (the default) renders test views as the field was trained: the
backbone's features are rasterized, the MLP runs per pixel, and composite's Eq. 6-7 are applied
per pixel (gamma from the pixel's own prefix features); ``"gaussians"`` is the paper's form. The
two differ where a pixel blends Gaussians with different backbone features (edges, thin parts).
A pixel no Gaussian covers has the zero feature in both (relevancy 0.5).
Measured in ``docs/measurements.md`` ("Test views rendered as the field was trained"). 3D queries
on the Gaussians use ``Theta_i`` either way.

Selection score of explicit / levels in 2D (``QueryConfig.selection``): ``"smoothed"`` (default)
is the maximum of LangSplat's ``R' = 0.5 (box(R) + R)`` from :mod:`n2f2.query.maps`, the rule
the evaluation protocol uses to pick the reported segmentation level; ``"max"`` is the maximum of
the raw relevancy (LERF). For 3D queries on Gaussians there is no image grid: always ``"max"``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from dataclasses import field as dc_field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Optional, Sequence, Union, cast

import numpy as np
import torch
from torch import Tensor

from ..config import option
from ..errors import InputError
from ..field.relevancy import DEFAULT_NEGATIVES, check_texts
from ..field.variants import LEVEL_NAMES, FieldVariant, get_variant
from ..segments.bins import supervised_dims
from ..train.runs import load_run_scene
from ..validate import composite_temperature
from .caches import (
    LinearCache,
    PrefixCache,
    ScoreCache,
    build_composite_cache,
    build_linear_cache,
    build_prefix_cache,
    select_scale,
    soft_scales,
)
from .composite import COMPOSITE_WEIGHTS, DEFAULT_CANONICAL, DEFAULT_WEIGHTS, PAPER_TEMPERATURE, premultiply
from .maps import (
    LANGSPLAT_BOX_SIZE,
    LANGSPLAT_THRESHOLD,
    BoxSize,
    mask_iou,
    normalized_for_threshold,
    resolve_box_size,
    segmentation_mask,
    smoothed_relevancy,
)
from .modes import COMPOSITE_CACHE, NODE_CACHE, PREFIX_CACHE, QUERY_MODES, QueryMode, get_mode
from .modes import MODES as MODES
from .nodes import TIE_WEIGHT, NodeAnswer, NodeCache, answer_mask, choose_nodes, gaussian_scores
from .soft import soft_relevancy

if TYPE_CHECKING:
    from ..cameras import Camera

SELECTIONS = ("smoothed", "max")
RENDERS = ("deferred", "gaussians")  # how a 2D view gets its pixels' features (QueryConfig.render)
DEFAULT_RENDER = "deferred"  # since n2f2 rendered test views per Gaussian: part of cached stage keys

# (view index, relevancy at every scale [S, H, W] for one query, query index) -> scores [S]
OracleScorer = Callable[[Tensor, int], Union[Tensor, np.ndarray, Sequence[float]]]
# A mode's answer: relevancy [Q, H, W] or [Q, N], the chosen scale per query (None: no one
# scale), and the [Q, S] scores it chose by (None: composite).
Answer = tuple[Tensor, list[Optional[int]], Optional[Tensor]]


@dataclass
class QueryConfig:
    """Settings of the query stage (the defaults are the paper's and LERF/LangSplat's). Fields
    declared with option() are flags of `n2f2 query` and `n2f2 eval` (query/commands.py)."""

    canonical: tuple[str, ...] = option(
        DEFAULT_CANONICAL, help="canonical phrases of gamma, paper Eq. 6", metavar="PHRASE", nargs="+"
    )
    negatives: tuple[str, ...] = DEFAULT_NEGATIVES  # negatives of the relevancy (LERF)
    # composite's weights over the scales (query/composite.py)
    composite_weights: str = option(
        DEFAULT_WEIGHTS,
        help="composite's weights over the scales: unit = the mean of the normalised scale features; "
        "eq6 = the paper's Eq. 6 at --temperature",
        choices=COMPOSITE_WEIGHTS,
    )
    temperature: float = option(
        PAPER_TEMPERATURE,
        help="T of --composite-weights eq6, gamma = softmax(score / T): 'paper' (T = 1), "
        "'uniform' (T = infinity: the plain mean of the scale features) or a number > 0",
        type=composite_temperature,
        metavar="T",
    )
    selection: str = option(
        "smoothed",
        help="explicit/levels scale choice: max of the protocol-smoothed map (LangSplat) or of the raw map (LERF)",
        choices=SELECTIONS,
    )
    box_size: Optional[BoxSize] = None  # protocol mean filter (px) or "scaled"; None = protocol's
    # 2D views (see the module docstring): "deferred" rasterizes the backbone's features and runs
    # the MLP per pixel, the form the field was trained in; "gaussians" (the paper's test time)
    # runs it per Gaussian and rasterizes Theta (and composite's Theta~ of Eq. 7 per Gaussian).
    render: str = option(
        DEFAULT_RENDER,
        help="2D views: deferred = rasterize the backbone's features and run the MLP per pixel, as the field "
        "was trained; gaussians = the MLP per Gaussian, the paper's test-time form",
        choices=RENDERS,
    )
    chunk: int = 65536  # points per block when building caches (bounds [chunk, E] memory)
    decomposition: Optional[str] = option(
        None,
        help="the run's hierarchy for --mode node (n2f2 decompose's folder; default RUN/decomposition)",
        metavar="DIR",
    )

    def __post_init__(self) -> None:
        if not self.canonical:
            raise ValueError("need at least one canonical phrase")
        if not self.negatives:
            raise ValueError("need at least one negative phrase")
        if not self.temperature > 0:
            raise ValueError(f"composite temperature must be positive, got {self.temperature}")
        if self.composite_weights not in COMPOSITE_WEIGHTS:
            raise ValueError(f"composite weights must be one of {COMPOSITE_WEIGHTS}, got {self.composite_weights!r}")
        if self.selection not in SELECTIONS:
            raise ValueError(f"selection must be one of {SELECTIONS}, got {self.selection!r}")
        if self.render not in RENDERS:
            raise ValueError(f"render must be one of {RENDERS}, got {self.render!r}")
        self.canonical = tuple(self.canonical)
        self.negatives = tuple(self.negatives)


# ---------------------------------------------------------------------------------- results
@dataclass
class ViewCache:
    """Everything a view needs to answer queries without rendering again."""

    camera: Camera
    index: Optional[int]  # view index in the scene, None for a free camera
    name: str  # image name (e.g. frame_00001) or "camera"
    caches: dict[str, ScoreCache]  # by cache kind: "composite" | "prefix" | "levels"
    alpha: Tensor  # [H, W] accumulated opacity
    rgb: Optional[Tensor] = None  # [H, W, 3] rendered colour in [0, 1]
    seconds: dict[str, float] = dc_field(default_factory=dict)  # render / cache timings

    @property
    def height(self) -> int:
        return int(self.alpha.shape[0])

    @property
    def width(self) -> int:
        return int(self.alpha.shape[1])


@dataclass
class QueryResult:
    """Relevancy of a batch of queries in one view (or over the Gaussians)."""

    texts: list[str]
    mode: str
    relevancy: Tensor  # [Q, H, W] (2D) or [Q, N] (Gaussians), in (0, 1)
    scale_labels: list[str]  # the candidate scales of the mode (["composite"] for composite)
    chosen: list[Optional[int]]  # per query: index into scale_labels (None for composite / soft)
    # [Q, S] selection score of every scale; soft: its peak (weights = softmax(peak / tau))
    scale_scores: Optional[Tensor] = None
    seconds: float = 0.0  # wall time of the query pass

    @property
    def chosen_labels(self) -> list[Optional[str]]:
        return [None if c is None else self.scale_labels[c] for c in self.chosen]


# ---------------------------------------------------------------------------------- engine
class QueryEngine:
    """Open-vocabulary queries on a trained run. Importing this module has no side effects; the
    engine builds its per-field data (Theta, Theta~, text embeddings) lazily and keeps it.

    Args:
        field: a :class:`n2f2.field.NestedField` (``W [E, D]``, ``field(xyz) -> theta``).
        gaussians: the run's :class:`n2f2.gaussians.Gaussians`.
        encoder: text encoder with ``encode_text(list[str]) -> [Q, E]`` and ``description``.
        meta: the field's metadata (``config`` with ``dim``, ``step_size``, ``variant``).
        config: :class:`QueryConfig`.
        device: torch device for every tensor.
        scene: optional :class:`n2f2.data.scene.Scene` giving the cameras for view indices.
        background: the learned background RGB views are composited over, as the fit rendered
            its test views (:func:`n2f2.gaussians.fit.read_background`); None: black.
    """

    def __init__(
        self,
        field: Any,
        gaussians: Any,
        encoder: Any,
        meta: dict,
        config: Optional[QueryConfig] = None,
        device: Union[str, torch.device] = "cpu",
        scene: Any = None,
        run_dir: Optional[Path] = None,
        background: Any = None,
    ) -> None:
        self.field = field
        self.gaussians = gaussians
        self._encoder = encoder  # None: built from meta["encoder_spec"] on first use
        self.meta = meta
        self.config = config or QueryConfig()
        self.device = torch.device(device)
        self.scene = scene
        self.run_dir = run_dir
        self.background = background  # Environment: camera -> [H, W, 3], or None
        cfg = meta.get("config", {})
        self.variant: str = str(cfg.get("variant", meta.get("variant", "nested")))  # the name, as in files
        self.kind: FieldVariant = get_variant(self.variant)  # what the variant supervises and answers
        self.dim: int = int(field.W.shape[1])
        # The flat field has a single scale (all D dims); nested fields have floor(D / k).
        self.step: int = self.kind.step(self.dim, int(cfg.get("step_size", 1)))
        self._text_cache: dict[str, Tensor] = {}
        self._theta: Optional[Tensor] = None
        self._theta_tilde: Optional[Tensor] = None
        self._backbone: Optional[Tensor] = None
        self._gaussian_caches: dict[str, ScoreCache] = {}
        self._tree: Any = None

    # ------------------------------------------------------------------ construction
    @staticmethod
    def from_run(
        run_dir: Union[str, Path],
        device: Union[str, torch.device] = "cpu",
        scene: Any = None,
        config: Optional[QueryConfig] = None,
        encoder: Any = None,
        full_res: bool = False,
    ) -> "QueryEngine":
        """Load ``RUN_DIR/field.pt`` and ``RUN_DIR/gaussians.ply`` (and the field's text encoder),
        and the fit's learned background when the run holds it (``background.json``).

        ``scene`` is a Scene, a scene folder, or None (then the scene recorded in the run's
        metadata is used when it exists; views can still be given as cameras). A folder is
        loaded at the downscale the run was trained at, or at the images' size with ``full_res``."""
        from ..field import load_field
        from ..gaussians import read_ply
        from ..gaussians.fit import read_background

        run_dir = Path(run_dir)
        if not run_dir.is_dir():
            raise InputError(run_dir, "run directory does not exist")
        field_path = run_dir / "field.pt"
        if not field_path.is_file():
            raise InputError(run_dir, "no field.pt in the run directory: not a trained run (run `n2f2 train` first)")
        ply_path = run_dir / "gaussians.ply"
        if not ply_path.is_file():
            raise InputError(run_dir, "no gaussians.ply in the run directory")
        field, meta = load_field(field_path, device)
        field.requires_grad_(False)
        gaussians = read_ply(ply_path, device=device)
        if encoder is None and meta.get("encoder_spec") is None:
            raise InputError(field_path, "field metadata names no text encoder (encoder_spec)")
        if scene is None or isinstance(scene, (str, Path)):
            scene = load_run_scene(run_dir, meta, scene, full_res)
        background = read_background(run_dir, device)
        return QueryEngine(field, gaussians, encoder, meta, config, device, scene, run_dir, background)

    # ------------------------------------------------------------------ field data
    @property
    def encoder(self) -> Any:
        """The field's text encoder, loaded on first use (so opening a run is cheap)."""
        if self._encoder is None:
            from ..segments.encoders import get_encoder

            self._encoder = get_encoder(self.meta["encoder_spec"], self.device)
        return self._encoder

    @property
    def W(self) -> Tensor:  # [E, D]
        return self.field.W.detach()

    @property
    def scale_dims(self) -> list[int]:
        """Prefix lengths of the scales (nested / flat fields)."""
        return supervised_dims(self.dim, self.step)

    @property
    def scale_labels(self) -> list[str]:
        """The names of the field's scales: ``d=...`` per prefix, or the 3 level names."""
        return self.kind.scale_labels(self.dim, self.step)

    def modes(self) -> tuple[str, ...]:
        """Modes this run answers: its field's, and ``node`` once it has a hierarchy."""
        tree = tuple(m.name for m in QUERY_MODES.values() if m.needs_tree) if self._tree_dir() else ()
        return self.kind.modes + tree

    def _tree_dir(self) -> Optional[Path]:
        """The hierarchy's folder (QueryConfig.decomposition, else RUN/decomposition) if it holds one."""
        from ..hierarchy.files import TREE_NAME

        root = self._tree_root()
        return root if root is not None and (root / TREE_NAME).is_file() else None

    def _tree_root(self) -> Optional[Path]:
        """Where the hierarchy is looked for: QueryConfig.decomposition, else RUN/decomposition."""
        from ..hierarchy.files import DEFAULT_OUT

        if self.config.decomposition:
            return Path(self.config.decomposition)
        return self.run_dir / DEFAULT_OUT if self.run_dir is not None else None

    @property
    def tree(self) -> Any:  # n2f2.hierarchy.LoadedTree
        """The run's hierarchy, read on first use."""
        if self._tree is None:
            from ..hierarchy.files import read_tree

            root = self._tree_dir()
            if root is None:
                where = self._tree_root() or Path("RUN/decomposition")
                raise InputError(where, "mode 'node' needs the run's hierarchy: run `n2f2 decompose RUN` first")
            self._tree = read_tree(root, num_gaussians=int(self.gaussians.means.shape[0]))
        return self._tree

    def _check_mode(self, mode: str) -> QueryMode:
        """The mode named ``mode``, if this field answers it (else an InputError saying why)."""
        query_mode = get_mode(mode)
        if query_mode.needs_tree:
            _ = self.tree  # the hierarchy, or one line saying how to make it
            return query_mode
        if mode not in self.modes():
            raise InputError(
                self.run_dir / "field.pt" if self.run_dir else None,
                f"mode {mode!r} does not apply to this {self.variant!r} field ({self.kind.other_modes_hint})",
            )
        return query_mode

    def _cache_kind(self, mode: str) -> str:
        """The score cache of ``mode`` on this field (:meth:`n2f2.query.modes.QueryMode.cache_for`)."""
        return get_mode(mode).cache_for(self.kind)

    @torch.no_grad()
    def encode(self, texts: Sequence[str]) -> Tensor:  # -> [Q, E] unit vectors
        """Text embeddings (cached per string), re-normalised so every dot product is a cosine."""
        missing = [t for t in dict.fromkeys(texts) if t not in self._text_cache]
        if missing:
            emb = torch.as_tensor(self.encoder.encode_text(list(missing)))
            emb = torch.nn.functional.normalize(emb.to(self.device, torch.float32), dim=-1)
            if emb.shape[-1] != self.W.shape[0]:
                raise InputError(
                    None,
                    f"text encoder gives {emb.shape[-1]}-dim embeddings but the "
                    f"field's W expects E = {self.W.shape[0]}",
                )
            for t, e in zip(missing, emb):
                self._text_cache[t] = e
        return torch.stack([self._text_cache[t] for t in texts])

    @property
    def theta(self) -> Tensor:  # [N, D] Theta_i at the Gaussian centres
        if self._theta is None:
            from ..field import gaussian_features

            self._theta = gaussian_features(self.field, self.gaussians.means.detach()).float()
        return self._theta

    @property
    def theta_tilde(self) -> Tensor:  # [N, D] revcumsum(gamma^3D) * Theta, computed once
        if self._theta_tilde is None:
            self._theta_tilde = self._premultiply(self.theta)
        return self._theta_tilde

    @torch.no_grad()
    def _premultiply(self, theta: Tensor) -> Tensor:  # theta [n, D] -> Theta~ [n, D]
        """:func:`~n2f2.query.composite.premultiply` with this engine's composite settings."""
        canon = self.encode(self.config.canonical)
        return premultiply(
            theta,
            self.W,
            canon,
            self.step,
            self.config.temperature,
            self.config.chunk,
            weights=self.config.composite_weights,
        )

    def level_maps(self) -> Tensor:  # [3, E, D] the "levels" field's three linear projections
        """The level projections of a "levels" field, read off ``field.level_features`` applied to
        the identity (it is linear: each level is a column block of W)."""
        eye = torch.eye(self.dim, device=self.device)
        with torch.no_grad():
            maps = self.field.level_features(eye)  # [D, 3, E]
        return maps.permute(1, 2, 0).contiguous()

    def _build_cache(self, kind: str, points: Tensor) -> ScoreCache:
        """``points`` is Theta~ for "composite" and raw Theta otherwise ([P, D])."""
        negs = self.encode(self.config.negatives)
        if kind == COMPOSITE_CACHE:
            return build_composite_cache(points, self.W, negs, self.config.chunk)
        if kind == PREFIX_CACHE:
            return build_prefix_cache(points, self.W, negs, self.step, self.config.chunk)
        return build_linear_cache(points, self.level_maps(), negs, LEVEL_NAMES, self.config.chunk)

    # ------------------------------------------------------------------ views
    def camera(self, view: Any) -> tuple[Any, Optional[int], str]:
        """A view index (into the scene) or a Camera -> (camera, index, name)."""
        if isinstance(view, (int, np.integer)):
            if self.scene is None:
                recorded = self.meta.get("scene")
                where = f" (its recorded scene {recorded} does not exist)" if recorded else ""
                raise InputError(
                    self.run_dir,
                    f"no scene is known for this run{where}: pass --scene DATA, "
                    "or give cameras instead of view indices",
                )
            n = len(self.scene.cameras)
            if not 0 <= int(view) < n:
                raise InputError(
                    getattr(self.scene, "root", None),
                    f"view index {int(view)} out of range: the scene has {n} views (0..{n - 1})",
                )
            i = int(view)
            return self.scene.cameras[i], i, self.scene.image_names[i]
        return view, None, "camera"

    @torch.no_grad()
    def render_view(self, view: Any, modes: Sequence[str] = ("composite",), rgb: bool = True) -> ViewCache:
        """Render what ``modes`` need for ``view`` (an index or a Camera) once, and cache it.

        Θ~ and Θ are rasterized in one pass when both are needed (rendering is linear)."""
        from ..render import rasterize_in_bands, view_colors

        for m in modes:
            self._check_mode(m)
        cam, index, name = self.camera(view)
        kinds = list(dict.fromkeys(self._cache_kind(m) for m in modes))
        # Composite needs Theta~, the other kinds raw Theta: one rasterization of both.
        parts = (["tilde"] if COMPOSITE_CACHE in kinds else []) + (
            ["theta"] if any(k not in (COMPOSITE_CACHE, NODE_CACHE) for k in kinds) else []
        )
        self.encode(self.config.negatives)  # loads the encoder on first use: not render time
        if "tilde" in parts:
            self.encode(self.config.canonical)
        g = self.gaussians
        H, W_ = cam.height, cam.width
        D = self.dim
        if not parts:  # node mode only: its maps are rendered per query; the alpha map here
            t0 = time.perf_counter()
            flat = g.means.new_zeros(H * W_, 1)
            out = rasterize_in_bands(g.means, g.normalized_quats, g.scales, g.opacities, flat[:1].expand(g.num, 1), cam)
        elif self.renders_deferred:
            _ = self.backbone_features  # computed once per engine: not render time
            t0 = time.perf_counter()
            flat, out = self._render_deferred(cam, parts)
        else:
            tensors = [self.theta_tilde if p == "tilde" else self.theta for p in parts]
            stacked = tensors[0] if len(tensors) == 1 else torch.cat(tensors, dim=1)
            t0 = time.perf_counter()
            # Rendered in bands straight into the buffer the score cache keeps (one kind: no copy),
            # so a view's transient memory is a band's, not a few copies of the whole [H, W, C].
            flat = stacked.new_empty(H * W_, stacked.shape[1])
            out = rasterize_in_bands(
                g.means, g.normalized_quats, g.scales, g.opacities, stacked, cam, out=flat.view(H, W_, -1)
            )
        t1 = time.perf_counter()
        caches = {}
        for k in kinds:
            if k == NODE_CACHE:
                caches[k] = self._node_cache(cam)
                continue
            j = parts.index("tilde" if k == COMPOSITE_CACHE else "theta")
            caches[k] = self._build_cache(k, flat[:, j * D : (j + 1) * D])
        t2 = time.perf_counter()
        image = None
        if rgb:  # as the fit renders its test views (gaussians.fit._render), over its background
            env = self.background
            black = None if env is not None else (0.0, 0.0, 0.0)
            colors = view_colors(g, cam)  # [N, 3]
            rendered = rasterize_in_bands(g.means, g.quats, g.scales, g.opacities, colors, cam, background=black)
            if env is not None:
                rendered.features += (1.0 - rendered.alpha) * env(cam).to(rendered.features)
            image = rendered.features.clamp_(0.0, 1.0)
        return ViewCache(
            cam, index, name, caches, out.alpha.reshape(H, W_), image, {"render": t1 - t0, "cache": t2 - t1}
        )

    @property
    def renders_deferred(self) -> bool:
        """Whether 2D views are rendered deferred: asked for, and the field has a backbone and an
        MLP (the lift's level blocks have neither)."""
        return self.config.render == "deferred" and hasattr(self.field, "encode") and hasattr(self.field, "decode")

    @property
    def backbone_features(self) -> Tensor:  # [N, F] the backbone at the Gaussian centres
        if self._backbone is None:
            with torch.no_grad():
                means = self.gaussians.means.detach().float()
                self._backbone = self.field.encode(self.field.normalize(means)).float().contiguous()
        assert self._backbone is not None  # set above
        return self._backbone

    def _render_deferred(self, cam: Any, parts: list[str]) -> tuple[Tensor, Any]:
        """``[H W, len(parts) D]`` pixel features rendered deferred (module docstring): the
        backbone's features rasterized, the MLP per pixel, composite's ``Theta~`` per pixel."""
        from ..render import rasterize_in_bands

        g = self.gaussians
        f = self.backbone_features
        H, W_, D = cam.height, cam.width, self.dim
        out = rasterize_in_bands(g.means, g.normalized_quats, g.scales, g.opacities, f, cam)
        blended = out.features.reshape(H * W_, -1)  # [H W, F]
        # A pixel no Gaussian covers has no feature (relevancy 0.5, as the per-Gaussian rendering
        # gives it), not the MLP's output for a zero input.
        covered = (out.alpha.reshape(H * W_, 1) > 0).to(blended.dtype)  # [H W, 1]
        flat = blended.new_empty(H * W_, len(parts) * D)
        with torch.no_grad():
            for a in range(0, H * W_, self.config.chunk):  # bounds the MLP's [chunk, hidden] memory
                b = a + self.config.chunk
                theta = self.field.decode(blended[a:b]).float() * covered[a:b]  # [c, D]
                for j, p in enumerate(parts):
                    block = flat[a : a + len(theta), j * D : (j + 1) * D]
                    if p == "tilde":
                        block.copy_(self._premultiply(theta))
                    else:
                        block.copy_(theta)
        return flat, out

    def view_cache_bytes(self, view: Any, modes: Sequence[str] = ("composite",), rgb: bool = True) -> int:
        """Bytes of what :meth:`render_view` keeps for ``view`` (an index or a Camera): per cache
        kind the ``[P, D]`` features (prefix: ``[S, k, P]`` blocks) and ``[S, P]`` norms and
        negatives, the alpha map and the colour image (``P`` = pixels; the shared ``W`` aside)."""
        cam, _, _ = self.camera(view)
        P = cam.width * cam.height
        item = self.theta.element_size()
        floats = P * (1 + (3 if rgb else 0))
        for k in dict.fromkeys(self._cache_kind(m) for m in modes):
            if k == PREFIX_CACHE:
                S = len(self.scale_dims)
                floats += P * (S * self.step + 2 * S)
            else:
                S = 1 if k == COMPOSITE_CACHE else 3
                floats += P * (self.dim + 2 * S)
        return floats * item

    @torch.no_grad()
    def query(
        self,
        view: ViewCache,
        texts: Sequence[str],
        mode: str = "composite",
        gt_masks: Optional[Any] = None,
        scorer: Optional[OracleScorer] = None,
    ) -> QueryResult:
        """Relevancy maps ``[Q, H, W]`` of ``texts`` in a rendered view.

        Oracle mode needs ``gt_masks`` (``[Q, H, W]`` bool, scored by protocol IoU at every scale)
        or ``scorer(relevancy_per_scale [S, H, W], query_index) -> [S]`` (higher is better)."""
        texts = check_texts(texts)
        query_mode = self._check_mode(mode)
        kind = query_mode.cache_for(self.kind)
        if kind not in view.caches:
            raise InputError(
                None, f"view {view.name} was not rendered for mode {mode!r}: render_view(..., modes=[{mode!r}])"
            )
        if query_mode.needs_truth and gt_masks is None and scorer is None:
            raise InputError(None, f"{mode} mode needs ground-truth masks or a scorer")
        t0 = time.perf_counter()
        emb = self.encode(texts)
        cache = view.caches[kind]
        answer = getattr(self, query_mode.view_query)
        rel, chosen, scores = answer(cache, emb, view.height, view.width, gt_masks, scorer)
        return QueryResult(texts, mode, rel, cache.labels, chosen, scores, time.perf_counter() - t0)

    def _view_composite(
        self, cache: ScoreCache, emb: Tensor, height: int, width: int, gt_masks: Any, scorer: Optional[OracleScorer]
    ) -> Answer:
        """Composite mode on a view: the cache's one map per query."""
        return cache.relevancy(emb)[0].view(len(emb), height, width), [None] * len(emb), None

    def _view_soft(
        self, cache: ScoreCache, emb: Tensor, height: int, width: int, gt_masks: Any, scorer: Optional[OracleScorer]
    ) -> Answer:
        """Soft mode on a view: every scale's map weighted by its peak (:func:`soft_relevancy`)."""
        S = len(cache.labels)
        out = emb.new_empty(len(emb), height, width)
        scores = emb.new_empty(len(emb), S)
        group = _query_group(S, height, width)
        for a in range(0, len(emb), group):
            soft, peaks = soft_relevancy(cache.relevancy(emb[a : a + group]))  # [q, H W], [q, S]
            out[a : a + len(peaks)] = soft.view(-1, height, width)
            scores[a : a + len(peaks)] = peaks
        return out, [None] * len(emb), scores

    def _view_selected(
        self, cache: ScoreCache, emb: Tensor, height: int, width: int, gt_masks: Any, scorer: Optional[OracleScorer]
    ) -> Answer:
        """Explicit / levels mode on a view: per query the scale with the highest selection score."""
        return self._view_best(cache, emb, height, width, lambda rel, qi: self._selection_scores(rel, image=True))

    def _view_oracle(
        self, cache: ScoreCache, emb: Tensor, height: int, width: int, gt_masks: Any, scorer: Optional[OracleScorer]
    ) -> Answer:
        """Oracle mode on a view: per query the scale that scores best against ``gt_masks`` or by ``scorer``."""
        return self._view_best(
            cache, emb, height, width, lambda rel, qi: _oracle_scores(rel, qi, gt_masks, scorer, self.config)
        )

    def _view_best(
        self, cache: ScoreCache, emb: Tensor, height: int, width: int, score: Callable[[Tensor, int], Tensor]
    ) -> Answer:
        """Per query the map of the scale with the highest ``score(relevancy [S, H, W], query index) -> [S]``."""
        S = len(cache.labels)
        out = emb.new_empty(len(emb), height, width)
        scores = emb.new_empty(len(emb), S)
        chosen: list[Optional[int]] = []
        group = _query_group(S, height, width)
        for a in range(0, len(emb), group):
            rel = cache.relevancy(emb[a : a + group]).view(S, -1, height, width)  # [S, q, H, W]
            for j in range(rel.shape[1]):
                qi = a + j
                s = score(rel[:, j], qi)
                scores[qi] = s
                best = int(torch.argmax(s))
                chosen.append(best)
                out[qi] = rel[best, j]
        return out, chosen, scores

    def _selection_scores(self, rel: Tensor, image: bool) -> Tensor:  # [S, ...] -> [S]
        """Per-scale selection score (see module docstring)."""
        if image and self.config.selection == "smoothed":
            size = resolve_box_size(_box(self.config), rel.shape[-1])
            sm = smoothed_relevancy(rel.float().cpu().numpy(), size)
            return torch.from_numpy(sm.reshape(len(sm), -1).max(axis=1)).to(rel.device)
        return rel.reshape(rel.shape[0], -1).amax(dim=1)

    # ------------------------------------------------------------------ 3D
    def gaussian_cache(self, mode: str = "composite") -> ScoreCache:
        """Score cache whose points are the Gaussians (built once per mode kind)."""
        self._check_mode(mode)
        kind = self._cache_kind(mode)
        if kind == NODE_CACHE:
            return self._node_cache(None)
        if kind not in self._gaussian_caches:
            pts = self.theta_tilde if kind == COMPOSITE_CACHE else self.theta
            with torch.no_grad():
                self._gaussian_caches[kind] = self._build_cache(kind, pts)
        return self._gaussian_caches[kind]

    @torch.no_grad()
    def query_gaussians(self, texts: Sequence[str], mode: str = "composite") -> QueryResult:
        """Relevancy ``[Q, N]`` of every Gaussian from its own feature (``W Theta~_i`` in composite
        mode), without rendering. Explicit / levels pick per query the scale with the highest
        maximum over the Gaussians; soft weighs every scale by those maxima."""
        texts = check_texts(texts)
        query_mode = get_mode(mode)
        if query_mode.gaussian_query is None:
            in_3d = [m.name for m in QUERY_MODES.values() if m.in_3d]
            raise InputError(None, f"{mode} mode has no 3D query; use {', '.join(in_3d)} in 3D")
        t0 = time.perf_counter()
        cache = self.gaussian_cache(mode)
        emb = self.encode(texts)
        rel, chosen, scores = getattr(self, query_mode.gaussian_query)(cache, emb)
        return QueryResult(texts, mode, rel, cache.labels, chosen, scores, time.perf_counter() - t0)

    def _gaussians_composite(self, cache: ScoreCache, emb: Tensor) -> Answer:
        """Composite mode over the Gaussians: the cache's one map per query."""
        return cache.relevancy(emb)[0], [None] * len(emb), None  # [1, Q, N] -> [Q, N]

    def _gaussians_soft(self, cache: ScoreCache, emb: Tensor) -> Answer:
        """Soft mode over the Gaussians (:func:`soft_scales`)."""
        out, peaks = soft_scales(cast(PrefixCache, cache), emb)
        return out, [None] * len(emb), peaks

    def _gaussians_selected(self, cache: ScoreCache, emb: Tensor) -> Answer:
        """Explicit / levels mode over the Gaussians: the scale with the highest maximum (:func:`select_scale`)."""
        chosen, scores, out = select_scale(cast(Union[PrefixCache, LinearCache], cache), emb)
        return out, chosen.tolist(), scores

    # ------------------------------------------------------------------ nodes of the hierarchy
    def _node_cache(self, camera: Any) -> NodeCache:
        tree = self.tree
        emb = torch.as_tensor(tree.embeddings, device=self.device)
        labels = [lv["scale_label"] for lv in tree.tree["levels"]]
        return NodeCache(emb, self.encode(self.config.negatives), labels, camera)

    def node_answers(self, texts: Sequence[str]) -> list[NodeAnswer]:
        """Per query its nodes of the run's hierarchy (:func:`n2f2.query.nodes.choose_nodes`)."""
        cache = self._node_cache(None)
        margins = cache.margins(self.encode(check_texts(texts))).cpu()  # [Q, K]
        return [choose_nodes(m, self.tree.levels, self.tree.last_levels, self.tree.parents) for m in margins]

    def _node_maps(self, cache: NodeCache, emb: Tensor) -> tuple[list[NodeAnswer], list[Tensor]]:
        tree = self.tree
        answers = [choose_nodes(m, tree.levels, tree.last_levels, tree.parents) for m in cache.margins(emb).cpu()]
        return answers, [answer_mask(self.tree.gaussian_nodes, a).to(self.device) for a in answers]

    def _view_node(
        self, cache: NodeCache, emb: Tensor, height: int, width: int, gt_masks: Any, scorer: Optional[OracleScorer]
    ) -> Answer:
        """Node mode on a view: each answer's rendered coverage, ties among the pixels it does
        not cover ordered by their nodes' score (:func:`n2f2.query.nodes.gaussian_scores`)."""
        from ..render import rasterize

        answers, masks = self._node_maps(cache, emb)
        g = self.gaussians
        assert cache.camera is not None  # render_view gives the node cache its view's camera
        out = emb.new_empty(len(emb), height, width)
        for q, (answer, mask) in enumerate(zip(answers, masks)):
            feats = torch.stack([mask.float(), gaussian_scores(self.tree.gaussian_nodes, answer)], dim=1)
            cov = rasterize(g.means, g.normalized_quats, g.scales, g.opacities, feats.to(g.means), cache.camera)
            out[q] = cov.features[..., 0] + TIE_WEIGHT * cov.features[..., 1]
        return out, [a.level for a in answers], self._node_scores(answers).to(emb)

    def _gaussians_node(self, cache: NodeCache, emb: Tensor) -> Answer:
        """Node mode over the Gaussians: 1 on the answer's Gaussians, else 0."""
        answers, masks = self._node_maps(cache, emb)
        out = torch.stack([m.to(emb) for m in masks])  # [Q, N]
        return out, [a.level for a in answers], self._node_scores(answers).to(emb)

    def _node_scores(self, answers: list[NodeAnswer]) -> Tensor:  # -> [Q, L], as other modes' [Q, S]
        tree = self.tree
        return torch.stack([a.level_scores(tree.levels, tree.last_levels, tree.num_levels) for a in answers])

    def select(self, text: str, threshold: Optional[float] = None, mode: str = "composite") -> Tensor:
        """Boolean ``[N]`` selection of the Gaussians relevant to ``text``.

        ``threshold`` is an absolute relevancy; ``None`` applies the evaluation protocol's rule
        to the Gaussians' relevancy (min-max normalise, map to [-1, 1], clip, ``> 0.4``; no box
        filter since Gaussians have no pixel grid), or for a mode that answers with a set (node)
        takes that set: min-max of an answer that holds every Gaussian would select none."""
        rel = self.query_gaussians([text], mode).relevancy[0]
        if threshold is not None:
            return rel >= float(threshold)
        if get_mode(mode).answers_sets:
            return rel > 0.5

        norm = normalized_for_threshold(rel.float().cpu().numpy())
        return torch.from_numpy(norm > LANGSPLAT_THRESHOLD).to(rel.device)

    @torch.no_grad()
    def render_selection(self, mask: Tensor, view: Any) -> Tensor:  # mask [N] bool -> [H, W]
        """Fraction of each pixel's colour that comes from the selected Gaussians (occlusion by
        unselected Gaussians respected): render the selection indicator as a 1-channel feature."""
        from ..render import rasterize

        cam, _, _ = self.camera(view) if not isinstance(view, ViewCache) else (view.camera, None, "")
        g = self.gaussians
        ind = mask.to(self.device, torch.float32).reshape(-1, 1)
        out = rasterize(g.means, g.normalized_quats, g.scales, g.opacities, ind, cam)
        return out.features[..., 0]

    def export_selection(self, mask: Tensor, path: Union[str, Path]) -> int:
        """Write the selected Gaussians as an INRIA 3DGS PLY; returns how many were written."""
        from ..gaussians import write_ply

        n = int(mask.sum())
        if n == 0:
            raise InputError(path, "the selection is empty: nothing to export (lower the threshold)")
        write_ply(path, self.gaussians.subset(mask.to(self.gaussians.device)))
        return n


def _oracle_scores(
    rel: Tensor, qi: int, gt_masks: Any, scorer: Optional[OracleScorer], config: QueryConfig
) -> Tensor:  # rel [S, H, W] -> [S]
    if scorer is not None:
        return torch.as_tensor(np.asarray(scorer(rel, qi), dtype=np.float64)).to(rel.device, torch.float32)

    gt = np.asarray(gt_masks[qi].cpu() if isinstance(gt_masks, Tensor) else gt_masks[qi]) != 0
    if gt.shape != tuple(rel.shape[1:]):
        raise InputError(None, f"ground-truth mask {gt.shape} does not match the view {tuple(rel.shape[1:])}")
    size = resolve_box_size(_box(config), rel.shape[-1])
    maps = rel.float().cpu().numpy()
    ious = [mask_iou(segmentation_mask(m, box_size=size), gt) if gt.any() else 0.0 for m in maps]
    return torch.tensor(ious, dtype=torch.float32, device=rel.device)


def _query_group(num_scales: int, height: int, width: int) -> int:
    """Queries per block of a view's answer, so that the ``[S, q, H, W]`` block stays near 4M
    floats (cache-friendlier than one big block: measured faster per query on the demo view)."""
    return max(1, (1 << 22) // max(1, num_scales * height * width))


def _box(config: QueryConfig) -> BoxSize:
    """The configured mean-filter size, or the evaluation protocol's default."""

    return LANGSPLAT_BOX_SIZE if config.box_size is None else config.box_size
