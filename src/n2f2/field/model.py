"""The nested feature field (paper Sec. 3.1-3.2).

``theta = Theta(x) = MLP(backbone(normalise(x)))`` in R^D, and the scale-aware feature

    phi(u, s) = W_{1:M(s)} theta(u)_{1:M(s)} = W (B(s) * theta(u))            (paper eq. 4)

with ``W [E, D]`` zero-initialised and ``B(s)`` the binary mask of the first ``M(s)`` dims
(appendix "Efficient Scale-aware Feature Computation"). ``M(s) = k ceil(floor(D / k) (1 - s))``
comes from :func:`n2f2.segments.bins.scale_to_dims` (k = step size, paper Table 6).

Variants (paper ablations, chosen by :attr:`FieldConfig.variant`):

* ``"nested"`` (N2F2): a segment of quantized scale s supervises the first M(s) dims.
* ``"flat"``: non-nested; every scale supervises all D dims (``B(s) = 1``), so phi does not
  depend on s.
* ``"levels"``: LangSplat-like in-house baseline. theta is split into 3 contiguous blocks and
  each of the three scale groups (:func:`n2f2.segments.bins.three_level_groups`) supervises only
  its block. ``W`` keeps its ``[E, D]`` shape: block ``b`` uses only the columns of block ``b``,
  i.e. the three projections ``[E, D/3]`` are the column blocks of ``W`` (equivalently one
  block-diagonal projection). As in the nested field, the first block holds the coarsest level:
  hierarchy level ``l`` (0 = part, 1 = object, 2 = group) lives in block ``2 - l``.

The backbone is the TriPlane (``backbone="triplane"``) or a positional encoding
(``backbone="mlp"``); either way ``encode`` gives the low-dimensional feature that deferred
rendering rasterizes, and ``decode`` is the 3-layer MLP.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, ClassVar, Optional

import numpy as np
import torch
from torch import Tensor, nn

from ..config import ConfigDict, option
from ..errors import InputError
from ..io import load_torch, save_torch
from ..validate import _non_finite, nonneg_int, positive_int
from .triplane import PositionalEncoding, TriPlane
from .variants import NUM_LEVELS, FieldVariant, get_variant, level_blocks, level_mask, level_to_block
from .variants import VARIANTS as FIELD_VARIANTS
from .variants import prefix_mask as prefix_mask

if TYPE_CHECKING:
    from ..gaussians.model import Gaussians

BACKBONES = ("triplane", "mlp")
VARIANTS = tuple(FIELD_VARIANTS)  # the names of the variants (n2f2.field.variants)
FIELD_FORMAT = "n2f2-field"
FIELD_VERSION = 1


@dataclass
class FieldConfig(ConfigDict):
    """Architecture of the feature field. Defaults are the CPU preset; :meth:`paper` gives the
    paper's sizes (TriPlane 512^2 x 64, MLP hidden 256, D = 512)."""

    PRESETS: ClassVar[tuple[str, ...]] = ("cpu", "paper")  # see the static methods of those names

    # Options of `n2f2 train` (and `run`'s --dim, --variant); their help lists each preset's value.
    backbone: str = option(
        "triplane",
        help="triplane: TriPlane + 3-layer MLP (paper); mlp: positional encoding + MLP",
        choices=BACKBONES,
    )
    dim: int = option(128, help="D, feature-field dims = number of quantized scales", type=positive_int)
    plane_resolution: int = option(128, help="TriPlane resolution: the side of each plane", type=positive_int)
    plane_channels: int = option(
        32, help="TriPlane channels = dims rasterized by deferred rendering", type=positive_int
    )
    plane_reduce: str = "sum"  # how the three plane samples combine: "sum" | "product"
    hidden: int = option(256, help="MLP hidden width", type=positive_int)
    num_layers: int = 3  # MLP linear layers (paper: 3)
    pe_frequencies: int = option(8, help="positional-encoding frequencies of the MLP backbone", type=nonneg_int)
    variant: str = option(
        "nested",
        help="nested (N2F2), flat (non-nested ablation), levels (3 scale groups, LangSplat-like)",
        choices=VARIANTS,
    )
    step_size: int = option(
        1, help="k of the dimension-scale mapping; paper Table 6: 1, 8, 32, 128, 170", type=positive_int
    )

    def __post_init__(self) -> None:
        if self.backbone not in BACKBONES:
            raise ValueError(f"backbone must be one of {BACKBONES}, got {self.backbone!r}")
        if self.variant not in VARIANTS:
            raise ValueError(f"variant must be one of {VARIANTS}, got {self.variant!r}")
        if self.dim < NUM_LEVELS:
            raise ValueError(f"feature dim D must be >= {NUM_LEVELS}, got {self.dim}")
        if not 1 <= self.step_size <= self.dim:
            raise ValueError(f"step size k must be in [1, D={self.dim}], got {self.step_size}")
        if self.num_layers < 1 or self.hidden < 1:
            raise ValueError("the MLP needs at least one layer and a positive hidden width")

    @staticmethod
    def cpu() -> "FieldConfig":
        """The defaults: D = 128, TriPlane 128^2 x 32 (the built-in demo scene on 2 cores)."""
        return FieldConfig()

    @staticmethod
    def paper(**overrides: Any) -> "FieldConfig":
        """The paper's sizes (appendix "Feature Field Optimization")."""
        base: dict[str, Any] = dict(dim=512, plane_resolution=512, plane_channels=64, hidden=256, num_layers=3)
        base.update(overrides)
        return FieldConfig(**base)

    @property
    def kind(self) -> FieldVariant:
        """The variant as an object (:mod:`n2f2.field.variants`): its scales, step rule and modes."""
        return get_variant(self.variant)


def mlp(in_dim: int, hidden: int, out_dim: int, num_layers: int) -> nn.Sequential:
    """``num_layers`` linear layers with ReLU between them (none after the last)."""
    dims = [in_dim] + [hidden] * (num_layers - 1) + [out_dim]
    layers: list[nn.Module] = []
    for i in range(num_layers):
        layers.append(nn.Linear(dims[i], dims[i + 1]))
        if i < num_layers - 1:
            layers.append(nn.ReLU(inplace=True))
    return nn.Sequential(*layers)


class NestedField(nn.Module):
    """TriPlane+MLP (or PE+MLP) feature field with the scale-aware projection ``W``.

    Args:
        config: architecture and variant.
        embed_dim: E, the teacher embedding size (``W`` is ``[E, D]``).
        bbox_min, bbox_max: ``[3]`` world-space box that is mapped to ``[-1, 1]^3``.
    """

    def __init__(
        self,
        config: FieldConfig,
        embed_dim: int,
        bbox_min: Tensor | np.ndarray,  # [3]
        bbox_max: Tensor | np.ndarray,  # [3]
    ) -> None:
        super().__init__()
        if embed_dim < 1:
            raise ValueError(f"embedding dim E must be positive, got {embed_dim}")
        self.config = config
        self.embed_dim = int(embed_dim)
        bmin = torch.as_tensor(np.asarray(bbox_min, dtype=np.float32)).reshape(3)
        bmax = torch.as_tensor(np.asarray(bbox_max, dtype=np.float32)).reshape(3)
        if not bool((bmax > bmin).all()):
            raise ValueError(f"bounding box must have positive size, got {bmin.tolist()} .. {bmax.tolist()}")
        self.bbox_min: Tensor  # [3] registered buffer
        self.bbox_max: Tensor  # [3] registered buffer
        self.register_buffer("bbox_min", bmin)
        self.register_buffer("bbox_max", bmax)
        if config.backbone == "triplane":
            self.backbone: TriPlane | PositionalEncoding = TriPlane(
                config.plane_resolution, config.plane_channels, config.plane_reduce
            )
        else:
            self.backbone = PositionalEncoding(config.pe_frequencies)
        self.mlp = mlp(self.backbone.out_dim, config.hidden, config.dim, config.num_layers)
        # Zero-initialised projection (paper appendix: "gives the best results").
        self.W = nn.Parameter(torch.zeros(self.embed_dim, config.dim))  # [E, D]

    # ------------------------------------------------------------------ sizes
    @property
    def dim(self) -> int:
        """D, the feature-field dims."""
        return self.config.dim

    @property
    def feature_dim(self) -> int:
        """F, the dims of :meth:`encode` (what deferred rendering rasterizes)."""
        return int(self.backbone.out_dim)

    @property
    def variant(self) -> str:
        return self.config.variant

    @property
    def kind(self) -> FieldVariant:
        """The variant as an object (:mod:`n2f2.field.variants`)."""
        return self.config.kind

    # ------------------------------------------------------------------ field
    def normalize(self, xyz: Tensor) -> Tensor:  # xyz [N, 3] world -> [N, 3] in [-1, 1]
        """Map the bounding box to ``[-1, 1]^3`` per axis; points outside are clamped."""
        lo, hi = self.bbox_min.to(xyz.dtype), self.bbox_max.to(xyz.dtype)
        return (2.0 * (xyz - lo) / (hi - lo) - 1.0).clamp(-1.0, 1.0)

    def encode(self, xyz_normalised: Tensor) -> Tensor:  # [N, 3] in [-1, 1] -> [N, F]
        return self.backbone(xyz_normalised)

    def fixed_point_encoder(self, xyz: Tensor) -> Callable[[], Tensor]:  # xyz [N, 3] world
        """``lambda: encode(normalize(xyz))`` for points that stay put while the field trains
        (the frozen Gaussian centres), with what does not depend on the parameters computed
        once: the TriPlane's bilinear taps, or the whole (parameter-free) positional encoding."""
        xyz_n = self.normalize(xyz.detach())
        backbone = self.backbone
        if isinstance(backbone, TriPlane):
            taps = backbone.taps(xyz_n)
            return lambda: backbone.sample(taps)
        encoded = self.encode(xyz_n).detach()
        return lambda: encoded

    def decode(self, features: Tensor) -> Tensor:  # [..., F] -> theta [..., D]
        return self.mlp(features)

    def forward(self, xyz: Tensor) -> Tensor:  # xyz [N, 3] world -> theta [N, D]
        return self.decode(self.encode(self.normalize(xyz)))

    # ------------------------------------------------------------------ scale-aware projection
    def dims_for_scale(self, s: Tensor) -> Tensor:  # s [B] quantized scale in [0, 1) -> M [B] long
        """M(s) of the nested field (``D`` for the flat variant; :meth:`FieldVariant.dims_for_scale`)."""
        return self.kind.dims_for_scale(s, self.dim, self.config.step_size)

    def scale_aware(self, theta: Tensor, M: Tensor) -> Tensor:  # theta [B, D], M [B] -> phi [B, E]
        """``phi = W (B(s) * theta) = W[:, :M] theta[:M]`` per row."""
        return self.project(theta, prefix_mask(M, self.dim, theta.dtype))

    def project(self, theta: Tensor, mask: Tensor) -> Tensor:  # theta [..., D], mask [..., D] -> [..., E]
        """``W (mask * theta)``: one matmul for a whole batch with per-row masks."""
        return (theta * mask) @ self.W.t()

    def supervision_mask(self, s: Tensor) -> Tensor:  # s [B] quantized scale -> [B, D] float
        """Which dims a segment of quantized scale ``s`` supervises (the variant's B(s),
        :meth:`FieldVariant.supervision_mask`)."""
        return self.kind.supervision_mask(s, self.dim, self.config.step_size)

    def level_mask(self, level: Tensor) -> Tensor:  # level [B] in {0, 1, 2} -> [B, D] float
        """ "levels" variant: ones on the block of hierarchy level ``level`` (0 = part)."""
        return level_mask(level, self.dim)

    def level_features(self, theta: Tensor) -> Tensor:  # theta [..., D] -> [..., 3, E]
        """ "levels" variant: the three level features, index 0 = part, 1 = object, 2 = group."""
        out = []
        for level in range(NUM_LEVELS):
            a, b = level_blocks(self.dim)[level_to_block(level)]
            out.append(theta[..., a:b] @ self.W[:, a:b].t())
        return torch.stack(out, dim=-2)

    # ------------------------------------------------------------------ optimisation
    def param_groups(self, lr_backbone: float, lr_mlp: float) -> list[dict]:
        """Adam groups: the TriPlane at ``lr_backbone``, the MLP and ``W`` at ``lr_mlp``."""
        groups = [{"name": "mlp", "params": list(self.mlp.parameters()) + [self.W], "lr": lr_mlp}]
        backbone = [p for p in self.backbone.parameters() if p.requires_grad]
        if backbone:
            groups.insert(0, {"name": "triplane", "params": backbone, "lr": lr_backbone})
        return groups


# ---------------------------------------------------------------------------------- test time
@torch.no_grad()
def gaussian_features(
    field: NestedField,
    means: Tensor | Gaussians,  # [N, 3] world-space Gaussian centres (or a Gaussians model)
    chunk: int = 65536,
) -> Tensor:  # -> Theta [N, D]
    """Full D-dim features at the Gaussian centres, no deferral (appendix: at test time the
    MLP runs per Gaussian so features can be pre-multiplied, e.g. by gamma^3D)."""
    if not isinstance(means, Tensor):  # a Gaussians model
        means = means.means
    means = means.detach()
    device = next(field.parameters()).device
    out = [field(means[i : i + chunk].to(device)) for i in range(0, means.shape[0], chunk)]
    if not out:
        return torch.zeros(0, field.dim, device=device)
    return torch.cat(out, dim=0)


def bbox_from_points(
    points: Tensor | np.ndarray,  # [N, 3]
    quantile: float = 0.001,
    pad: float = 0.05,
) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned box of ``points`` between the ``quantile`` and ``1 - quantile`` marginals,
    padded by ``pad`` of its size per side, so a few floaters do not waste plane resolution
    (points outside are clamped onto the box by :meth:`NestedField.normalize`)."""
    pts = np.asarray(points.detach().cpu() if isinstance(points, Tensor) else points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) == 0:
        raise ValueError(f"need a non-empty [N, 3] point array, got shape {pts.shape}")
    lo = np.quantile(pts, quantile, axis=0)
    hi = np.quantile(pts, 1.0 - quantile, axis=0)
    size = np.maximum(hi - lo, 1e-6 * max(1.0, float(np.abs(pts).max())))
    return lo - pad * size, hi + pad * size


# ---------------------------------------------------------------------------------- files
def save_field(path: str | Path, field: NestedField, meta: Optional[dict] = None) -> None:
    """Write ``field`` (weights, including W) and ``meta`` atomically. ``meta`` is extended with
    config, E, bbox and variant so :func:`load_field` can rebuild the module."""
    meta = dict(meta or {})
    meta.update(
        {
            "config": field.config.to_dict(),
            "embed_dim": field.embed_dim,
            "variant": field.variant,
            "bbox_min": field.bbox_min.tolist(),
            "bbox_max": field.bbox_max.tolist(),
        }
    )
    state = {k: v.detach().cpu() for k, v in field.state_dict().items()}
    save_torch(path, {"format": FIELD_FORMAT, "version": FIELD_VERSION, "meta": meta, "state_dict": state})


def build_field(meta: dict) -> NestedField:
    """An untrained field with the architecture recorded in ``meta``."""
    return NestedField(
        FieldConfig.from_dict(meta["config"]),
        int(meta["embed_dim"]),
        np.asarray(meta["bbox_min"]),
        np.asarray(meta["bbox_max"]),
    )


def load_field(path: str | Path, device: str | torch.device = "cpu") -> tuple[NestedField, dict]:
    """Read a file written by :func:`save_field` -> ``(field in eval mode, meta)``."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "feature field file does not exist")
    blob = load_torch(path, "feature field")
    if not isinstance(blob, dict) or blob.get("format") != FIELD_FORMAT:
        raise InputError(path, "not an n2f2 feature field (expected the field.pt written by `n2f2 train`)")
    if blob.get("version", 0) > FIELD_VERSION:
        raise InputError(
            path,
            f"feature field format version {blob['version']} is newer than this n2f2 (reads up to {FIELD_VERSION})",
        )
    meta = blob.get("meta")
    if not isinstance(meta, dict) or not isinstance(blob.get("state_dict"), dict):
        raise InputError(path, "feature field is incomplete (no meta or state_dict); retrain it with `n2f2 train`")
    # Older versions could save a diverged field; its NaN would surface as a crash mid-query.
    bad = _non_finite(blob["state_dict"]) or _non_finite(
        {"bbox_min": meta.get("bbox_min"), "bbox_max": meta.get("bbox_max")}
    )
    if bad:
        raise InputError(path, f"feature field holds NaN or infinite values: {bad}; retrain it with `n2f2 train`")
    try:
        field = build_field(meta)
        field.load_state_dict(blob["state_dict"])
    except (KeyError, ValueError, RuntimeError) as e:
        raise InputError(path, f"feature field is inconsistent with its recorded config ({e})") from None
    return field.to(device).eval(), meta


def check_embed_dim(meta: dict, embed_dim: int, path: str | Path, what: str = "embedding") -> None:
    """Raise a clear error when an ``embed_dim``-sized embedding meets a field trained for
    another E (e.g. a text encoder or segment bank that is not the one used in training)."""
    if int(meta["embed_dim"]) != int(embed_dim):
        raise InputError(
            path,
            f"{what} dim {embed_dim} does not match the feature field's E = "
            f"{meta['embed_dim']} (trained with encoder {meta.get('encoder_spec')!r})",
        )
