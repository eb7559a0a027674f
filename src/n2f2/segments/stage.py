"""The segments stage's runner: ``n2f2 segments``, ``n2f2 segments-from-langsplat``, ``n2f2 run``
and the bench all build a segment bank through :func:`run_bank`, which claims the bank folder,
reads the scene, the Gaussians and the models (or LangSplat's features) before anything is
replaced, builds the bank and prints its summary."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Callable, Optional

from ..config import StageJob
from .lifting import LiftSettings

if TYPE_CHECKING:
    from ..distributed import Executor

Log = Callable[[str], None]


@dataclass
class BankJob(StageJob):
    """One segment bank: what ``n2f2 segments`` (or, with ``features``,
    ``segments-from-langsplat``) takes on its command line."""

    data: Path  # scene folder
    out: Path  # bank folder
    gaussians: Optional[Path] = None  # whose rendered depth lifts the segments (depth_source "render")
    lift: LiftSettings = field(default_factory=LiftSettings)
    segmenter: str = "sam"
    encoder: Optional[str] = "clip"  # with features: None = the one recorded beside them, else clip
    model: Optional[str] = None  # CLIP model id or folder
    sam_model: Optional[str] = None  # SAM / SAM 2 model id or folder
    features: Optional[Path] = None  # LangSplat language_features: imported instead of segmenting
    depth_source: str = "render"
    keep_unfinished: bool = False  # with force: a bank left unfinished with the same settings is finished


def bank_results(out: Path) -> list[str]:
    """What a bank folder holds of a bank: ``bank.json`` and the per-image record folders."""
    from .bank import RECORD_FILES

    out = Path(out)
    records = (
        [d.name for d in out.iterdir() if d.is_dir() and any((d / f).is_file() for f in RECORD_FILES)]
        if out.is_dir()
        else []
    )
    return ["bank.json", *sorted(records)]


def setup_of(job: BankJob):  # -> SegmentsSetup
    """The settings a worker rebuilds the scene, segmenter, encoder and depth from."""
    from .setup import SegmentsSetup

    return SegmentsSetup(
        data=str(job.data),
        downscale=float(job.downscale),
        skip_missing=bool(job.skip_missing),
        depth_source=job.depth_source,
        gaussians=None if job.gaussians is None else str(job.gaussians),
        segmenter=job.segmenter,
        encoder=job.encoder or "clip",
        model=job.model,
        sam_model=job.sam_model,
        device=str(job.device),
    )


def run_bank(job: BankJob, executor: Optional["Executor"] = None, log: Log = print) -> dict:
    """Build (or with ``resume`` finish) the segment bank ``job.out`` and return its report.
    Images are segmented and embedded with ``job.segmenter`` and ``job.encoder``, or read from
    LangSplat's ``job.features``; ``executor`` (Ray) spreads the images over workers."""
    from ..io import claim_out_dir, remove_results
    from .bank import bank_header, build_bank, unfinished_bank
    from .setup import depth_provider, langsplat_source, load_bank_scene, report_lines

    out = Path(job.out)
    present = claim_out_dir(out, bank_results(out), resume=job.resume, force=job.force)
    setup = None
    if job.features is not None:
        source = langsplat_source(job.features, job.encoder, job.model)  # before the scene and Gaussians
        scene = load_bank_scene(job.data, job.downscale, job.skip_missing)
        depth = depth_provider(scene, job.depth_source, job.gaussians, job.device)
        # Every file checked and hashed before the bank is touched.
        source.prepare(scene.image_names, [(c.height, c.width) for c in scene.cameras])
        if job.resume:
            source.check_resumed_bank(out)
    else:
        setup = setup_of(job)
        scene, source, depth = setup.build()
    finish = job.keep_unfinished and unfinished_bank(out, bank_header(scene, source, job.depth_source, job.lift))
    if job.force and not finish:  # the inputs are read: now the old bank goes
        remove_results(out, present)
    if executor is None or setup is None:
        report = build_bank(
            scene, source, depth, out, depth_source=job.depth_source, lift=job.lift, progress=job.progress
        )
    else:
        with executor:
            report = build_bank(
                scene,
                source,
                depth,
                out,
                depth_source=job.depth_source,
                lift=job.lift,
                progress=job.progress,
                executor=executor,
                worker_setup=setup.for_ray_worker(),
            )
    for line in report_lines(report):
        log(line)
    return report
