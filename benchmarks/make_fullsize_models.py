"""Randomly initialised SAM ViT-H, SAM 2.1 (Hiera-tiny, Hiera-large) and CLIP ViT-B/16 at full
size, saved as local model folders.

The real checkpoints (``facebook/sam-vit-huge``, ``facebook/sam2.1-hiera-tiny``,
``facebook/sam2.1-hiera-large``, ``laion/CLIP-ViT-B-16-laion2B-s34B-b88K``) cannot be downloaded
everywhere; models with the same architecture and random weights exercise exactly the code path
the real ones take (``from_pretrained`` on a folder, full-size tensors, the same memory and
time), only the masks and embeddings mean nothing::

    python benchmarks/make_fullsize_models.py /tmp/fullsize_models
    n2f2 segments SCENE --out BANK --segmenter sam --sam-model /tmp/fullsize_models/sam-vit-huge \\
        --encoder clip --model /tmp/fullsize_models/clip-vit-b-16 ...
    python benchmarks/make_fullsize_models.py /tmp/fullsize_models --only sam2.1-hiera-tiny

Writes ``OUT/sam-vit-huge/`` (``SamModel``: config.json + model.safetensors, 2.6 GB),
``OUT/sam2.1-hiera-tiny/`` (0.16 GB) and ``OUT/sam2.1-hiera-large/`` (0.9 GB) (``Sam2VideoModel``,
as the released SAM 2.1 folders are; ``Sam2Model`` loads their image part) and
``OUT/clip-vit-b-16/`` (``CLIPModel`` + tokenizer, 0.6 GB), all with ``save_pretrained``;
``--only`` picks some of them.

* SAM: ViT-H image encoder as in ``facebook/sam-vit-huge`` (hidden 1280, 32 layers, 16 heads,
  MLP 5120, windowed attention 14 with global attention in layers 7, 15, 23, 31, 1024 x 1024
  input, 256-d 64 x 64 embedding); prompt encoder and mask decoder are the same for every SAM.
  The vision encoder is initialised with std 0.02 (``SamVisionConfig``'s default, 1e-10, gives
  activations around 1e-20: denormal floats, which make CPU arithmetic about ten times slower
  than with real weights).
  Random weights predict masks whose IoU and stability scores fail SAM's filters (IoU ~ 0,
  logits ~ 0), so nothing would reach post-processing or CLIP. Two output layers are therefore
  rescaled (on by default, ``--no-calibrate`` to skip): the IoU head's output layer, so
  predicted IoUs spread around 0.65, and the mask hypernetworks' output layers, so logits
  reach many units. About 10 % of the 3,072 candidate masks then pass both filters (290 on
  the plush-dog photo IMG_3496), which is what post-processing cost depends on. The masks are
  speckle, not objects, and overlap so much that NMS keeps ~80 and LangSplat's mask NMS about
  a dozen, fewer than a real photo gives; ``bench_fullsize_models.py`` therefore also times
  CLIP on 100 box-shaped segments.
* SAM 2.1: the released configurations of ``facebook/sam2.1-hiera-tiny`` and
  ``facebook/sam2.1-hiera-large``. Hiera trunk from SAM 2's ``sam2/configs/sam2.1/
  sam2.1_hiera_t.yaml`` / ``sam2.1_hiera_l.yaml`` (``embed_dim``, ``num_heads``, ``stages``,
  ``global_att_blocks``, ``window_pos_embed_bkg_spatial_size``, the large one's
  ``window_spec``) with the defaults of ``Hiera`` in ``sam2/modeling/backbones/hieradet.py``
  (tiny's ``window_spec`` (8, 4, 14, 7); dimensions and heads doubling at each of the 3
  query-pooling stages: ``dim_mul = head_mul = 2``, ``q_stride`` (2, 2); MLP ratio 4); neck from
  the same yamls (``d_model`` 256, ``backbone_channel_list``, ``fpn_top_down_levels`` [2, 3]);
  prompt encoder and mask decoder are the same for every size (``Sam2PromptEncoderConfig`` /
  ``Sam2MaskDecoderConfig`` defaults: 1024 input, 256-d, 2 two-way layers, 8 heads, MLP 2048,
  sigmoid IoU head, object-score head, high-res features). The same values as ``transformers``'
  ``convert_sam2_to_hf.py`` ``get_config`` (whose tiny is ``Sam2HieraDetConfig()``'s defaults).
  The video parts (memory attention / encoder, unused on images) keep ``Sam2VideoConfig``'s
  defaults. ``transformers``' initialisation (std 0.02) gives normal activations here, so no
  change there. Calibration as for SAM (``--no-calibrate`` skips it): the IoU head ends in a
  sigmoid, so its output layer gets a bias (the IoU logit's centre) and scaled weights; the
  mask hypernetworks' output layers are scaled. Values per size were measured on IMG_3496
  (:data:`SAM2_CALIBRATION`) so that, as for SAM, about a quarter of the 3,072 candidate masks
  exceed the IoU threshold and about 10 % also pass the stability filter.
* CLIP: the OpenCLIP ViT-B/16 the paper uses, as its Hugging Face port configures it (vision
  hidden 768, 12 layers, 12 heads, patch 16, image 224; text hidden 512, 12 layers, 8 heads,
  context 77, vocabulary 49408; projection 512; GELU).
* CLIP tokenizer: CLIP's byte-level BPE (``bpe_simple_vocab_16e6.txt.gz``, 48,894 merges,
  49,408 tokens), turned into ``vocab.json`` + ``merges.txt`` exactly as OpenAI's
  ``SimpleTokenizer`` builds its vocabulary, then saved as ``transformers``' ``CLIPTokenizer``
  (``tokenizer.json``). The BPE file is read from ``--bpe`` (the ``.txt.gz`` or a wheel that
  holds it) or, by default, from the ``open-clip-torch`` wheel on PyPI, which ships it and is
  fetched with ``pip download open-clip-torch --no-deps`` (not installed). n2f2 itself does
  not depend on open-clip-torch.
"""

from __future__ import annotations

import argparse
import gzip
import io
import json
import sys
import tempfile
import time
import zipfile
from pathlib import Path

import torch

SAM_DIR = "sam-vit-huge"
CLIP_DIR = "clip-vit-b-16"
SAM2_DIRS = ("sam2.1-hiera-tiny", "sam2.1-hiera-large")


# ----------------------------------------------------------------------------- SAM
def sam_vit_h_config():
    """``facebook/sam-vit-huge``'s configuration."""
    from transformers import SamConfig
    from transformers.models.sam.configuration_sam import (SamMaskDecoderConfig, SamPromptEncoderConfig,
                                                           SamVisionConfig)

    vision = SamVisionConfig(hidden_size=1280, num_hidden_layers=32, num_attention_heads=16, mlp_dim=5120,
                             global_attn_indexes=[7, 15, 23, 31], image_size=1024, patch_size=16,
                             output_channels=256, window_size=14, num_pos_feats=128,
                             initializer_range=0.02)
    return SamConfig(vision_config=vision.to_dict(), prompt_encoder_config=SamPromptEncoderConfig().to_dict(),
                     mask_decoder_config=SamMaskDecoderConfig().to_dict())


@torch.no_grad()
def calibrate_sam(model, iou_center: float = 0.65, iou_gain: float = 6.0, logit_gain: float = 3000.0) -> None:
    """Make a random SAM's masks pass the automatic mask generator's filters in realistic
    numbers (see the module docstring). With the default seed and a 750 x 500 photo, about a
    quarter of the predicted IoUs exceed 0.7 (centre ``iou_center``, spread ~0.1 from
    ``iou_gain``) and about a third of those masks are stable (logits ``logit_gain`` times
    larger), so ~10 % of the 3,072 candidate masks reach NMS."""
    dec = model.mask_decoder
    head = dec.iou_prediction_head
    head.proj_out.weight.mul_(iou_gain)
    head.proj_out.bias.fill_(iou_center)
    for mlp in dec.output_hypernetworks_mlps:
        mlp.proj_out.weight.mul_(logit_gain)
        mlp.proj_out.bias.mul_(logit_gain)


def make_sam(out: Path, seed: int, calibrate: bool) -> None:
    from transformers import SamModel

    torch.manual_seed(seed)
    model = SamModel(sam_vit_h_config()).eval()
    if calibrate:
        calibrate_sam(model)
    model.save_pretrained(out, safe_serialization=True)


# ----------------------------------------------------------------------------- SAM 2.1
def sam2_config(name: str):
    """The configuration of ``facebook/<name>`` (``sam2.1-hiera-tiny`` or ``-large``), as the
    released folders store it (``Sam2VideoConfig``; see the module docstring for the sources)."""
    from transformers import Sam2VideoConfig
    from transformers.models.sam2.configuration_sam2 import Sam2HieraDetConfig, Sam2VisionConfig

    if name == "sam2.1-hiera-tiny":
        # sam2.1_hiera_t.yaml: embed_dim 96, num_heads 1, stages [1, 2, 7, 2], global_att_blocks
        # [5, 7, 9], window_pos_embed_bkg_spatial_size [7, 7]; window_spec: Hiera's default.
        trunk = Sam2HieraDetConfig(hidden_size=96, num_attention_heads=1, embed_dim_per_stage=[96, 192, 384, 768],
                                   num_attention_heads_per_stage=[1, 2, 4, 8], blocks_per_stage=[1, 2, 7, 2],
                                   global_attention_blocks=[5, 7, 9], window_size_per_stage=[8, 4, 14, 7],
                                   window_positional_embedding_background_size=[7, 7])
    elif name == "sam2.1-hiera-large":
        # sam2.1_hiera_l.yaml: embed_dim 144, num_heads 2, stages [2, 6, 36, 4], global_att_blocks
        # [23, 33, 43], window_pos_embed_bkg_spatial_size [7, 7], window_spec [8, 4, 16, 8].
        trunk = Sam2HieraDetConfig(hidden_size=144, num_attention_heads=2, embed_dim_per_stage=[144, 288, 576, 1152],
                                   num_attention_heads_per_stage=[2, 4, 8, 16], blocks_per_stage=[2, 6, 36, 4],
                                   global_attention_blocks=[23, 33, 43], window_size_per_stage=[8, 4, 16, 8],
                                   window_positional_embedding_background_size=[7, 7])
    else:
        raise ValueError(f"no SAM 2.1 configuration for {name!r}")
    # Neck (FpnNeck in the yamls): d_model 256, backbone_channel_list = the stage widths, deepest first,
    # fpn_top_down_levels [2, 3]; 3 feature levels of a 1024 input: 256^2, 128^2, 64^2.
    vision = Sam2VisionConfig(backbone_config=trunk.to_dict(), backbone_channel_list=trunk.embed_dim_per_stage[::-1],
                              fpn_hidden_size=256, fpn_top_down_levels=[2, 3],
                              backbone_feature_sizes=[[256, 256], [128, 128], [64, 64]])
    return Sam2VideoConfig(vision_config=vision.to_dict())


# Per size: (IoU-logit bias, IoU-logit gain, mask-logit gain), measured with seed 0 on 192 of the
# 1,024 grid points of IMG_3496 (750 x 500): predicted IoUs then have mean 0.64 and spread ~0.09,
# 27 % of the candidate masks exceed IoU 0.7 and 11 % (tiny: 11.5 %, large: 10.9 %) pass the
# stability filter too. The IoU head's random output has mean -0.003 (tiny) / -0.011 (large)
# against a spread of 0.013, hence the different biases.
SAM2_CALIBRATION = {"sam2.1-hiera-tiny": (0.70, 30.0, 3000.0), "sam2.1-hiera-large": (0.95, 30.0, 2500.0)}


@torch.no_grad()
def calibrate_sam2(model, iou_bias: float, iou_gain: float, logit_gain: float) -> None:
    """Make a random SAM 2's masks pass the automatic mask generator's filters in realistic
    numbers (see :data:`SAM2_CALIBRATION`): predicted IoUs ``sigmoid(iou_gain * z + iou_bias)``
    (z: the random IoU head's output without bias, ~0), mask logits ``logit_gain`` times larger
    (the hypernetworks' output layers are linear, so the logits scale exactly)."""
    dec = model.mask_decoder
    head = dec.iou_prediction_head  # ends in a sigmoid (SAM 2's iou_prediction_use_sigmoid)
    head.proj_out.weight.mul_(iou_gain)
    head.proj_out.bias.fill_(iou_bias)
    for mlp in dec.output_hypernetworks_mlps:
        mlp.proj_out.weight.mul_(logit_gain)
        mlp.proj_out.bias.mul_(logit_gain)


def make_sam2(out: Path, name: str, seed: int, calibrate: bool) -> None:
    from transformers import Sam2VideoModel

    torch.manual_seed(seed)
    model = Sam2VideoModel(sam2_config(name)).eval()
    if calibrate:
        calibrate_sam2(model, *SAM2_CALIBRATION[name])
    model.save_pretrained(out, safe_serialization=True)


# ----------------------------------------------------------------------------- CLIP
def clip_vit_b16_config():
    """``laion/CLIP-ViT-B-16-laion2B-s34B-b88K``'s configuration (OpenCLIP ViT-B/16)."""
    from transformers import CLIPConfig

    text = dict(vocab_size=49408, hidden_size=512, intermediate_size=2048, num_hidden_layers=12,
                num_attention_heads=8, max_position_embeddings=77, hidden_act="gelu", projection_dim=512,
                bos_token_id=49406, eos_token_id=49407, pad_token_id=1)
    vision = dict(hidden_size=768, intermediate_size=3072, num_hidden_layers=12, num_attention_heads=12,
                  image_size=224, patch_size=16, hidden_act="gelu", projection_dim=512)
    return CLIPConfig(text_config=text, vision_config=vision, projection_dim=512)


def bytes_to_unicode() -> dict[int, str]:
    """CLIP's / GPT-2's reversible byte -> printable character table."""
    bs = [*range(ord("!"), ord("~") + 1), *range(ord("¡"), ord("¬") + 1), *range(ord("®"), ord("ÿ") + 1)]
    cs = bs[:]
    n = 0
    for b in range(256):
        if b not in bs:
            bs.append(b)
            cs.append(256 + n)
            n += 1
    return dict(zip(bs, map(chr, cs)))


def read_bpe(path: Path) -> list[str]:
    """Lines of ``bpe_simple_vocab_16e6.txt.gz``, from the file or from a wheel that holds it."""
    if path.suffix == ".whl":
        with zipfile.ZipFile(path) as z:
            name = next((n for n in z.namelist() if n.endswith("bpe_simple_vocab_16e6.txt.gz")), None)
            if name is None:
                sys.exit(f"{path}: no bpe_simple_vocab_16e6.txt.gz inside")
            data = z.read(name)
    else:
        data = path.read_bytes()
    return gzip.open(io.BytesIO(data)).read().decode("utf-8").split("\n")


def write_clip_vocab(lines: list[str], out: Path) -> tuple[Path, Path]:
    """OpenAI ``SimpleTokenizer``'s vocabulary: bytes, bytes + ``</w>``, one token per merge,
    then the two special tokens; ``merges.txt`` in the Hugging Face layout."""
    merges = [tuple(m.split()) for m in lines[1:49152 - 256 - 2 + 1]]
    vocab = list(bytes_to_unicode().values())
    vocab = vocab + [v + "</w>" for v in vocab] + ["".join(m) for m in merges]
    vocab += ["<|startoftext|>", "<|endoftext|>"]
    vocab_path, merges_path = out / "vocab.json", out / "merges.txt"
    vocab_path.write_text(json.dumps({t: i for i, t in enumerate(vocab)}, ensure_ascii=False))
    merges_path.write_text("#version: 0.2\n" + "\n".join(" ".join(m) for m in merges) + "\n", encoding="utf-8")
    return vocab_path, merges_path


def default_bpe() -> Path:
    """The open-clip-torch wheel, fetched with pip (no dependencies, not installed)."""
    import subprocess

    dest = Path(tempfile.gettempdir()) / "n2f2-open-clip-wheel"
    wheels = sorted(dest.glob("open_clip_torch-*.whl"))
    if not wheels:
        subprocess.run([sys.executable, "-m", "pip", "download", "open-clip-torch", "--no-deps", "-q",
                        "-d", str(dest)], check=True)
        wheels = sorted(dest.glob("open_clip_torch-*.whl"))
    return wheels[-1]


def make_clip(out: Path, seed: int, bpe: Path) -> None:
    from transformers import CLIPModel, CLIPTokenizer

    torch.manual_seed(seed)
    CLIPModel(clip_vit_b16_config()).eval().save_pretrained(out, safe_serialization=True)
    with tempfile.TemporaryDirectory() as tmp:
        vocab, merges = write_clip_vocab(read_bpe(bpe), Path(tmp))
        tokenizer = CLIPTokenizer(vocab=str(vocab), merges=str(merges), model_max_length=77)
    # Token ids every CLIP release shares (OpenAI's tokenizer: "a photo of a" -> 320 1125 539 320).
    if tokenizer("a photo of a")["input_ids"] != [49406, 320, 1125, 539, 320, 49407]:
        sys.exit(f"{bpe}: the tokenizer built from it does not give CLIP's token ids")
    tokenizer.save_pretrained(out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("out", type=Path, help=f"folder to write {SAM_DIR}/, {'/, '.join(SAM2_DIRS)}/ and {CLIP_DIR}/ into")
    ap.add_argument("--bpe", type=Path, default=None,
                    help="bpe_simple_vocab_16e6.txt.gz or an open_clip_torch wheel (default: pip download it)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--no-calibrate", dest="calibrate", action="store_false",
                    help="leave SAM's / SAM 2's random output layers as initialised (then no mask passes the filters)")
    ap.add_argument("--only", action="append", choices=["sam", "clip", *SAM2_DIRS], default=None, metavar="MODEL",
                    help=f"make only this one (repeatable): sam (ViT-H), clip, {', '.join(SAM2_DIRS)} (default: all)")
    args = ap.parse_args(argv)
    only = set(args.only or ["sam", "clip", *SAM2_DIRS])
    args.out.mkdir(parents=True, exist_ok=True)
    if "clip" in only:
        t = time.perf_counter()
        make_clip(args.out / CLIP_DIR, args.seed, args.bpe or default_bpe())
        print(f"CLIP ViT-B/16 -> {args.out / CLIP_DIR} ({time.perf_counter() - t:.0f} s)")
    if "sam" in only:
        t = time.perf_counter()
        make_sam(args.out / SAM_DIR, args.seed, args.calibrate)
        print(f"SAM ViT-H -> {args.out / SAM_DIR} ({time.perf_counter() - t:.0f} s)")
    for name in SAM2_DIRS:
        if name in only:
            t = time.perf_counter()
            make_sam2(args.out / name, name, args.seed, args.calibrate)
            print(f"SAM 2.1 {name} -> {args.out / name} ({time.perf_counter() - t:.0f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
