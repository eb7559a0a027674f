"""The query stage's runner: ``n2f2 query`` and the demo's relevancy PNGs answer text queries on
a trained run through :func:`run_query`, which checks the texts and settings, answers every
query in each view (:func:`~n2f2.query.answer.answer_queries`) and prints one line per answer,
followed by a ``warning:`` line when that answer's relevancy map is flat (it carries no signal)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Callable, Optional, Sequence

from ..errors import InputError

if TYPE_CHECKING:
    from .maps import BoxSize

Log = Callable[[str], None]
# Query texts longer than this are shortened on the console; query.json keeps them whole.
SHOWN_TEXT_CHARS = 80


def shown(text: str, limit: int = SHOWN_TEXT_CHARS) -> str:
    """``text`` for a console line: at most ``limit`` characters, the length said when cut."""
    return text if len(text) <= limit else f"{text[: limit - 25]}... ({len(text)} characters)"


@dataclass
class QueryJob:
    """One set of queries: what ``n2f2 query`` takes on its command line."""

    run_dir: Path  # trained run folder (field.pt + gaussians.ply)
    texts: Sequence[str]
    out: Path
    views: Sequence[int] = (0,)
    mode: str = "composite"
    scene: Optional[Path] = None  # None: the scene recorded in the run
    three_d: bool = False  # also select Gaussians per query, export them, render their masks
    threshold: Optional[float] = None  # 3D selection's absolute threshold; None: the protocol rule
    mask_threshold: Optional[float] = None  # None: the protocol's (LANGSPLAT_THRESHOLD)
    box_size: Optional[BoxSize] = None  # None: LangSplat's 30 px box; "scaled": sized to the width
    composite_weights: Optional[str] = None  # QueryConfig.composite_weights; None: its default
    temperature: Optional[float] = None  # QueryConfig.temperature; None: its default
    render: Optional[str] = None  # QueryConfig.render; None: its default
    canonical: Optional[tuple[str, ...]] = None
    selection: str = "smoothed"
    force: bool = False  # replace an answer already in OUT
    device: str = "cpu"
    progress: bool = True
    full_res: bool = False  # views at the images' size, not at the downscale the run was trained at
    decomposition: Optional[Path] = None  # the run's hierarchy for mode node; None: RUN/decomposition
    path: bool = False  # mode node: print each answer's ancestors


def run_query(job: QueryJob, log: Log = print) -> dict:
    """Answer ``job.texts`` in ``job.views`` into ``job.out`` and return the ``query.json`` summary."""
    from ..field.relevancy import check_texts
    from .answer import answer_queries
    from .maps import LANGSPLAT_BOX_SIZE, LANGSPLAT_THRESHOLD

    texts = check_texts(job.texts)
    mask_threshold = LANGSPLAT_THRESHOLD if job.mask_threshold is None else job.mask_threshold
    if not 0.0 <= mask_threshold < 1.0:
        raise InputError(None, f"--mask-threshold must be in [0, 1), got {mask_threshold}")
    out = Path(job.out)
    summary = answer_queries(
        job.run_dir,
        texts,
        job.views,
        out,
        mode=job.mode,
        scene=job.scene,
        three_d=job.three_d,
        threshold=job.threshold,
        mask_threshold=mask_threshold,
        box_size=LANGSPLAT_BOX_SIZE if job.box_size is None else job.box_size,
        temperature=job.temperature,
        composite_weights=job.composite_weights,
        render=job.render,
        canonical=job.canonical,
        selection=job.selection,
        force=job.force,
        device=job.device,
        progress=job.progress,
        full_res=job.full_res,
        decomposition=job.decomposition,
    )
    for v in summary["views"]:
        for r in v["queries"]:
            loc = r["localization"]
            log(
                f"{v['view']}  {shown(r['query'])!r}: max relevancy {r['relevancy_max']:.3f} at "
                f"({loc['x']}, {loc['y']}), mask {r['mask_area_px']} px"
                + (f", scale {r['chosen_scale']}" if r["chosen_scale"] else "")
            )
            if r.get("warning"):  # a flat map (query.maps.flat_warning): said right under its line
                log(f'warning: "{shown(r["query"])}": {r["warning"]}')
    if job.path and "nodes" in summary:
        for text, ans in summary["nodes"].items():
            log(f"{shown(text)!r}: " + " -> ".join(_node_shown(p) for p in ans["path"]))
    elif job.path:
        log("note: --path prints the ancestors of a node answer (--mode node)")
    sel3d = summary.get("selection_3d")
    for t, s in (sel3d["selections"] if sel3d else {}).items():
        assert sel3d is not None  # the loop runs over sel3d's selections only
        log(
            f"3D {shown(t)!r}: {s['count']} of {sel3d['num_gaussians']} Gaussians"
            + (f" -> {out / s['ply']}" if s["ply"] else " (empty selection, no PLY written)")
        )
    log(f"query: {len(texts)} queries x {len(summary['views'])} views ({job.mode}) -> {out}")
    return summary


def _node_shown(p: dict) -> str:
    """``node 12 "teapot" (lid of the teapot 0.61)``: a node of a path, with its phrase."""
    name = f' "{p["text"]}"' if p.get("text") else ""
    return f"node {p['node']}{name} ({p['best_query']} {p['relevancy']:.2f})"
