"""Evaluation reports: Markdown tables and PNG plots (matplotlib's Agg canvas, no display).

Scores are shown in percent with one decimal, as the paper's tables are. Every table states the
mean-filter size it was computed with, so exact (30 px) and scaled-box numbers cannot be
confused.

(Longer than 600 lines: every table and plot of ``n2f2 eval``, each a few lines; none computes a
score.)
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING, Any, Mapping, Optional, Union

import numpy as np

from ..io import atomic_path
from ..query.modes import get_mode
from .runner import ONE_MAP_MODES, QUERY_KINDS, QUERY_TYPES, SCALE_MODES, compare_evals, load_eval
from .tables import fmt, markdown_table, pct

if TYPE_CHECKING:
    from .metrics import QueryDeltas
    from .protocol import SceneScores
    from .runner import EvalResult

# What `n2f2 eval` writes into OUT (n2f2.eval.runner.write_eval_outputs), plots by pattern.
RESULT_NAMES = ("eval.json", "eval.md", "relevancy", "scores.png", "simple_compound.png", "recall_at_k.png")
RESULT_PATTERNS = ("scales_*.png", "delta_*.png")


def mode_summary_lines(result: EvalResult) -> list[str]:
    """One line per mode of an evaluation result: loc, mIoU and mAP at every box."""
    lines = []
    for m in result.modes:
        parts = [
            f"{b}: loc {100 * s.loc_accuracy:.1f}% mIoU {100 * s.miou:.1f}% mAP {100 * result.ap[m][b]['map']:.1f}% "
            f"(box {','.join(map(str, s.box_sizes))} px)"
            for b, s in result.scores[m].items()
        ]
        lines.append(f"eval {m}: " + "; ".join(parts))
    return lines


def protocol3d_summary_lines(d: Mapping) -> list[str]:
    """One line per mode of the 3D protocol (``Protocol3dResult.to_dict()``): mIoU, mAcc, loc."""
    lines = []
    for m in d["modes"]:
        s = d["scores"][m]
        acc = " ".join(f"mAcc@{k} {100 * v:.1f}%" for k, v in s["acc"].items())
        lines.append(
            f"eval 3D {m}: mIoU {100 * s['miou']:.1f}% {acc} loc {100 * s['loc_accuracy']:.1f}% "
            f"({s['num_pairs']} pairs, {len(s['empty_selections'])} empty selections)"
        )
    return lines


def ovs3d_summary_lines(d: Mapping) -> list[str]:
    """One line per mode of a 3D-OVS evaluation (``n2f2.eval.ovs3d.evaluate_run_ovs3d``)."""
    lines = []
    for m in d["modes"]:
        parts = []
        for b, s in d["scores"][m].items():
            acc = f" acc {100 * s['accuracy']:.1f}%" if s.get("accuracy") is not None else ""
            parts.append(f"{b}: mIoU {100 * s['miou']:.1f}%{acc} (box {','.join(map(str, s['box_sizes']))} px)")
        lines.append(f"eval 3D-OVS {m}: " + "; ".join(parts))
    return lines


def eval_results(out: Union[str, Path]) -> list[str]:
    """The names of a previous evaluation's files that ``out`` may hold."""
    out = Path(out)
    found = sorted(p.name for pattern in RESULT_PATTERNS for p in out.glob(pattern)) if out.is_dir() else []
    return [*RESULT_NAMES, *found]


def scene_scores_table(
    scores: Mapping[str, SceneScores],  # scene name -> scores
    mean_row: bool = True,
) -> str:
    """One row per scene: mIoU and localization accuracy (%), pairs, box size and majority radius
    used, skips. The mean row averages scenes (as the paper's tables do)."""
    rows = []
    for scene, s in scores.items():
        rows.append(
            [
                scene,
                fmt(s.miou, percent=True),
                fmt(s.loc_accuracy, percent=True),
                fmt(s.oracle_miou, percent=True),
                s.num_pairs,
                ",".join(str(b) for b in s.box_sizes),
                ",".join(str(r) for r in s.majority_radii),
                len(s.skipped_frames),
                s.skipped_objects,
            ]
        )
    if mean_row and len(scores) > 1:
        vals = list(scores.values())
        rows.append(
            [
                "**mean**",
                fmt(sum(v.miou for v in vals) / len(vals), percent=True),
                fmt(sum(v.loc_accuracy for v in vals) / len(vals), percent=True),
                fmt(sum(v.oracle_miou for v in vals) / len(vals), percent=True),
                sum(v.num_pairs for v in vals),
                "",
                "",
                "",
                "",
            ]
        )
    return markdown_table(
        [
            "scene",
            "mIoU %",
            "loc. acc. %",
            "oracle-level mIoU %",
            "pairs",
            "box px",
            "majority radius",
            "skipped frames",
            "skipped objects",
        ],
        rows,
    )


def pairs_table(scores: SceneScores) -> str:
    """Every (frame, category) pair: IoU, hit, chosen levels."""
    rows = [
        [
            p.frame,
            p.category,
            fmt(p.iou, percent=True),
            fmt(p.hit),
            p.seg_level,
            p.loc_level,
            " ".join(fmt(v, percent=True) for v in p.iou_per_level),
        ]
        for p in scores.pairs
    ]
    return markdown_table(["frame", "category", "IoU %", "hit", "seg level", "loc level", "IoU % per level"], rows)


def deltas_table(deltas: QueryDeltas, name_a: str = "a", name_b: str = "b", percent: bool = True) -> str:
    """Top and bottom per-query deltas (metrics.QueryDeltas)."""
    rows = []
    for tag, items in (("top", deltas.top), ("bottom", deltas.bottom)):
        for d in items:
            rows.append(
                [
                    tag,
                    d.query,
                    fmt(d.a, percent=percent),
                    fmt(d.b, percent=percent),
                    ("+" if d.delta >= 0 else "") + fmt(d.delta, percent=percent),
                ]
            )
    return markdown_table(["", "query", name_a, name_b, "delta"], rows, ["l", "l", "r", "r", "r"])


# ------------------------------------------------------------------------------ plots
def _save(fig, path: Union[str, Path], dpi: int = 120) -> Path:
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    FigureCanvasAgg(fig)
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=dpi, bbox_inches="tight")
    return path


def plot_grouped_bars(
    path: Union[str, Path],
    values: Mapping[str, Mapping[str, float]],  # series -> group -> value in [0, 1]
    title: str = "",
    ylabel: str = "%",
    percent: bool = True,
) -> Path:
    """Grouped bar chart (e.g. mIoU per scene for several methods) written as PNG."""
    from matplotlib.figure import Figure

    series = list(values)
    groups = list(dict.fromkeys(g for s in series for g in values[s]))
    fig = Figure(figsize=(max(4.0, 1.2 * len(groups) + 1.5), 3.2))
    ax = fig.add_subplot(1, 1, 1)
    width = 0.8 / max(1, len(series))
    x = np.arange(len(groups))
    scale = 100.0 if percent else 1.0
    for i, s in enumerate(series):
        ys = [scale * values[s].get(g, float("nan")) for g in groups]
        ax.bar(x + (i - (len(series) - 1) / 2) * width, ys, width, label=s)
    ax.set_xticks(x)
    ax.set_xticklabels(groups, rotation=20, ha="right")
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    if len(series) > 1:  # beside the axes, so that it never hides a bar (the saved PNG is cropped to fit)
        ax.legend(fontsize="small", loc="upper left", bbox_to_anchor=(1.01, 1.0))
    ax.grid(axis="y", alpha=0.3)
    return _save(fig, path)


def plot_lines(
    path: Union[str, Path],
    curves: Mapping[str, tuple],  # name -> (x, y)
    xlabel: str,
    ylabel: str,
    title: str,
    logy: bool = False,
) -> Path:
    """One line per curve, with markers on short ones; ``logy``: log-scale y axis."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(5.0, 3.4))
    ax = fig.add_subplot(1, 1, 1)
    for name, (x, y) in curves.items():
        ax.plot(x, y, label=name, marker="o" if len(x) < 12 else None)
    if logy:
        ax.set_yscale("log")
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend(fontsize="small")
    return _save(fig, path)


def plot_query_deltas(
    path: Union[str, Path],
    deltas: QueryDeltas,
    title: str = "per-query delta",
    percent: bool = True,
) -> Path:
    """Horizontal bars of every shared query's delta, largest gain on top."""
    from matplotlib.figure import Figure

    items = list(deltas.deltas)
    fig = Figure(figsize=(6.0, max(2.0, 0.28 * len(items) + 1.0)))
    ax = fig.add_subplot(1, 1, 1)
    scale = 100.0 if percent else 1.0
    ys = list(range(len(items)))[::-1]
    ax.barh(ys, [scale * d.delta for d in items], color=["tab:green" if d.delta >= 0 else "tab:red" for d in items])
    ax.set_yticks(ys)
    ax.set_yticklabels([d.query for d in items], fontsize="small")
    ax.axvline(0.0, color="black", linewidth=0.8)
    ax.set_xlabel("delta (points)" if percent else "delta")
    ax.set_title(title)
    return _save(fig, path)


def plot_level_histogram(
    path: Union[str, Path],
    scores: SceneScores,
    title: str = "chosen levels",
) -> Path:
    """How often each level was chosen for segmentation and for localization."""
    from matplotlib.figure import Figure

    seg = [p.seg_level for p in scores.pairs]
    loc = [p.loc_level for p in scores.pairs]
    n = max(seg + loc) + 1 if seg else 1
    fig = Figure(figsize=(4.0, 3.0))
    ax = fig.add_subplot(1, 1, 1)
    x = np.arange(n)
    counts = {"segmentation": np.bincount(seg, minlength=n), "localization": np.bincount(loc, minlength=n)}
    if n <= 16:
        for shift, (label, c) in zip((-0.2, 0.2), counts.items()):
            ax.bar(x + shift, c, 0.4, label=label)
        ax.set_xticks(x)
    else:  # a field's many scales: one outline per series (a bar each costs seconds), sparse ticks
        from matplotlib.ticker import MaxNLocator

        for label, c in counts.items():
            ax.stairs(c, np.arange(n + 1) - 0.5, label=label)
        ax.xaxis.set_major_locator(MaxNLocator(nbins=8, integer=True))
    ax.set_xlabel("level")
    ax.set_ylabel("pairs")
    ax.set_title(title)
    ax.legend(fontsize="small")
    return _save(fig, path)


# ------------------------------------------------------------------------------ eval.md and its plots
def box_title(result: Mapping, box: str) -> str:
    """ "exact 30 px" / "scaled 5 px" (sizes actually used, from the protocol's record)."""
    return f"{box} {','.join(str(s) for s in result['boxes'][box]['box_sizes'])} px"


def _composite_weights(field: Mapping) -> str:
    """How composite weighs the scales, from ``field`` of eval.json (written before the weights
    were recorded: the paper's Eq. 6 at T = 1)."""
    if field.get("composite_weights") == "unit":
        return "the mean of the normalised scale features (n2f2's default)"
    temperature = field.get("composite_temperature", 1.0)
    if temperature == "uniform":
        return "the plain mean of the scale features (Eq. 6 at T = infinity)"
    if temperature == 1.0:
        return "scales weighted by the paper's Eq. 6 (T = 1)"
    return f"scales weighted by Eq. 6 at T = {float(temperature):g}"


def _radii(result: Mapping, box: str) -> str:
    return ",".join(str(s) for s in result["boxes"][box]["majority_radii"])


def _at(d: Mapping, k: int) -> Any:  # K-keyed dicts have int keys in memory, str keys after JSON
    return d[k] if k in d else d[str(k)]


def markdown_report(result: Mapping, deltas: Optional[Mapping] = None, reference: str = "") -> str:
    """``eval.md`` from an ``eval.json`` dict (and optional :func:`compare_evals` output)."""
    boxes = list(result["boxes"])
    title = {b: box_title(result, b) for b in boxes}
    out = _report_header(result, title)
    out += _scores_section(result, boxes, title)
    if result.get("protocol3d"):
        from .protocol3d import protocol3d_markdown

        out.append(protocol3d_markdown(result["protocol3d"]))
    out += _split_section(result, boxes, title)
    if result.get("kinds"):
        out += _kinds_section(result, boxes, title)
    if result.get("budget"):
        from .budget import budget_markdown

        out.append(budget_markdown(result["budget"]))
    out += _retrieval_section(result, boxes, title)
    out += _per_query_section(result, boxes, title)
    if deltas:
        out += _deltas_section(deltas, reference, title)
    return "".join(out)


def _report_header(result: Mapping, title: Mapping[str, str]) -> list[str]:
    """The run, labels, field, teacher and protocol, and what each mode is."""
    from ..query.soft import SOFT_TEMPERATURE

    radii = {b: _radii(result, b) for b in title}
    out = [
        f"# n2f2 eval: {result['scene']}\n",
        f"- run: `{result['run_dir']}`\n- labels: `{result['label_dir']}`\n"
        f"- field: {result['field']['variant']}, D = {result['field']['dim']}, k = {result['field']['step']} "
        f"({result['field']['num_scales']} scales)\n"
        f"- text encoder / teacher: {result['encoder']['description']}\n"
        f"- protocol: LangSplat's LERF-OVS rules. Box sizes, always both: **{title['exact']}** "
        f"(LangSplat's, sized for ~986 px-wide images; majority radius {radii['exact']}) and "
        f"**{title['scaled']}** (round(30 W / 986); majority radius {radii['scaled']}).\n",
    ]
    n_scales = result["field"]["num_scales"]
    about = {
        "composite": "one composite-embedding map per query (paper Sec. 3.3), " + _composite_weights(result["field"]),
        "explicit": f"LangSplat's level choice over the {n_scales} scales (max R' for segmentation, "
        "max box(R) for localization)",
        "levels": "LangSplat's level choice over the 3 levels of the baseline field",
        "soft": f"one map per query: the {n_scales} scales' maps weighted by softmax(peak / {SOFT_TEMPERATURE:g}) "
        "of each scale's highest relevancy in the view",
        "oracle": f"per pair the best of the {n_scales} scales for each task (best IoU; any scale that "
        "localizes): an upper bound of the explicit choice, not of composite; with many "
        "scales the localization bound is loose",
    }
    for m in result["modes"]:
        out.append(f"- mode {m}: {about.get(m) or get_mode(m).description}\n")
    for note in result.get("notes", []):
        out.append(f"- note: {note}\n")
    return out


def _scores_section(result: Mapping, boxes: list[str], title: Mapping[str, str]) -> list[str]:
    """Localization, mIoU and mAP per mode and box, and the scene's pair counts."""
    modes = result["modes"]
    out = ["\n## Localization and segmentation, and mAP\n\n"]
    first = result["scores"][modes[0]]
    ap = result.get("ap") or {}
    rows = []
    for m in modes:
        s = result["scores"][m]
        rows.append(
            [m]
            + [pct(s[b]["loc_accuracy"]) for b in boxes]
            + [pct(s[b]["miou"]) for b in boxes]
            + [pct(ap[m][b]["map"]) if m in ap else "-" for b in boxes]
            + [s["exact"]["num_pairs"]]
        )
    out.append(
        markdown_table(
            ["mode"]
            + [f"loc. % ({title[b]})" for b in boxes]
            + [f"mIoU % ({title[b]})" for b in boxes]
            + [f"mAP % ({title[b]} choice)" for b in boxes]
            + ["pairs"],
            rows,
        )
    )
    if ap:
        a = next(iter(next(iter(ap.values())).values()))
        out.append(
            f"\nmAP: average precision of ranking each labelled view's pixels by the mode's segmentation "
            f"map (ties as one threshold), mean over pairs; against the exact mask in {a['exact_masks']} "
            f"of {a['num_pairs']} pairs, the label polygons otherwise. The box only changes which scale "
            "explicit / levels / oracle take.\n"
        )
    out.append(
        f"\nScene {result['scene']}: {first['exact']['num_frames']} labelled frames, "
        f"{first['exact']['num_pairs']} (frame, query) pairs; skipped frames: "
        f"{len(first['exact']['skipped_frames'])}, objects outside the image: "
        f"{first['exact']['skipped_objects']}, empty pairs: {first['exact']['skipped_categories']}.\n"
    )
    return out


def _split_section(result: Mapping, boxes: list[str], title: Mapping[str, str]) -> list[str]:
    """Simple vs compound queries (paper Table 7)."""
    out = [
        "\n## Simple vs compound queries (paper Table 7)\n\n",
        f"Query types from {result['query_types_source']}.\n\n",
    ]
    rows = []
    for m in result["modes"]:
        for b in boxes:
            sp = result["split"][m][b]
            rows.append(
                [m, title[b]]
                + [pct(sp[k]["miou"]) for k in ("simple", "compound")]
                + [pct(sp[k]["loc_accuracy"]) for k in ("simple", "compound")]
                + [sp[k]["pairs"] for k in QUERY_TYPES]
            )
    out.append(
        markdown_table(
            [
                "mode",
                "box",
                "simple mIoU %",
                "compound mIoU %",
                "simple loc. %",
                "compound loc. %",
                "simple pairs",
                "compound pairs",
                "unknown pairs",
            ],
            rows,
            ["l", "l"] + ["r"] * 7,
        )
    )
    return out


def _kinds_section(result: Mapping, boxes: list[str], title: Mapping[str, str]) -> list[str]:
    """mIoU, localization and mAP by query kind (part / object / group), the kinds with pairs."""
    modes = result["modes"]
    out = ["\n## By query kind\n\n", f"Query kinds from {result.get('query_kinds_source')}.\n\n"]
    shown = [k for k in QUERY_KINDS if any(result["kinds"][m][b][k]["pairs"] for m in modes for b in boxes)]
    rows = []
    for m in modes:
        for b in boxes:
            kd = result["kinds"][m][b]
            rows.append(
                [m, title[b]]
                + [f"{pct(kd[k]['miou'])} / {pct(kd[k]['loc_accuracy'])} / {pct(kd[k]['map'])}" for k in shown]
            )
    counts = ", ".join(f"{k} {result['kinds'][modes[0]]['exact'][k]['pairs']}" for k in shown)
    out.append(
        markdown_table(
            ["mode", "box"] + [f"{k}: mIoU / loc. / mAP %" for k in shown], rows, ["l", "l"] + ["r"] * len(shown)
        )
    )
    out.append(f"\nPairs per kind: {counts}.\n")
    return out


def _retrieval_section(result: Mapping, boxes: list[str], title: Mapping[str, str]) -> list[str]:
    """R@K over the segment pool, or why it was not computed."""
    out = ["\n## Retrieval R@K over the segment pool\n\n"]
    if not result["retrieval"]:
        out.append("Not computed (no segment bank).\n")
        return out
    any_r = next(iter(next(iter(result["retrieval"].values())).values()))
    ks = any_r["ks"]
    out.append(
        f"Pool: the segment bank's segments of each labelled view ({result['bank_dir']}); a segment "
        f"matches when its IoU with the label mask is >= {any_r['iou_threshold']}; a pair is "
        "retrieved at K when a matching segment ranks in the top K by mean relevancy (ties count "
        "against it). Pairs with no matching segment are skipped and counted.\n\n"
    )
    rows = []
    for m in result["modes"]:
        for b in boxes:
            r = result["retrieval"][m][b]
            rows.append(
                [m, title[b] if m not in ONE_MAP_MODES else "any"]
                + [pct(_at(r["recall"], k)) for k in ks]
                + [_fmt_num(r["mean_first_rank"]), r["num_pairs"], len(r["skipped"])]
            )
            if m in ONE_MAP_MODES:
                break  # the composite and soft maps do not depend on the box
    out.append(
        markdown_table(
            ["mode", "box"] + [f"R@{k} %" for k in ks] + ["mean first rank", "pairs", "skipped (no matching segment)"],
            rows,
            ["l", "l"] + ["r"] * (len(ks) + 3),
        )
    )
    return out


def _per_query_section(result: Mapping, boxes: list[str], title: Mapping[str, str]) -> list[str]:
    """Each query's IoU per mode and box and AP per mode, with its type, kind and frames."""
    modes = result["modes"]
    out = [
        "\n## Per query (IoU %, and AP % of the exact box's choice; mean over the frames a query is labelled in)\n\n"
    ]
    queries = sorted(result["query_types"], key=lambda q: (result["query_types"][q], q))
    rows = []
    for q in queries:
        row = [q, result["query_types"][q]]
        frames = None
        for m in modes:
            for b in boxes:
                v = result["per_query"][m][b].get(q)
                row.append(pct(v["iou"]) if v else "-")
                frames = frames or (v["frames"] if v else None)
        for m in modes:  # AP of the exact box's choice
            v = result["per_query"][m]["exact"].get(q)
            row.append(pct(v.get("ap", math.nan)) if v else "-")
        kind = (result.get("query_kinds") or {}).get(q, "unknown")
        rows.append(row[:2] + [kind, frames if frames is not None else 0] + row[2:])
    out.append(
        markdown_table(
            ["query", "type", "kind", "frames"]
            + [f"{m} {title[b]}" for m in modes for b in boxes]
            + [f"{m} AP" for m in modes],
            rows,
            ["l", "l", "l"] + ["r"] * (1 + len(modes) * (len(boxes) + 1)),
        )
    )
    return out


def _deltas_section(deltas: Mapping, reference: str, title: Mapping[str, str]) -> list[str]:
    """Per-query IoU deltas against a reference run (paper Table 8), per mode and box."""
    out = [
        f"\n## Per-query IoU delta: this run - reference (paper Table 8: top and bottom 3)\n\nReference: {reference}.\n"
    ]
    for m, by in deltas.items():
        for b, d in by.items():
            out.append(
                f"\n### {m}, {title[b]}: mean delta {_signed(d.mean_delta)} points over "
                f"{len(d.deltas)} shared queries\n\n"
            )
            out.append(deltas_table(d, name_a="reference IoU %", name_b="this run IoU %"))
            if d.only_a or d.only_b:
                out.append(f"\nQueries only in the reference: {len(d.only_a)}; only in this run: {len(d.only_b)}.\n")
    return out


def _fmt_num(v: Any) -> str:
    return fmt(v, digits=2)


def _signed(v: float) -> str:
    return "n/a" if not np.isfinite(v) else f"{100 * v:+.1f}"


def plot_recall_curves(path: Union[str, Path], curves: Mapping[str, Mapping[int, float]], title: str = "R@K") -> Path:
    """R@K against K, one line per (mode, box), written as PNG."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(4.5, 3.2))
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    for name, rec in curves.items():
        ks = sorted(int(k) for k in rec)
        ax.plot(ks, [100 * rec[k] for k in ks], marker="o", label=name)
    ax.set_xlabel("K")
    ax.set_ylabel("R@K %")
    ax.set_ylim(0, 100)
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend(fontsize="small")
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=120, bbox_inches="tight")
    return Path(path)


def write_eval_outputs(
    result: EvalResult, out_dir: Union[str, Path], compare: Optional[Union[str, Path]] = None
) -> dict[str, Path]:
    """Write ``eval.json``, ``eval.md`` and the PNG plots into ``out_dir``; returns the paths."""
    from ..io import write_json, write_text

    out = Path(out_dir)
    data = result.to_dict()
    deltas, reference = None, ""
    if compare is not None:
        other = load_eval(compare)
        reference = f"`{compare}` (run `{other.get('run_dir')}`)"
        deltas = compare_evals(other, data)
        data["compare"] = {
            "reference": str(compare),
            "reference_run": other.get("run_dir"),
            "iou_deltas": {m: {b: d.to_dict() for b, d in by.items()} for m, by in deltas.items()},
        }
    paths = {"json": out / "eval.json", "md": out / "eval.md"}
    title = {b: box_title(data, b) for b in data["boxes"]}
    modes = result.modes
    bars = {}
    for b in data["boxes"]:
        bars[f"loc. ({title[b]})"] = {m: result.scores[m][b].loc_accuracy for m in modes}
        bars[f"mIoU ({title[b]})"] = {m: result.scores[m][b].miou for m in modes}
    paths["scores_png"] = plot_grouped_bars(out / "scores.png", bars, title=f"{result.scene}: per mode")
    split = {
        k: {f"{m} {title[b]}": result.split[m][b][k]["miou"] for m in modes for b in data["boxes"]}
        for k in ("simple", "compound")
        if any(result.split[m][b][k]["pairs"] for m in modes for b in data["boxes"])
    }
    if split:
        paths["split_png"] = plot_grouped_bars(out / "simple_compound.png", split, title="mIoU by query type")
    if result.retrieval:
        curves = {}
        for m in modes:
            for b in data["boxes"]:
                curves[m if m in ONE_MAP_MODES else f"{m} ({title[b]})"] = result.retrieval[m][b].recall
        paths["recall_png"] = plot_recall_curves(out / "recall_at_k.png", curves)
    for m in modes:
        if m in SCALE_MODES:
            for b in data["boxes"]:
                paths[f"levels_{m}_{b}"] = plot_level_histogram(
                    out / f"scales_{m}_{b}.png", result.scores[m][b], title=f"{m}: chosen scale ({title[b]})"
                )
    if deltas:
        for m, by in deltas.items():
            for b, d in by.items():
                if d.deltas:
                    paths[f"delta_{m}_{b}"] = plot_query_deltas(
                        out / f"delta_{m}_{b}.png", d, title=f"IoU delta vs reference: {m}, {title[b]}"
                    )
    write_text(paths["md"], markdown_report(data, deltas, reference))
    write_json(paths["json"], data)  # last: its presence marks a finished evaluation
    return paths
