"""The ``sam`` segmenter: SAM automatic mask generation as used by the paper and LangSplat (32 x 32
point grid, predicted-IoU threshold 0.7, min region area 100) through ``transformers.SamModel``,
with SAM's preprocessing and mask post-processing re-implemented in torch (``transformers``' SAM
image processor needs torchvision, which has no CPU build here) and a vectorised version of
LangSplat's mask NMS (:func:`n2f2.segments.segmenters.mask_nms`)."""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass
from typing import Optional

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from .encoders import device_autocast, device_sync
from .segmenters import SegmentSet, check_image, greedy_mask_nms, mask_nms, remove_small_regions

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
        return {"name": self.name, "model_id": self.model_id, **asdict(self.settings)}

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
            embeddings = self.model.get_image_embeddings(pixel_values)
        points = torch.as_tensor(self.point_grid(H, W), dtype=torch.float32, device=self.device)
        points = points * torch.tensor([w / W, h / H], device=self.device)  # into SAM's frame
        lap("image_encoder")

        all_masks, all_iou, all_stab = [], [], []
        settled = 0  # leading masks of all_masks that already passed NMS together
        for start in range(0, points.shape[0], st.points_per_batch):
            pts = points[start : start + st.points_per_batch]
            with device_autocast(self.device):
                out = self.model(
                    image_embeddings=embeddings,
                    input_points=pts[None, :, None, :],
                    input_labels=torch.ones(1, pts.shape[0], 1, dtype=torch.long, device=self.device),
                    multimask_output=True,
                )
            iou = out.iou_scores[0].reshape(-1).float()  # [B * 3]
            low = out.pred_masks[0].reshape(-1, *out.pred_masks.shape[-2:])  # [B * 3, h0, w0]
            keep = torch.nonzero(iou > st.pred_iou_thresh).flatten()
            lap("mask_decoder")
            counts["candidates"] += int(iou.numel())
            counts["iou_kept"] += int(keep.numel())
            if keep.numel() == 0:
                continue
            masks, stability, kept = self.filter_masks(low[keep], (h, w), (H, W))
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
