"""The ``sam2`` segmenter: SAM 2.1 automatic mask generation through ``transformers.Sam2Model``,
with the ``sam`` segmenter's settings (the paper's / LangSplat's, :class:`~.sam.SamSettings`) and
post-processing (:class:`~.sam.SamSegmenter`: IoU and stability filters, mask NMS, small
regions, LangSplat's mask NMS). A lighter alternative to SAM ViT-H: the default Hiera-tiny image
encoder has 27 M parameters against ViT-H's 637 M. The mask decoder is about as large as
SAM's and runs for 1,024 prompts an image, so on CPU it dominates; :class:`FastSam2Decoder`
computes it with the model's own weights about 4x faster than ``Sam2Model``'s forward
(``fast_decoder=False`` runs the forward).

What differs from SAM, as SAM 2's own image predictor does it (``sam2/utils/transforms.py``):

* input: the image is resized to the model's square input (T = 1024) *without* keeping its
  aspect ratio and without padding, then ImageNet-normalised;
* prompts: an image point (x, y) goes to (x T / W, y T / H);
* masks: the 256 x 256 logits cover the whole image, so one bilinear upsampling to the image
  size gives SAM 2's image-resolution logits;
* the image encoder gives three feature levels: the 64 x 64 image embedding and two
  higher-resolution maps the mask decoder adds while upsampling.

SAM 2's own automatic mask generator also fills holes and removes islands of up to
``min_mask_region_area`` low-res pixels in the 256 x 256 logits (only where its CUDA extension is
built); here, as for ``sam``, small regions are removed at image resolution after NMS.

Released checkpoints loadable with ``Sam2Model``: ``facebook/sam2.1-hiera-tiny`` (default),
``-small``, ``-base-plus`` and ``-large`` (stored as ``sam2_video`` models; ``Sam2Model`` takes
their image part and ignores the video memory weights).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from .sam import SAM_PIXEL_MEAN, SAM_PIXEL_STD, SamSegmenter, SamSettings

DEFAULT_SAM2_MODEL = "facebook/sam2.1-hiera-tiny"


@dataclass
class Sam2Settings(SamSettings):
    """:class:`~.sam.SamSettings`, the paper's / LangSplat's automatic-mask settings, for SAM 2.1
    (``fast_decoder``: :class:`FastSam2Decoder`, the same masks as ``Sam2Model``'s forward up to
    float rounding; False runs the forward, :meth:`Sam2Segmenter.reference_decode`)."""


class Sam2Segmenter(SamSegmenter):
    """SAM 2.1 automatic mask generation with a ``transformers.Sam2Model`` (no crop layers).

    Per image, as :class:`~.sam.SamSegmenter`: one image-encoder pass; the point grid decoded
    ``points_per_batch`` prompts at a time from the cached image features (by
    :class:`FastSam2Decoder`, or with ``fast_decoder=False`` by :meth:`reference_decode`,
    ``Sam2Model``'s own forward); per batch only the masks above the IoU threshold upsampled and checked for
    stability (:meth:`~.sam.SamSegmenter.filter_masks`); NMS whenever ``max_pending_masks``
    accumulate; then small regions and LangSplat's mask NMS. This class supplies SAM 2's input
    frame, decoding and mask upsampling; the filters and NMS are ``sam``'s. ``last_timing`` and
    ``last_counts`` are filled as for ``sam``, whose per-image loop this is. ``settings``:
    :class:`Sam2Settings`, or a :class:`~.sam.SamSettings` (decoded by the fast decoder unless
    it has ``fast_decoder=False``)."""

    name = "sam2"

    def __init__(
        self,
        model,
        settings: Optional[SamSettings] = None,
        model_id: str = "",
        device: str | torch.device = "cpu",
    ) -> None:
        super().__init__(model, settings or Sam2Settings(), model_id=model_id, device=device)

    @staticmethod
    def from_pretrained(
        model_id: str = DEFAULT_SAM2_MODEL,
        device: str | torch.device = "cpu",
        settings: Optional[SamSettings] = None,
    ) -> "Sam2Segmenter":
        """Load ``model_id`` (a Hugging Face id or a ``save_pretrained`` folder; SAM 2.1
        folders of type ``sam2_video`` load too) into a segmenter, or raise one
        :class:`~n2f2.errors.MissingModelError` saying what to download."""
        from transformers import Sam2Model

        from .encoders import load_pretrained

        alternative = "--segmenter sam or --segmenter classical"
        model = load_pretrained(Sam2Model, model_id, what="SAM 2.1", alternative=alternative, flag="--sam-model")
        return Sam2Segmenter(model, settings, model_id=model_id, device=device)

    def _input_size(self) -> int:
        return int(self.model.config.prompt_encoder_config.image_size)

    def preprocess(
        self,
        image: np.ndarray,  # [H, W, 3] float in [0, 1]
    ) -> tuple[Tensor, tuple[int, int]]:
        """float [H, W, 3] in [0, 1] -> normalised [1, 3, T, T] and the frame size (T, T): SAM 2's
        plain resize to the square input (bilinear, antialiased) and ImageNet normalisation."""
        T = self._input_size()
        x = torch.as_tensor(image, dtype=torch.float32, device=self.device).permute(2, 0, 1)[None]
        x = F.interpolate(x, size=(T, T), mode="bilinear", align_corners=False, antialias=True)
        mean = torch.tensor(SAM_PIXEL_MEAN, device=self.device).view(1, 3, 1, 1)
        std = torch.tensor(SAM_PIXEL_STD, device=self.device).view(1, 3, 1, 1)
        return (x - mean) / std, (T, T)

    def postprocess_masks(
        self,
        low_res: Tensor,  # [N, h0, w0] mask logits covering the whole image
        resized: tuple[int, int],
        original: tuple[int, int],
    ) -> Tensor:  # [N, H, W]
        """SAM 2's ``postprocess_masks``: bilinear upsampling of the logits to the image size
        (nothing to crop: the input frame has no padding). ``resized`` is unused."""
        return F.interpolate(low_res[:, None].float(), size=original, mode="bilinear", align_corners=False)[:, 0]

    def image_embeddings(self, pixel_values: Tensor):  # [1, 3, T, T] -> the decoder's image inputs
        return self.model.get_image_embeddings(pixel_values)

    def fast_decoder(self, embeddings):
        return FastSam2Decoder(self.model, embeddings)

    def reference_decode(
        self,
        embeddings: list[Tensor],  # from get_image_embeddings: [1, C/8, 4e, 4e], [1, C/4, 2e, 2e], [1, C, e, e]
        points: Tensor,  # [B, 2] (x, y) prompts in the model's input frame
    ) -> tuple[Tensor, Tensor]:  # [B, 3] IoU predictions, [B, 3, 4e, 4e] low-res mask logits
        """``Sam2Model``'s own forward on one batch of point prompts (one positive point each,
        3 masks each), from the cached image features."""
        labels = torch.ones(1, points.shape[0], 1, dtype=torch.long, device=points.device)
        out = self.model(
            image_embeddings=embeddings,
            input_points=points[None, :, None, :],
            input_labels=labels,
            multimask_output=True,
        )
        return out.iou_scores[0], out.pred_masks[0]


# ----------------------------------------------------------------------------- fast decoder
# SAM 2's mask decoder per prompt: a two-way transformer between 8 prompt tokens (object-score
# token, IoU token, 4 mask tokens, the point and a padding point) and the e x e = 4096 image
# tokens, then two 2x2 transposed convolutions of the image tokens (adding the encoder's two
# high-resolution maps) and a per-mask product with the mask tokens. ``Sam2Model``'s forward
# copies the image tokens, their positional embedding and both high-resolution maps once per
# prompt (~1 GB for 64 prompts) and projects every image token per prompt (~1.3 GMAC a prompt
# in the transformer, ~0.4 in the upscaling).
#
# :class:`FastSam2Decoder` computes the same function with the model's own modules and weights:
# * block 0's image-side inputs are the same for every prompt, so their projections are made
#   once per image; nothing per-image is copied per prompt (broadcasting instead);
# * after block 0 the image tokens differ per prompt, and each attention between them and the
#   few prompt tokens is computed with the projections moved to the token side: logits
#   q . (W_k x + b_k) are (W_k^T q) . x plus a per-row constant that the softmax removes;
#   sum_n p_n (W_v x_n + b_v) = W_v (sum_n p_n x_n) + b_v; and an image token's update
#   sum_{h,t} p_{h,t} W_o,h v_{h,t} + b_o is one [4096, heads x tokens] x [heads x tokens, C]
#   product. With 8 heads and <= 8 tokens that halves each 4096 x 256 projection;
# * the final token-to-image attention runs for the tokens that are read (IoU and mask tokens);
# * the two transposed convolutions (kernel 2, stride 2: no overlap) are per-token matrix
#   products in a channels-last layout, and run only for the prompts with a mask above the IoU
#   threshold, a few prompts at a time (the transformer too), so the intermediates stay in cache.
# Results equal the forward's up to float rounding (sums in another order).


def _heads(
    x: Tensor,  # [..., L, H * D]
    heads: int,
) -> Tensor:  # [..., H, L, D]
    return x.unflatten(-1, (heads, -1)).transpose(-3, -2)


def _head_weight(linear: torch.nn.Linear, heads: int) -> Tensor:  # [H, D, C]
    """A projection's weight [H * D, C], split by output head."""
    return linear.weight.unflatten(0, (heads, -1))


class FastSam2Decoder:
    """SAM 2's mask decoder (``multimask_output=True``) for many single-point prompts on one
    image, with the per-image work done once (see the notes above). Built from the modules of
    ``model`` itself; one per image; :meth:`decode` takes batches of points. ``chunk`` prompts
    go through the transformer together, ``mask_chunk`` through the upscaling."""

    @torch.no_grad()
    def __init__(
        self,
        model,
        embeddings: list[Tensor],  # from get_image_embeddings: [1, C/8, 4e, 4e], [1, C/4, 2e, 2e], [1, C, e, e]
        chunk: int = 4,
        mask_chunk: int = 2,
    ) -> None:
        if embeddings[-1].shape[0] != 1:
            raise ValueError("FastSam2Decoder takes the features of one image")
        self.model, self.dec = model, model.mask_decoder
        self.chunk, self.mask_chunk = max(1, chunk), max(1, mask_chunk)
        self.blocks = list(self.dec.transformer.layers)
        if not self.blocks[0].skip_first_layer_pe or any(b.skip_first_layer_pe for b in self.blocks[1:]):
            raise ValueError("unexpected SAM 2 mask decoder: only block 0 may skip the prompt positional embedding")
        C = self.dec.hidden_size
        self.size = tuple(embeddings[-1].shape[-2:])
        if self.size[0] != self.size[1]:
            raise ValueError(f"FastSam2Decoder needs a square image embedding, got {self.size}")
        dense = model.prompt_encoder.no_mask_embed.weight.reshape(1, C, 1, 1)
        self.image = (embeddings[-1] + dense).flatten(2)[0].t().contiguous()  # [N, C] tokens + "no mask"
        self.pos = model.get_image_wide_positional_embeddings().flatten(2)[0].t().contiguous()  # [N, C]
        keyed = self.image + self.pos
        # Block 0's image-side projections, shared by every prompt.
        t2i, i2t = self.blocks[0].cross_attn_token_to_image, self.blocks[0].cross_attn_image_to_token
        self.k0 = _heads(t2i.k_proj(keyed), t2i.num_attention_heads)  # [H, N, D]
        self.v0 = _heads(t2i.v_proj(self.image), t2i.num_attention_heads)  # [H, N, D]
        self.q0 = _heads(i2t.q_proj(keyed) * i2t.scaling, i2t.num_attention_heads)  # [H, N, D]
        # The transposed convolutions (kernel 2, stride 2: each output pixel has one input
        # token) as per-token matrix products, channels last: a token (y, x) gives the 2 x 2
        # pixels (ky, kx) of conv 1, each of those the 2 x 2 pixels (ky2, kx2) of conv 2.
        dec, e = self.dec, self.size[0]
        w1, w2 = dec.upscale_conv1.weight, dec.upscale_conv2.weight  # [in, out, 2, 2]
        self.up1_w, self.up1_b = w1.permute(0, 2, 3, 1).flatten(1), dec.upscale_conv1.bias.repeat(4)  # [C, 4 C/4]
        self.up2_w, self.up2_b = w2.permute(0, 2, 3, 1).flatten(1), dec.upscale_conv2.bias.repeat(4)  # [C/4, 4 C/8]
        # The high-resolution maps in the same order: rows (y, x, ky, kx), then (ky2, kx2, channel).
        s1, s0 = embeddings[1][0], embeddings[0][0]  # [C/4, 2e, 2e], [C/8, 4e, 4e]
        self.s1 = s1.view(s1.shape[0], e, 2, e, 2).permute(1, 3, 2, 4, 0).reshape(4 * e * e, -1)
        self.s0 = s0.view(s0.shape[0], e, 2, 2, e, 2, 2).permute(1, 4, 2, 5, 3, 6, 0).reshape(4 * e * e, -1)

    def _tokens(
        self,
        points: Tensor,  # [B, 2] (x, y) in the model's input frame
    ) -> Tensor:  # [B, T, C]
        """Object-score, IoU and mask tokens, then the point's and the padding point's
        embeddings from the model's prompt encoder."""
        dec = self.dec
        labels = torch.ones(1, points.shape[0], 1, dtype=torch.long, device=points.device)
        sparse, _ = self.model.prompt_encoder(
            input_points=points[None, :, None, :], input_labels=labels, input_boxes=None, input_masks=None
        )
        out = torch.cat([dec.obj_score_token.weight, dec.iou_token.weight, dec.mask_tokens.weight])
        return torch.cat([out.expand(points.shape[0], *out.shape), sparse[0].to(out.dtype)], dim=1)

    @staticmethod
    def _token_to_image(
        attn,
        queries: Tensor,  # [B, T, C] prompt tokens + their positional embedding
        keyed: Tensor,  # [B, N, C] image tokens + positional embedding
        image: Tensor,  # [B, N, C] image tokens
    ) -> Tensor:  # [B, T, C]
        """Prompt tokens attending to per-prompt image tokens, projections on the token side."""
        B, T, _ = queries.shape
        H = attn.num_attention_heads
        q = _heads(attn.q_proj(queries) * attn.scaling, H)  # [B, H, T, D]
        a = torch.einsum("bhtd,hdc->bhtc", q, _head_weight(attn.k_proj, H)).flatten(1, 2)  # [B, H*T, C]
        p = torch.softmax(torch.bmm(a, keyed.transpose(1, 2)), dim=-1)  # [B, H*T, N]
        r = torch.bmm(p, image).unflatten(1, (H, T))  # [B, H, T, C]
        v = torch.einsum("bhtc,hdc->bthd", r, _head_weight(attn.v_proj, H)).flatten(2) + attn.v_proj.bias
        return attn.o_proj(v)

    @staticmethod
    def _image_to_token(
        attn,
        probs: Tensor,  # [B, N, H, T] attention of each image token over the prompt tokens
        values: Tensor,  # [B, T, C] prompt tokens (the value input)
    ) -> Tensor:  # [B, N, C]
        """An image token's update sum_{h,t} p_{h,t} W_o,h (W_v v_t + b_v)_h + b_o as one
        [N, H*T] x [H*T, C] product per prompt."""
        B, N, H, T = probs.shape
        v = _heads(attn.v_proj(values), H)  # [B, H, T, D]
        u = torch.einsum("bhtd,chd->bhtc", v, attn.o_proj.weight.unflatten(1, (H, -1))).flatten(1, 2)
        return torch.baddbmm(attn.o_proj.bias, probs.reshape(B, N, H * T), u)

    def _transformer(
        self,
        tokens: Tensor,  # [B, T, C] prompt tokens (also their positional embedding)
    ) -> tuple[Tensor, Tensor]:  # [B, T', C] tokens 0..5, [B, N, C] image tokens
        B, T, C = tokens.shape
        pe = queries = tokens
        image = keyed = None
        for i, block in enumerate(self.blocks):
            if i == 0:
                x = queries[None]
                queries = block.self_attn(query=x, key=x, value=x)[0][0]
            else:
                x = (queries + pe)[None]
                queries = queries + block.self_attn(query=x, key=x, value=queries[None])[0][0]
            queries = block.layer_norm1(queries)
            t2i, i2t = block.cross_attn_token_to_image, block.cross_attn_image_to_token
            if i == 0:  # the image side is the same for all prompts: one [H, B*T, N] attention
                q = _heads(t2i.q_proj(queries + pe), t2i.num_attention_heads)  # [B, H, T, D]
                q = q.transpose(0, 1).flatten(1, 2)  # [H, B*T, D]
                o = F.scaled_dot_product_attention(q, self.k0, self.v0, scale=t2i.scaling)
                o = t2i.o_proj(o.unflatten(1, (B, T)).permute(1, 2, 0, 3).flatten(2))
            else:
                assert image is not None and keyed is not None
                o = self._token_to_image(t2i, queries + pe, keyed, image)
            queries = block.layer_norm2(queries + o)
            queries = block.layer_norm3(queries + block.mlp(queries))
            # Image tokens attend to the prompt tokens.
            H = i2t.num_attention_heads
            k = _heads(i2t.k_proj(queries + pe), H)  # [B, H, T, D]
            if i == 0:
                s = torch.einsum("hnd,bhtd->bnht", self.q0, k)  # [B, N, H, T]
                residual = self.image
            else:
                assert image is not None and keyed is not None
                # logits (W_q x + b_q) . k = x . (W_q^T k) + b_q . k
                g = torch.einsum("bhtd,hdc->bhtc", k, _head_weight(i2t.q_proj, H)).flatten(1, 2)  # [B, H*T, C]
                c = torch.einsum("bhtd,hd->bht", k, i2t.q_proj.bias.view(H, -1)).flatten(1)  # [B, H*T]
                s = torch.baddbmm(c[:, None], keyed, g.transpose(1, 2)) * i2t.scaling
                s = s.unflatten(2, (H, T))  # [B, N, H, T]
                residual = image
            image = block.layer_norm4(residual + self._image_to_token(i2t, torch.softmax(s, dim=-1), queries))
            keyed = image + self.pos
        assert image is not None and keyed is not None
        final = self.dec.transformer.final_attn_token_to_image
        read = 2 + self.dec.num_mask_tokens  # object-score, IoU and mask tokens (the last two are points)
        o = self._token_to_image(final, (queries + pe)[:, :read], keyed, image)
        return self.dec.transformer.layer_norm_final_attn(queries[:, :read] + o), image

    def _masks(
        self,
        image: Tensor,  # [b, N, C] image tokens after the transformer
        hyper: Tensor,  # [b, M, C/8] per-mask weights from the mask tokens
    ) -> Tensor:  # [b, M, 4e, 4e] low-res mask logits
        """``upscale_conv1`` + the 2e map, layer norm, activation, ``upscale_conv2`` + the 4e map,
        activation, product with the mask weights; then the pixels back in image order."""
        dec = self.dec
        b, N, C = image.shape
        e = self.size[0]
        x = torch.addmm(self.up1_b, image.reshape(b * N, C), self.up1_w).view(b, 4 * N, -1) + self.s1
        ln = dec.upscale_layer_norm  # over channels, per pixel
        x = dec.activation(F.layer_norm(x, ln.normalized_shape, ln.weight, ln.bias, ln.eps))
        x = torch.addmm(self.up2_b, x.view(b * 4 * N, -1), self.up2_w).view(b, 4 * N, -1) + self.s0
        x = dec.activation(x).view(b, 16 * N, -1)  # [b, (y, x, ky, kx, ky2, kx2), C/8]
        m = torch.bmm(hyper, x.transpose(1, 2)).view(b, -1, e, e, 2, 2, 2, 2)
        # row 4y + 2ky + ky2, column 4x + 2kx + kx2
        return m.permute(0, 1, 2, 4, 6, 3, 5, 7).reshape(b, -1, 4 * e, 4 * e)

    @torch.no_grad()
    def decode(
        self,
        points: Tensor,  # [B, 2] (x, y) prompts in the model's input frame
        min_iou: Optional[float] = None,
    ) -> tuple[Tensor, Tensor, Tensor]:
        """IoU predictions [B, 3] of every prompt's three masks, and the low-res logits
        [K, 4e, 4e] of the masks whose prediction is above ``min_iou`` (all when None), with
        their flat indices [K] into ``iou.reshape(-1)`` (ascending). No upscaling runs for a
        prompt with no such mask."""
        dec = self.dec
        multi = range(1, 1 + dec.num_multimask_outputs)  # mask tokens 1..3 (tokens 3..5)
        ious, logits, indices = [], [], []
        for start in range(0, points.shape[0], self.chunk):
            queries, image = self._transformer(self._tokens(points[start : start + self.chunk]))
            iou = dec.iou_prediction_head(queries[:, 1])[:, 1:]  # [b, 3]
            ious.append(iou)
            M = iou.shape[1]
            wanted = torch.ones_like(iou, dtype=torch.bool) if min_iou is None else iou.float() > min_iou
            prompts = torch.nonzero(wanted.any(1)).flatten()
            for s in range(0, prompts.numel(), self.mask_chunk):
                sel = prompts[s : s + self.mask_chunk]
                hyper = torch.stack([dec.output_hypernetworks_mlps[j](queries[sel, 2 + j]) for j in multi], dim=1)
                keep = wanted[sel]
                logits.append(self._masks(image[sel], hyper)[keep])
                indices.append(((sel[:, None] + start) * M + torch.arange(M, device=sel.device))[keep])
        iou = torch.cat(ious)
        if not logits:
            size = (4 * self.size[0], 4 * self.size[1])
            return iou, iou.new_zeros(0, *size), torch.zeros(0, dtype=torch.long, device=iou.device)
        return iou, torch.cat(logits), torch.cat(indices)
