"""The query-time breakdown of the bench (paper Table 4)."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any, Optional

import numpy as np

from ..errors import InputError

if TYPE_CHECKING:
    from .config import BenchConfig, BenchData


def timing_breakdown(
    nested_run: Path, levels_run: Optional[Path], data: "BenchData", config: "BenchConfig", encoder: Any = None
) -> dict:
    """Paper Table 4 on one labelled view: render-and-cache time, time per query at 1 and at 10
    queries, and totals, for composite and explicit (N2F2 field) and levels (3-level field).

    Times are the engine's own (``ViewCache.seconds``, ``QueryResult.seconds``), medians over
    ``timing_repeats``; text embeddings are computed once beforehand (the encoder costs the same
    in every mode) and ``Theta~`` (gamma^3D premultiplied, once per field) is timed separately."""
    import torch

    from ..data import load_scene
    from ..data.scene import read_scene_meta
    from ..query.engine import QueryEngine

    threads = torch.get_num_threads()
    if config.timing_threads > 0:
        torch.set_num_threads(config.timing_threads)
    try:
        scene = load_scene(data.scene_dir)
        queries = _scene_queries(data.scene_dir)[:10]
        labelled = read_scene_meta(data.scene_dir).get("labelled_views") or [0]
        view = int(labelled[0])
        rows, once = [], {}

        def measure(engine: Any, mode: str, label: str) -> None:
            engine.encode(queries + list(engine.config.negatives) + list(engine.config.canonical))
            render, cache = [], []
            for _ in range(config.timing_repeats):
                vc = engine.render_view(view, modes=[mode], rgb=False)
                render.append(vc.seconds["render"])
                cache.append(vc.seconds["cache"])
            per, scales = {}, 0
            for n in (1, len(queries)):
                scales = len(engine.query(vc, queries[:n], mode).scale_labels)  # warm-up; its candidate scales
                per[n] = float(
                    np.median([engine.query(vc, queries[:n], mode).seconds for _ in range(config.timing_repeats)])
                )
            r, c = float(np.median(render)), float(np.median(cache))
            n = len(queries)
            rows.append(
                {
                    "method": label,
                    "mode": mode,
                    "scales": scales,
                    "render_s": r,
                    "cache_s": c,
                    "query_1_s": per[1],
                    "per_query_s": per[n] / n,
                    f"queries_{n}_s": per[n],
                    "total_1_s": r + c + per[1],
                    f"total_{n}_s": r + c + per[n],
                    "num_queries": n,
                }
            )

        engine = QueryEngine.from_run(nested_run, device=config.device, scene=scene, encoder=encoder)
        t0 = time.perf_counter()
        _ = engine.theta_tilde
        once["theta_tilde_s"] = time.perf_counter() - t0
        once["gaussians"] = int(engine.gaussians.means.shape[0])
        measure(engine, "composite", "N2F2 composite")
        measure(engine, "explicit", f"N2F2 explicit ({len(engine.scale_dims)} scales, LERF-like)")
        if levels_run is not None:
            lv = QueryEngine.from_run(levels_run, device=config.device, scene=scene, encoder=encoder)
            measure(lv, "levels", "3-level field (LangSplat-like)")
        cam = scene.cameras[view]
        return {
            "rows": rows,
            "once": once,
            "view": view,
            "size": [cam.width, cam.height],
            "dim": engine.dim,
            "threads": torch.get_num_threads(),
            "repeats": config.timing_repeats,
            "queries": queries,
        }
    finally:
        torch.set_num_threads(threads)


def _scene_queries(scene_dir: Path) -> list[str]:
    path = scene_dir / "queries.json"
    if not path.is_file():
        raise InputError(path, "the demo scene has no queries.json")
    return [q["query"] for q in json.loads(path.read_text())["queries"]]
