"""Answer text queries on a trained run and write what ``n2f2 query`` writes: per view and
query a raw relevancy .npy, a heatmap and a mask PNG over the rendered RGB, ``OUT/query.json``,
and with ``three_d`` the selected Gaussians as a PLY and their mask in every view. The command
and the demo's relevancy pictures both call :func:`answer_queries`."""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING, Any, Optional, Sequence, Union

import torch

from .modes import get_mode

if TYPE_CHECKING:
    from .maps import BoxSize


def listed_results(out: Path) -> list[str]:
    """The files that the query.json already in ``out`` lists (so --force replaces a previous
    answer as a whole, not only the names a new one shares with it); [] when it is unreadable."""
    try:
        summary = json.loads((Path(out) / "query.json").read_text())
        names = []
        for view in summary.get("views", []):
            names.append(f"{view['view']}_rgb.png")
            for rec in view.get("queries", []):
                names += list(rec.get("files", {}).values())
                if rec.get("selection"):
                    names.append(rec["selection"]["file"])
        for sel in summary.get("selection_3d", {}).get("selections", {}).values():
            if sel.get("ply"):
                names.append(sel["ply"])
    except (OSError, ValueError, TypeError, KeyError, AttributeError):
        return []
    # Only plain names inside out: a hand-edited query.json must not point --force elsewhere.
    return [n for n in names if isinstance(n, str) and n and Path(n).name == n and n not in (".", "..")]


def query_results(texts: Sequence[str], view_names: Sequence[str], three_d: bool) -> list[str]:
    """The files a query writes into its output folder (see :mod:`n2f2.query.outputs`)."""
    from .outputs import unique_slugs

    slugs = unique_slugs(list(texts))
    names = ["query.json"]
    for v in view_names:
        names.append(f"{v}_rgb.png")
        for slug in slugs:
            names += [f"{v}_{slug}.npy", f"{v}_{slug}_heatmap.png", f"{v}_{slug}_mask.png"]
            if three_d:
                names.append(f"{v}_{slug}_selection.png")
    if three_d:
        names += [f"{slug}_selection.ply" for slug in slugs]
    return names


def answer_queries(
    run_dir: Union[str, Path],
    texts: Sequence[str],
    views: Sequence[int],
    out: Path,
    *,
    mode: str = "composite",
    scene: Optional[Union[str, Path]] = None,
    three_d: bool = False,
    threshold: Optional[float] = None,
    mask_threshold: float,
    box_size: BoxSize,
    temperature: Optional[float] = None,  # QueryConfig.temperature; None: its default
    composite_weights: Optional[str] = None,  # QueryConfig.composite_weights; None: its default
    render: Optional[str] = None,  # QueryConfig.render; None: its default
    canonical: Optional[tuple[str, ...]] = None,
    selection: str = "smoothed",
    force: bool = False,
    device: str = "cpu",
    progress: bool = True,
    full_res: bool = False,  # views at the images' size, not at the run's downscale
    decomposition: Optional[Union[str, Path]] = None,  # QueryConfig.decomposition; None: RUN/decomposition
) -> dict:
    """Render each view's feature cache once, answer every query of ``texts`` in one pass, and
    write the outputs into ``out`` (refused when it holds an answer, unless ``force``).
    Returns the ``query.json`` summary."""
    from tqdm import tqdm

    from ..io import claim_out_dir, remove_results, write_png
    from .composite import temperature_name
    from .engine import QueryConfig, QueryEngine
    from .maps import LANGSPLAT_THRESHOLD, resolve_box_size
    from .outputs import mask_overlay, unique_slugs, write_summary, write_view_outputs

    texts = list(texts)
    # A finished query is refused before anything is loaded; the per-view names are checked
    # once the scene is (they hold its image names).
    claim_out_dir(out, ["query.json"], force=force, resume_flag=None)
    overrides: dict[str, Any] = {"canonical": tuple(canonical)} if canonical else {}  # QueryConfig keywords
    if render is not None:
        overrides["render"] = render
    if temperature is not None:
        overrides["temperature"] = temperature
    if composite_weights is not None:
        overrides["composite_weights"] = composite_weights
    if decomposition is not None:
        overrides["decomposition"] = str(decomposition)
    config = QueryConfig(selection=selection, box_size=box_size, **overrides)
    engine = QueryEngine.from_run(run_dir, device=device, scene=scene, config=config, full_res=full_res)
    view_names = [engine.camera(i)[2] for i in views]  # fail before any work on a bad index
    results = list(dict.fromkeys(query_results(texts, view_names, three_d) + listed_results(out)))
    present = claim_out_dir(out, results, force=force, resume_flag=None)
    if force:  # the inputs are read: now the old results go
        remove_results(out, present)
    views_out = []
    selections = {}
    if three_d:
        for text, slug in zip(texts, unique_slugs(texts)):
            mask = engine.select(text, threshold, mode)
            n = int(mask.sum())
            path = out / f"{slug}_selection.ply"
            if n:
                engine.export_selection(mask, path)
            selections[text] = {"mask": mask, "slug": slug, "count": n, "ply": path.name if n else None}
    for i in tqdm(views, desc="query", unit="view", disable=not progress):
        view = engine.render_view(i, modes=[mode])
        result = engine.query(view, texts, mode=mode)
        size = resolve_box_size(box_size, view.width)
        records = write_view_outputs(out, view, result, size, mask_threshold)
        rgb = view.rgb.float().cpu().numpy() if view.rgb is not None else None
        for rec in records:
            sel = selections.get(rec["query"])
            if sel is None:
                continue
            cover = engine.render_selection(sel["mask"], view).float().cpu().numpy()
            m = cover > 0.5
            name = f"{view.name}_{sel['slug']}_selection.png"
            if rgb is not None:
                write_png(out / name, mask_overlay(rgb, m))
            rec["selection"] = {"file": name, "mask_area_px": int(m.sum())}
        views_out.append(
            {
                "view": view.name,
                "view_index": i,
                "height": view.height,
                "width": view.width,
                "box_size": size,
                "render_s": view.seconds.get("render"),
                "cache_s": view.seconds.get("cache"),
                "query_s": result.seconds,
                "queries": records,
            }
        )
    summary = {
        "run_dir": str(Path(run_dir)),
        "mode": mode,
        "queries": texts,
        "encoder": getattr(engine.encoder, "description", str(engine.meta.get("encoder_spec"))),
        "field": {
            "variant": engine.variant,
            "D": engine.dim,
            "step_size": engine.step,
            "num_scales": len(engine.scale_labels),
        },
        "composite": {
            "weights": config.composite_weights,
            "canonical": list(config.canonical),
            "temperature": temperature_name(config.temperature),
        },
        "render": config.render,
        "relevancy": {"negatives": list(config.negatives), "feature_normalisation": "L2 (cosine)"},
        "segmentation": {"threshold": mask_threshold, "box_size": box_size, "selection": config.selection},
        "views": views_out,
    }
    if three_d:
        rule = (
            f"relevancy >= {threshold}"
            if threshold is not None
            else f"protocol rule (normalised > {LANGSPLAT_THRESHOLD})"
        )
        summary["selection_3d"] = {
            "rule": rule,
            "num_gaussians": engine.gaussians.num,
            "selections": {t: {"count": s["count"], "ply": s["ply"]} for t, s in selections.items()},
        }
    if get_mode(mode).needs_tree:
        summary["nodes"] = node_paths(engine, texts)
    write_summary(out / "query.json", summary)
    return summary


def node_paths(engine: Any, texts: list[str]) -> dict[str, dict]:
    """Per query of node mode its answer (nodes, level) and the best node's path to the root:
    each node's id, level, the phrase ``n2f2 decompose --vocabulary`` gave it, and the best of
    this query's texts with its relevancy."""
    answers = engine.node_answers(texts)
    tree = engine.tree
    rel = torch.stack([a.relevancy for a in answers])  # [Q, K]
    out = {}
    for text, answer in zip(texts, answers):
        path = []
        for node in tree.path(answer.nodes[0]):
            best = int(torch.argmax(rel[:, node]))
            rec = tree.tree["nodes"][node]
            path.append(
                {
                    "node": node,
                    "level": rec["level"],
                    "last_level": int(tree.last_levels[node]),
                    "gaussians": rec["gaussians"],
                    "text": rec.get("text"),
                    "best_query": texts[best],
                    "relevancy": float(rel[best, node]),
                }
            )
        out[text] = {"nodes": answer.nodes, "level": answer.level, "path": path}
    return out
