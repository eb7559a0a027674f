"""The segment bank: every training segment of a scene with its language embedding and scale.

On disk (one folder per scene)::

    BANK/
      bank.json            format, version, scene fingerprint (image names + sizes), segmenter
                           and encoder specs, lifting settings, fitted quantile transform,
                           counts (incl. degenerate segments dropped by lifting), timing
      <stem>/              one record per image, written atomically (temp folder + rename)
        layers.npy         int32 [L, H, W]  non-overlapping segment-id layers, -1 = none
        embeddings.npy     float16 [S, E]   L2-normalised language embeddings
        scales.npy         float32 [S]      raw lifted scale (NaN = degenerate, dropped)
        areas.npy          int64 [S]        pixels per segment
        valid.npy          bool [S]         finite scale and non-empty
        num_points.npy     int64 [S]        3D points the scale was measured on
        scores.npy         float32 [S]      segmenter confidence
        source_ids.npy     int64 [S]        (ground truth only) region id of each segment
        captions.json      [S] strings      (ground truth only)

Records are plain ``.npy`` files, so :class:`SegmentBank` memory-maps them. Extraction is
resumable: a rerun skips images whose record exists, then (re)fits the quantile transform
over all valid segments (paper: scales quantised by a quantile transformation, s in [0, 1)).
With a Ray executor (``n2f2 segments --executor ray``) each image is a Ray task; the calling
process still writes every record, so the bank resumes the same way.
"""

from __future__ import annotations

import json
import os
import shutil
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Optional, Protocol, Sequence

import numpy as np

from ..errors import InputError
from ..io import make_dirs, write_json
from .bins import QuantileScaleBins
from .lifting import SCALE_DESCRIPTIONS, DepthProvider, LiftSettings, lift_view
from .segmenters import SegmentSet, layers_to_masks, segment_layers

if TYPE_CHECKING:
    from ..distributed import Executor

BANK_FORMAT = "n2f2-segment-bank"
BANK_VERSION = 1
RECORD_FILES = ("layers.npy", "embeddings.npy", "scales.npy", "areas.npy", "valid.npy")


# ----------------------------------------------------------------------------- sources
class SegmentSource(Protocol):
    """Where a view's segments and embeddings come from (segmenter + encoder, or LangSplat)."""

    @property
    def segmenter_spec(self) -> dict: ...

    @property
    def encoder_spec(self) -> dict: ...

    def prepare(self, stems: list[str]) -> None: ...

    def extract(
        self,
        index: int,
        stem: str,
        image: np.ndarray,  # [H, W, 3] float
    ) -> tuple[SegmentSet, np.ndarray]: ...  # segments, embeddings [S, E]


def check_pairing(segmenter: str, encoder: str, requires_captions: bool) -> None:
    """Refuse an encoder that embeds captions beside a segmenter that has none (checked by
    name, before either model loads)."""
    if requires_captions and segmenter != "ground-truth":
        raise InputError(
            None,
            f"--encoder {encoder} embeds ground-truth captions, so it needs "
            "--segmenter ground-truth (the demo scene); use --encoder clip otherwise",
        )


class SegmentAndEncode:
    """Segments from a segmenter, embeddings from an encoder (CLIP on masked crops, or the
    segments' captions for the offline teacher)."""

    def __init__(self, segmenter, encoder, chunk: int = 64) -> None:
        check_pairing(segmenter.name, encoder.name, encoder.requires_captions)
        self.segmenter = segmenter
        self.encoder = encoder
        self.chunk = chunk  # segments whose full-size masks are materialised at once
        self.last_timing: dict[str, float] = {}  # seconds of the last image by part (see extract)

    @property
    def segmenter_spec(self) -> dict:
        return self.segmenter.spec

    @property
    def encoder_spec(self) -> dict:
        return self.encoder.spec

    def prepare(self, stems: list[str]) -> None:
        pass

    def extract(self, index: int, stem: str, image: np.ndarray) -> tuple[SegmentSet, np.ndarray]:
        """The image's segments and their embeddings; ``last_timing`` then holds its seconds by
        part: the segmenter's own parts where it reports them (SAM: ``image_encoder``,
        ``mask_decoder``, ``postprocess``), else ``segmenter``; and ``encoder``."""
        t0 = time.perf_counter()
        segs = self.segmenter(image, view=index)
        t1 = time.perf_counter()
        parts = dict(getattr(self.segmenter, "last_timing", None) or {"segmenter": t1 - t0})
        self.last_timing = parts
        S = segs.num_segments
        if S == 0:
            emb = np.zeros((0, self.encoder.dim), np.float32)
        elif self.encoder.requires_captions:
            emb = self.encoder.encode_segments(image, np.zeros((S, 0, 0), bool), captions=segs.captions).numpy()
        else:
            layer_of = segs.layer_of()
            out = []
            for start in range(0, S, self.chunk):
                ids = np.arange(start, min(S, start + self.chunk))
                out.append(self.encoder.encode_segments(image, layers_to_masks(segs.layers, ids, layer_of)).numpy())
            emb = np.concatenate(out)
        parts["encoder"] = time.perf_counter() - t1
        return segs, emb


# ----------------------------------------------------------------------------- reading
@dataclass
class ImageSegments:
    """The segments of one image, as stored (arrays may be memory-mapped, read-only)."""

    layers: np.ndarray  # [L, H, W] int32, -1 = none
    embeddings: np.ndarray  # [S, E] float16
    scales: np.ndarray  # [S] float32 raw lifted scale, NaN = degenerate
    quantized: np.ndarray  # [S] float32 quantised scale in [0, 1), NaN where not valid
    areas: np.ndarray  # [S] int64
    valid: np.ndarray  # [S] bool

    @property
    def num_segments(self) -> int:
        return int(self.scales.shape[0])

    def masks(self, ids: Optional[Sequence[int]] = None) -> np.ndarray:
        """Boolean masks [n, H, W] of segments ``ids`` (default: all)."""
        S = self.num_segments
        return layers_to_masks(
            np.asarray(self.layers), S if ids is None else ids, layer_of=segment_layers(np.asarray(self.layers), S)
        )


class SegmentBank:
    """A finished segment bank, opened lazily: records are memory-mapped on access."""

    def __init__(self, root: Path, meta: dict) -> None:
        self.root = Path(root)
        self.meta = meta
        self.bins = QuantileScaleBins.from_dict(meta["quantile"])

    @staticmethod
    def open(path: str | Path) -> "SegmentBank":
        root = Path(path)
        meta_path = root / "bank.json"
        if not meta_path.is_file():
            raise InputError(meta_path, "not a segment bank (no bank.json); create one with `n2f2 segments`")
        try:
            meta = json.loads(meta_path.read_text())
        except (OSError, ValueError) as e:
            raise InputError(meta_path, f"cannot read bank.json ({e})") from None
        if meta.get("format") != BANK_FORMAT:
            raise InputError(meta_path, f"not a segment bank (format {meta.get('format')!r})")
        if int(meta.get("version", -1)) > BANK_VERSION:
            raise InputError(
                meta_path, f"bank format version {meta.get('version')} is newer than this n2f2 ({BANK_VERSION})"
            )
        if not meta.get("complete"):
            raise InputError(
                meta_path,
                "segment bank is incomplete (extraction was interrupted); "
                "rerun the same `n2f2 segments` command with --resume to finish it",
            )
        try:
            return SegmentBank(root, meta)
        except (KeyError, ValueError) as e:
            raise InputError(meta_path, f"malformed bank.json ({e})") from None

    # -- scene-level facts
    @property
    def image_names(self) -> list[str]:
        return [im["name"] for im in self.meta["scene"]["images"]]

    @property
    def sizes(self) -> list[tuple[int, int]]:
        """(height, width) of every image."""
        return [(int(im["height"]), int(im["width"])) for im in self.meta["scene"]["images"]]

    @property
    def num_images(self) -> int:
        return len(self.meta["scene"]["images"])

    def __len__(self) -> int:
        return self.num_images

    def _size(self) -> tuple[int, int]:
        sizes = set(self.sizes)
        if len(sizes) != 1:
            raise ValueError("images of this bank differ in size; use .sizes")
        return sizes.pop()

    @property
    def height(self) -> int:
        return self._size()[0]

    @property
    def width(self) -> int:
        return self._size()[1]

    @property
    def embed_dim(self) -> int:
        return int(self.meta["encoder"]["embed_dim"])

    @property
    def encoder_spec(self) -> dict:
        """What :func:`n2f2.segments.encoders.get_encoder` needs to rebuild the text encoder."""
        return dict(self.meta["encoder"])

    @property
    def segmenter_spec(self) -> dict:
        return dict(self.meta["segmenter"])

    @property
    def counts(self) -> dict:
        return dict(self.meta.get("counts", {}))

    def index(self, name: str) -> int:
        try:
            return self.image_names.index(name)
        except ValueError:
            raise KeyError(f"image {name!r} is not in the segment bank") from None

    # -- records
    def _load(self, i: int, name: str) -> np.ndarray:
        path = self.root / self.image_names[i] / name
        try:
            return np.load(path, mmap_mode="r")
        except (OSError, ValueError) as e:
            raise InputError(path, f"cannot read segment bank record ({e})") from None

    def record(self, i: int) -> ImageSegments:
        if not 0 <= i < self.num_images:
            raise IndexError(f"image index {i} out of range (bank has {self.num_images} images)")
        scales = np.asarray(self._load(i, "scales.npy"))
        valid = np.asarray(self._load(i, "valid.npy"))
        quant = self.bins.transform(scales).astype(np.float32)
        quant[~valid] = np.nan
        return ImageSegments(
            layers=self._load(i, "layers.npy"),
            embeddings=self._load(i, "embeddings.npy"),
            scales=scales,
            quantized=quant,
            areas=np.asarray(self._load(i, "areas.npy")),
            valid=valid,
        )

    def optional(self, i: int, name: str) -> Optional[np.ndarray]:
        """An optional per-record array (``"source_ids"``, ``"num_points"``, ...) or None."""
        path = self.root / self.image_names[i] / (name if name.endswith(".npy") else f"{name}.npy")
        return np.load(path, mmap_mode="r") if path.is_file() else None

    def quantized_scale(self, scales: np.ndarray) -> np.ndarray:
        """Raw scales -> s in [0, 1) with the bank's fitted quantile transform."""
        return self.bins.transform(scales)

    def validate_against(self, scene) -> None:
        """Raise :class:`InputError` naming bank.json when ``scene`` is not the scene (image
        names, count, sizes) this bank was extracted from."""
        path = self.root / "bank.json"
        names = list(scene.image_names)
        if len(names) != self.num_images:
            raise InputError(path, f"bank has {self.num_images} images, the scene has {len(names)}")
        if names != self.image_names:
            bad = next(a for a, b in zip(self.image_names, names) if a != b)
            raise InputError(
                path,
                f"image names differ from the scene's (bank has {bad!r} where the scene "
                "differs); was the bank made for another scene?",
            )
        for (h, w), cam, name in zip(self.sizes, scene.cameras, names):
            if (cam.height, cam.width) != (h, w):
                raise InputError(
                    path,
                    f"image {name} is {w}x{h} in the bank but {cam.width}x{cam.height} in "
                    "the scene (different --downscale?)",
                )


# ----------------------------------------------------------------------------- writing
def scene_fingerprint(scene) -> dict:
    return {
        "images": [{"name": n, "width": c.width, "height": c.height} for n, c in zip(scene.image_names, scene.cameras)]
    }


def _earlier_timing(meta_path: Path) -> dict:
    """``{stem: seconds by part}`` an unfinished ``bank.json`` recorded (empty when unreadable)."""
    try:
        per_image = json.loads(meta_path.read_text()).get("timing", {}).get("per_image", {})
    except (OSError, ValueError, AttributeError):
        return {}
    return per_image if isinstance(per_image, dict) else {}


def _record_dir(root: Path, stem: str) -> Path:
    return root / stem


def _write_record(root: Path, stem: str, arrays: dict, captions: Optional[list[str]]) -> None:
    """Write one image's record into a temporary folder, then rename it into place, so a
    record folder either is complete or does not exist."""
    from ..io import DISK_ERRNOS, output_error

    final = _record_dir(root, stem)
    tmp = root / f".{stem}.tmp-{os.getpid()}"
    if tmp.exists():
        shutil.rmtree(tmp)
    try:
        tmp.mkdir(parents=True)
        for name, arr in arrays.items():
            np.save(tmp / f"{name}.npy", arr)
        if captions is not None:
            (tmp / "captions.json").write_text(json.dumps(captions))
        if final.exists():  # a record finished by another process meanwhile: ours replaces it
            shutil.rmtree(final)
        os.rename(tmp, final)  # complete records are resumable state: kept if the command fails
    except OSError as e:
        if e.errno in DISK_ERRNOS:
            raise output_error(final, e) from None
        raise
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)


def _record_complete(root: Path, stem: str) -> bool:
    d = _record_dir(root, stem)
    return d.is_dir() and all((d / f).is_file() for f in RECORD_FILES)


def bank_header(scene, source: SegmentSource, depth_source: str, lift: LiftSettings) -> dict:
    """What ``bank.json`` records of how a bank is made; a resumed bank must match it."""
    return {
        "format": BANK_FORMAT,
        "version": BANK_VERSION,
        "scene": scene_fingerprint(scene),
        "segmenter": source.segmenter_spec,
        "encoder": source.encoder_spec,
        "lifting": {**asdict(lift), "depth_source": depth_source, "scale": SCALE_DESCRIPTIONS[lift.scale_measure]},
    }


def unfinished_bank(out: str | Path, header: dict) -> bool:
    """``out`` holds a bank that an interrupted build left (``complete: false``) with the
    settings of ``header``: building it again finishes it."""
    try:
        old = json.loads((Path(out) / "bank.json").read_text())
    except (OSError, ValueError):
        return False
    return isinstance(old, dict) and old.get("complete") is False and all(old.get(k) == v for k, v in header.items())


def _check_resume(meta_path: Path, header: dict) -> None:
    try:
        old = json.loads(meta_path.read_text())
    except (OSError, ValueError) as e:
        raise InputError(
            meta_path,
            f"cannot read existing bank.json ({e}); pass --force to replace the bank, or choose another --out",
        ) from None
    if old.get("format") != BANK_FORMAT:
        raise InputError(meta_path, "output folder holds something that is not a segment bank")
    for key in ("scene", "segmenter", "encoder", "lifting"):
        if old.get(key) != header.get(key):
            raise InputError(
                meta_path,
                f"existing bank was made with different {key} settings; pass --force to "
                "replace it, or choose another --out",
            )


def extract_record(
    scene, source: SegmentSource, depth: DepthProvider, i: int, lift: LiftSettings
) -> tuple[dict, Optional[list[str]], dict]:
    """Image ``i``'s record: segments and embeddings from ``source``, each segment's scale lifted
    with ``depth``. Returns the arrays the bank stores (name -> array), the captions (ground
    truth only) and the image's seconds by part (the source's parts, ``lift``, ``total``) with
    its segment count (``segments``). The same code runs in the driver and in a Ray worker."""
    start = time.perf_counter()
    stem, cam = scene.image_names[i], scene.cameras[i]
    image = scene.image(i)
    segs, emb = source.extract(i, stem, image)
    parts: dict = {k: round(float(v), 3) for k, v in (getattr(source, "last_timing", None) or {}).items()}
    t_lift = time.perf_counter()
    S = segs.num_segments
    if segs.layers.shape[1:] != (cam.height, cam.width):
        raise InputError(
            scene.image_paths[i], f"segments are {segs.width}x{segs.height} but the image is {cam.width}x{cam.height}"
        )
    emb = np.asarray(emb, dtype=np.float32)
    if emb.shape != (S, int(source.encoder_spec["embed_dim"])):
        raise ValueError(f"{stem}: embeddings {emb.shape} for {S} segments")
    d, ok = depth(i)
    scales, npts = lift_view(segs.layers, d, ok, cam, S, lift)
    areas = segs.areas()
    arrays = {
        "layers": segs.layers.astype(np.int32),
        "embeddings": emb.astype(np.float16),
        "scales": scales.astype(np.float32),
        "areas": areas.astype(np.int64),
        "valid": np.isfinite(scales) & (areas > 0),
        "num_points": npts.astype(np.int64),
        "scores": segs.scores.astype(np.float32),
    }
    if segs.source_ids is not None:
        arrays["source_ids"] = np.asarray(segs.source_ids, dtype=np.int64)
    now = time.perf_counter()
    parts.update(lift=round(now - t_lift, 3), total=round(now - start, 3), segments=S)
    return arrays, segs.captions, parts


class WorkerSetup(Protocol):
    """How a Ray worker builds what :func:`extract_record` needs: a picklable, hashable recipe
    (e.g. the options of ``n2f2 segments``), built once per worker process."""

    def build(self) -> tuple:  # (scene, source, depth provider)
        ...


def _extract_in_worker(task: tuple) -> tuple[dict, Optional[list[str]], dict]:
    """One Ray task: image ``i``'s record, built in the worker from ``setup``."""
    from ..distributed import worker_state

    setup, i, stem, lift = task

    def build():
        scene, source, depth = setup.build()
        source.prepare(list(scene.image_names))
        return scene, source, depth

    scene, source, depth = worker_state(setup, build)
    if i >= len(scene) or scene.image_names[i] != stem:
        raise InputError(
            scene.root,
            f"the worker's scene has no image {stem!r} at index {i}; do all Ray nodes see the same scene folder?",
        )
    return extract_record(scene, source, depth, i, lift)  # timed as the serial loop does (models loaded)


def build_bank(
    scene,
    source: SegmentSource,
    depth: DepthProvider,
    out: str | Path,
    *,
    depth_source: str = "render",
    lift: Optional[LiftSettings] = None,
    num_quantiles: int = 1000,
    progress: bool = True,
    executor: Optional["Executor"] = None,
    worker_setup: Optional[WorkerSetup] = None,
) -> dict:
    """Extract (or finish extracting) the segment bank of ``scene`` into ``out``.

    For every image without a record: segments + embeddings from ``source``, depth from
    ``depth``, lifted scales, one atomic record. Then fit the quantile transform over all
    valid segments and write the final ``bank.json``. Returns the report (counts, timing).

    With a Ray ``executor`` (:mod:`n2f2.distributed`), each missing image is one Ray task that
    builds its own scene, source and depth from ``worker_setup``; records are written here, as
    tasks finish. An image failing on bad input is reported and the others go on; the bank
    then stays incomplete and an :class:`InputError` names the failed images. Without one
    (or with the serial executor), images are extracted here in order and the first error stops."""
    from tqdm import tqdm

    lift = lift or LiftSettings()
    out = Path(out)
    make_dirs(out)
    stems = list(scene.image_names)
    if len(set(stems)) != len(stems):
        raise InputError(
            scene.root, "image file names (without extension) are not unique; the bank keys records by them"
        )
    if executor is not None and executor.name == "serial":
        executor = None  # the in-process loop below
    if executor is not None and worker_setup is None:
        raise ValueError("a distributed executor needs worker_setup")
    source.prepare(stems)
    header = bank_header(scene, source, depth_source, lift)
    meta_path = out / "bank.json"
    earlier: dict = {}  # seconds by part of the images an interrupted run finished
    if meta_path.exists():
        _check_resume(meta_path, header)
        earlier = _earlier_timing(meta_path)
    for stale in out.glob(".*.tmp-*"):  # leftovers of an interrupted record write
        shutil.rmtree(stale, ignore_errors=True)
    todo = [i for i, s in enumerate(stems) if not _record_complete(out, s)]
    times, per_image = [], {s: earlier[s] for s in stems if s in earlier and _record_complete(out, s)}

    def unfinished() -> None:
        """Resumable state, kept if the command fails: --resume checks the settings against it,
        and a resumed run reports the timing of every image."""
        meta = {**header, "complete": False, "source": str(scene.root), "timing": {"per_image": per_image}}
        write_json(meta_path, meta, keep=True)

    unfinished()
    # The bar's rate and ETA come from the images of this run (a resumed run starts at its count).
    bar = tqdm(total=len(stems), initial=len(stems) - len(todo), desc="segments", unit="img", disable=not progress)

    def done(i: int, arrays: dict, captions, parts: dict) -> None:
        _write_record(out, stems[i], arrays, captions)
        times.append(parts["total"])
        per_image[stems[i]] = parts
        unfinished()
        bar.set_postfix_str(_parts_line(parts), refresh=False)
        bar.update(1)

    if executor is None:
        for i in todo:
            t0 = time.perf_counter()
            arrays, captions, parts = extract_record(scene, source, depth, i, lift)
            parts["total"] = round(time.perf_counter() - t0, 3)
            done(i, arrays, captions, parts)
    else:
        from ..distributed import TaskFailure

        failed = []
        tasks = [(worker_setup, i, stems[i], lift) for i in todo]
        for k, result in executor.map(_extract_in_worker, tasks):
            i = todo[k]
            if isinstance(result, TaskFailure):
                failed.append(i)
                bar.write(f"segments: {result}", file=sys.stderr)
                continue
            done(i, *result)
        if failed:
            bar.close()
            names = ", ".join(Path(scene.image_paths[i]).name for i in sorted(failed))
            raise InputError(
                out,
                f"{len(failed)} of {len(todo)} images failed ({names}); the records of the "
                "others are kept: fix the inputs and rerun with --resume to finish the bank",
            )
    bar.close()

    return _finish_bank(scene, out, stems, header, per_image, times, num_quantiles)


def _finish_bank(
    scene,
    out: Path,
    stems: list[str],
    header: dict,
    per_image: dict[str, dict],  # image -> its seconds by part
    times: list[float],  # seconds of each image extracted by this run
    num_quantiles: int,
) -> dict:
    """Fit the quantile transform over every valid segment of the scene's records, write the
    final ``bank.json`` and return the report."""
    meta_path = out / "bank.json"
    all_scales, all_sources, n_total, n_empty, n_degenerate, n_layers = [], [], 0, 0, 0, []
    for stem in stems:
        d = _record_dir(out, stem)
        sc, va, ar = np.load(d / "scales.npy"), np.load(d / "valid.npy"), np.load(d / "areas.npy")
        n_layers.append(int(np.load(d / "layers.npy", mmap_mode="r").shape[0]))
        all_scales.append(sc[va])
        if all_sources is not None and (d / "source_ids.npy").is_file():
            all_sources.append(np.load(d / "source_ids.npy")[va])
        else:  # segments without ground-truth region ids (SAM, classical, LangSplat)
            all_sources = None
        n_total += sc.size
        n_empty += int((ar == 0).sum())
        n_degenerate += int(((ar > 0) & ~va).sum())
    scales = np.concatenate(all_scales) if all_scales else np.zeros(0)
    if scales.size == 0:
        raise InputError(
            out,
            "no segment could be lifted to 3D (no valid depth under any segment); check the Gaussians / depth source",
        )
    bins = QuantileScaleBins.fit(scales, num_quantiles)
    counts = {
        "images": len(stems),
        "segments": n_total,
        "valid": int(scales.size),
        "dropped_degenerate": n_degenerate,
        "dropped_empty": n_empty,
        "max_layers": max(n_layers) if n_layers else 0,
        "segments_per_image": n_total / max(1, len(stems)),
    }
    part_names = sorted({k for p in per_image.values() for k in p if k not in ("total", "segments")})
    timing = {
        "images_extracted_now": len(times),
        "seconds": float(sum(times)),
        "seconds_per_image": float(np.mean([p["total"] for p in per_image.values()])) if per_image else None,
        # Mean seconds per image of each part, and each image's own (also those of an
        # interrupted run this one finished).
        "seconds_per_image_by_part": {
            k: float(np.mean([p.get(k, 0.0) for p in per_image.values()])) for k in part_names
        },
        "per_image": per_image,
    }
    stats = {
        "scale_median": float(np.median(scales)),
        "scale_min": float(scales.min()),
        "scale_max": float(scales.max()),
    }
    check = None
    if all_sources is not None and scene.ground_truth is not None:
        check = ground_truth_scale_check(scales, np.concatenate(all_sources), scene.ground_truth.regions)
    meta = {
        **header,
        "complete": True,
        "source": str(scene.root),
        "quantile": bins.to_dict(),
        "counts": counts,
        "scale_stats": stats,
        "timing": timing,
        "ground_truth_check": check,
    }
    write_json(meta_path, meta)
    return {"bank": str(out), "counts": counts, "timing": timing, "scale_stats": stats, "ground_truth_check": check}


def _parts_line(parts: dict) -> str:
    """One image's parts for the progress bar: ``enc 20.1s dec 12.0s post 3.1s encoder 2.0s lift 0.2s, 95 segments``."""
    short = {"image_encoder": "enc", "mask_decoder": "dec", "postprocess": "post"}
    shown = [f"{short.get(k, k)} {v:.1f}s" for k, v in parts.items() if k not in ("total", "segments")]
    return " ".join(shown) + f", {parts.get('segments', 0)} segments"


def ground_truth_scale_check(
    scales: np.ndarray,  # [S] lifted scales of the valid segments
    region_ids: np.ndarray,  # [S] ground-truth region of each segment
    regions: dict,  # the demo scene's regions.json
) -> dict:
    """How well lifting worked, where the true regions are known (the demo scene): Spearman rank
    correlation of the lifted scales with the regions' true 3D extents, and the median scale per
    hierarchy level (it should grow from parts to objects to groups)."""
    from scipy.stats import spearmanr

    table = {int(r["id"]): r for r in regions["regions"]}
    extent = np.array([table[int(r)]["extent"] for r in region_ids], dtype=np.float64)
    level = np.array([table[int(r)]["level"] for r in region_ids])
    names = list(regions.get("levels", []))
    medians = {}
    for lv in sorted(set(level.tolist())):
        name = names[lv] if lv < len(names) else str(lv)
        medians[name] = float(np.median(scales[level == lv]))
    # scipy builds its result class at runtime, so its items have no static type.
    rho = float(spearmanr(scales, extent)[0]) if scales.size > 1 else float("nan")  # pyright: ignore[reportArgumentType]
    return {"spearman_scale_vs_true_extent": rho, "segments": int(scales.size), "median_scale_by_level": medians}
