"""The loss budget: where accuracy goes between the teacher and the field's answers.

For one run, one label set and one protocol, the same evaluation code (:func:`n2f2.eval.runner.
evaluate_run`) scores, in order along the pipeline:

1. **teacher**: the segment bank's own per-view 2D features at its 3 levels (part, object,
   group; :func:`n2f2.field.lift.level_segments`), each pixel taking the embedding of the
   segment covering it at that level (zero where none does: relevancy 0.5), with LangSplat's
   level choice (``levels`` mode); and at the oracle level;
2. **lift**: the teacher lifted onto the Gaussians (:func:`n2f2.field.lift.lift_features`, the
   training views' blending weights, no network) and rendered back with the rasterizer, the same
   two ways: what geometry and rendering cost;
3. **field**: the trained field at the oracle scale, then ``composite``, ``explicit`` and ``soft``
   (:mod:`n2f2.query.soft`): what distillation and the choice of scale cost.

Each row has mIoU and localization under both box sizes, mAP (threshold-free), and the
part / object / group split (:func:`n2f2.eval.runner.kind_scores`). ``n2f2 eval --budget``
writes it into ``eval.json`` (``"budget"``) and ``eval.md``; :func:`loss_budget` is the function
other code (the bench) calls.

The teacher exists at every view of the bank, held-out views included; the lift and the field
saw only the training views, so on held-out labelled views the teacher row is also an upper
bound of what novel-view synthesis keeps.
"""

from __future__ import annotations

import math
import time
from dataclasses import replace
from pathlib import Path
from typing import Any, Mapping, Optional, Sequence, Union

import numpy as np
import torch

from ..errors import InputError
from ..field.lift import bank_level_rule, level_segments
from ..query.engine import ViewCache
from ..query.lifted import LevelBlockEngine
from .runner import BOXES, QUERY_KINDS, EvalConfig, EvalResult, evaluate_run
from .tables import markdown_table, pct

# (row name, source, mode of that source's evaluation), in pipeline order
ROWS = (
    ("teacher, 3 levels", "teacher", "levels"),
    ("teacher, oracle level", "teacher", "oracle"),
    ("lift, 3 levels", "lift", "levels"),
    ("lift, oracle level", "lift", "oracle"),
    ("field, oracle scale", "field", "oracle"),
    ("composite", "field", "composite"),
    ("explicit", "field", "explicit"),
    ("soft", "field", "soft"),
)
ABOUT = {
    "teacher": "the segment bank's 2D features of each labelled view at its 3 levels, no 3D",
    "lift": "the teacher lifted onto the Gaussians (blending-weight average over the training views) and "
    "rendered back: no network",
    "field": "the trained field",
}


# ------------------------------------------------------------------------------ the teacher
class TeacherEngine(LevelBlockEngine):
    """The bank's per-view features at 3 levels, answered as a 3-level field is (modes
    ``levels`` and ``oracle``), at the scene's views only (no Gaussians)."""

    def __init__(
        self,
        bank: Any,
        encoder: Any,
        meta: dict,
        config: Any = None,
        device: Any = "cpu",
        scene: Any = None,
        run_dir: Any = None,
    ) -> None:
        super().__init__(int(bank.embed_dim), None, encoder, meta, config, device, scene, run_dir)
        self.bank = bank
        self.rule = bank_level_rule(bank)

    @torch.no_grad()
    def render_view(self, view: Any, modes: Sequence[str] = ("levels",), rgb: bool = False) -> ViewCache:
        """The view's teacher features ``[P, 3E]`` (no rendering) and their score cache."""
        for m in modes:
            self._check_mode(m)
        cam, index, name = self.camera(view)
        if index is None:
            raise InputError(None, "the teacher's features exist only at the scene's views, not at a free camera")
        t0 = time.perf_counter()
        rec = self.bank.record(self.bank.index(name))
        ids = level_segments(rec, self.rule)  # [3, h, w]
        if ids.shape[1:] != (cam.height, cam.width):
            from ..segments.segmenters import resize_nearest

            ids = resize_nearest(ids, cam.height, cam.width)
        emb = torch.from_numpy(np.asarray(rec.embeddings, dtype=np.float32)).to(self.device)  # [S, E]
        ids_t = torch.from_numpy(np.ascontiguousarray(ids).reshape(3, -1)).to(self.device)  # [3, P]
        P, E = ids_t.shape[1], emb.shape[1]
        feats = torch.zeros(P, 3, E, device=self.device)
        for level in range(3):
            sel = torch.nonzero(ids_t[level] >= 0).squeeze(1)
            feats[sel, level] = emb[ids_t[level, sel]]
        t1 = time.perf_counter()
        caches = {"levels": self._build_cache("levels", feats.reshape(P, 3 * E))}
        alpha = torch.ones(cam.height, cam.width, device=self.device)
        return ViewCache(cam, index, name, caches, alpha, None, {"render": t1 - t0, "cache": time.perf_counter() - t1})


def teacher_engine(
    bank: Any, encoder: Any, meta: dict, config: Any = None, device: Any = "cpu", scene: Any = None, run_dir: Any = None
) -> Any:
    """A query engine over the bank's own per-view features (see the module docstring)."""
    return TeacherEngine(bank, encoder, meta, config, device, scene, run_dir)


# ------------------------------------------------------------------------------ the budget
def _row(name: str, source: str, mode: str, ev: EvalResult) -> dict:
    scores = {}
    for b in ev.scores[mode]:
        s = ev.scores[mode][b]
        scores[b] = {
            "miou": s.miou,
            "loc_accuracy": s.loc_accuracy,
            "map": ev.ap[mode][b]["map"],
            "oracle_miou": s.oracle_miou,
            "num_pairs": s.num_pairs,
            "kinds": {
                k: {f: v[f] for f in ("pairs", "miou", "loc_accuracy", "map")} for k, v in ev.kinds[mode][b].items()
            },
        }
    per_query = {
        b: {q: {f: v.get(f, math.nan) for f in ("iou", "hit", "ap")} for q, v in by.items()}
        for b, by in ev.per_query[mode].items()
    }
    return {"name": name, "source": source, "mode": mode, "scores": scores, "per_query": per_query}


def loss_budget(
    run_dir: Union[str, Path],
    label_dir: Union[str, Path],
    *,
    scene: Optional[Union[str, Path]] = None,
    bank: Optional[Union[str, Path]] = None,  # default: the run's segment bank (needed)
    query_types: Optional[Union[str, Path, Mapping[str, str]]] = None,
    config: EvalConfig = EvalConfig(),
    query_config: Any = None,
    device: str = "cpu",
    encoder: Any = None,
    field_result: Optional[EvalResult] = None,  # the run's own evaluation, reused when it has the modes
    engine: Any = None,  # the run's query engine, when one is open already (its text encoder is reused)
) -> dict:
    """The loss budget table of a run (see the module docstring): ``{"rows": [...], "lift":
    {...}, "teacher": {...}, "notes": [...]}``; each row holds, per box, mIoU, localization,
    mAP and the per-kind split, and its per-query IoU / hit / AP."""
    from ..query.engine import QueryEngine
    from ..query.lifted import lift_engine, run_lift
    from ..segments.bank import SegmentBank

    t0 = time.perf_counter()
    base = (
        engine
        if engine is not None
        else QueryEngine.from_run(run_dir, device=device, scene=scene, config=query_config, encoder=encoder)
    )
    if base.scene is None:
        raise InputError(run_dir, "the run does not record its scene folder: pass --scene DIR")
    bank_path = bank if bank is not None else base.meta.get("bank")
    if not bank_path or not Path(bank_path).is_dir():
        raise InputError(
            Path(bank_path) if bank_path else Path(run_dir),
            "the loss budget needs the run's segment bank (the teacher): pass --bank DIR",
        )
    bank_obj = SegmentBank.open(bank_path)
    bank_obj.validate_against(base.scene)
    common: dict[str, Any] = {
        "scene": base.scene.root,
        "bank": bank_path,
        "query_types": query_types,
        "query_config": query_config,
        "device": device,
    }
    field_modes = base.modes()  # the field variant's: composite / explicit / oracle, or levels / oracle
    if field_result is None or any(m not in field_result.modes for m in field_modes):
        field_result = evaluate_run(
            run_dir, label_dir, config=replace(config, modes=field_modes), encoder=encoder, engine=base, **common
        )
    shared_encoder = base.encoder  # loaded once, used by the three engines
    level_cfg = replace(config, modes=("levels", "oracle"))

    teacher = teacher_engine(bank_obj, shared_encoder, dict(base.meta), base.config, device, base.scene, Path(run_dir))
    teacher_result = evaluate_run(run_dir, label_dir, config=level_cfg, engine=teacher, **common)

    lift, from_file = run_lift(run_dir, base, bank_obj, progress=config.progress)
    views = lift.views
    lifted = lift_engine(
        lift, base.gaussians, shared_encoder, dict(base.meta), base.config, device, base.scene, Path(run_dir)
    )
    lift_result = evaluate_run(run_dir, label_dir, config=level_cfg, engine=lifted, **common)

    results = {"teacher": teacher_result, "lift": lift_result, "field": field_result}
    rows = []
    for name, source, row_mode in ROWS:
        # A field answers each row with its own variant's mode (a levels field: explicit -> levels).
        mode = base.kind.mode_for(row_mode) if source == "field" else row_mode
        if mode is not None and mode != row_mode:
            name = f"{base.variant} field, {len(base.scale_labels)} {mode}"
        if mode is None or mode not in results[source].modes:
            continue
        rows.append(_row(name, source, mode, results[source]))
    notes = [
        f"The teacher's levels: {teacher.rule[0]} of the bank ({bank_path}).",
        (
            f"The lift: {len(views)} training views, {int(lift.features.shape[0])} Gaussians; "
            + (
                f"written by training from its cached blending weights (RUN/lift.pt), averaging "
                f"{lift.seconds['lift']:.1f} s."
                if from_file
                else f"built now in {lift.seconds['total']:.1f} s ({lift.seconds['blend']:.1f} s blending weights, "
                f"{lift.seconds['lift']:.1f} s averaging)."
            )
        ),
    ]
    held = sum(bool(v.get("heldout")) for v in field_result.views)
    if held:
        notes.append(
            f"{held} of {len(field_result.views)} labelled views are held out from training: the teacher "
            "has features there, the lift and the field only render them."
        )
    return {
        "rows": rows,
        "about": dict(ABOUT),
        "lift": {
            "views": views,
            "num_gaussians": int(lift.features.shape[0]),
            "rule": lift.rule,
            "from": "RUN/lift.pt (training's blend cache)" if from_file else "built by the evaluation",
            "seconds": dict(lift.seconds),
            "coverage": dict(zip(("part", "object", "group"), lift.coverage())),
        },
        "teacher": {"rule": teacher.rule[0], "bank": str(bank_path)},
        "boxes": {b: field_result.boxes[b]["box_sizes"] for b in field_result.boxes},
        "notes": notes,
        "seconds": time.perf_counter() - t0,
    }


# ------------------------------------------------------------------------------ report
def budget_table(budget: Mapping, kinds: bool = False) -> str:
    """The budget as a Markdown table: per row mIoU / loc. / mAP under both boxes, or with
    ``kinds`` the part / object / group split (exact box: mIoU, scaled box: mIoU, mAP)."""
    rows = budget["rows"]
    boxes = [b for b in BOXES if all(b in r["scores"] for r in rows)]
    size = {b: ",".join(str(s) for s in budget.get("boxes", {}).get(b, [])) for b in boxes}
    label = {b: f"{b} {size[b]} px" if size[b] else b for b in boxes}
    if not kinds:
        ref = rows[0]["scores"]["exact"]["miou"] if rows else math.nan
        body = []
        for r in rows:
            s = r["scores"]
            body.append(
                [r["name"]]
                + [pct(s[b]["miou"]) for b in boxes]
                + [pct(s[b]["loc_accuracy"]) for b in boxes]
                + [pct(s[b]["map"]) for b in boxes]
                + [f"{100 * (s['exact']['miou'] - ref):+.1f}" if np.isfinite(ref) else "n/a", s["exact"]["num_pairs"]]
            )
        return markdown_table(
            ["source"]
            + [f"mIoU % ({label[b]})" for b in boxes]
            + [f"loc. % ({label[b]})" for b in boxes]
            + [f"mAP % ({label[b]} choice)" for b in boxes]
            + [f"mIoU vs {rows[0]['name'] if rows else '-'} (exact)", "pairs"],
            body,
        )
    shown = [k for k in QUERY_KINDS if any(r["scores"]["exact"]["kinds"][k]["pairs"] for r in rows)]
    body = []
    for r in rows:
        ex, sc = r["scores"]["exact"]["kinds"], r["scores"].get("scaled", r["scores"]["exact"])["kinds"]
        body.append([r["name"]] + [f"{pct(ex[k]['miou'])} / {pct(sc[k]['miou'])} / {pct(ex[k]['map'])}" for k in shown])
    pairs = {k: rows[0]["scores"]["exact"]["kinds"][k]["pairs"] for k in shown}
    return markdown_table(
        ["source"] + [f"{k} ({pairs[k]} pairs): mIoU exact / mIoU scaled / mAP %" for k in shown],
        body,
        ["l"] + ["r"] * len(shown),
    )


def budget_markdown(budget: Mapping) -> str:
    """The ``eval.md`` section of the loss budget."""
    out = [
        "\n## Loss budget: teacher -> lift -> field -> answers\n\n",
        "Same labels, same protocol, same evaluation code for every row. Sources: "
        + "; ".join(f"**{k}**: {v}" for k, v in budget.get("about", ABOUT).items())
        + ". "
        "`3 levels` is LangSplat's level choice (max R' for segmentation, max box(R) for localization); "
        "`oracle` the best level / scale per pair (an upper bound of that choice).\n\n",
        budget_table(budget),
        "\n### By query kind\n\n",
        budget_table(budget, kinds=True),
    ]
    for note in budget.get("notes", []):
        out.append(f"\n- {note}")
    out.append("\n")
    return "".join(out)
