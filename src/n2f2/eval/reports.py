"""Evaluation reports: Markdown tables and PNG plots (matplotlib's Agg canvas, no display).

Scores are shown in percent with one decimal, as the paper's tables are. Every table states the
mean-filter size it was computed with, so exact (30 px) and scaled-box numbers cannot be
confused.
"""

from __future__ import annotations

import math
import numbers
from pathlib import Path
from typing import TYPE_CHECKING, Mapping, Optional, Sequence, Union

import numpy as np

from ..io import atomic_path

if TYPE_CHECKING:
    from .metrics import QueryDeltas, RetrievalScores
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


def eval_results(out: Union[str, Path]) -> list[str]:
    """The names of a previous evaluation's files that ``out`` may hold."""
    out = Path(out)
    found = sorted(p.name for pattern in RESULT_PATTERNS for p in out.glob(pattern)) if out.is_dir() else []
    return [*RESULT_NAMES, *found]


def _fmt(value: object, digits: int = 1, percent: bool = False) -> str:
    """Numbers as text: percent (x100) with ``digits`` decimals, NaN as "n/a", None as "-"."""
    if value is None:
        return "-"
    if isinstance(value, (bool, np.bool_)):
        return "yes" if value else "no"
    if isinstance(value, (int, np.integer)) and not percent:
        return str(int(value))
    if isinstance(value, numbers.Real):
        v = float(value)
        if math.isnan(v):
            return "n/a"
        return f"{100 * v:.{digits}f}" if percent else f"{v:.{digits}f}"
    return str(value)


def _cell(text: object) -> str:
    return str(text).replace("|", "\\|").replace("\n", " ")


def markdown_table(
    headers: Sequence[str],
    rows: Sequence[Sequence[object]],
    align: Optional[Sequence[str]] = None,  # per column "l" | "r" | "c"; default l then r
) -> str:
    """A GitHub Markdown table; cells are str()-ed (floats should be formatted by the caller),
    and '|' in a cell is escaped."""
    n = len(headers)
    if any(len(r) != n for r in rows):
        raise ValueError(f"every row needs {n} cells")
    align = list(align) if align is not None else ["l"] + ["r"] * (n - 1)
    rule = {"l": ":---", "r": "---:", "c": ":---:"}
    lines = ["| " + " | ".join(_cell(h) for h in headers) + " |", "| " + " | ".join(rule[a] for a in align) + " |"]
    lines += ["| " + " | ".join(_cell(c) for c in r) + " |" for r in rows]
    return "\n".join(lines) + "\n"


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
                _fmt(s.miou, percent=True),
                _fmt(s.loc_accuracy, percent=True),
                _fmt(s.oracle_miou, percent=True),
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
                _fmt(sum(v.miou for v in vals) / len(vals), percent=True),
                _fmt(sum(v.loc_accuracy for v in vals) / len(vals), percent=True),
                _fmt(sum(v.oracle_miou for v in vals) / len(vals), percent=True),
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
            _fmt(p.iou, percent=True),
            _fmt(p.hit),
            p.seg_level,
            p.loc_level,
            " ".join(_fmt(v, percent=True) for v in p.iou_per_level),
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
                    _fmt(d.a, percent=percent),
                    _fmt(d.b, percent=percent),
                    ("+" if d.delta >= 0 else "") + _fmt(d.delta, percent=percent),
                ]
            )
    return markdown_table(["", "query", name_a, name_b, "delta"], rows, ["l", "l", "r", "r", "r"])


def retrieval_table(results: Mapping[str, RetrievalScores]) -> str:  # run name -> scores
    ks = sorted({k for r in results.values() for k in r.ks})
    rows = [
        [name]
        + [_fmt(r.recall.get(k), percent=True) for k in ks]
        + [_fmt(r.mean_first_rank), len(r.per_query), len(r.skipped)]
        for name, r in results.items()
    ]
    return markdown_table(["run"] + [f"R@{k} %" for k in ks] + ["mean first rank", "queries", "skipped"], rows)


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
    if len(series) > 1:
        ax.legend(fontsize="small")
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
    ax.bar(x - 0.2, np.bincount(seg, minlength=n), 0.4, label="segmentation")
    ax.bar(x + 0.2, np.bincount(loc, minlength=n), 0.4, label="localization")
    ax.set_xticks(x)
    ax.set_xlabel("level")
    ax.set_ylabel("pairs")
    ax.set_title(title)
    ax.legend(fontsize="small")
    return _save(fig, path)
