"""``n2f2 run-many``: :func:`~n2f2.pipeline.run.run_pipeline` on several scenes, one task each
(serially or on Ray, :mod:`n2f2.distributed`), and a summary table of the runs."""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

from ..io import make_dirs, write_json
from .run import RunOptions, check_models_before_work, run_pipeline

SUMMARY_NAME = "summary"  # DIR/summary.json and DIR/summary.md
SUMMARY_STAGES = ("fit-gaussians", "segments", "train", "eval")


def _eval_mious(eval_json: str | None) -> dict:
    """{mode: {box: mIoU}} of a run's eval.json ({} without evaluation)."""
    if eval_json is None:
        return {}
    scores = json.loads(Path(eval_json).read_text())["scores"]
    return {mode: {box: float(v["miou"]) for box, v in boxes.items()} for mode, boxes in scores.items()}


def run_scene(opt: RunOptions) -> dict:
    """One scene of ``run-many``: :func:`run_pipeline` into ``opt.out``, then the scene's summary
    row. Bad input is the row's status (``failed`` and the error), not an exception, so the
    other scenes go on."""
    from ..errors import N2F2Error
    from ..io import command_outputs

    name = Path(opt.out).name
    start = time.perf_counter()
    row = {"scene": name, "data": str(opt.data), "run_dir": str(opt.out)}
    try:
        # One scene's writes as a set (its finished stages stay): a failed scene leaves its folder
        # as it was, and a Ray worker lets go of the folder's lock when its task ends.
        with command_outputs():
            result = run_pipeline(opt, log=lambda msg: print(f"{name}: {msg}", flush=True))
        mious = _eval_mious(result["eval"])
    except N2F2Error as e:
        return {
            **row,
            "status": "failed",
            "error": str(e),
            "seconds": round(time.perf_counter() - start, 2),
            "stages": {},
            "miou": {},
            "eval": None,
        }
    stages = {
        stage: {"seconds": rec.get("seconds"), "ran": stage in result["ran"]} for stage, rec in result["stages"].items()
    }
    return {
        **row,
        "status": "ok",
        "error": None,
        "seconds": round(time.perf_counter() - start, 2),
        "stages": stages,
        "miou": mious,
        "eval": result["eval"],
    }


def summary_markdown(summary: dict) -> str:
    """``summary.md``: per scene its status, mIoU per mode and box, and time per stage."""
    from ..eval.reports import markdown_table

    rows = summary["scenes"]
    modes = [m for m in ("composite", "explicit", "soft", "oracle") if any(m in r["miou"] for r in rows)]
    modes += sorted({m for r in rows for m in r["miou"]} - set(modes))
    boxes = [b for b in ("exact", "scaled") if any(b in r["miou"].get(m, {}) for r in rows for m in modes)]
    body = []
    for r in rows:
        cells = [r["scene"], r["status"]]
        for m in modes:
            cells.append(
                " / ".join(f"{100 * r['miou'][m][b]:.1f}" if b in r["miou"].get(m, {}) else "-" for b in boxes)
            )
        for stage in SUMMARY_STAGES:
            st = r["stages"].get(stage)
            cells.append(
                "-"
                if st is None or st["seconds"] is None
                else f"{st['seconds']:.1f}" + ("" if st["ran"] else " (cached)")
            )
        cells.append(f"{r['seconds']:.1f}")
        body.append(cells)
    box_note = " / ".join(boxes)
    headers = (
        ["scene", "status"]
        + [f"{m} mIoU % ({box_note})" for m in modes]
        + [f"{s} s" for s in SUMMARY_STAGES]
        + ["wall s"]
    )
    text = (
        f"# run-many: {len(rows)} scenes, executor {summary['executor']}, {summary['seconds']:.1f} s\n\n"
        + markdown_table(headers, body)
    )
    failed = [r for r in rows if r["status"] != "ok"]
    if failed:
        text += "\n" + "".join(f"- {r['scene']}: {r['error']}\n" for r in failed)
    text += (
        "\nmIoU per box of LangSplat's protocol (exact: 30 px box; scaled: box scaled to the image "
        "width). Stage times are those of the stage's last run; (cached): skipped this time, its inputs "
        "unchanged.\n"
    )
    return text


def run_many(opts: list[RunOptions], out: Path, executor, progress: bool = True) -> dict:
    """:func:`run_scene` for every scene, one task each on ``executor`` (serial or Ray), then
    ``out/summary.json`` and ``out/summary.md``. Returns the summary."""
    from tqdm import tqdm

    from ..distributed import TaskFailure
    from ..io import claim_out_dir, commit_outputs, write_text

    for opt in opts:  # a missing model stops every scene before the first one's work
        check_models_before_work(opt)
    claim_out_dir(out, ())  # writable, and ours alone: before any scene's work
    start = time.perf_counter()
    rows: list = [None] * len(opts)
    bar = tqdm(total=len(opts), desc="run-many", unit="scene", disable=not progress)
    with executor:
        for k, row in executor.map(run_scene, opts):
            if isinstance(row, TaskFailure):  # run_scene reports bad input itself; kept for safety
                row = {
                    "scene": Path(opts[k].out).name,
                    "data": str(opts[k].data),
                    "run_dir": str(opts[k].out),
                    "status": "failed",
                    "error": str(row),
                    "seconds": 0.0,
                    "stages": {},
                    "miou": {},
                    "eval": None,
                }
            rows[k] = row
            if row["status"] != "ok":
                bar.write(f"run-many: {row['scene']} failed: {row['error']}", file=sys.stderr)
            bar.update(1)
    bar.close()
    summary = {"executor": executor.name, "seconds": round(time.perf_counter() - start, 2), "scenes": rows}
    make_dirs(out)
    write_json(out / f"{SUMMARY_NAME}.json", summary)
    write_text(out / f"{SUMMARY_NAME}.md", summary_markdown(summary))
    commit_outputs()  # the summary stays when the command then exits 2 for a failed scene
    return summary
