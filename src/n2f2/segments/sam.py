"""The ``sam`` segmenter: SAM automatic mask generation as used by the paper and LangSplat (32 x 32
point grid, predicted-IoU threshold 0.7, min region area 100) through ``transformers.SamModel``,
with SAM's preprocessing and mask post-processing re-implemented in torch (``transformers``' SAM
image processor needs torchvision, which has no CPU build here) and a vectorised version of
LangSplat's mask NMS (:func:`n2f2.segments.masks.mask_nms`).

The mask decoder runs through :class:`FastSamDecoder` by default: the same masks as
``SamModel``'s forward (kept as :func:`reference_decode`, ``SamSettings.fast_decoder=False``)
with the per-image work shared between prompts and the per-prompt work in low-rank form, less
than half the arithmetic and none of the per-prompt copies of the image embedding. The image
encoder runs under :func:`contiguous_rel_pos`, which drops a copy of its attention bias."""

from __future__ import annotations

import contextlib
import functools
import inspect
import time
from dataclasses import asdict, dataclass
from typing import Iterator, Optional

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from .encoders import device_autocast, device_sync
from .masks import SegmentSet, check_image, greedy_mask_nms, mask_nms, remove_small_regions

DEFAULT_SAM_MODEL = "facebook/sam-vit-huge"

# SAM's input normalisation (ImageNet statistics, images in [0, 1]).
SAM_PIXEL_MEAN = (0.485, 0.456, 0.406)
SAM_PIXEL_STD = (0.229, 0.224, 0.225)


@dataclass
class SamSettings:
    """SAM automatic mask generation, with the paper's / LangSplat's settings as defaults.

    The paper's settings are the 32 x 32 point grid, predicted-IoU threshold 0.7 and minimum
    mask region area 100; stability 0.85 and box-NMS 0.7 are LangSplat's (``preprocess.py``).
    LangSplat also runs SAM on one layer of crops (``crop_n_layers=1``: four overlapping
    half-size crops, each with its own 32 x 32 grid, about 5x the work); n2f2 runs the
    full-image layer only."""

    points_per_side: int = 32  # paper: 32 x 32 grid of point prompts
    points_per_batch: int = 64  # prompts decoded together (memory vs speed; SAM's default)
    pred_iou_thresh: float = 0.7  # paper: predicted-IoU threshold 0.7
    stability_score_thresh: float = 0.85  # LangSplat
    stability_score_offset: float = 1.0  # SAM default
    box_nms_thresh: float = 0.7  # SAM/LangSplat; applied to mask IoU here
    min_mask_region_area: int = 100  # paper: minimum mask region area 100
    mask_threshold: float = 0.0  # logit threshold for binarising masks
    # LangSplat's extra pass (``masks_update``): mask NMS on predicted IoU x stability.
    nms_iou_thr: float = 0.8
    nms_score_thr: float = 0.7
    nms_inner_thr: float = 0.5
    # Run the IoU NMS early whenever this many masks are pending (memory bound on big images).
    max_pending_masks: int = 384
    # Decode prompts with :class:`FastSamDecoder` (the same masks as ``SamModel``'s forward, up
    # to float rounding, several times faster on CPU); False runs ``SamModel`` itself
    # (:func:`reference_decode`). Not part of the segmenter's spec: it does not change results.
    fast_decoder: bool = True


# Values (float32 logits and the boolean maps made from them) held at once while upsampling
# mask logits to image resolution: 128 MB at most. Smaller chunks cost more per mask (many
# small parallel regions); at 750 x 500 this is ~18 masks per chunk.
UPSAMPLE_BUDGET = 1 << 25


class SamSegmenter:
    """SAM automatic mask generation with a ``transformers.SamModel`` (no crop layers).

    Per image: one image-encoder pass, the point grid decoded ``points_per_batch`` prompts at
    a time (3 masks each), and per batch only the masks above the IoU threshold upsampled to
    image resolution, a bounded number at a time; NMS runs whenever ``max_pending_masks``
    accumulate, on the model's device. On CUDA the model runs under float16 autocast;
    post-processing is float32. ``last_timing`` holds the seconds the last image
    spent in the image encoder, the mask decoder and post-processing; ``last_counts`` how many
    masks it had after each step."""

    name = "sam"

    def __init__(
        self, model, settings: Optional[SamSettings] = None, model_id: str = "", device: str | torch.device = "cpu"
    ) -> None:
        self.model = model.to(device).eval()
        self.settings = settings or SamSettings()
        self.model_id = model_id
        self.device = torch.device(device)
        self.last_timing: dict[str, float] = {}
        self.last_counts: dict[str, int] = {}

    @staticmethod
    def from_pretrained(
        model_id: str = DEFAULT_SAM_MODEL, device: str | torch.device = "cpu", settings: Optional[SamSettings] = None
    ) -> "SamSegmenter":
        from transformers import SamModel

        from .encoders import load_pretrained

        model = load_pretrained(SamModel, model_id, what="SAM", alternative="--segmenter classical", flag="--sam-model")
        return SamSegmenter(model, settings, model_id=model_id, device=device)

    @property
    def spec(self) -> dict:
        settings = asdict(self.settings)
        settings.pop("fast_decoder")  # how the masks are computed, not which
        return {"name": self.name, "model_id": self.model_id, **settings}

    # -- geometry of SAM's input frame
    def _input_size(self) -> int:
        return int(self.model.config.vision_config.image_size)

    def preprocess(
        self,
        image: np.ndarray,  # [H, W, 3] float in [0, 1]
    ) -> tuple[Tensor, tuple[int, int]]:
        """float [H, W, 3] in [0, 1] -> normalised, padded [1, 3, T, T] and the resized (h, w):
        SAM's ResizeLongestSide to T = model input size, ImageNet normalisation, zero pad
        bottom/right."""
        T = self._input_size()
        H, W = image.shape[:2]
        scale = T / max(H, W)
        h, w = int(H * scale + 0.5), int(W * scale + 0.5)
        x = torch.as_tensor(image, dtype=torch.float32, device=self.device).permute(2, 0, 1)[None]
        x = F.interpolate(x, size=(h, w), mode="bilinear", align_corners=False, antialias=True)
        mean = torch.tensor(SAM_PIXEL_MEAN, device=self.device).view(1, 3, 1, 1)
        std = torch.tensor(SAM_PIXEL_STD, device=self.device).view(1, 3, 1, 1)
        x = (x - mean) / std
        return F.pad(x, (0, T - w, 0, T - h)), (h, w)

    def postprocess_masks(
        self,
        low_res: Tensor,  # [N, h0, w0] mask logits in SAM's frame
        resized: tuple[int, int],
        original: tuple[int, int],
    ) -> Tensor:
        """SAM's ``postprocess_masks``: upsample low-res logits to the padded input size, crop
        the padding, upsample to the original image size. Returns logits [N, H, W].

        Only the low-res rows and columns that the unpadded region samples are upsampled
        (bilinear interpolation with the same scale factor reads nothing else), so padding
        costs no time or memory; the result equals SAM's."""
        T = self._input_size()
        h0, w0 = low_res.shape[-2:]
        fy, fx = T / h0, T / w0
        # Output row y < h samples input rows <= floor((y + 0.5) / fy - 0.5) + 1 <= h // fy + 1.
        rows = min(h0, int(resized[0] / fy) + 2)
        cols = min(w0, int(resized[1] / fx) + 2)
        x = F.interpolate(
            low_res[:, None, :rows, :cols].float(),
            scale_factor=(fy, fx),
            mode="bilinear",
            align_corners=False,
            recompute_scale_factor=False,
        )
        x = x[..., : resized[0], : resized[1]]
        return F.interpolate(x, size=original, mode="bilinear", align_corners=False)[:, 0]

    def point_grid(self, height: int, width: int) -> np.ndarray:
        """[n * n, 2] (x, y) prompts in image pixels, SAM's ``build_point_grid`` layout."""
        n = self.settings.points_per_side
        offset = 1.0 / (2 * n)
        side = np.linspace(offset, 1 - offset, n)
        xs, ys = np.meshgrid(side, side)
        return np.stack([xs.ravel() * width, ys.ravel() * height], axis=-1)

    def filter_masks(
        self,
        low_res: Tensor,  # [N, h0, w0] logits of masks that passed the IoU filter
        resized: tuple[int, int],
        original: tuple[int, int],
    ) -> tuple[Tensor, Tensor, Tensor]:
        """Upsample logits to image resolution (at most :data:`UPSAMPLE_BUDGET` values at a
        time), keep the stable, non-empty masks. Returns ``(masks [K, H, W] bool,
        stability [K], kept [K] indices into low_res)``, on the segmenter's device.

        Stability is SAM's: IoU of the masks thresholded at +- ``stability_score_offset``
        around ``mask_threshold``, on the image-resolution logits as SAM computes it."""
        st = self.settings
        T = self._input_size()
        H, W = original
        h0, w0 = low_res.shape[-2:]
        # Per mask: the input-frame logits (cropped to the image, plus a margin), the image-
        # resolution logits, three boolean maps of them and an int32 copy of one being summed.
        per_mask = int((resized[0] + 2 * T / h0) * (resized[1] + 2 * T / w0)) + 3 * H * W
        chunk = max(1, UPSAMPLE_BUDGET // per_mask)
        masks, stability, kept = [], [], []
        for start in range(0, low_res.shape[0], chunk):
            logits = self.postprocess_masks(low_res[start : start + chunk], resized, original)  # [c, H, W]
            # (int32 sums of booleans are several times faster than the default int64 ones)
            hi = (logits > st.mask_threshold + st.stability_score_offset).flatten(1).sum(1, dtype=torch.int32)
            lo = (logits > st.mask_threshold - st.stability_score_offset).flatten(1).sum(1, dtype=torch.int32)
            stab = hi.float() / lo.float().clamp_min(1)
            binary = logits > st.mask_threshold
            ok = (stab >= st.stability_score_thresh) & binary.flatten(1).any(1)
            masks.append(binary[ok])
            stability.append(stab[ok])
            kept.append(torch.nonzero(ok).flatten() + start)
            del logits, binary
        if not masks:
            return (
                torch.zeros(0, H, W, dtype=torch.bool, device=low_res.device),
                torch.zeros(0, device=low_res.device),
                torch.zeros(0, dtype=torch.long, device=low_res.device),
            )
        return torch.cat(masks), torch.cat(stability), torch.cat(kept)

    def _nms(
        self, masks: list[Tensor], iou: list[Tensor], stability: list[Tensor], settled: int
    ) -> tuple[Tensor, Tensor, Tensor]:
        all_masks, all_iou, all_stability = torch.cat(masks), torch.cat(iou), torch.cat(stability)
        masks.clear()  # the caller's list: only the concatenated copy stays alive
        kept = greedy_mask_nms(all_masks, all_iou, self.settings.box_nms_thresh, settled=settled)
        return all_masks[kept], all_iou[kept], all_stability[kept]

    def __call__(
        self,
        image: np.ndarray,  # [H, W, 3] float in [0, 1] or uint8
        view: Optional[int] = None,
    ) -> SegmentSet:
        with torch.inference_mode():
            return self._generate(check_image(image))

    # -- the model-specific steps of _generate (Sam2Segmenter supplies SAM 2's)
    def image_embeddings(self, pixel_values: Tensor):  # [1, 3, T, T] -> the decoder's image input
        with contiguous_rel_pos(self.model):
            return self.model.get_image_embeddings(pixel_values)

    def fast_decoder(self, embeddings):
        """The decoder of one image's prompts: ``.decode(points, min_iou)`` -> IoU ``[B, 3]``,
        the logits of the masks above ``min_iou`` ``[K, h0, w0]`` and their flat indices ``[K]``."""
        return FastSamDecoder(self.model, embeddings)

    def reference_decode(
        self,
        embeddings: Tensor,  # [1, 256, 64, 64]
        points: Tensor,  # [B, 2] (x, y) prompts in the model's input frame
    ) -> tuple[Tensor, Tensor]:  # [B, 3] IoU predictions, [B, 3, h0, w0] low-res mask logits
        """The model's own forward on one batch of prompts."""
        return reference_decode(self.model, embeddings, points)

    def _generate(self, image: np.ndarray) -> SegmentSet:  # [H, W, 3] float32
        H, W = image.shape[:2]
        st = self.settings
        timing = {"image_encoder": 0.0, "mask_decoder": 0.0, "postprocess": 0.0}
        counts = {"candidates": 0, "iou_kept": 0, "stable": 0, "after_nms": 0, "final": 0}
        self.last_timing, self.last_counts = timing, counts
        clock = time.perf_counter()

        def lap(part: str) -> None:
            nonlocal clock
            device_sync(self.device)
            now = time.perf_counter()
            timing[part] += now - clock
            clock = now

        pixel_values, (h, w) = self.preprocess(image)
        with device_autocast(self.device):
            embeddings = self.image_embeddings(pixel_values)
        points = torch.as_tensor(self.point_grid(H, W), dtype=torch.float32, device=self.device)
        points = points * torch.tensor([w / W, h / H], device=self.device)  # into SAM's frame
        lap("image_encoder")

        all_masks, all_iou, all_stab = [], [], []
        settled = 0  # leading masks of all_masks that already passed NMS together
        with device_autocast(self.device):
            decoder = self.fast_decoder(embeddings) if st.fast_decoder else None
        for start in range(0, points.shape[0], st.points_per_batch):
            pts = points[start : start + st.points_per_batch]
            with device_autocast(self.device):
                if decoder is not None:
                    # only the masks above the IoU threshold are upscaled
                    iou, low, keep = decoder.decode(pts, st.pred_iou_thresh)
                    iou = iou.reshape(-1).float()  # [B * 3]
                else:
                    iou, low = self.reference_decode(embeddings, pts)
                    iou = iou.reshape(-1).float()  # [B * 3]
                    keep = torch.nonzero(iou > st.pred_iou_thresh).flatten()
                    low = low.reshape(-1, *low.shape[-2:])[keep]  # [K, h0, w0]
            lap("mask_decoder")
            counts["candidates"] += int(iou.numel())
            counts["iou_kept"] += int(keep.numel())
            if keep.numel() == 0:
                continue
            masks, stability, kept = self.filter_masks(low, (h, w), (H, W))
            counts["stable"] += int(kept.numel())
            all_masks.append(masks)
            all_iou.append(iou[keep][kept])
            all_stab.append(stability)
            if sum(len(m) for m in all_masks) > st.max_pending_masks:
                # Bound memory on large images: NMS what has accumulated so far (SAM itself
                # runs NMS per crop, then across crops, in the same spirit).
                kept_masks, kept_iou, kept_stab = self._nms(all_masks, all_iou, all_stab, settled)
                all_masks, all_iou, all_stab = [kept_masks], [kept_iou], [kept_stab]
                settled = len(kept_masks)
            lap("postprocess")
        if not all_masks or sum(len(m) for m in all_masks) == 0:
            return SegmentSet.empty(H, W)
        masks, iou, stability = self._nms(all_masks, all_iou, all_stab, settled)
        masks, iou, stability = masks.cpu(), iou.cpu(), stability.cpu()  # cv2 and packing: CPU
        counts["after_nms"] = len(masks)
        if st.min_mask_region_area > 0:
            cleaned = np.stack([remove_small_regions(m, st.min_mask_region_area) for m in masks.numpy()])
            big = cleaned.reshape(len(cleaned), -1).sum(1) >= st.min_mask_region_area
            masks, iou, stability = torch.from_numpy(cleaned[big]), iou[big], stability[big]
        if len(masks) == 0:
            lap("postprocess")
            return SegmentSet.empty(H, W)
        score = iou * stability
        kept = mask_nms(masks, score, st.nms_iou_thr, st.nms_score_thr, st.nms_inner_thr)
        out = SegmentSet.from_masks(masks[kept].numpy(), score[kept].numpy())
        counts["final"] = out.num_segments
        lap("postprocess")
        return out


# ----------------------------------------------------------------------------- image encoder
# The ViT's attention adds a decomposed relative-position bias, rel_h[q, key row] +
# rel_w[q, key column], built by broadcasting two einsum outputs. Those come out head-major
# (not contiguous), so the broadcast sum takes their layout and the reshape to
# [batch, heads, queries, keys] that follows copies it: 1 GB per global-attention layer of
# ViT-H (16 heads x 4096^2 floats), 61 MB per windowed one. Building the sum in a contiguous
# buffer makes that reshape a view; the values are bit for bit the same.


def _decomposed_rel_pos(
    attn,
    query: Tensor,  # [B, qh * qw, D]
    rel_pos_h: Tensor,  # [2 * max(qh, kh) - 1, D]
    rel_pos_w: Tensor,  # [2 * max(qw, kw) - 1, D]
    q_size: tuple[int, int],
    k_size: tuple[int, int],
) -> Tensor:  # [B, qh, qw, kh, kw], contiguous
    """``SamVisionAttention.get_decomposed_rel_pos`` with a contiguous result."""
    (qh, qw), (kh, kw) = q_size, k_size
    table_h = attn.get_rel_pos(qh, kh, rel_pos_h)  # [qh, kh, D]
    table_w = attn.get_rel_pos(qw, kw, rel_pos_w)  # [qw, kw, D]
    q = query.reshape(query.shape[0], qh, qw, -1)
    rel_h = torch.einsum("bhwc,hkc->bhwk", q, table_h).contiguous()
    rel_w = torch.einsum("bhwc,wkc->bhwk", q, table_w).contiguous()
    out = torch.empty(*rel_h.shape, kw, dtype=torch.result_type(rel_h, rel_w), device=rel_h.device)
    return torch.add(rel_h[..., None], rel_w[..., None, :], out=out)


_REL_POS_PARAMETERS = ["self", "query", "rel_pos_h", "rel_pos_w", "q_size", "k_size"]


@contextlib.contextmanager
def contiguous_rel_pos(model) -> Iterator[int]:
    """While active, the vision encoder's attention layers build their relative-position bias
    with :func:`_decomposed_rel_pos` (same values, one copy fewer); yields how many layers.
    Layers whose ``get_decomposed_rel_pos`` has another signature are left as they are."""
    patched = []
    for module in model.vision_encoder.modules():
        method = getattr(type(module), "get_decomposed_rel_pos", None)
        if not getattr(module, "use_rel_pos", False) or method is None or not hasattr(module, "get_rel_pos"):
            continue
        if list(inspect.signature(method).parameters) != _REL_POS_PARAMETERS:
            continue
        module.get_decomposed_rel_pos = functools.partial(_decomposed_rel_pos, module)
        patched.append(module)
    try:
        yield len(patched)
    finally:
        for module in patched:
            del module.get_decomposed_rel_pos


# ----------------------------------------------------------------------------- mask decoder
# SAM's mask decoder per prompt: a two-way transformer between the prompt's 7 tokens (IoU
# token, 4 mask tokens, the point and a padding point) and the 64 x 64 = 4096 image tokens,
# then two 2x2 transposed convolutions of the image tokens to 256 x 256 and a per-mask product
# with the mask tokens. ``transformers`` repeats the image embedding and its positional
# embedding per prompt and runs every 4096 x 256 -> 128 projection per prompt (~1.8 GMAC a
# prompt, most of it copies, adds and projections of the same or low-rank data).
#
# The fast path below computes the same function with the model's own weights, in a different
# order:
# * block 0's image-side inputs (image + "no mask" embedding, + positional embedding) are the
#   same for every prompt: their key / value / query projections are computed once per image
#   and shared (broadcast, never repeated);
# * after block 0 the image tokens differ per prompt, but only by a low-rank update (attention
#   of 4096 tokens over 7 token values per head) followed by a layer norm; so each per-prompt
#   projection of image tokens is folded into the few per-prompt vectors it meets instead:
#   scores q . (W_k x) are x . (W_k^T q), values sum_n p_n W_v x_n are W_v (sum_n p_n x_n),
#   and image-to-token outputs are sum_{head, token} p W_o v: a [4096, 56] x [56, 256] product.
#   The positional embedding's share of the logits is projected once per image. Key biases
#   add a constant to each softmax row and drop out; value biases pass through the
#   (normalised) attention weights, so they are added to the outputs;
# * the transposed convolutions (kernel 2, stride 2: no overlap) are per-token matrix products
#   in a channels-last layout, with the layer norm over the last dimension, and run only for
#   prompts with a mask above the segmenter's IoU threshold (the IoU head needs only the
#   tokens), and only the 3 multimask outputs are formed.
# About 0.83 GMAC a prompt against 1.81 (benchmarks/profile_sam_decoder.py counts both); the
# results equal the reference's to float rounding (sums run in a different order), see
# tests/test_sam_fast.py.


@torch.no_grad()
def reference_decode(
    model,
    image_embeddings: Tensor,  # [1, 256, 64, 64] from ``model.get_image_embeddings``
    points: Tensor,  # [B, 2] (x, y) point prompts in SAM's input frame
) -> tuple[Tensor, Tensor]:
    """``SamModel``'s own forward on one batch of point prompts (3 masks each), as the
    segmenter ran it before the fast path. Returns IoU predictions [B, 3] and low-res mask
    logits [B, 3, 256, 256]."""
    labels = torch.ones(1, points.shape[0], 1, dtype=torch.long, device=points.device)
    out = model(
        image_embeddings=image_embeddings,
        input_points=points[None, :, None, :],
        input_labels=labels,
        multimask_output=True,
    )
    return out.iou_scores[0], out.pred_masks[0]


def _heads(
    x: Tensor,  # [..., T, H * D]
    heads: int,
) -> Tensor:  # [..., T, H, D]
    return x.unflatten(-1, (heads, x.shape[-1] // heads))


def _head_weight(linear: torch.nn.Linear, heads: int) -> Tensor:  # [H, D, C]
    """A projection's weight [H * D, C] split by output head."""
    return linear.weight.unflatten(0, (heads, -1))


def _add_bmm_(
    acc: Tensor,  # [B, n, m], overwritten when the dtypes allow
    a: Tensor,  # [B, n, k]
    b: Tensor,  # [B, k, m]
) -> Tensor:  # [B, n, m]
    """acc + a @ b, in place unless autocast left the operands in different dtypes."""
    if acc.dtype == a.dtype == b.dtype:
        return acc.baddbmm_(a, b)
    return torch.baddbmm(acc, a, b)


def _by_head(
    x: Tensor,  # [N, H * D] projected image tokens
    heads: int,
) -> Tensor:  # [H, D, N]
    return x.unflatten(-1, (heads, -1)).permute(1, 2, 0).contiguous()


class FastSamDecoder:
    """SAM's mask decoder (``multimask_output=True``) for many point prompts on one image,
    with the per-image work done once and the per-prompt work in low-rank form (see the
    notes above). Uses the modules and weights of ``model`` itself, so it always matches the
    loaded model. Build one per image embedding; :meth:`decode` takes batches of points.

    ``chunk`` prompts run through the transformer together and ``mask_chunk`` through the
    mask upscaling, ``tile_tokens`` image tokens of each at a time (a band of token rows; all
    when None). Small groups keep the per-prompt tensors (4 MB of image tokens, 12 MB of
    upscaled features) in cache; large ones run fewer, larger operations, which matters when
    other processes compete for the cores (every parallel operation waits for all of torch's
    threads). The defaults were the fastest of those tried on 2 cores, idle and with one
    competing process (benchmarks/profile_sam_decoder.py).
    """

    @torch.no_grad()
    def __init__(
        self,
        model,
        image_embeddings: Tensor,  # [1, 256, 64, 64] from ``model.get_image_embeddings``
        chunk: int = 4,
        mask_chunk: int = 2,
        tile_tokens: Optional[int] = None,
    ) -> None:
        if image_embeddings.shape[0] != 1:
            raise ValueError("FastSamDecoder takes the embedding of one image")
        self.model = model
        self.chunk = max(1, chunk)
        self.mask_chunk = max(1, mask_chunk)
        dec = model.mask_decoder
        self.dec = dec
        blocks = list(dec.transformer.layers)
        if not blocks or not blocks[0].skip_first_layer_pe:
            raise ValueError("unexpected SAM mask decoder: block 0 must skip the token positional embedding")
        self.blocks = blocks
        C = dec.hidden_size
        self.size = image_embeddings.shape[-2:]
        self.tile_rows = self.size[0] if tile_tokens is None else max(1, tile_tokens // self.size[1])
        dense = model.prompt_encoder.no_mask_embed.weight.reshape(1, C, 1, 1)
        # Image tokens and their positional embeddings, token-major: [N, C].
        self.image = (image_embeddings + dense).flatten(2)[0].t().contiguous()
        pos = model.get_image_wide_positional_embeddings().flatten(2)[0].t()
        # Block 0's image side is the same for every prompt: its projections are shared.
        b0 = blocks[0]
        keyed = self.image + pos  # image tokens + positional embedding
        t2i, i2t = b0.cross_attn_token_to_image, b0.cross_attn_image_to_token
        self.k0 = _heads(t2i.k_proj(keyed), t2i.num_attention_heads).transpose(0, 1).contiguous()  # [H, N, D]
        self.v0 = _heads(t2i.v_proj(self.image), t2i.num_attention_heads).transpose(0, 1).contiguous()  # [H, N, D]
        self.q0 = _by_head(i2t.q_proj(keyed) * i2t.scaling, i2t.num_attention_heads)  # [H, D, N]
        self.image_out0 = self.image + i2t.out_proj.bias  # the output bias joins the residual once
        # Later blocks see per-prompt image tokens x, and attention logits split into an x
        # part (per prompt) and a positional part (shared): for tokens -> image,
        # q . (W_k (x + pos) + b_k) = (W_k^T q) . x + q . (W_k pos) + const, the constant
        # dropping out of the softmax; for image -> tokens,
        # (W_q (x + pos) + b_q) . k = x . (W_q^T k) + (W_q pos + b_q) . k.
        self.pos_keys: list[Tensor] = []  # [H, D, N] per block after the first
        self.pos_queries: list[Tensor] = []  # [H, D, N] per block after the first
        for b in blocks[1:]:
            t2i, i2t = b.cross_attn_token_to_image, b.cross_attn_image_to_token
            self.pos_keys.append(_by_head(F.linear(pos, t2i.k_proj.weight), t2i.num_attention_heads))
            self.pos_queries.append(_by_head(i2t.q_proj(pos), i2t.num_attention_heads))
        final = dec.transformer.final_attn_token_to_image
        self.pos_keys_final = _by_head(F.linear(pos, final.k_proj.weight), final.num_attention_heads)
        # The transposed convolutions (kernel = stride = 2) as per-token matrices, output
        # channels last: column (ky, kx, out).
        w1, w2 = dec.upscale_conv1.weight, dec.upscale_conv2.weight  # [in, out, 2, 2]
        self.up1_w = w1.permute(0, 2, 3, 1).flatten(1)  # [C, 4 * C1]
        self.up1_b = dec.upscale_conv1.bias.repeat(4)
        self.up2_w = w2.permute(0, 2, 3, 1).flatten(1)  # [C1, 4 * C2]
        self.up2_b = dec.upscale_conv2.bias.repeat(4)
        act = dec.activation
        self.gelu_in_place = isinstance(act, torch.nn.GELU)

    # -- the transformer
    def _tokens(
        self,
        points: Tensor,  # [B, 2] (x, y) in SAM's input frame
    ) -> Tensor:  # [B, T, C]
        """The prompt tokens: IoU token, mask tokens, the point's and the padding point's
        embeddings (the model's own prompt encoder)."""
        dec = self.dec
        labels = torch.ones(1, points.shape[0], 1, dtype=torch.long, device=points.device)
        sparse, _ = self.model.prompt_encoder(
            input_points=points[None, :, None, :], input_labels=labels, input_boxes=None, input_masks=None
        )
        out = torch.cat([dec.iou_token.weight, dec.mask_tokens.weight])
        out = out.expand(points.shape[0], *out.shape)
        return torch.cat([out, sparse[0]], dim=1).to(dec.iou_token.weight.dtype)

    @staticmethod
    def _self_attention(
        block,
        queries: Tensor,  # [B, T, C]
        pe: Tensor,  # [B, T, C] the tokens' positional embedding
    ) -> Tensor:  # [B, T, C]
        if block.skip_first_layer_pe:
            queries = block.self_attn(query=queries[None], key=queries[None], value=queries[None])[0][0]
        else:
            q = (queries + pe)[None]
            queries = queries + block.self_attn(query=q, key=q, value=queries[None])[0][0]
        return block.layer_norm1(queries)

    @staticmethod
    def _logits(
        rows: Tensor,  # [B, T, H, D] per-head query or key vectors of the tokens
        weight: Tensor,  # [H * D, C] the projection applied to the image tokens
        image: Tensor,  # [B, N, C] per-prompt image tokens
        shared: Tensor,  # [H, D, N] the positional (and bias) part of that projection
    ) -> Tensor:  # [B, H * T, N]
        """Attention logits rows . (W x_n) + rows . shared_n between T tokens and N image
        tokens, as one [H*T, C] x [C, N] product per prompt (W folded into the rows)."""
        B, T, H, D = rows.shape
        a = torch.einsum("bthd,hdc->bhtc", rows, weight.view(H, D, -1)).flatten(1, 2)  # [B, H*T, C]
        s = torch.bmm(rows.permute(2, 0, 1, 3).reshape(H, B * T, D), shared)  # [H, B*T, N]
        s = s.view(H, B, T, -1).transpose(0, 1).reshape(B, H * T, -1)
        return _add_bmm_(s, a, image.transpose(1, 2))

    def _token_to_image(
        self,
        attn,
        queries: Tensor,  # [B, T, C] tokens with positional embedding
        image: Tensor,  # [B, N, C] per-prompt image tokens
        pos_keys: Tensor,  # [H, D, N] key projection of the image positional embedding
    ) -> Tensor:  # [B, T, C] attention output
        """Tokens attending to per-prompt image tokens without projecting them: the logits
        fold W_k into the queries (:meth:`_logits`), the output is W_v (sum_n p_n x_n) + b_v."""
        B, T, _ = queries.shape
        H = attn.num_attention_heads
        q = _heads(attn.q_proj(queries) * attn.scaling, H)  # [B, T, H, D]
        p = torch.softmax(self._logits(q, attn.k_proj.weight, image, pos_keys), dim=-1)  # [B, H*T, N]
        r = torch.bmm(p, image).unflatten(1, (H, T))  # [B, H, T, C]
        v = torch.einsum("bhtc,hdc->bthd", r, _head_weight(attn.v_proj, H)).flatten(2) + attn.v_proj.bias
        return attn.out_proj(v)

    @staticmethod
    def _image_update(
        attn,
        logits: Tensor,  # [B, H, T, N] image-to-token attention logits (N image tokens query T tokens)
        values: Tensor,  # [B, T, C] token values (before the value projection)
        residual: Tensor,  # [B or 1, N, C] image tokens the update adds to
        first: bool,  # block 0: residual is shared (written to a new tensor), its output bias included
    ) -> Tensor:  # [B, N, C]
        """residual + image-to-token attention output, as one [N, H*T] x [H*T, C] product per
        prompt: the value and output projections are applied to the T token values first.
        (The logits come token-major so that the softmax over T runs along whole rows of N.)"""
        B, H, T, N = logits.shape
        p = torch.softmax(logits, dim=2).view(B, H * T, N)
        v = _heads(attn.v_proj(values), H)  # [B, T, H, D]
        wo = attn.out_proj.weight.unflatten(1, (H, -1))  # [C, H, D]
        u = torch.einsum("bthd,chd->bhtc", v, wo).flatten(1, 2)  # [B, H*T, C]
        if first:
            return torch.baddbmm(residual, p.transpose(1, 2), u)
        # Each head's weights sum to one over the T tokens: spread the output bias over heads.
        u = u + attn.out_proj.bias / H
        return _add_bmm_(residual, p.transpose(1, 2), u)

    def _transformer(
        self,
        tokens: Tensor,  # [B, T, C] prompt tokens (also their positional embedding)
    ) -> tuple[Tensor, Tensor]:  # [B, 1 + M, C] IoU and mask tokens, [B, N, C] image tokens
        B, T, C = tokens.shape
        pe = queries = tokens
        image = self.image[None]  # [1, N, C]: the same for all prompts in block 0
        for i, block in enumerate(self.blocks):
            queries = self._self_attention(block, queries, pe)
            t2i, i2t = block.cross_attn_token_to_image, block.cross_attn_image_to_token
            # tokens -> image
            if i == 0:
                H = t2i.num_attention_heads
                q = _heads(t2i.q_proj(queries + pe), H).flatten(0, 1).transpose(0, 1)  # [H, B*T, D]
                o = F.scaled_dot_product_attention(q, self.k0, self.v0, scale=t2i.scaling)
                o = t2i.out_proj(o.transpose(0, 1).reshape(B, T, -1))
            else:
                o = self._token_to_image(t2i, queries + pe, image, self.pos_keys[i - 1])
            queries = block.layer_norm2(queries + o)
            queries = block.layer_norm3(queries + block.mlp(queries))
            # image -> tokens: image tokens query the prompt tokens
            H = i2t.num_attention_heads
            k = _heads(i2t.k_proj(queries + pe), H)  # [B, T, H, D]
            if i == 0:
                s = torch.bmm(k.permute(2, 0, 1, 3).flatten(1, 2), self.q0)  # [H, B*T, N]
                image = self._image_update(i2t, s.view(H, B, T, -1).transpose(0, 1), queries, self.image_out0, True)
            else:
                s = self._logits(k * i2t.scaling, i2t.q_proj.weight, image, self.pos_queries[i - 1])
                image = self._image_update(i2t, s.view(B, H, T, -1), queries, image, False)
            image = block.layer_norm4(image)
        final = self.dec.transformer.final_attn_token_to_image
        n_out = 1 + self.dec.num_mask_tokens  # only the IoU and mask tokens are read
        o = self._token_to_image(final, (queries + pe)[:, :n_out], image, self.pos_keys_final)
        queries = self.dec.transformer.layer_norm_final_attn(queries[:, :n_out] + o)
        return queries, image

    # -- masks
    def _gelu(self, x: Tensor) -> Tensor:
        if self.gelu_in_place:
            return torch.ops.aten.gelu_(x, approximate=self.dec.activation.approximate)
        return self.dec.activation(x)

    def _masks(
        self,
        image: Tensor,  # [b, N, C] image tokens of b prompts after the transformer
        hyper: Tensor,  # [b, M, C2] their per-mask weights (from the mask tokens)
        out: Tensor,  # [b, M, 4h, 4w] their low-res mask logits, written here
    ) -> None:
        """Both transposed convolutions, the layer norm, GELUs and the per-mask products, over
        a band of token rows at a time. Token (y, x) and kernel offsets (ky, kx), (ky2, kx2)
        give mask pixel (4y + 2ky + ky2, 4x + 2kx + kx2)."""
        ln = self.dec.upscale_layer_norm
        h, w = self.size
        b, M = hyper.shape[:2]
        for r0 in range(0, h, self.tile_rows):
            r = min(self.tile_rows, h - r0)
            n = r * w
            x = image[:, r0 * w : r0 * w + n].reshape(b * n, -1)
            x = torch.addmm(self.up1_b, x, self.up1_w)  # [bn, 4 * C1]
            x = F.layer_norm(x.view(4 * b * n, -1), ln.normalized_shape, ln.weight, ln.bias, ln.eps)
            x = self._gelu(torch.addmm(self.up2_b, self._gelu(x), self.up2_w))  # [4bn, 4 * C2]
            m = torch.bmm(hyper, x.view(b, 16 * n, -1).transpose(1, 2))  # [b, M, 16n]: (y, x, ky, kx, ky2, kx2)
            band = out[:, :, 4 * r0 : 4 * (r0 + r)].view(b, M, r, 2, 2, w, 2, 2)  # (y, ky, ky2, x, kx, kx2)
            band.copy_(m.view(b, M, r, w, 2, 2, 2, 2).permute(0, 1, 2, 4, 6, 3, 5, 7))

    @torch.no_grad()
    def decode(
        self,
        points: Tensor,  # [B, 2] (x, y) point prompts in SAM's input frame
        min_iou: Optional[float] = None,
    ) -> tuple[Tensor, Tensor, Tensor]:
        """IoU predictions [B, 3] for every prompt, and the low-res logits [K, 256, 256] of
        the masks whose prediction is above ``min_iou`` (all masks when None), with their flat
        indices [K] into ``iou.reshape(-1)`` (prompt-major, ascending). Masks below the
        threshold are not computed, nor a prompt's upscaled features when none passes."""
        dec = self.dec
        multi = range(1, 1 + dec.num_multimask_outputs)  # mask token 0 is the single-mask output
        h, w = self.size
        ious, logits, indices = [], [], []
        for start in range(0, points.shape[0], self.chunk):
            queries, image = self._transformer(self._tokens(points[start : start + self.chunk]))
            iou = dec.iou_prediction_head(queries[:, 0])[:, multi.start : multi.stop]  # [b, 3]
            ious.append(iou)
            M = iou.shape[1]
            wanted = torch.ones_like(iou, dtype=torch.bool) if min_iou is None else iou.float() > min_iou
            prompts = torch.nonzero(wanted.any(1)).flatten().tolist()
            if not prompts:
                continue
            hyper = torch.stack([dec.output_hypernetworks_mlps[j](queries[prompts, j + 1]) for j in multi], 1)
            out = torch.empty(len(prompts), M, 4 * h, 4 * w, dtype=hyper.dtype, device=hyper.device)
            for g in range(0, len(prompts), self.mask_chunk):
                group = prompts[g : g + self.mask_chunk]
                consecutive = group[-1] - group[0] == len(group) - 1
                tokens = image[group[0] : group[-1] + 1] if consecutive else image[group]
                self._masks(tokens, hyper[g : g + len(group)], out[g : g + len(group)])
            keep = wanted[prompts]  # [n, 3]
            flat = (torch.tensor(prompts, device=iou.device)[:, None] + start) * M + torch.arange(M, device=iou.device)
            logits.append(out.flatten(0, 1) if bool(keep.all()) else out[keep])  # [k, 4h, 4w]
            indices.append(flat[keep])
        iou = torch.cat(ious)
        if not logits:
            return iou, iou.new_zeros(0, 4 * h, 4 * w), torch.zeros(0, dtype=torch.long, device=iou.device)
        return iou, torch.cat(logits), torch.cat(indices)

    def __call__(
        self,
        points: Tensor,  # [B, 2] (x, y) point prompts in SAM's input frame
    ) -> tuple[Tensor, Tensor]:
        """All masks: IoU predictions [B, 3] and low-res logits [B, 3, 256, 256]."""
        iou, logits, _ = self.decode(points)
        return iou, logits.view(iou.shape[0], iou.shape[1], *logits.shape[-2:])


def fast_decode(
    model,
    image_embeddings: Tensor,  # [1, 256, 64, 64] from ``model.get_image_embeddings``
    points: Tensor,  # [B, 2] (x, y) point prompts in SAM's input frame
) -> tuple[Tensor, Tensor]:
    """:class:`FastSamDecoder` on one batch: the same outputs as :func:`reference_decode`
    (IoU predictions [B, 3], low-res logits [B, 3, 256, 256]) up to float rounding."""
    return FastSamDecoder(model, image_embeddings)(points)
