"""Structure from motion for plain photo folders, with pycolmap (COLMAP's Python bindings).

Kept as one module (about 600 lines): one job, one SfM run, whose stages share its working
folder, cache key and report.

``n2f2 sfm PHOTOS --out DATA`` poses a folder of photos and writes the COLMAP scene layout that
:func:`n2f2.data.load_scene` reads::

    DATA/
      images/*                              the registered photos, undistorted (PINHOLE cameras)
      sparse/0/{cameras,images,points3D}.bin
      colmap/                               working files: database.db (features, matches),
                                            sparse/K/ (the raw models), colmap.log.*
      sfm_report.json                       counts, errors, timings, settings and the cache key

Stages: SIFT extraction -> matching (every pair, or a sliding window for video-like sets) ->
incremental mapping (COLMAP may split the photos into several models; the largest is kept) ->
undistortion to PINHOLE, since Gaussian splatting renders an ideal pinhole camera.

The result is built in ``DATA.partial/`` and renamed to ``DATA`` only when complete (with
``sfm_report.json`` inside), so an interrupted run never leaves a ``DATA`` that looks finished.
A rerun on the same photos (names, sizes, modification times) with the same settings reuses the
result; anything else into a finished ``DATA`` is refused unless ``overwrite`` is set.

:func:`posed_scene_path` lets the commands that take a scene (``fit-gaussians``, ``run``) take
a plain photo folder too.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import time
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Callable, Optional, TypeVar

from ..config import option
from ..errors import InputError
from ..io import LOCK_NAME, write_json
from ..validate import positive_int

__all__ = [
    "CAMERA_MODELS",
    "IMAGE_EXTENSIONS",
    "MATCHERS",
    "REPORT_NAME",
    "SfmReport",
    "SfmSettings",
    "find_photo_folder",
    "list_photos",
    "posed_scene_path",
    "run_sfm",
]

_T = TypeVar("_T")

REPORT_NAME = "sfm_report.json"
WORK_DIR = "colmap"
PARTIAL_MARKER = ".n2f2-sfm-partial"
FORMAT_VERSION = 1  # part of the cache key: bump when the output of the same settings changes
IMAGE_EXTENSIONS = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp")
MATCHERS = ("auto", "exhaustive", "sequential")
# Perspective models COLMAP can undistort to PINHOLE; fisheye models are left out (a wide
# fisheye does not fit one undistorted pinhole image).
CAMERA_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV")
EXHAUSTIVE_MAX_IMAGES = 200  # SfmSettings.exhaustive_max_images: the most photos "auto" matches exhaustively


@dataclass(frozen=True)
class SfmSettings:
    """Settings of :func:`run_sfm`. The defaults are chosen for handheld phone photos of one
    object or room (tens to a few hundred photos); each says why it differs from COLMAP's.
    Fields declared with option() are flags of `n2f2 sfm`."""

    # "exhaustive" matches every pair (most robust for unordered photos, O(N^2));
    # "sequential" matches each photo with its `sequential_overlap` successors in file-name
    # order (and with i + 2^k), for video frames; "auto" picks exhaustive up to
    # `exhaustive_max_images` photos (plush-dog's 3,486 pairs of ~1,300 features each took
    # ~50 s of CPU time; 200 photos are 19,900 pairs).
    matcher: str = option(
        "auto",
        help="exhaustive: every pair; sequential: neighbours in file-name order (video frames); "
        f"auto: exhaustive up to {EXHAUSTIVE_MAX_IMAGES} photos",
        choices=MATCHERS,
    )
    exhaustive_max_images: int = EXHAUSTIVE_MAX_IMAGES
    sequential_overlap: int = 10  # COLMAP's default
    # SIMPLE_RADIAL (one focal length, principal point at the centre, one radial term) is
    # COLMAP's default: phone and compact-camera lenses are close to it, and with few or
    # weakly textured photos it is better determined than OPENCV's eight parameters. Use
    # OPENCV for a wide lens with visible barrel distortion and many good photos.
    camera_model: str = option("SIMPLE_RADIAL", help="lens model estimated before undistortion", choices=CAMERA_MODELS)
    # One camera shared by all photos (COLMAP's SINGLE mode): photos from one phone at one
    # zoom share intrinsics, and pooling them constrains focal length and distortion far
    # better than per-photo estimates. Photos of different sizes get one camera each anyway.
    per_image_camera: bool = False
    # Longest side features are extracted at: bigger photos are downscaled for SIFT only
    # (keypoints are scaled back; the undistorted images keep the full resolution). COLMAP's
    # 3200 quadruples the SIFT work on a 12 MP phone photo, whose first octave is already
    # upsampled twice, for features far finer than a Gaussian-splatting fit resolves.
    max_image_size: int = option(1600, help="longest side features are extracted at", type=positive_int, metavar="N")
    # SIFT's difference-of-Gaussians threshold. COLMAP's 0.0067 finds only ~470 features a
    # photo on a soft, low-contrast object in 750x500 photos (plush-dog: 44 of 84 registered);
    # 0.0025 finds ~1,300 (79 of 84). On well-textured photos `max_num_features` caps the count.
    peak_threshold: float = 0.0025
    max_num_features: int = 8192  # COLMAP's default
    # Domain-size pooling (DSP-SIFT, Dong & Soatto 2015; COLMAP's FAQ suggests it for hard
    # scenes) pools each descriptor over several patch sizes, so more true matches pass the
    # ratio test on blurry or weakly textured surfaces. On plush-dog it took the weakest
    # photo from 31 to 68 registered points and all 84 photos register (4,586 points instead
    # of 3,110), for about 1.8x the extraction CPU time.
    domain_size_pooling: bool = True
    # Minimum 2D-3D inliers to register a photo: COLMAP's 30. Without domain-size pooling,
    # 20 also registers all of plush-dog, but lowering it admits wrong poses on repetitive
    # scenes; better descriptors fix the cause instead.
    abs_pose_min_num_inliers: int = 30
    init_min_num_inliers: int = 100  # COLMAP's default: the first pair must be well posed
    min_num_matches: int = 15  # COLMAP's default: verified matches for a pair to count
    seed: int = 0  # RANSAC and mapper seed, for repeatable results
    num_threads: int = -1  # -1: all cores (not part of the cache key)

    def __post_init__(self) -> None:
        if self.matcher not in MATCHERS:
            raise InputError(None, f"unknown matcher {self.matcher!r}; expected one of {', '.join(MATCHERS)}")
        if self.camera_model not in CAMERA_MODELS:
            raise InputError(
                None, f"unknown camera model {self.camera_model!r}; expected one of {', '.join(CAMERA_MODELS)}"
            )
        if not self.max_image_size >= 64:
            raise InputError(None, f"max image size must be >= 64 pixels, got {self.max_image_size}")
        for name in (
            "exhaustive_max_images",
            "sequential_overlap",
            "max_num_features",
            "abs_pose_min_num_inliers",
            "init_min_num_inliers",
            "min_num_matches",
        ):
            if not getattr(self, name) >= 1:
                raise InputError(None, f"{name} must be >= 1, got {getattr(self, name)}")
        if not 0 < self.peak_threshold < 1:
            raise InputError(None, f"peak_threshold must be in (0, 1), got {self.peak_threshold}")

    def resolved_matcher(self, num_images: int) -> str:
        if self.matcher != "auto":
            return self.matcher
        return "exhaustive" if num_images <= self.exhaustive_max_images else "sequential"

    def key_fields(self) -> dict:
        """The settings that change the result (all but the thread count)."""
        d = asdict(self)
        d.pop("num_threads")
        return d


@dataclass
class SfmReport:
    """What :func:`run_sfm` did (``DATA/sfm_report.json``)."""

    photos: str  # the photo folder
    out: str
    images_given: int
    registered: int
    points: int
    mean_reprojection_error_px: float
    mean_track_length: float
    models: list[int]  # registered photos of each model COLMAP made, largest (the one kept) first
    unregistered: list[str]  # photo names left out of the kept model
    matcher: str  # "exhaustive" or "sequential"
    camera_mode: str  # "shared" or "per-image"
    cameras: list[dict]  # as estimated, before undistortion: {"model", "width", "height", "params"}
    features_per_image: float
    verified_pairs: int
    timings_s: dict[str, float]
    key: str
    settings: dict
    pycolmap_version: str
    format_version: int = FORMAT_VERSION
    reused: bool = field(default=False, compare=False)  # this call reused a finished result

    def to_dict(self) -> dict:
        d = asdict(self)
        d.pop("reused")
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "SfmReport":
        names = {f.name for f in fields(cls)}
        return cls(**{k: v for k, v in d.items() if k in names})

    def summary(self) -> str:
        """One line for the terminal."""
        stages = ", ".join(f"{name} {seconds:.0f} s" for name, seconds in self.timings_s.items())
        models = "one model" if len(self.models) == 1 else f"the largest of {len(self.models)} models"
        return (
            f"sfm: registered {self.registered} of {self.images_given} photos ({models}), "
            f"{self.points:,} points, mean reprojection error {self.mean_reprojection_error_px:.2f} px, "
            f"mean track length {self.mean_track_length:.1f}; {stages} -> {self.out}"
        )


# ----------------------------------------------------------------------------- photo folders
def list_photos(folder: Path) -> list[str]:
    """Names of the image files directly inside ``folder`` (not recursive), sorted."""
    return sorted(
        p.name
        for p in Path(folder).iterdir()
        if p.is_file() and not p.name.startswith(".") and p.suffix.lower() in IMAGE_EXTENSIONS
    )


def find_photo_folder(data: Path) -> Optional[Path]:
    """The folder of photos in ``data``: ``data`` itself when image files lie directly in it,
    else ``data/images`` when that holds images; ``None`` when neither does."""
    data = Path(data)
    for folder in (data, data / "images"):
        if folder.is_dir() and list_photos(folder):
            return folder
    return None


def _photo_sizes(folder: Path, names: list[str]) -> list[tuple[int, int]]:
    """(width, height) of each photo from its header; an unreadable file is an InputError."""
    from PIL import Image, UnidentifiedImageError

    sizes = []
    for name in names:
        try:
            with Image.open(folder / name) as im:
                sizes.append(im.size)
        except (UnidentifiedImageError, OSError, Image.DecompressionBombError) as e:
            raise InputError(folder / name, f"cannot read image ({e})") from None
    return sizes


def _cache_key(folder: Path, names: list[str], settings: SfmSettings, version: str) -> str:
    stats = [os.stat(folder / n) for n in names]
    inputs = {
        "photos": [[n, s.st_size, s.st_mtime_ns] for n, s in zip(names, stats)],
        "settings": settings.key_fields(),
        "pycolmap": version,
        "format": FORMAT_VERSION,
    }
    return hashlib.sha256(json.dumps(inputs, sort_keys=True).encode()).hexdigest()[:16]


def _is_within(path: Path, folder: Path) -> bool:
    path, folder = path.resolve(), folder.resolve()
    return path == folder or folder in path.parents


def _finished_report(out: Path) -> Optional[dict]:
    path = out / REPORT_NAME
    if not path.is_file():
        return None
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


# ----------------------------------------------------------------------------- the stages
def _pair_batches(num_images: int, matcher: str, overlap: int, block: int = 50) -> list[list[tuple[int, int]]]:
    """Image index pairs (i < j) to match, in batches that touch few images each (as COLMAP's
    own exhaustive matcher does: each image's descriptors are loaded once per batch).

    Exhaustive: every pair, in blocks of ``block`` x ``block`` images. Sequential: each photo
    with its ``overlap`` successors and with i + 2^k (COLMAP's quadratic overlap, which
    bridges longer gaps), in batches of ``block`` consecutive first images."""
    starts = range(0, num_images, block)
    if matcher == "exhaustive":
        return [
            [
                (i, j)
                for i in range(a, min(a + block, num_images))
                for j in range(b, min(b + block, num_images))
                if i < j
            ]
            for a in starts
            for b in starts
            if b >= a
        ]
    batches = []
    for a in starts:
        pairs = set()
        for i in range(a, min(a + block, num_images)):
            for k in range(1, overlap + 1):
                for j in (i + k, i + 2 ** (k - 1)):
                    if j < num_images:
                        pairs.add((i, j))
        batches.append(sorted(pairs))
    return [b for b in batches if b]


def _models_text(registered: list[int]) -> str:
    """What the map stage found, for its progress line: ``[84, 2]`` gives "2 models, 84 and 2
    photos registered (the largest is kept)"."""
    if not registered:
        return "no model"
    counts = [str(n) for n in registered]
    listed = counts[0] if len(counts) == 1 else ", ".join(counts[:-1]) + " and " + counts[-1]
    photos = "photo" if registered == [1] else "photos"
    if len(registered) == 1:
        return f"1 model, {listed} {photos} registered"
    return f"{len(registered)} models, {listed} {photos} registered (the largest is kept)"


class _Stages:
    """Runs the pycolmap stages in ``work`` with one settings object; records timings."""

    def __init__(
        self,
        photos: Path,
        names: list[str],
        work: Path,
        settings: SfmSettings,
        progress: bool,
        log: Callable[[str], None],
    ):
        import pycolmap

        self.pycolmap = pycolmap
        self.photos, self.names, self.work, self.settings = photos, names, work, settings
        self.database = work / "database.db"
        self.progress, self.log = progress, log
        self.timings: dict[str, float] = {}

    def _bar(self, total: Optional[int], desc: str, unit: str):
        from tqdm import tqdm

        # A named unit: tqdm writes the rate as "1.02s/photo" (an empty one gives "1.02s/]").
        return tqdm(total=total, desc=desc, unit=unit, leave=False, disable=not self.progress)

    def extract(self, shared_camera: bool) -> float:
        """SIFT features of every photo, in chunks so that progress can be shown. Returns
        the mean number of features per photo."""
        pc, s = self.pycolmap, self.settings
        reader = pc.ImageReaderOptions()
        reader.camera_model = s.camera_model
        options = pc.FeatureExtractionOptions()
        options.max_image_size = s.max_image_size
        options.num_threads = s.num_threads
        options.sift.peak_threshold = s.peak_threshold
        options.sift.max_num_features = s.max_num_features
        options.sift.domain_size_pooling = s.domain_size_pooling
        mode = pc.CameraMode.SINGLE if shared_camera else pc.CameraMode.PER_IMAGE
        chunk = max(8, 4 * (os.cpu_count() or 1))
        with self._bar(len(self.names), "sfm: extracting features", "photo") as bar:
            for start in range(0, len(self.names), chunk):
                batch = self.names[start : start + chunk]
                pc.extract_features(
                    self.database,
                    self.photos,
                    image_names=batch,
                    camera_mode=mode,
                    reader_options=reader,
                    extraction_options=options,
                )
                if shared_camera and reader.existing_camera_id < 0:
                    # Later chunks must reuse the first chunk's camera, not make their own.
                    with pc.Database.open(self.database) as db:
                        reader.existing_camera_id = db.read_all_cameras()[0].camera_id
                bar.update(len(batch))
        with pc.Database.open(self.database) as db:
            images = db.read_all_images()
            counts = [db.num_keypoints_for_image(im.image_id) for im in images]
        missing = sorted(set(self.names) - {im.name for im in images})
        if missing:
            raise InputError(
                self.photos / missing[0], f"COLMAP could not read {len(missing)} of the photos (first: {missing[0]})"
            )
        return sum(counts) / max(len(counts), 1)

    def match(self, matcher: str) -> int:
        """Match the chosen pairs and verify them geometrically. Returns the number of pairs
        with at least ``min_num_matches`` verified matches."""
        pc, s = self.pycolmap, self.settings
        options = pc.FeatureMatchingOptions()
        options.num_threads = s.num_threads
        verification = pc.TwoViewGeometryOptions()
        verification.ransac.random_seed = s.seed
        if any(len(name.split()) != 1 for name in self.names):
            # COLMAP's pair lists are space-separated: let its own pairing run (no progress bar).
            if matcher == "exhaustive":
                pc.match_exhaustive(self.database, matching_options=options, verification_options=verification)
            else:
                pairing = pc.SequentialPairingOptions()
                pairing.overlap = s.sequential_overlap
                pc.match_sequential(
                    self.database, matching_options=options, pairing_options=pairing, verification_options=verification
                )
        else:
            self._match_batches(_pair_batches(len(self.names), matcher, s.sequential_overlap), options, verification)
        with pc.Database.open(self.database) as db:
            _, inliers = db.read_two_view_geometry_num_inliers()
        return sum(n >= s.min_num_matches for n in inliers)

    def _match_batches(self, batches: list[list[tuple[int, int]]], options, verification) -> None:
        """Match batches of image index pairs, one pycolmap call each, to show progress."""
        pc = self.pycolmap
        pair_file = self.work / "pairs.txt"
        with self._bar(sum(len(b) for b in batches), "sfm: matching pairs", "pair") as bar:
            for batch in batches:
                pair_file.write_text("".join(f"{self.names[i]} {self.names[j]}\n" for i, j in batch))
                pairing = pc.ImportedPairingOptions()
                pairing.match_list_path = pair_file
                pc.match_image_pairs(
                    self.database, matching_options=options, pairing_options=pairing, verification_options=verification
                )
                bar.update(len(batch))

    def map(self):
        """Incremental mapping into ``work/sparse/K``; returns ``[(K, reconstruction)]``,
        largest (most registered photos, then most points) first."""
        pc, s = self.pycolmap, self.settings
        options = pc.IncrementalPipelineOptions()
        options.num_threads = s.num_threads
        options.random_seed = s.seed
        options.min_num_matches = s.min_num_matches
        options.mapper.abs_pose_min_num_inliers = s.abs_pose_min_num_inliers
        options.mapper.init_min_num_inliers = s.init_min_num_inliers
        sparse = self.work / "sparse"
        sparse.mkdir(parents=True, exist_ok=True)
        with self._bar(len(self.names), "sfm: registering photos", "photo") as bar:
            models = pc.incremental_mapping(
                self.database, self.photos, sparse, options=options, next_image_callback=lambda: bar.update(1)
            )
        return sorted(models.items(), key=lambda kv: (kv[1].num_reg_images(), kv[1].num_points3D()), reverse=True)

    def undistort(self, model_dir: Path, dest: Path) -> None:
        """Undistort the photos of ``model_dir`` to PINHOLE into ``dest/images`` and
        ``dest/sparse/0``."""
        pc = self.pycolmap
        undistorted = self.work / "undistorted"
        if undistorted.exists():
            shutil.rmtree(undistorted)
        pc.undistort_images(
            undistorted, model_dir, self.photos, output_type="COLMAP", num_threads=self.settings.num_threads
        )
        os.replace(undistorted / "images", dest / "images")
        (dest / "sparse").mkdir(exist_ok=True)
        os.replace(undistorted / "sparse", dest / "sparse" / "0")
        shutil.rmtree(undistorted)  # the dense-stereo folder and scripts are not used

    def timed(self, name: str, fn: Callable[[], _T], describe: Callable[[_T], str] = lambda r: "") -> _T:
        start = time.perf_counter()
        result = fn()
        self.timings[name] = round(time.perf_counter() - start, 2)
        detail = describe(result)
        self.log(f"sfm: {name:<9} {self.timings[name]:7.1f} s" + (f"  {detail}" if detail else ""))
        return result


class _ColmapLog:
    """Send COLMAP's log (several lines per photo and pair) to ``work/colmap.log.*`` instead of
    the terminal while the stages run; failures reach the user as InputErrors instead."""

    def __init__(self, pycolmap, work: Path):
        self.logging, self.work = pycolmap.logging, work

    def __enter__(self):
        log = self.logging
        self.saved = (log.logtostderr, log.alsologtostderr, log.stderrthreshold)
        log.logtostderr, log.alsologtostderr, log.stderrthreshold = False, False, 3  # FATAL only
        log.set_log_destination(log.INFO, str(self.work / "colmap.log."))
        return self

    def __exit__(self, *exc):
        log = self.logging
        log.set_log_destination(log.INFO, "")  # closes the file
        log.logtostderr, log.alsologtostderr, log.stderrthreshold = self.saved


def run_sfm(
    photos: str | Path,
    out: str | Path,
    settings: SfmSettings = SfmSettings(),
    *,
    overwrite: bool = False,
    keep_partial: bool = False,
    progress: bool = True,
    log: Callable[[str], None] = print,
) -> SfmReport:
    """Pose the photos in ``photos`` (image files directly inside, or in ``photos/images``)
    and write the COLMAP scene layout to ``out`` (see the module docstring).

    Reuses a finished ``out`` made from the same photos and settings; refuses a finished
    ``out`` made from others unless ``overwrite``, and refuses any other non-empty ``out``.
    Raises :class:`InputError` when there are no photos or fewer than half of them register.
    """
    try:
        import pycolmap
    except ImportError:
        raise InputError(None, "structure from motion needs pycolmap: pip install pycolmap") from None

    photos, out = Path(photos), Path(out).absolute()  # absolute: "." has no name for DATA.partial
    if not photos.is_dir():
        raise InputError(photos, "photo folder does not exist")
    folder = find_photo_folder(photos)
    if folder is None:
        raise InputError(photos, f"no images here ({', '.join(IMAGE_EXTENSIONS)}, directly inside or in images/)")
    names = list_photos(folder)
    if len(names) < 3:
        raise InputError(
            folder, f"only {len(names)} image(s): structure from motion needs at least 3 overlapping photos"
        )
    if _is_within(folder, out):
        raise InputError(out, f"the output folder contains the photos ({folder}); choose another --out")
    key = _cache_key(folder, names, settings, pycolmap.__version__)

    previous = _finished_report(out)
    if previous is not None:
        same = previous.get("key") == key
        if same and (out / "sparse" / "0").is_dir() and (out / "images").is_dir():
            report = SfmReport.from_dict(previous)
            report.reused = True
            log(f"sfm: {out} is up to date (key {key}): reusing it")
            return report
        if not same and not overwrite:
            raise InputError(
                out,
                "holds the structure-from-motion result of other photos or settings; "
                "pass --force to replace it, or choose another --out",
            )
    elif out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise InputError(
            out, f"exists and is not a finished sfm result (no {REPORT_NAME}); choose a new or empty --out"
        )

    partial = out.with_name(out.name + ".partial")
    if partial.exists() and not (partial / PARTIAL_MARKER).is_file():
        raise InputError(partial, "exists and was not made by n2f2 sfm; move it away")
    from ..io import check_writable_dir, lock_out_dir

    check_writable_dir(partial)
    lock_out_dir(partial)  # a second sfm into the same DATA stops here, naming the first
    for leftover in partial.iterdir():  # an earlier, interrupted attempt
        if leftover.name != LOCK_NAME:
            shutil.rmtree(leftover) if leftover.is_dir() and not leftover.is_symlink() else leftover.unlink()
    try:
        report = _pose(pycolmap, folder, names, out, partial, key, settings, progress, log)
    except BaseException:
        if keep_partial:
            log(f"sfm: working files kept in {partial} (--keep-partial)")
        else:
            shutil.rmtree(partial, ignore_errors=True)
        raise
    return report


def _pose(
    pycolmap,
    folder: Path,
    names: list[str],
    out: Path,
    partial: Path,
    key: str,
    settings: SfmSettings,
    progress: bool,
    log: Callable[[str], None],
) -> SfmReport:
    """The work of :func:`run_sfm` in ``partial``, renamed to ``out`` when complete."""
    work = partial / WORK_DIR
    work.mkdir(parents=True)
    (partial / PARTIAL_MARKER).touch()

    sizes = _photo_sizes(folder, names)
    shared = not settings.per_image_camera and len(set(sizes)) == 1
    if not settings.per_image_camera and not shared:
        log(f"sfm: the photos have {len(set(sizes))} different sizes: one camera per photo")
    matcher = settings.resolved_matcher(len(names))
    log(
        f"sfm: {len(names)} photos in {folder}, {matcher} matching, "
        f"{'one shared' if shared else 'one per-photo'} {settings.camera_model} camera"
    )

    stages = _Stages(folder, names, work, settings, progress, log)
    with _ColmapLog(pycolmap, work):
        features = stages.timed("extract", lambda: stages.extract(shared), lambda n: f"{n:.0f} features per photo")
        pairs = stages.timed("match", lambda: stages.match(matcher), lambda n: f"{n} verified pairs")
        models = stages.timed(
            "map",
            stages.map,
            lambda m: _models_text([r.num_reg_images() for _, r in m]),
        )
        registered = models[0][1].num_reg_images() if models else 0
        if 2 * registered < len(names):
            raise InputError(
                folder,
                f"registered {registered} of {len(names)} photos; structure from "
                f"motion needs sharp, textured photos that overlap (every part of the "
                f"scene in 3 or more photos, taken a small step apart)"
                + ("; try --matcher exhaustive" if matcher == "sequential" else "")
                + "; `n2f2 sfm --keep-partial` keeps the working files",
            )
        index, model = models[0]
        stages.timed("undistort", lambda: stages.undistort(work / "sparse" / str(index), partial))

    result = pycolmap.Reconstruction(partial / "sparse" / "0")
    kept = {im.name for im in result.images.values()}
    report = SfmReport(
        photos=str(folder),
        out=str(out),
        images_given=len(names),
        registered=result.num_reg_images(),
        points=result.num_points3D(),
        mean_reprojection_error_px=round(float(result.compute_mean_reprojection_error()), 4),
        mean_track_length=round(float(result.compute_mean_track_length()), 3),
        models=[r.num_reg_images() for _, r in models],
        unregistered=[n for n in names if n not in kept],
        matcher=matcher,
        camera_mode="shared" if shared else "per-image",
        cameras=[
            {
                "model": c.model.name,
                "width": c.width,
                "height": c.height,
                "params": [round(float(p), 6) for p in c.params],
            }
            for c in model.cameras.values()
        ],
        features_per_image=round(features, 1),
        verified_pairs=pairs,
        timings_s=dict(stages.timings),
        key=key,
        settings=settings.key_fields(),
        pycolmap_version=pycolmap.__version__,
    )
    write_json(partial / REPORT_NAME, report.to_dict())
    (partial / PARTIAL_MARKER).unlink()
    (partial / LOCK_NAME).unlink(missing_ok=True)  # the lock stays held (by its descriptor) until the end
    if out.exists():  # a finished result being overwritten, or an empty folder
        shutil.rmtree(out) if out.is_dir() else out.unlink()
    os.replace(partial, out)
    return report


def posed_scene_path(
    data: str | Path,
    cache_root: str | Path,
    settings: Optional[SfmSettings] = None,
    *,
    progress: bool = True,
    log: Callable[[str], None] = print,
) -> Path:
    """``data`` itself when it is a scene (``transforms.json`` or a COLMAP model) or not a photo
    folder; for a plain folder of photos (images directly inside, or ``images/`` without a
    model), the scene :func:`run_sfm` makes from them in ``cache_root`` (reused while the
    photos and settings are unchanged)."""
    from . import detect_format

    data = Path(data)
    try:
        detect_format(data)
        return data
    except InputError:
        pass
    if find_photo_folder(data) is None:
        return data  # not photos either: load_scene reports what is missing
    log(f"{data} holds photos without camera poses: structure from motion into {cache_root}")
    report = run_sfm(data, cache_root, settings or SfmSettings(), overwrite=True, progress=progress, log=log)
    if not report.reused:
        log(report.summary())
    return Path(cache_root)
