"""Time up front: what ``n2f2 run`` and ``n2f2 doctor`` expect each stage to take, from the
scene's size and the machine's measured speed.

The machine is measured once per process and device (:func:`calibrate`, about 2 s): the median
time of a fixed [1024, 1024] x [1024, 1024] float32 matmul on torch's threads (dense arithmetic:
SAM, CLIP) and of rasterizing 4,000 fixed random Gaussians into a 160 x 120 view with
:func:`n2f2.render.rasterize` (the numba backend the CPU stages use; the torch backend on a GPU,
where gsplat's first call may build its kernels). Each stage's cost at the reference machine's
speed (:func:`stage_estimates`, constants below) is then divided by this machine's speed, the
reference's time over this one's, for its kind of work: the rasterizer's for the fit; the
matmul's for SAM and CLIP; for the rest (the other segmenters, the lifting, the training, the
evaluation: torch's operations on its threads around the renders) the slower of the two, since
other processes on the same cores slow torch's threaded operations most (a training step of the
demo 9x, its fit step 2x, at a load average of 7 on 2 cores).

Models' loading and each stage's fixed work are constants; compiling numba's kernels (once per
install) is left out. On a GPU the estimates are rougher still, the constants being a CPU's.

The cost model, per stage:

* fit-gaussians: steps x pixels of a step (a view at the chosen ``--downscale``, less during a
  coarse-to-fine schedule's coarse steps), the schedule :meth:`FitConfig.for_scene` sizes;
* segments: per image, the segmenter's cost (a fixed cost for SAM and SAM 2.1, which resize every
  image to 1024 x 1024, a per-pixel one for the others) + the lifting's per-pixel cost + CLIP's per
  segment (about 100 segments a photo for SAM's real masks);
* train: steps x pixels per step, plus the blend cache (once per training view and pixel) or,
  without it, one rasterized view per step;
* eval: labelled views x pixels x modes.
"""

from __future__ import annotations

import functools
import os
import statistics
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Optional

# ----------------------------------------------------------------------------- reference machine
# The reference: AMD EPYC (/proc/cpuinfo "AMD EPYC", cpu family 25, model 1: Zen 3), 2 cores,
# torch 2.13 CPU (MKL, AVX2), 2 torch threads, GOMP_SPINCOUNT as the CLI sets it.
#
# Calibration: the matmul's and the torch rasterizer's times are the fastest of many repeats of
# calibrate()'s kernels on that machine while other jobs shared it, i.e. its quietest moments
# (the matmul then ran at ~170 GFLOP/s, as the 165 GFLOP/s of docs/measurements.md's SAM floors
# on the same machine, quiet). The numba rasterizer's could not be had quiet: it is the quiet
# demo fit step (40 ms) over the fit step's time in units of calibrate()'s numba raster, which
# 200-step demo fits timed back to back with calibrate() under load put at 1.6x to 3.4x (2.4x
# on average); 3.1x is taken, a whole fit's steps costing more than a short one's (up to 12,000
# Gaussians against 7,400).
#
# Stage constants: that machine's quiet times in docs/measurements.md (the demo scene: 40 views
# of 160 x 120, 35 for training, cpu preset: fit 60 s, segments 5 s, train 88 s with a 3.1 s
# blend cache, eval 15 s; full-size SAM ViT-H, SAM 2.1 tiny and CLIP ViT-B/16 on 750 x 500
# photos), less a fixed part per stage (reading the scene and the inputs, loading models,
# writing), over the sizes of the module docstring. The classical segmenter's was timed here on a
# demo view (0.085 s for 19,200 pixels).
REFERENCE_MACHINE = "AMD EPYC (Zen 3), 2 cores, 2 torch threads"
REF_MATMUL_S = 0.0125  # one [1024, 1024] x [1024, 1024] float32 matmul
REF_RASTER_S = {  # 4,000 random Gaussians into 160 x 120, by the rasterizer's backend
    "numba": 0.013,
    "torch": 0.0135,
}
FIXED_S = {"fit-gaussians": 2.0, "segments": 1.5, "train": 3.0, "eval": 4.0}  # whatever the sizes
MODEL_LOAD_S = {"sam": 5.0, "sam2": 3.0, "clip": 1.5}  # ViT-H + CLIP loaded in 6 s, SAM 2.1 tiny ~4 s
FIT_S_PER_PIXEL = 2.0e-6  # a fit step per pixel of its view: demo 1500 steps x 19,200 px in 58 s
TRAIN_S_PER_PIXEL = 13.3e-6  # a training step per sampled pixel: demo 3000 x 2048 px in 82 s (cpu preset)
BLEND_S_PER_PIXEL = 4.6e-6  # the blend cache, per training-view pixel: 3.1 s for 35 x 19,200 px
EVAL_S_PER_PIXEL = 1.8e-5  # a labelled view's pixel in one mode: demo 11 s for 8 views x 4 modes
LIFT_S_PER_PIXEL = 3.3e-6  # lifting a photo's segments (depth render, record): ~1.2 s at 750 x 500
SEGMENTER_S_PER_PIXEL = {  # besides the lifting
    "ground-truth": 1.3e-6,  # with the captions' MiniLM: demo 3.5 s for 40 views with the lifting (4.6e-6)
    "classical": 4.4e-6,  # three Felzenszwalb scales
}
SEGMENTER_S_PER_IMAGE = {  # encoder + mask decoder (1,024 prompts) + post-processing, any image size
    "sam": 68.8,  # ViT-H 47.1 + 17.8 + 3.9
    "sam2": 26.8,  # SAM 2.1 tiny 2.6 + 22.0 + 2.2 (large: ~95 s)
}
ENCODER_S_PER_SEGMENT = {"clip": 0.234}  # CLIP ViT-B/16 crop + image model (captions: in the segmenter's)
SEGMENTS_PER_IMAGE = 100  # a real SAM's masks kept on a photo (docs/measurements.md)
# Segmenters whose segments grow with the image. Classical: 24 a photo on the plush-dog photos at
# 185 x 123 (--downscale 4, bank.json of a run on 21 of them); taken as proportional to the
# pixels, at most SAM's count.
SEGMENTS_PER_PIXEL = {"classical": 24 / (185 * 123)}


def segments_per_image(segmenter: str, pixels: float) -> int:
    """The segments the encoder embeds per image: SAM's kept masks, or in proportion to the pixels."""
    if segmenter in SEGMENTS_PER_PIXEL:
        return max(1, min(SEGMENTS_PER_IMAGE, round(SEGMENTS_PER_PIXEL[segmenter] * pixels)))
    return SEGMENTS_PER_IMAGE


# ----------------------------------------------------------------------------- the machine
def cpu_name() -> str:
    """The CPU's model name from ``/proc/cpuinfo`` (``platform.processor()`` elsewhere)."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    import platform

    return platform.processor() or "unknown CPU"


def machine_line(device: str) -> str:
    """The CPU, the CPUs this process may use, torch's threads, CUDA, and ``--device``."""
    import torch

    try:
        usable = len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        usable = os.cpu_count() or 1
    cuda = (
        f"CUDA available ({torch.cuda.device_count()} x {torch.cuda.get_device_name(0)})"
        if torch.cuda.is_available()
        else "CUDA not available"
    )
    try:  # other processes on the same CPUs slow every stage, and the calibration with them
        load = f", load average {float(Path('/proc/loadavg').read_text().split()[0]):.1f}"
    except (OSError, ValueError, IndexError):
        load = ""
    threads = torch.get_num_threads()
    return f"{cpu_name()}, {usable} CPUs usable{load}, torch uses {threads} threads; {cuda}; --device {device}"


@dataclass(frozen=True)
class Speed:
    """The machine's calibration: median seconds of the two fixed kernels (see the module)."""

    device: str
    matmul_s: float
    raster_s: float
    backend: str  # the rasterizer's backend timed: numba on a CPU (as the stages use), else torch
    seconds: float  # the calibration's own time

    @property
    def arithmetic(self) -> float:
        """How many times the reference machine's speed at dense arithmetic."""
        return REF_MATMUL_S / self.matmul_s

    @property
    def raster(self) -> float:
        """How many times the reference machine's speed at rasterizing."""
        return REF_RASTER_S[self.backend] / self.raster_s

    @property
    def mixed(self) -> float:
        """The speed of torch's operations around renders: the slower of the two."""
        return min(self.arithmetic, self.raster)

    def describe(self) -> str:
        return (
            f"calibrated in {self.seconds:.1f} s: arithmetic {self.arithmetic:.2f}x, rasterizing "
            f"{self.raster:.2f}x the reference machine ({REFERENCE_MACHINE})"
        )


def _median_seconds(fn: Callable[[], object], sync: Callable[[], None], budget_s: float) -> float:
    """Median time of ``fn`` over as many calls as fit in ``budget_s`` (1 to 40), after one
    untimed call (a first call allocates and initialises). On a loaded machine a call can take
    a second: then one timed call is all there is."""
    fn()
    sync()
    times: list[float] = []
    end = time.perf_counter() + budget_s
    while len(times) < 40 and (not times or time.perf_counter() < end):
        start = time.perf_counter()
        fn()
        sync()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


@functools.lru_cache(maxsize=None)
def calibrate(device: str = "cpu", budget_s: float = 0.7) -> Speed:
    """Time the two fixed kernels on ``device`` (once per process and device: ``run-many``'s
    scenes share it). Random inputs come from a private generator: the caller's seeds are kept."""
    import torch

    from ..cameras import Camera
    from ..render import rasterize
    from ..render.numba_runtime import numba_usable

    start = time.perf_counter()
    dev = torch.device(device)

    def sync() -> None:
        if dev.type == "cuda":
            torch.cuda.synchronize(dev)

    gen = torch.Generator().manual_seed(0)
    n = 4000
    means = torch.rand(n, 3, generator=gen) * 2 - 1
    means[:, 2] += 4.0  # in front of the camera at the origin
    gaussians = [
        means,
        torch.randn(n, 4, generator=gen),  # quaternions
        0.01 + 0.04 * torch.rand(n, 3, generator=gen),  # scales
        torch.full((n,), 0.5),  # opacities
        torch.rand(n, 3, generator=gen),  # colours
    ]
    means_, quats, scales, opac, colours = (g.to(dev) for g in gaussians)
    camera = Camera(fx=160.0, fy=160.0, cx=80.0, cy=60.0, width=160, height=120)
    a, b = (torch.randn(1024, 1024, generator=gen).to(dev) for _ in range(2))
    backend = "numba" if dev.type == "cpu" and numba_usable() else "torch"
    with torch.no_grad():
        matmul_s = _median_seconds(lambda: a @ b, sync, budget_s)
        raster_s = _median_seconds(
            lambda: rasterize(means_, quats, scales, opac, colours, camera, backend=backend), sync, budget_s
        )
    return Speed(str(device), matmul_s, raster_s, backend, time.perf_counter() - start)


# ----------------------------------------------------------------------------- the scene
@dataclass(frozen=True)
class SceneSize:
    """What the stages' costs depend on."""

    views: int
    train_views: int
    width: int  # of the median view, at the chosen downscale
    height: int
    points: Optional[int]  # sparse points; None: none
    labelled_views: int  # 0: no evaluation
    source: str = ""  # the scene's format, for people

    @property
    def pixels(self) -> int:
        return self.width * self.height

    def describe(self, downscale: float) -> str:
        points = "no sparse points" if not self.points else f"{self.points:,} sparse points"
        labels = f", {self.labelled_views} labelled views" if self.labelled_views else ", no labels"
        return (
            f"{self.source + ', ' if self.source else ''}{self.views} views of {self.width}x{self.height} at "
            f"--downscale {downscale:g} ({self.train_views} for training), {points}{labels}"
        )


def scene_size(scene, labels: Optional[Path]) -> SceneSize:
    """The size of a loaded scene and its label folder (frame_*.json files)."""
    import numpy as np

    from ..gaussians.fit_config import FitConfig, split_views

    train, _ = split_views(scene, FitConfig().test_every)
    pixels = [c.width * c.height for c in scene.cameras]
    median = scene.cameras[int(np.argsort(pixels)[len(pixels) // 2])]
    return SceneSize(
        views=len(scene),
        train_views=len(train),
        width=median.width,
        height=median.height,
        points=None if scene.points is None else int(len(scene.points)),
        labelled_views=len(list(Path(labels).glob("frame_*.json"))) if labels is not None else 0,
        source=scene.source_format,
    )


# ----------------------------------------------------------------------------- the stages
@dataclass(frozen=True)
class StageEstimate:
    """One stage's expected seconds on this machine and the sizes it came from."""

    stage: str
    seconds: float
    workload: str

    def line(self) -> str:
        shown = f"~{self.seconds:.0f} s" if self.seconds >= 1 else f"~{self.seconds:.1f} s"
        if self.seconds >= 120:
            shown += f" ({self.seconds / 60:.0f} min)"
        return f"expected {self.stage}: {shown} ({self.workload})"


def _fit_estimate(opt, size: SceneSize, scene, speed: Speed) -> StageEstimate:
    """Steps x pixels of a step, with the schedule the fit will use."""
    from ..gaussians.fit_config import FitConfig

    config = FitConfig.for_scene(opt.preset, scene, steps=opt.fit_steps)
    pixel_steps, done = 0.0, 0.0  # over the fractions of the run at each further downscale
    for until, factor in zip(config.coarse_until, config.coarse_downscale):
        pixel_steps += (until - done) * config.steps * size.pixels / factor**2
        done = until
    pixel_steps += (1.0 - done) * config.steps * size.pixels
    cap = f", up to {config.max_gaussians:,} Gaussians" if config.max_gaussians else ""
    seconds = (FIXED_S["fit-gaussians"] + pixel_steps * FIT_S_PER_PIXEL) / speed.raster
    return StageEstimate("fit-gaussians", seconds, f"{config.steps} steps x {size.pixels:,} px{cap}")


def _segments_estimate(opt, size: SceneSize, speed: Speed) -> StageEstimate:
    """Per image: the segmenter, the lifting and, with CLIP, its segments; once: the models."""
    segmenting = opt.langsplat_features is None
    models = [m for m in (opt.segmenter if segmenting else None, opt.encoder if segmenting else None) if m]
    fixed = (FIXED_S["segments"] + sum(MODEL_LOAD_S.get(str(m), 0.0) for m in models)) / speed.mixed
    lift = LIFT_S_PER_PIXEL * size.pixels / speed.mixed
    if opt.langsplat_features is not None:
        per_image, what = lift, "LangSplat features imported"
    elif opt.segmenter in SEGMENTER_S_PER_IMAGE:
        per_image, what = SEGMENTER_S_PER_IMAGE[opt.segmenter] / speed.arithmetic + lift, opt.segmenter
    else:
        per_image = SEGMENTER_S_PER_PIXEL.get(str(opt.segmenter), 0.0) * size.pixels / speed.mixed + lift
        what = str(opt.segmenter)
    if opt.langsplat_features is None and opt.encoder in ENCODER_S_PER_SEGMENT:
        count = segments_per_image(str(opt.segmenter), size.pixels)
        per_image += ENCODER_S_PER_SEGMENT[opt.encoder] * count / speed.arithmetic
        what += f" + {opt.encoder} on ~{count} segments an image"
    elif opt.langsplat_features is None:
        what += f" + {opt.encoder}"
    return StageEstimate("segments", fixed + size.views * per_image, f"{size.views} images, {what}")


def _train_estimate(opt, size: SceneSize, speed: Speed) -> StageEstimate:
    """Steps x sampled pixels, plus the blend cache or a rasterized view per step."""
    from dataclasses import replace

    from ..train.config import TrainConfig

    config = TrainConfig.preset(opt.preset)
    if opt.train_steps:
        config = replace(config, iterations=opt.train_steps)
    seconds = FIXED_S["train"] + config.iterations * config.pixels_per_step * TRAIN_S_PER_PIXEL
    if config.blend_cache:
        seconds += size.train_views * size.pixels * BLEND_S_PER_PIXEL
    else:
        render = config.views_per_step * size.pixels / config.render_downscale**2
        seconds += config.iterations * render * FIT_S_PER_PIXEL
    workload = f"{config.iterations} steps x {config.pixels_per_step:,} px" + (
        "" if config.blend_cache else ", a rasterized view a step"
    )
    return StageEstimate("train", seconds / speed.mixed, workload)


def _eval_estimate(opt, size: SceneSize, speed: Speed) -> StageEstimate:
    """Labelled views x pixels x modes."""
    modes = len(opt.modes)
    seconds = (FIXED_S["eval"] + size.labelled_views * size.pixels * modes * EVAL_S_PER_PIXEL) / speed.mixed
    return StageEstimate("eval", seconds, f"{size.labelled_views} labelled views x {modes} modes")


def stage_estimates(opt, stages: list[str], size: SceneSize, scene, speed: Speed) -> list[StageEstimate]:
    """The expected time of each of ``stages`` (``opt``: resolved :class:`RunOptions`; ``scene``:
    the loaded scene the fit's schedule is sized to)."""
    made = {
        "fit-gaussians": lambda: _fit_estimate(opt, size, scene, speed),
        "segments": lambda: _segments_estimate(opt, size, speed),
        "train": lambda: _train_estimate(opt, size, speed),
        "eval": lambda: _eval_estimate(opt, size, speed),
    }
    return [made[stage]() for stage in stages]


def total_line(estimates: list[StageEstimate]) -> str:
    total = sum(e.seconds for e in estimates)
    return f"expected in all: ~{total:.0f} s" + (f" ({total / 60:.0f} min)" if total >= 120 else "")
