"""Query benchmark: one run, one view.

Prints the render-and-cache time of the view, the per-query time of composite, explicit and
levels at 1 and at 10 queries, and the floor: one plain ``[H*W, D] x [D]`` matrix-vector product
on the same machine (a composite query cannot do less than read the cached ``H x W x D``
features once). Text embeddings are computed once beforehand (and timed separately): the
encoder's cost is the same in every mode.

    python benchmarks/bench_query.py RUN_DIR [--scene DATA] [--view 0] [--levels-run RUN_DIR]

The levels mode needs a field trained with variant "levels"; without ``--levels-run`` it is
timed on a stand-in of the same size (the run's own field read as a levels field: W cut into
the 3 column blocks of the levels variant), which costs what a levels field of the same D and E
costs.
Times are medians (and minima) over ``--repeats`` runs. The "x floor" column is the median of
per-run ratios, the floor timed right before each query call, so both see the same load from
other processes (on a shared machine absolute times drift by 2-4x).
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

QUERIES = ["teapot", "lid of the teapot", "red mug", "blue mug", "handle of the blue mug",
           "bag of cookies", "loose cookies", "plate of fruit", "banana", "table"]


def timeit(fn, repeats: int) -> tuple[float, float]:
    """(median, min) wall seconds over ``repeats`` calls after one warm-up call."""
    fn()
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts), min(ts)


def paired(fn, floor_fn, n: int, repeats: int) -> tuple[float, float, float]:
    """Per-query (median, min) seconds of ``fn`` (which answers ``n`` queries), and the median
    over repeats of (per-query time / floor time), the floor timed right before each call so
    both see the same load from other processes."""
    fn()
    floor_fn()
    ts, ratios = [], []
    for _ in range(repeats):
        t0 = time.perf_counter()
        floor_fn()
        t1 = time.perf_counter()
        fn()
        t2 = time.perf_counter()
        ts.append((t2 - t1) / n)
        ratios.append((t2 - t1) / n / (t1 - t0))
    return statistics.median(ts), min(ts), statistics.median(ratios)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("run_dir")
    p.add_argument("--scene", default=None)
    p.add_argument("--view", type=int, default=0)
    p.add_argument("--levels-run", default=None, help="a run trained with variant 'levels'")
    p.add_argument("--repeats", type=int, default=15)
    p.add_argument("--device", default="cpu")
    p.add_argument("--threads", type=int, default=1,
                   help="torch threads (default 1: on a shared 2-core machine multi-threaded BLAS "
                        "and elementwise kernels stall on each other; 0 = torch's default)")
    args = p.parse_args(argv)
    if args.threads > 0:
        torch.set_num_threads(args.threads)

    from n2f2.query import QueryConfig, QueryEngine

    engine = QueryEngine.from_run(args.run_dir, device=args.device, scene=args.scene)
    t0 = time.perf_counter()
    engine.encode(QUERIES + list(engine.config.negatives) + list(engine.config.canonical))
    t_text = time.perf_counter() - t0
    t0 = time.perf_counter()
    _ = engine.theta_tilde  # Theta at the Gaussians + gamma + premultiply, once per field
    t_field = time.perf_counter() - t0

    with torch.no_grad():
        t_render, _ = timeit(lambda: engine.render_view(args.view, modes=["composite"], rgb=False), 3)
        view = engine.render_view(args.view, modes=["composite", "explicit"], rgb=False)
        H, W = view.height, view.width
        P, D = H * W, engine.dim
        E = engine.W.shape[0]
        t_render_explicit = view.seconds["render"] + view.seconds["cache"]

        # Floor: one plain [H*W, D] x [D] matrix-vector product on the cached features.
        feats = view.caches["composite"].features  # [P, D] contiguous
        vec = torch.randn(D, device=feats.device)
        floor, floor_min = timeit(lambda: feats @ vec, args.repeats * 4)

        rows = []

        def floor_fn():
            return feats @ vec

        def per_query(mode, n, **kw):
            texts = QUERIES[:n]
            return paired(lambda: engine.query(view, texts, mode, **kw), floor_fn, n, args.repeats)

        for n in (1, 10):
            rows.append(("composite", n, *per_query("composite", n)))
        for sel in ("smoothed", "max"):
            engine.config.selection = sel
            for n in (1, 10):
                rows.append((f"explicit ({sel})", n, *per_query("explicit", n)))
        engine.config.selection = "smoothed"

        # Levels: a real levels run if given, else the same field read as a levels field
        # (NestedField.level_features: 3 column blocks of W), which has the same cost.
        if args.levels_run:
            lv = QueryEngine.from_run(args.levels_run, device=args.device, scene=args.scene)
            levels_label = "levels"
        else:
            meta = dict(engine.meta, config=dict(engine.meta["config"], variant="levels"))
            lv = QueryEngine(engine.field, engine.gaussians, engine.encoder, meta, QueryConfig(),
                             args.device, engine.scene)
            levels_label = "levels (same-size stand-in)"
        lv.encode(QUERIES)
        lview = lv.render_view(args.view, modes=["levels"], rgb=False)
        for sel in ("smoothed", "max"):
            lv.config.selection = sel
            for n in (1, 10):
                texts = QUERIES[:n]
                rows.append((f"{levels_label} ({sel})", n,
                             *paired(lambda: lv.query(lview, texts, "levels"), floor_fn, n, args.repeats)))

    print(f"device: {args.device}, torch threads: {torch.get_num_threads()}")
    print(f"run: {args.run_dir}, view {args.view} ({view.name}), H x W = {H} x {W}, D = {D}, E = {E}, "
          f"k = {engine.step}, scales = {len(engine.scale_dims)}, Gaussians = {engine.gaussians.num}")
    print(f"text encoding of {len(QUERIES) + 9} phrases (once): {t_text * 1e3:.1f} ms")
    print(f"Theta~ for all Gaussians (field + gamma + premultiply, once per field): {t_field * 1e3:.1f} ms")
    print(f"render-and-cache, composite (render Theta~ + norms + negatives): {t_render * 1e3:.1f} ms")
    print(f"render-and-cache, composite + explicit caches: {t_render_explicit * 1e3:.1f} ms")
    print(f"floor: one [H*W, D] x [D] matrix-vector product: {floor * 1e3:.3f} ms (min {floor_min * 1e3:.3f})")
    print()
    print("| mode | queries | per-query ms (median) | per-query ms (min) | x floor (paired median) |")
    print("|---|---|---|---|---|")
    for mode, n, med, mn, ratio in rows:
        print(f"| {mode} | {n} | {med * 1e3:.3f} | {mn * 1e3:.3f} | {ratio:.2f} |")


if __name__ == "__main__":
    main()
