"""``n2f2 query``: open-vocabulary queries on a trained run (2D maps and, with ``--3d``, a 3D
selection exported as an INRIA PLY)."""

from __future__ import annotations

import argparse

from ..validate import (
    add_device_option,
    composite_temperature,
    finite_float,
    nonneg_int,
    unit_interval,
)


def add_render_option(p: argparse.ArgumentParser) -> None:
    """``--render``: how 2D views get their features (``QueryConfig.render``)."""
    from .engine import DEFAULT_RENDER, RENDERS

    p.add_argument(
        "--render",
        choices=RENDERS,
        default=DEFAULT_RENDER,
        help="2D views: deferred = rasterize the backbone's features and run the MLP per pixel, as the field was "
        "trained (default); gaussians = the MLP per Gaussian, the paper's test-time form",
    )


def add_composite_options(p: argparse.ArgumentParser) -> None:
    """``--composite-weights`` and ``--temperature``: composite's weights over the scales
    (``QueryConfig.composite_weights`` and ``.temperature``; read back by :func:`composite_config`)."""
    from .composite import COMPOSITE_WEIGHTS, DEFAULT_WEIGHTS

    p.add_argument(
        "--composite-weights",
        choices=COMPOSITE_WEIGHTS,
        default=DEFAULT_WEIGHTS,
        help="composite's weights over the scales: unit = the mean of the normalised scale features "
        "(default); eq6 = the paper's Eq. 6 at --temperature",
    )
    p.add_argument(
        "--temperature",
        type=composite_temperature,
        default=None,
        metavar="T",
        help="T of --composite-weights eq6, gamma = softmax(score / T): 'paper' (T = 1, default), "
        "'uniform' (T = infinity: the plain mean of the scale features) or a number > 0",
    )


def composite_config(args: argparse.Namespace) -> dict:
    """The ``QueryConfig`` keywords of :func:`add_composite_options`' flags (an unset temperature
    keeps QueryConfig's, the paper's). A temperature without ``eq6`` would be ignored: refused."""
    from ..errors import InputError

    if args.temperature is not None and args.composite_weights != "eq6":
        raise InputError(None, "--temperature is the T of Eq. 6: give it with --composite-weights eq6")
    config = {"composite_weights": args.composite_weights}
    if args.temperature is not None:
        config["temperature"] = args.temperature
    return config


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
    from .soft import SOFT_TEMPERATURE

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
    p.add_argument("texts", metavar="TEXT", nargs="+", help='text queries, e.g. "lid of the teapot"')
    p.add_argument(
        "--views",
        type=nonneg_int,
        nargs="+",
        default=[0],
        metavar="I",
        help="view indices (sorted image order, 0-based; default 0)",
    )
    p.add_argument(
        "--mode",
        choices=[m for m in MODES if m != "oracle"],
        default="composite",
        help="composite (default, paper), explicit (best of the D/k scales per query, "
        "LERF/LangSplat), levels (3-level baseline field), soft (every scale weighted by "
        f"softmax(peak / {SOFT_TEMPERATURE:g}) of its highest relevancy; nested and flat fields)",
    )
    p.add_argument("--out", required=True, metavar="DIR", help="output folder")
    p.add_argument(
        "--scene", default=None, metavar="DATA", help="scene folder (default: the scene recorded in the run)"
    )
    p.add_argument(
        "--3d",
        dest="three_d",
        action="store_true",
        help="also select Gaussians per query, export them as PLY and render their masks",
    )
    p.add_argument(
        "--threshold",
        type=finite_float,
        default=None,
        help="3D selection: absolute relevancy threshold (default: the protocol rule on "
        "the Gaussians' relevancy: min-max normalise, map to [-1, 1], > 0.4)",
    )
    p.add_argument(
        "--mask-threshold",
        type=unit_interval,
        default=None,
        help="2D segmentation threshold of the evaluation protocol (default 0.4)",
    )
    p.add_argument(
        "--box-size",
        type=_box_size,
        default=None,
        help="protocol mean-filter size in pixels, or 'scaled' = round(30 W / 986) "
        "(default 30, LangSplat's; use 'scaled' on small renders)",
    )
    add_composite_options(p)
    add_render_option(p)
    p.add_argument(
        "--canonical",
        nargs="+",
        default=None,
        metavar="PHRASE",
        help="canonical phrases of gamma (default: object stuff thing part texture)",
    )
    p.add_argument(
        "--selection",
        choices=["smoothed", "max"],
        default="smoothed",
        help="explicit/levels scale choice: max of the protocol-smoothed map "
        "(LangSplat, default) or of the raw map (LERF)",
    )
    p.add_argument(
        "--force",
        action="store_true",
        help="replace the query results already in --out (query.json and the files it lists)",
    )
    add_device_option(p)
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


# Query texts longer than this are shortened on the console; query.json keeps them whole.
SHOWN_TEXT_CHARS = 80


def shown(text: str, limit: int = SHOWN_TEXT_CHARS) -> str:
    """``text`` for a console line: at most ``limit`` characters, the length said when cut."""
    return text if len(text) <= limit else f"{text[: limit - 25]}... ({len(text)} characters)"


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from ..errors import InputError
    from .answer import answer_queries
    from .maps import LANGSPLAT_BOX_SIZE, LANGSPLAT_THRESHOLD
    from .relevancy import check_texts

    texts = check_texts(args.texts)
    composite = composite_config(args)
    mask_threshold = LANGSPLAT_THRESHOLD if args.mask_threshold is None else args.mask_threshold
    if not 0.0 <= mask_threshold < 1.0:
        raise InputError(None, f"--mask-threshold must be in [0, 1), got {mask_threshold}")
    box = LANGSPLAT_BOX_SIZE if args.box_size is None else args.box_size
    out = Path(args.out)
    summary = answer_queries(
        args.run_dir,
        texts,
        args.views,
        out,
        mode=args.mode,
        scene=args.scene,
        three_d=args.three_d,
        threshold=args.threshold,
        mask_threshold=mask_threshold,
        box_size=box,
        **composite,
        render=args.render,
        canonical=tuple(args.canonical) if args.canonical else None,
        selection=args.selection,
        force=args.force,
        device=args.device,
        progress=not args.quiet,
    )
    for v in summary["views"]:
        for r in v["queries"]:
            loc = r["localization"]
            print(
                f"{v['view']}  {shown(r['query'])!r}: max relevancy {r['relevancy_max']:.3f} at "
                f"({loc['x']}, {loc['y']}), mask {r['mask_area_px']} px"
                + (f", scale {r['chosen_scale']}" if r["chosen_scale"] else "")
            )
    sel3d = summary.get("selection_3d")
    for t, s in (sel3d["selections"] if sel3d else {}).items():
        assert sel3d is not None  # the loop runs over sel3d's selections only
        print(
            f"3D {shown(t)!r}: {s['count']} of {sel3d['num_gaussians']} Gaussians"
            + (f" -> {out / s['ply']}" if s["ply"] else " (empty selection, no PLY written)")
        )
    print(f"query: {len(texts)} queries x {len(summary['views'])} views ({args.mode}) -> {out}")
    return 0
