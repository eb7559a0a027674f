"""``n2f2 query``: open-vocabulary queries on a trained run (2D maps and, with ``--3d``, a 3D
selection exported as an INRIA PLY)."""

from __future__ import annotations

import argparse

from ..validate import finite_float, nonneg_int, positive_float, unit_interval


def _box_size(value: str):
    if value == "scaled":
        return value
    try:
        v = int(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"box size must be a positive integer or 'scaled', got {value!r}")
    if v < 1:
        raise argparse.ArgumentTypeError(f"box size must be >= 1, got {v}")
    return v


def register(subparsers) -> None:
    from .engine import MODES

    p = subparsers.add_parser(
        "query",
        help="answer text queries on a trained run: relevancy maps, masks, localization, 3D selection",
        description="Render each view's feature cache once, then answer every query in one pass. "
                    "Writes per view and query a raw relevancy .npy, a heatmap and a mask PNG over "
                    "the rendered RGB, and OUT/query.json with the numbers. With --3d, also selects "
                    "the relevant Gaussians, writes them as OUT/<query>_selection.ply (INRIA 3DGS "
                    "layout) and renders the selection's mask into every view.",
    )
    p.add_argument("run_dir", metavar="RUN_DIR", help="trained run folder (field.pt + gaussians.ply)")
    p.add_argument("texts", metavar="TEXT", nargs="+", help="text queries, e.g. \"lid of the teapot\"")
    p.add_argument("--views", type=nonneg_int, nargs="+", default=[0], metavar="I",
                   help="view indices (sorted image order, 0-based; default 0)")
    p.add_argument("--mode", choices=MODES[:3], default="composite",
                   help="composite (default, paper), explicit (best of the D/k scales per query, "
                        "LERF/LangSplat), levels (3-level baseline field)")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder")
    p.add_argument("--scene", default=None, metavar="DATA",
                   help="scene folder (default: the scene recorded in the run)")
    p.add_argument("--3d", dest="three_d", action="store_true",
                   help="also select Gaussians per query, export them as PLY and render their masks")
    p.add_argument("--threshold", type=finite_float, default=None,
                   help="3D selection: absolute relevancy threshold (default: the protocol rule on "
                        "the Gaussians' relevancy: min-max normalise, map to [-1, 1], > 0.4)")
    p.add_argument("--mask-threshold", type=unit_interval, default=None,
                   help="2D segmentation threshold of the evaluation protocol (default 0.4)")
    p.add_argument("--box-size", type=_box_size, default=None,
                   help="protocol mean-filter size in pixels, or 'scaled' = round(30 W / 986) "
                        "(default 30, LangSplat's; use 'scaled' on small renders)")
    p.add_argument("--temperature", type=positive_float, default=1.0,
                   help="composite gamma = softmax(score / T); 1 = paper (default)")
    p.add_argument("--canonical", nargs="+", default=None, metavar="PHRASE",
                   help="canonical phrases of gamma (default: object stuff thing part texture)")
    p.add_argument("--selection", choices=["smoothed", "max"], default="smoothed",
                   help="explicit/levels scale choice: max of the protocol-smoothed map "
                        "(LangSplat, default) or of the raw map (LERF)")
    p.add_argument("--force", action="store_true",
                   help="replace the query results already in --out (query.json and the files it lists)")
    p.add_argument("--device", default="cpu", help="torch device (default cpu)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def _listed_results(out) -> list[str]:
    """The files that the query.json already in ``out`` lists (so --force replaces a previous
    answer as a whole, not only the names a new one shares with it); [] when it is unreadable."""
    import json
    from pathlib import Path

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


def _query_results(texts: list[str], view_names: list[str], three_d: bool) -> list[str]:
    """The files this query writes into ``--out`` (see :mod:`n2f2.query.outputs`)."""
    from .outputs import unique_slugs

    slugs = unique_slugs(texts)
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


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from tqdm import tqdm

    from ..errors import InputError
    from .maps import LANGSPLAT_BOX_SIZE, LANGSPLAT_THRESHOLD, resolve_box_size
    from ..io import claim_out_dir, remove_results, write_png
    from .engine import QueryConfig, QueryEngine
    from .outputs import mask_overlay, unique_slugs, write_summary, write_view_outputs
    from .relevancy import check_texts

    texts = check_texts(args.texts)
    out = Path(args.out)
    # A finished query is refused before anything is loaded; the per-view names are checked
    # once the scene is (they hold its image names).
    claim_out_dir(out, ["query.json"], force=args.force, resume_flag=None)
    if args.temperature <= 0:
        raise InputError(None, f"--temperature must be > 0, got {args.temperature}")
    mask_threshold = LANGSPLAT_THRESHOLD if args.mask_threshold is None else args.mask_threshold
    if not 0.0 <= mask_threshold < 1.0:
        raise InputError(None, f"--mask-threshold must be in [0, 1), got {mask_threshold}")
    box = LANGSPLAT_BOX_SIZE if args.box_size is None else args.box_size
    overrides = {"canonical": tuple(args.canonical)} if args.canonical else {}
    config = QueryConfig(temperature=args.temperature, selection=args.selection, box_size=box, **overrides)
    engine = QueryEngine.from_run(args.run_dir, device=args.device, scene=args.scene, config=config)
    view_names = [engine.camera(i)[2] for i in args.views]  # fail before any work on a bad index
    results = list(dict.fromkeys(_query_results(texts, view_names, args.three_d) + _listed_results(out)))
    present = claim_out_dir(out, results, force=args.force, resume_flag=None)
    if args.force:  # the inputs are read: now the old results go
        remove_results(out, present)
    views_out = []
    selections = {}
    if args.three_d:
        for text, slug in zip(texts, unique_slugs(texts)):
            mask = engine.select(text, args.threshold, args.mode)
            n = int(mask.sum())
            path = out / f"{slug}_selection.ply"
            if n:
                engine.export_selection(mask, path)
            selections[text] = {"mask": mask, "slug": slug, "count": n,
                                "ply": path.name if n else None}
    for i in tqdm(args.views, desc="query", unit="view", disable=args.quiet):
        view = engine.render_view(i, modes=[args.mode])
        result = engine.query(view, texts, mode=args.mode)
        size = resolve_box_size(box, view.width)
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
        views_out.append({"view": view.name, "view_index": i, "height": view.height, "width": view.width,
                          "box_size": size, "render_s": view.seconds.get("render"),
                          "cache_s": view.seconds.get("cache"), "query_s": result.seconds,
                          "queries": records})
    summary = {
        "run_dir": str(Path(args.run_dir)),
        "mode": args.mode,
        "queries": texts,
        "encoder": getattr(engine.encoder, "description", str(engine.meta.get("encoder_spec"))),
        "field": {"variant": engine.variant, "D": engine.dim, "step_size": engine.step,
                  "num_scales": len(engine.scale_dims) if engine.variant != "levels" else 3},
        "composite": {"canonical": list(config.canonical), "temperature": config.temperature},
        "relevancy": {"negatives": list(config.negatives), "feature_normalisation": "L2 (cosine)"},
        "segmentation": {"threshold": mask_threshold, "box_size": box, "selection": config.selection},
        "views": views_out,
    }
    if args.three_d:
        rule = (f"relevancy >= {args.threshold}" if args.threshold is not None
                else f"protocol rule (normalised > {LANGSPLAT_THRESHOLD})")
        summary["selection_3d"] = {"rule": rule, "num_gaussians": engine.gaussians.num,
                                   "selections": {t: {"count": s["count"], "ply": s["ply"]}
                                                  for t, s in selections.items()}}
    write_summary(out / "query.json", summary)
    for v in views_out:
        for r in v["queries"]:
            loc = r["localization"]
            print(f"{v['view']}  {r['query']!r}: max relevancy {r['relevancy_max']:.3f} at "
                  f"({loc['x']}, {loc['y']}), mask {r['mask_area_px']} px"
                  + (f", scale {r['chosen_scale']}" if r["chosen_scale"] else ""))
    for t, s in selections.items():
        print(f"3D {t!r}: {s['count']} of {engine.gaussians.num} Gaussians"
              + (f" -> {out / s['ply']}" if s["ply"] else " (empty selection, no PLY written)"))
    print(f"query: {len(texts)} queries x {len(views_out)} views ({args.mode}) -> {out}")
    return 0
