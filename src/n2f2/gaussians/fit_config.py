"""The Gaussian fit's settings (:class:`FitConfig`): 3DGS's defaults (``paper``), the cpu preset
for small scenes on a few cores (``cpu``), and how that preset sizes itself to a scene
(:meth:`FitConfig.sized_for`, from the scene's views and sparse points)."""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, replace
from pathlib import Path
from typing import ClassVar, Optional, Union

import numpy as np

from ..config import PRESET_NAMES, ConfigDict, option
from ..data.scene import Scene
from ..errors import InputError
from ..validate import nonneg_float, nonneg_int, positive_int
from .init import (
    uncovered_cells,
)
from .model import Gaussians


# ------------------------------------------------------------------------------------ config
@dataclass
class FitConfig(ConfigDict):
    """Hyper-parameters of :func:`fit_gaussians`. Defaults are the 3DGS paper's
    (``arguments/__init__.py`` of the reference code); see :meth:`cpu` and :meth:`paper`.

    Step counters are 1-based as in 3DGS: an event "every n steps" happens after step n, 2n..."""

    PRESETS: ClassVar[tuple[str, ...]] = PRESET_NAMES  # see the static methods of those names
    SIZED_PRESETS: ClassVar[tuple[str, ...]] = ("cpu",)  # sized to the scene (sized_for)

    # Fields declared with option() are flags of `n2f2 fit-gaussians`; their help lists each
    # preset's value.
    steps: int = option(
        30_000,
        help="optimisation steps of the Gaussian fit; the cpu preset sizes its count to the scene (shown: the "
        "demo scene's) and keeps its schedule's fractions of a count given here",
        type=positive_int,
    )
    sh_degree: int = 3  # maximum SH degree of the model
    sh_degree_interval: int = 1000  # raise the active SH degree by one every this many steps
    lambda_dssim: float = 0.2
    # Weight of the depth-spread regulariser: the pixel mean of sqrt(sum_i w_i (z_i - zbar)^2),
    # z in units of the extent, i.e. the spread of the depths blended into a pixel (times
    # sqrt(alpha)). It pulls the Gaussians along a ray onto one depth, like Mip-NeRF 360's
    # distortion loss. The square root keeps pixels on depth edges (table rim against the far
    # floor) from dominating; the squared form cost 2-3x more PSNR for the same depth gain. It
    # also removes structures thinner than a pixel, whose pixels always blend two depths (see
    # FitConfig.cpu). 0: off, as in 3DGS.
    depth_spread_weight: float = option(
        0.0,
        help="weight of the depth-spread regulariser, which pulls the Gaussians a ray meets onto one depth; "
        "0 = off, as 3DGS",
        type=nonneg_float,
        flag="depth-spread",
        metavar="W",
    )
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)  # colour behind the Gaussians
    # Replace ``background`` at the start of a fit by the median colour of the training views'
    # border pixels (recorded in the checkpoint and report). A plain backdrop then needs no
    # Gaussians: painting it with them on a black background filled the held-out views of a
    # real object capture with backdrop-coloured floaters (17.5 vs 21.6 dB after 1000 steps).
    background_from_images: bool = False
    # Learn the background as a colour over ray directions (spherical harmonics of this degree,
    # started at ``background``), an environment behind every Gaussian: a real backdrop shades
    # smoothly (light falloff, shadows) where a constant leaves most of a capture's error.
    # Saved as background.json beside the PLY. -1: the constant ``background``, as 3DGS.
    background_sh_degree: int = -1
    background_lr: float = 0.005

    # Adam learning rates. Positions are scaled by the scene extent and decay exponentially
    # from means_lr_init to means_lr_final over means_lr_max_steps.
    means_lr_init: float = 1.6e-4
    means_lr_final: float = 1.6e-6
    means_lr_max_steps: int = 30_000
    sh_dc_lr: float = 2.5e-3
    sh_rest_lr: float = 2.5e-3 / 20.0
    opacity_lr: float = 0.05
    scaling_lr: float = 5e-3
    rotation_lr: float = 1e-3
    adam_eps: float = 1e-15

    # Adaptive density control.
    densify_from: int = 500
    densify_until: int = 15_000
    densify_every: int = 100
    densify_grad_threshold: float = 2e-4  # on the NDC-space positional gradient, as 3DGS
    percent_dense: float = 0.01  # clone below / split above this fraction of the extent
    opacity_reset_every: int = 3000  # 0: never (and then large Gaussians are never pruned)
    prune_opacity: float = 0.005
    prune_world_size: float = 0.1  # prune Gaussians larger than this x extent (after 1st reset)
    max_gaussians: Optional[int] = option(
        None,
        help="cap on the Gaussian count, densification keeping the largest gradients; the cpu preset sizes "
        "it to the views' pixels (shown: the demo scene's)",
        type=positive_int,
        metavar="N",
    )
    # Also split Gaussians whose screen radius exceeded this fraction of the image size since the
    # last densification (gsplat's grow_scale2d); None: off, as in 3DGS.
    split_screen_size: Optional[float] = None

    # Initialisation when the scene has no sparse points (random inside the frusta).
    random_init_count: int = 100_000
    random_init_depth: tuple[float, float] = (0.2, 1.6)  # z-depth range, x extent
    # Largest initial scale, x extent. k-NN distances of sparse or random points can be huge
    # (far walls with few points), and one such Gaussian near a camera covers the whole screen
    # and makes a step many times slower. None: no clamp, as 3DGS.
    init_max_scale: Optional[float] = None
    # With sparse points, also start random Gaussians where they miss: plain walls and backdrops
    # get no SfM points, and densification only grows Gaussians near existing ones. This many
    # per point, times the fraction of the training views' grid cells (16 along the longer side)
    # that no point projects into, drawn through random pixels of those cells (coloured by
    # them) onto a sphere behind every camera (init.background_shell). Generated scenes, whose
    # points cover every surface, get almost none. 0: points only, as 3DGS.
    init_extra_random: float = 0.0
    # With sparse points, also start this many random Gaussians inside the views'
    # overlap (drawn as for a random initialisation: ``random_init_depth``,
    # ``random_init_min_seen``, pixel colours): SfM triangulates no point on textureless
    # surfaces near the object (a mat, a tabletop), and nothing else would grow there. 0: points only.
    init_extra_seen: int = 0
    # Without sparse points: the fraction of the random Gaussians put on that sphere, and the
    # fraction of the training views each of the others must be seen in (0: anywhere in a frustum).
    random_init_shell: float = 0.0
    random_init_min_seen: float = 0.0

    # Coarse to fine: up to step ``coarse_until[i] * steps`` the views are rendered and compared
    # at a further ``coarse_downscale[i]`` (images area-averaged). A step's cost scales with its
    # pixels, and the early model is blurry anyway. Empty: full resolution throughout, as 3DGS.
    coarse_until: tuple[float, ...] = ()
    coarse_downscale: tuple[float, ...] = ()
    # Prune Gaussians whose screen radius exceeded this fraction of the image size since the
    # last densification (gsplat's prune_scale2d), bounding the screen area any one can cover.
    # None: off, as in 3DGS before its first opacity reset.
    prune_screen_size: Optional[float] = None

    # Evaluation and bookkeeping.
    test_every: int = 8  # hold out every n-th view when scene.json lists no test views; 0: none
    checkpoint_every: int = option(
        1000, help="write a checkpoint every N steps; 0: only at the end", type=nonneg_int, metavar="N"
    )
    seed: int = 0
    device: str = "cpu"
    log_every: int = 10  # loss-curve sampling and progress-bar refresh

    @staticmethod
    def paper() -> "FitConfig":
        """The 30k-step schedule of the 3DGS paper (for GPU users)."""
        return FitConfig()

    @classmethod
    def for_scene(
        cls,
        name: str,
        scene: Scene,
        steps: Optional[int] = None,
        init: Union[None, str, Gaussians] = None,
        seed: int = 0,
    ) -> "FitConfig":
        """Preset ``name`` for ``scene``: a preset in ``SIZED_PRESETS`` sizes its schedule to the
        scene (:meth:`sized_for`), the paper's is 3DGS's as it stands; ``steps`` sets the step
        count (a sized schedule keeps its fractions of the run)."""
        config = replace(cls.preset(name), seed=seed)
        if name in cls.SIZED_PRESETS:
            config = config.sized_for(scene, steps=steps, init=init)
        return config if steps is None else replace(config, steps=steps)

    def sized_for(
        self, scene: Scene, steps: Optional[int] = None, init: Union[None, str, Gaussians] = None
    ) -> "FitConfig":
        """This schedule with its scene-dependent constants derived from ``scene`` (the cpu
        preset's rule; the constants above give the demo scene's 1500 steps and 12k cap):

        * Gaussian cap: ``GAUSSIANS_PER_PIXEL`` per pixel of a (median) view, the detail an
          image can show;
        * steps: ``EPOCHS`` passes over the training views, within [MIN_STEPS, MAX_STEPS];
          the densification window, SH schedule and position-rate decay keep their fractions
          of the run (also when ``steps`` is given);
        * views larger than ``COARSE_PIXELS`` are fitted at about that many pixels for the
          first ``COARSE_FRACTION`` of the steps (a step's cost scales with its pixels);
        * the background is learned only for a backdrop without sparse points
          (``BACKDROP_UNCOVERED``); otherwise it is black, as 3DGS;
        * a random initialisation (``init`` as :func:`fit_gaussians` takes it: ``"random"``, or
          ``None`` on a scene without sparse points) resets opacities every
          ``RANDOM_INIT_RESET_FRACTION`` of the steps, as 3DGS does on every scene: random
          Gaussians that only some training views constrain become floaters in front of the
          others, and only a reset clears them;
        * sparse points that leave a backdrop uncovered get ``BACKDROP_EXTRA_SEEN`` x
          ``random_init_count`` random Gaussians where the views overlap, and the same resets
          (points alone, on generated scenes, do better without resets; see :meth:`cpu`)."""
        train, _ = split_views(scene, self.test_every)
        cams = [scene.cameras[i] for i in train]
        if _has_points(scene):
            points = scene.points
            assert points is not None  # _has_points checked it
            uncovered = float(np.mean([uncovered_cells(points, c).mean() for c in cams]))
        else:
            uncovered = 1.0
        backdrop = uncovered > BACKDROP_UNCOVERED
        pixels = float(np.median([c.width * c.height for c in scene.cameras]))
        if steps is None:
            steps = int(np.clip(round(EPOCHS * len(train), -2), MIN_STEPS, MAX_STEPS))
        ref = FitConfig.cpu()  # the fractions of the 1500-step schedule
        frac = steps / ref.steps
        kind = init_kind(scene, init)
        # Random Gaussians (all of them, or beside points that miss a backdrop) need resets.
        extra_seen = round(BACKDROP_EXTRA_SEEN * self.random_init_count) if backdrop and kind == "points" else 0
        random_part = kind == "random" or extra_seen > 0
        reset = int(round(RANDOM_INIT_RESET_FRACTION * steps, -2)) if random_part else self.opacity_reset_every
        coarse = math.sqrt(pixels / COARSE_PIXELS)
        return replace(
            self,
            steps=steps,
            max_gaussians=max(2000, int(round(GAUSSIANS_PER_PIXEL * pixels))),
            means_lr_max_steps=steps,
            sh_degree_interval=max(1, round(ref.sh_degree_interval * frac)),
            densify_from=round(ref.densify_from * frac),
            densify_until=round(ref.densify_until * frac),
            coarse_until=(COARSE_FRACTION,) if coarse > 1.25 else (),
            coarse_downscale=(coarse,) if coarse > 1.25 else (),
            background_from_images=self.background_from_images and backdrop,
            background_sh_degree=self.background_sh_degree if backdrop else -1,
            opacity_reset_every=reset,
            init_extra_seen=extra_seen or self.init_extra_seen,
        )

    @staticmethod
    def cpu() -> "FitConfig":
        """A short schedule for small scenes on a CPU (the built-in demo scene in under 1.5
        minutes on 2 cores): fewer steps, earlier and capped densification, faster SH schedule;
        the decay of the position learning rate is compressed to the shorter run.

        Two 3DGS rules are off because a 1500-step run has no time to recover from them: no
        opacity reset (3DGS resets every 3000 steps and trains 27k more), and so, as in 3DGS
        before its first reset, no pruning of Gaussians larger than 0.1 x extent (the far floor
        and wall need large ones).

        The depth-spread regulariser stays off, as in 3DGS. At weight 1 it halved the demo
        tabletop's held-out depth error (1.7 against 3.9 % of the extent) for 1 dB, but on the
        lounge layout it cost 4.5 dB, left the depth error no better, and erased the floor lamp
        (a pole thinner than a pixel, a shade against a wall of similar colour) and with it the
        answers to "lamp" and "shade of the lamp"; on the plush-dog photos it cost 3.3 dB. The
        fields trained on its fits ranked worse on both layouts (docs/measurements.md, "The
        depth-spread regulariser off in the cpu fit preset").

        For scenes it was not tuned on (real photos, captures without sparse points): initial
        scales at most 0.1 x extent (the size 3DGS prunes above), and the background learned
        over ray directions from the views' border colour (``background_sh_degree=2``) where the
        sparse points leave a backdrop uncovered. ``sized_for`` then fits steps, cap, schedule
        and initialisation to the scene. The measurements behind each rule are in
        docs/measurements.md ("The cpu fit preset")."""
        return FitConfig(
            steps=1500,
            background_from_images=True,
            background_sh_degree=2,
            random_init_min_seen=0.5,
            init_max_scale=0.1,
            sh_degree_interval=400,
            means_lr_max_steps=1500,
            densify_from=200,
            densify_until=1100,
            densify_every=100,
            opacity_reset_every=0,
            max_gaussians=12_000,
            random_init_count=5000,
            checkpoint_every=500,
        )


# How the cpu preset sizes itself to a scene (FitConfig.sized_for).
GAUSSIANS_PER_PIXEL = 0.625  # Gaussian cap per pixel of one view (160x120 -> 12k)
EPOCHS = 43.0  # passes over the training views (35 views -> 1500 steps; rounded to 100s)
MIN_STEPS, MAX_STEPS = 1000, 2000  # the upper bound keeps a 70-view, 370x250 capture near 10 min on 2 cores
COARSE_PIXELS = 25_000  # views larger than this start coarse, at about this many pixels
COARSE_FRACTION = 0.5  # ... for this fraction of the steps
# Learn the background (border colour, then SH over directions) only when the sparse points
# leave more than this fraction of the training views' grid cells empty, or there are none:
# a backdrop SfM could not triangulate. The generated layouts' points leave 1-3 % empty (their
# walls are surfaces; a learned background cost the tabletop 1 dB), real object captures ~70 %.
BACKDROP_UNCOVERED = 0.1
# Opacity reset period of a random initialisation, as a fraction of the steps: twice inside the
# densification window (which ends at 73 % of the run), the second leaving 30 % of the run to
# recover (3DGS's last reset, at 12k of 30k steps, leaves 60 %).
RANDOM_INIT_RESET_FRACTION = 0.35
# Sparse points that leave a backdrop uncovered (a real object capture: SfM triangulates nothing
# on the plain mat or table around the object) are joined by this many times
# ``random_init_count`` random Gaussians inside the views' overlap (``init_extra_seen``), and the
# fit then resets opacities as a random initialisation does (docs/measurements.md, "Sparse
# points and random Gaussians").
BACKDROP_EXTRA_SEEN = 2.0


# ------------------------------------------------------------------------------------ views
def split_views(scene: Scene, test_every: int) -> tuple[list[int], list[int]]:
    """(train, test) view indices: scene.json's ``test_views`` when present, else every
    ``test_every``-th view (3DGS ``llffhold``: indices 0, 8, 16, ...); no test views if 0."""
    n = len(scene)
    test: list[int] = []
    meta = Path(scene.root) / "scene.json"
    listed = None
    if meta.is_file():
        try:
            listed = json.loads(meta.read_text()).get("test_views")
        except (json.JSONDecodeError, AttributeError):
            raise InputError(meta, "not a valid JSON object") from None
    if listed is not None:
        if not all(isinstance(i, int) and 0 <= i < n for i in listed):
            raise InputError(meta, f"test_views must be view indices in [0, {n})")
        test = sorted(set(listed))
    elif test_every > 0 and n > 1:
        test = list(range(0, n, test_every))
    train = [i for i in range(n) if i not in set(test)]
    if not train:
        raise InputError(scene.root, "no training views left after holding out the test views")
    return train, test


def _has_points(scene: Scene) -> bool:
    return scene.points is not None and len(scene.points) > 0


def init_kind(scene: Scene, init: Union[None, str, Gaussians]) -> str:
    """What :func:`fit_gaussians` starts from for ``init``: ``"points"``, ``"random"`` or
    ``"ply"`` (Gaussians given); ``None`` means the sparse points when the scene has them."""
    if isinstance(init, Gaussians):
        return "ply"
    return init or ("points" if _has_points(scene) else "random")
