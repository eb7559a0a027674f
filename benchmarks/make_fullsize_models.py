"""Randomly initialised SAM ViT-H and CLIP ViT-B/16 at full size, saved as local model folders.

The real checkpoints (``facebook/sam-vit-huge``, ``laion/CLIP-ViT-B-16-laion2B-s34B-b88K``)
cannot be downloaded everywhere; models with the same architecture and random weights exercise
exactly the code path the real ones take (``from_pretrained`` on a folder, full-size tensors,
the same memory and time), only the masks and embeddings mean nothing::

    python benchmarks/make_fullsize_models.py /tmp/fullsize_models
    n2f2 segments SCENE --out BANK --segmenter sam --sam-model /tmp/fullsize_models/sam-vit-huge \\
        --encoder clip --model /tmp/fullsize_models/clip-vit-b-16 ...

Writes ``OUT/sam-vit-huge/`` (``SamModel``: config.json + model.safetensors, 2.6 GB) and
``OUT/clip-vit-b-16/`` (``CLIPModel`` + tokenizer, 0.6 GB), both with ``save_pretrained``.

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
    ap.add_argument("out", type=Path, help="folder to write sam-vit-huge/ and clip-vit-b-16/ into")
    ap.add_argument("--bpe", type=Path, default=None,
                    help="bpe_simple_vocab_16e6.txt.gz or an open_clip_torch wheel (default: pip download it)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--no-calibrate", dest="calibrate", action="store_false",
                    help="leave SAM's random output layers as initialised (then no mask passes SAM's filters)")
    ap.add_argument("--only", choices=["sam", "clip"], default=None, help="make only one of the two")
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    if args.only in (None, "clip"):
        t = time.perf_counter()
        make_clip(args.out / CLIP_DIR, args.seed, args.bpe or default_bpe())
        print(f"CLIP ViT-B/16 -> {args.out / CLIP_DIR} ({time.perf_counter() - t:.0f} s)")
    if args.only in (None, "sam"):
        t = time.perf_counter()
        make_sam(args.out / SAM_DIR, args.seed, args.calibrate)
        print(f"SAM ViT-H -> {args.out / SAM_DIR} ({time.perf_counter() - t:.0f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
