"""The bench's report: ``bench.md`` (the claims' verdicts and one section per ablation) and
its PNG plots (mIoU per method, the k sweep, the training loss curves).

(Longer than 600 lines: one section writer per ablation table and plot of ``bench.md``, each
short; none computes a score.)"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Mapping, Optional, Sequence

import numpy as np

from ..eval.reports import box_title, pct
from ..eval.runner import BOXES
from ..eval.tables import markdown_table
from ..query.modes import MODES, QUERY_MODES
from .claims import PAPER_RENDER, UNIT, convergence, score, signed_pts, tag, temperature_label
from .variants import PAPER_STEPS, VARIANTS

PAPER_MODES = tuple(m for m in MODES if QUERY_MODES[m].paper)  # the paper's Table 3 and Table 6 columns


def write_plots(out: Path, result: Mapping, runs: Mapping[str, dict], variant_runs: Mapping[str, str]) -> dict:
    """mIoU per method (both boxes), the k sweep, and the training loss curves."""
    from ..eval.reports import plot_grouped_bars, plot_lines

    plots: dict[str, Path] = {}
    methods = _method_rows(runs, variant_runs)
    if methods:
        values = {f"mIoU ({b})": {label: score(e, m, b) for label, e, m in methods} for b in BOXES}
        values.update(
            {f"loc. ({b})": {label: score(e, m, b, "loc_accuracy") for label, e, m in methods} for b in BOXES}
        )
        plots["methods"] = plot_grouped_bars(out / "methods.png", values, title="demo scene: per method")
    ks = _k_rows(runs, variant_runs, result)
    if len(ks) > 1:
        curves = {}
        for mode in PAPER_MODES:
            for b in BOXES:
                pts = [(k, score(e, mode, b)) for k, _, e in ks if mode in e["scores"]]
                if pts:
                    curves[f"{mode} ({b})"] = ([p[0] for p in pts], [100 * p[1] for p in pts])
        plots["k_sweep"] = plot_lines(
            out / "k_sweep.png", curves, "paper step size k (log scale of scales)", "mIoU %", "step size k (Table 6)"
        )
    curves = {
        name: (r["curve"]["step"], r["curve"]["loss"])
        for name, r in result["runs"].items()
        if r.get("curve") and r["curve"].get("loss")
    }
    if curves:
        plots["loss"] = plot_lines(
            out / "loss_curves.png", curves, "step", "training loss (L2 + 0.001 cos)", "training loss", logy=True
        )
    return plots


# (variant, mode, label[, evaluation]) of the per-method plot and table, in this order; the
# evaluation is "T1" (T = 1, test views rendered deferred) unless named
METHODS: tuple[tuple[str, ...], ...] = (
    ("nested", "composite", "N2F2 composite"),
    ("nested", "composite", "N2F2 composite, mean of normalised scale features (n2f2's default)", UNIT),
    ("nested", "composite", "N2F2 composite, plain mean of scale features (T = infinity)", tag(math.inf)),
    ("nested", "composite", "N2F2 composite, per-Gaussian render (paper)", PAPER_RENDER),
    ("nested", "soft", "N2F2 soft"),
    ("nested", "explicit", "N2F2 explicit"),
    ("nested", "explicit", "N2F2 explicit, per-Gaussian render (paper)", PAPER_RENDER),
    ("nested", "oracle", "N2F2 oracle"),
    ("flat", "composite", "flat composite"),
    ("levels", "levels", "3-level"),
    ("levels", "oracle", "3-level oracle"),
    ("lift", "levels", "lift (training-free)"),
    ("lift", "oracle", "lift oracle"),
    ("mlp", "composite", "MLP-backbone composite"),
)


def _methods(runs: Mapping[str, dict], variant_runs: Mapping[str, str]) -> list[tuple[str, str, str, Mapping, str]]:
    """(label, variant, run, evaluation, mode) of each of :data:`METHODS` the bench ran."""
    rows = []
    for variant, mode, label, *which in METHODS:
        name = variant_runs.get(variant)
        e = runs[name]["evals"].get(which[0] if which else "T1") if name else None
        if e is not None and mode in e["scores"]:
            rows.append((label, variant, name, e, mode))
    return rows


def _method_rows(runs: Mapping[str, dict], variant_runs: Mapping[str, str]) -> list[tuple[str, Mapping, str]]:
    return [(label, e, m) for label, _, _, e, m in _methods(runs, variant_runs)]


def method_rows(result: Mapping, runs: Mapping[str, dict], variant_runs: Mapping[str, str]) -> list[dict]:
    """The methods side by side (``bench.json``'s ``methods``): per box mIoU, localization and mAP
    in percent, and the seconds it took to build the method's run (``build_time_s`` of
    :func:`n2f2.experiments.bench._run_summary`)."""
    rows = []
    for label, variant, name, e, m in _methods(runs, variant_runs):
        rows.append(
            {
                "method": label,
                "variant": variant,
                "run": name,
                "mode": m,
                "training_free": VARIANTS[variant].training_free,
                "scores": {
                    b: {
                        "miou_pct": 100 * score(e, m, b),
                        "loc_pct": 100 * score(e, m, b, "loc_accuracy"),
                        "map_pct": 100 * float(e["ap"][m][b]["map"]),
                    }
                    for b in BOXES
                },
                "build_time_s": result["runs"][name].get("build_time_s"),
            }
        )
    return rows


def protocol3d_rows(runs: Mapping[str, dict]) -> dict:
    """The 3D protocol's numbers (``bench.json``'s ``protocol3d``): the rules its evaluations
    applied and, per run and 3D mode, mIoU, mAcc@t and localization in percent, the (frame, query)
    pairs scored and the queries that selected no Gaussian (each run's pairs are in its
    ``eval3d/eval.json``)."""
    rules: dict = {}
    acc: list[str] = []
    rows: dict[str, dict] = {}
    for name, entry in runs.items():
        d = entry.get("eval3d")
        if d is None:
            continue
        rules = rules or dict(d["rules"])
        acc = list(dict.fromkeys(acc + [t for s in d["scores"].values() for t in s["acc"]]))
        rows[name] = {}
        for m in d["modes"]:
            s = d["scores"][m]
            rows[name][m] = {
                "miou_pct": 100 * float(s["miou"]),
                **{f"macc_{t}_pct": 100 * float(v) for t, v in s["acc"].items()},
                "loc_pct": 100 * float(s["loc_accuracy"]),
                "pairs": int(s["num_pairs"]),
                "empty_selections": len(s["empty_selections"]),
                "empty_queries": list(s["empty_selections"]),
                "queries": len(s["selections"]),
            }
    return {"rules": rules, "acc_ious": acc, "runs": rows}


def _protocol3d_section(result: Mapping) -> str:
    """The 3D protocol's section of ``bench.md``: one row per (run, mode)."""
    from ..eval.reports import markdown_table

    p3 = result["protocol3d"]
    rules = p3["rules"]
    acc = p3["acc_ious"]
    rows = []
    for name, modes in p3["runs"].items():
        for m, r in modes.items():
            rows.append(
                [name, result["runs"][name]["variant"], m, f"{r['miou_pct']:.1f}"]
                + [f"{r[f'macc_{t}_pct']:.1f}" for t in acc]
                + [f"{r['loc_pct']:.1f}", r["pairs"], f"{r['empty_selections']} of {r['queries']}"]
            )
    return "".join(
        [
            "\n## 3D protocol (select Gaussians, render the selection)\n\n",
            f"Selection rule (one per query, shared by every view): {rules['selection']}.\n\n",
            f"Mask: {rules['mask']}; IoU against the union of the category's label polygons, an empty "
            f"selection scores 0; mAcc@t = fraction of (frame, query) pairs with IoU > t (OpenGaussian); "
            f"loc.: {rules['localization']}. No 2D smoothing, the same labels as the tables above "
            "(`n2f2 eval --protocol 3d`; every pair in `runs/<run>/eval3d/eval.json`); oracle has no 3D query.\n\n",
            markdown_table(
                ["run", "variant", "mode", "mIoU %"]
                + [f"mAcc@{t} %" for t in acc]
                + ["loc. %", "pairs", "empty selections"],
                rows,
                ["l", "l", "l"] + ["r"] * (len(acc) + 4),
            ),
        ]
    )


def _k_rows(
    runs: Mapping[str, dict], variant_runs: Mapping[str, str], result: Mapping
) -> list[tuple[int, str, Mapping]]:
    rows = []
    for k in PAPER_STEPS:
        v = "nested" if k == 1 else f"k{k}"
        name = variant_runs.get(v)
        if name:
            rows.append((k, name, runs[name]["evals"]["T1"]))
    return rows


def markdown_bench(result: Mapping, runs: Mapping[str, dict], variant_runs: Mapping[str, str]) -> str:
    """``bench.md`` from the collected results."""
    any_ev = next(iter(next(iter(runs.values()))["evals"].values()))
    bt = {b: box_title(any_ev, b) for b in BOXES}
    out = _bench_header(result, variant_runs, any_ev, bt)
    out += _claims_section(result)
    if result.get("methods"):
        out.append("\n## Every method, with the time to build it (the training-free lift beside the fields)\n\n")
        out.append(_methods_table(result, bt))
    if (result.get("protocol3d") or {}).get("runs"):
        out.append(_protocol3d_section(result))
    nested = runs[variant_runs["nested"]]["evals"]["T1"] if "nested" in variant_runs else None
    if nested is not None:
        out += _table3_section(nested, variant_runs, bt)
    if "levels" in variant_runs:
        out += _levels_section(runs, variant_runs, nested, bt)
    if "flat" in variant_runs or "nested" in variant_runs:
        out += _nested_flat_section(result, runs, variant_runs, nested, bt)
    ks = _k_rows(runs, variant_runs, result)
    if len(ks) > 1:
        out += _k_sweep_section(result, ks, bt)
    if result["gamma"]:
        out += _temperature_section(result, runs, variant_runs, bt)
    if "mlp" in variant_runs and "nested" in variant_runs:
        out += _backbone_section(result, runs, variant_runs, bt)
    if result["timing"]:
        out += _timing_section(result["timing"])
    out += _runs_section(result)
    return "".join(out)


def _bench_header(
    result: Mapping, variant_runs: Mapping[str, str], any_ev: Mapping, bt: Mapping[str, str]
) -> list[str]:
    """What was run on what: the data, the teacher, the fields, the step sizes, the protocol and
    the machine, and the teacher's notes."""
    cfg = result["config"]
    fields = [r for r in result["runs"].values() if r.get("field_config")]
    first = fields[0] if fields else None
    num_gaussians = next(iter(result["runs"].values()))["num_gaussians"]
    out: list[str] = ["# n2f2 bench: the paper's ablations on the demo scene\n\n"]
    steps = result["steps"]
    k_map = ", ".join(
        f"k={VARIANTS[v].paper_step} -> {steps[n]}"
        for v, n in variant_runs.items()
        if VARIANTS[v].kind.uses_step and VARIANTS[v].backbone == "triplane"
    )
    out.append(
        f"- scene: `{result['data']['scene']}` ({any_ev['scene']}), Gaussians `{result['data']['gaussians']}` "
        f"({num_gaussians} Gaussians), segment bank `{result['data']['bank']}`; "
        f"built now: {', '.join(k for k, v in result['data']['built'].items() if v) or 'nothing (all reused)'}\n"
        f"- teacher / text encoder: {any_ev['encoder']['description']}\n"
        + (
            f"- every field: D = {cfg['dim']}, TriPlane {first['field_config']['plane_resolution']}^2 x "
            f"{first['field_config']['plane_channels']}, MLP hidden {first['field_config']['hidden']}, "
            f"{cfg['iterations']} steps of {cfg['pixels_per_step']} pixels"
            f"{' with every covering segment' if first.get('train_config', {}).get('every_segment') else ''}, "
            f"pixel balance {first.get('train_config', {}).get('pixel_balance', 0.0)} (paper 0: uniform pixels), "
            f"seed {cfg['seed']}, one seed per variant\n"
            if first is not None
            else "- no field trained (the training-free lift only)\n"
        )
        + f"- segment scales: {result['data'].get('scale_measure', 'eigenvalue')} measure, training scale jitter "
        f"{cfg.get('scale_jitter', 0.0)} (paper: eigenvalue, 0)\n"
        f"- step sizes (paper D = 512 -> this D = {cfg['dim']}, keeping floor(512 / k) scales): {k_map or 'n/a'}\n"
        f"- protocol: LangSplat's, always both boxes: **{bt['exact']}** (LangSplat's, sized for ~986 px-wide "
        f"images) and **{bt['scaled']}** (scaled to the image width). On the small demo renders the 30 px box "
        f"erases small parts.\n"
        f"- {any_ev['scores'][any_ev['modes'][0]]['exact']['num_pairs']} (frame, query) pairs on "
        f"{any_ev['scores'][any_ev['modes'][0]]['exact']['num_frames']} labelled frames. Deltas are paired over "
        f'these pairs, shown as mean ± standard error in points; "within noise" = |delta| < 2 SE.\n'
        f"- machine: {result['environment']['cpus']} CPUs, torch {result['environment']['torch']} "
        f"({result['environment']['threads']} threads); load average at start "
        f"{result['load_average']['start'][0]:.1f}, at end {result['load_average']['end'][0]:.1f}; "
        f"bench wall time {result['seconds'] / 60:.1f} min\n"
    )
    for note in any_ev.get("notes", []):
        if "Teacher" in note:
            out.append(f"- note: {note}\n")
    return out


def _claims_section(result: Mapping) -> list[str]:
    """The verdict on each of the paper's claims."""
    rows = [[c["claim"], c["paper"], c["box"], c["metric"], c["here"], c["verdict"]] for c in result["claims"]]
    return [
        "\n## Verdicts: which of the paper's claims hold here\n\n",
        markdown_table(["claim", "paper", "box", "metric", "here", "verdict"], rows, ["l", "l", "l", "l", "r", "l"]),
    ]


def _table3_section(nested: Mapping, variant_runs: Mapping[str, str], bt: Mapping[str, str]) -> list[str]:
    """Composite vs explicit vs oracle on the nested field (paper Table 3), and the scales chosen."""
    out = ["\n## Composite vs explicit vs oracle (paper Table 3)\n\n"]
    out.append(f"N2F2 field ({variant_runs['nested']}), {nested['field']['num_scales']} scales.\n\n")
    table3 = [
        ("composite", nested, "composite"),
        ("explicit", nested, "explicit"),
        ("oracle (upper bound of explicit)", nested, "oracle"),
    ]
    if "soft" in nested["scores"]:
        from ..query.soft import SOFT_TEMPERATURE

        soft = f"soft (the scales weighted by softmax(peak / {SOFT_TEMPERATURE:g}); not in the paper)"
        table3.insert(1, (soft, nested, "soft"))
    out.append(_mode_table(table3, bt))
    out.append(
        "\nScales chosen per (frame, query) pair (prefix length d of the chosen scale, D = "
        f"{nested['field']['dim']}):\n\n"
    )
    out.append(_choice_table(nested, ["explicit", "oracle"]))
    return out


def _levels_section(
    runs: Mapping[str, dict], variant_runs: Mapping[str, str], nested: Optional[Mapping], bt: Mapping[str, str]
) -> list[str]:
    """N2F2 vs the 3-level LangSplat-like field: scores, simple vs compound (paper Table 7) and
    per-query deltas (paper Table 8)."""
    lv = runs[variant_runs["levels"]]["evals"]["T1"]
    out = ["\n## N2F2 vs the 3-level LangSplat-like field (same data)\n\n"]
    out.append(
        "The 3-level field splits theta into 3 blocks, each supervised by one tercile of the "
        "quantized scale, and answers a query with LangSplat's level choice.\n\n"
    )
    rows = [("3-level (levels mode)", lv, "levels"), ("3-level oracle", lv, "oracle")]
    if nested is not None:
        rows = [("N2F2 composite", nested, "composite"), ("N2F2 explicit", nested, "explicit")] + rows
    out.append(_mode_table(rows, bt))
    out.append("\n### Simple vs compound queries (paper Table 7)\n\n")
    out.append(_split_table(rows, bt))
    if nested is not None:
        out.append("\n### Per-query IoU delta, N2F2 composite - 3-level (paper Table 8: top and bottom 3)\n\n")
        out.append(_delta_tables(lv, "levels", nested, "composite", bt))
    return out


def _nested_flat_section(
    result: Mapping,
    runs: Mapping[str, dict],
    variant_runs: Mapping[str, str],
    nested: Optional[Mapping],
    bt: Mapping[str, str],
) -> list[str]:
    """Nested vs non-nested: scores, and the held-out cosine to the teacher per level."""
    out = ["\n## Nested vs non-nested\n\n"]
    rows = []
    if nested is not None:
        rows.append(("nested composite", nested, "composite"))
    if "flat" in variant_runs:
        rows.append(
            (
                "flat composite (= explicit = oracle: 1 scale)",
                runs[variant_runs["flat"]]["evals"]["T1"],
                "composite",
            )
        )
    out.append(_mode_table(rows, bt))
    out.append(
        "\nMean cosine between phi(u, s) and the teacher embedding of the ground-truth segment "
        "covering u, on held-out views (`evaluate_cosine_by_level`; each variant's own mask B(s)):\n\n"
    )
    out.append(_cosine_table(result, variant_runs))
    return out


def _k_sweep_section(result: Mapping, ks: list[tuple[int, str, Mapping]], bt: Mapping[str, str]) -> list[str]:
    """mIoU and localization per step size k (paper Table 6)."""
    steps = result["steps"]
    out = ["\n## Step size k (paper Table 6: 69.2, 68.7, 68.1, 67.2, 66.4 mIoU on teatime)\n\n"]
    rows = []
    for k, name, e in ks:
        rows.append(
            [k, steps.get(name, "-"), e["field"]["num_scales"]]
            + [pct(score(e, m, b)) for m in PAPER_MODES for b in BOXES]
            + [pct(score(e, "composite", b, "loc_accuracy")) for b in BOXES]
        )
    out.append(
        markdown_table(
            ["paper k", "k here", "scales"]
            + [f"{m} mIoU % ({bt[b]})" for m in PAPER_MODES for b in BOXES]
            + [f"composite loc. % ({bt[b]})" for b in BOXES],
            rows,
        )
    )
    return out


def _temperature_section(
    result: Mapping, runs: Mapping[str, dict], variant_runs: Mapping[str, str], bt: Mapping[str, str]
) -> list[str]:
    """The composite weights gamma at each temperature T, and the composite scores there."""
    out = [
        "\n## Composite temperature T: gamma = softmax(score / T) (T = 1 is the paper's Eq. 6 and the "
        "bench's composite rows; uniform = T -> infinity, the plain mean of the scale features)\n\n"
    ]
    out.append(
        "max gamma x scales = 1 means uniform weights; effective scales = exp(entropy of gamma); "
        "mass centre = gamma-weighted prefix length / D; prefix weight r_j = sum_{d >= j} gamma_d "
        "(paper Eq. 7) averaged over the Gaussians.\n\n"
    )
    g0 = result["gamma"][0]
    at = list(g0["prefix_weight_at"])
    rows = []
    main = runs[variant_runs["nested"]]["evals"]
    for g in result["gamma"]:
        e = main.get(tag(g["temperature"]))  # "T1": the main evaluation (the paper's T)
        rows.append(
            [
                temperature_label(g["temperature"]),
                g["scales"],
                f"{g['max_gamma_mean']:.4g}",
                f"{g['max_gamma_x_scales_mean']:.2f}",
                f"{g['max_gamma_p95'] * g['scales']:.2f}",
                f"{g['effective_scales_mean']:.1f}",
                f"{g['mass_centre_mean']:.2f}",
            ]
            + [f"{g['prefix_weight_at'][j]:.2f}" for j in at]
            + (
                [pct(score(e, "composite", b)) for b in BOXES]
                + [pct(score(e, "composite", b, "loc_accuracy")) for b in BOXES]
                + [pct(e["split"]["composite"]["scaled"][k]["miou"]) for k in ("simple", "compound")]
                if e
                else ["-"] * 6
            )
        )
    out.append(
        markdown_table(
            [
                "T",
                "scales",
                "mean max gamma",
                "mean max gamma x scales",
                "p95 max gamma x scales",
                "effective scales",
                "mass centre",
            ]
            + [f"r_{j}" for j in at]
            + [f"mIoU % ({bt[b]})" for b in BOXES]
            + [f"loc. % ({bt[b]})" for b in BOXES]
            + ["simple mIoU % (scaled)", "compound mIoU % (scaled)"],
            rows,
        )
    )
    return out


def _backbone_section(
    result: Mapping, runs: Mapping[str, dict], variant_runs: Mapping[str, str], bt: Mapping[str, str]
) -> list[str]:
    """TriPlane+MLP vs MLP backbone: memory, speed, convergence and scores."""
    out = [
        "\n## TriPlane+MLP vs MLP backbone (appendix: similar accuracy, TriPlane 20x faster "
        "convergence, MLP 2.3x less memory)\n\n"
    ]
    names = {"TriPlane+MLP": variant_runs["nested"], "PE+MLP": variant_runs["mlp"]}
    conv = convergence({n: result["runs"][r]["curve"] for n, r in names.items()})
    rows = []
    for label, name in names.items():
        r = result["runs"][name]
        mem = r.get("memory") or {}
        e = runs[name]["evals"]["T1"]
        rows.append(
            [
                label,
                mem.get("parameters", "-"),
                _mb(mem.get("parameter_adam_grad_mb")),
                _mb(mem.get("activation_peak_mb")),
                mem.get("rasterized_channels", "-"),
                _millions((result.get("paper_size_parameters") or {}).get(r["backbone"])),
                _ms(r.get("time_per_iteration_s")),
                _ms(r.get("cpu_time_per_iteration_s")),
                f"{r['final_loss']:.5f}",
                conv.get(label, "-") if conv.get(label) is not None else "not reached",
                pct(score(e, "composite", "exact")),
                pct(score(e, "composite", "scaled")),
            ]
            + _cos_cells(r.get("cosine"))
        )
    cos_names = _cos_names(result)
    out.append(
        markdown_table(
            [
                "backbone",
                "parameters",
                "params+grad+Adam MB",
                "activations / step MB",
                "rasterized channels",
                "parameters at paper size",
                "ms / step (wall)",
                "ms / step (CPU)",
                "final loss",
                f"steps to loss {conv.get('target_loss', math.nan):.5f}",
                f"composite mIoU % ({bt['exact']})",
                f"composite mIoU % ({bt['scaled']})",
            ]
            + [f"cos {n}" for n in cos_names],
            rows,
        )
    )
    out.append(
        "\nActivations: bytes autograd saved for backward in one training step (peak over steps; "
        "parameters excluded). The paper's memory numbers are GPU totals at paper size (TriPlane "
        "512^2 x 64); the parameter column at paper size shows where that ratio comes from. The "
        "process RSS on CPU is dominated by torch, the scene and the bank and is not compared.\n"
    )
    return out


def _timing_section(tm: Mapping) -> list[str]:
    """The query time breakdown (paper Table 4)."""
    n = tm["rows"][0]["num_queries"]
    out = [
        f"\n## Query time breakdown (paper Table 4; one {tm['size'][0]}x{tm['size'][1]} view, "
        f"D = {tm['dim']}, {tm['threads']} torch thread(s), medians of {tm['repeats']})\n\n"
    ]
    rows = [
        [
            r["method"],
            r["scales"],
            _ms(r["render_s"]),
            _ms(r["cache_s"]),
            _ms(r["query_1_s"]),
            _ms(r["per_query_s"]),
            _ms(r[f"queries_{n}_s"]),
            _ms(r["total_1_s"]),
            _ms(r[f"total_{n}_s"]),
        ]
        for r in tm["rows"]
    ]
    out.append(
        markdown_table(
            [
                "method",
                "maps per query",
                "render ms",
                "cache ms",
                "1 query ms",
                f"per query ms (at {n})",
                f"{n} queries ms",
                "total 1 query ms",
                f"total {n} queries ms",
            ],
            rows,
        )
    )
    out.append(
        f"\nOnce per field: Theta~ = revcumsum(gamma^3D) * Theta for {tm['once']['gaussians']} "
        f"Gaussians in {_ms(tm['once']['theta_tilde_s'])} ms. Explicit / levels pick a scale per "
        "query with LangSplat's smoothed maximum (the protocol's rule). Unlike LangSplat, the "
        "3-level field renders D channels (no 3-d latent + decoder).\n"
    )
    return out


def _runs_section(result: Mapping) -> list[str]:
    """Every run with its training and build times, the stage wall times and the plots."""
    rows = [
        [
            name,
            r["variant"],
            r["backbone"] or "-",
            r["field_config"]["step_size"] if r.get("field_config") else "-",
            r["steps"] if r.get("steps") is not None else "-",
            f"{r['final_loss']:.5f}" if r.get("final_loss") is not None else "-",
            f"{r['train_time_s']:.0f}" if r.get("train_time_s") is not None else "-",
            _seconds(r.get("build_time_s")),
            "yes" if r["reused"] else "no",
            ", ".join(r["evals"]),
        ]
        for name, r in result["runs"].items()
    ]
    return [
        "\n## Runs\n\n",
        markdown_table(
            [
                "run",
                "variant",
                "backbone",
                "k",
                "steps",
                "final loss",
                "train s (this session)",
                "build s",
                "reused",
                "evaluations",
            ],
            rows,
            ["l", "l", "l", "r", "r", "r", "r", "r", "l", "l"],
        ),
        "\nStage wall times: "
        + ", ".join(f"{k} {v:.0f} s" for k, v in result["stage_seconds"].items())
        + ".\n\nPlots: "
        + ", ".join(f"`{Path(p).name}`" for p in result.get("plots", {}).values())
        + ".\n",
    ]


def _seconds(v: Any) -> str:
    """Build seconds: 3 significant digits (a lift takes well under a second on the quick scene)."""
    return "-" if v is None else f"{float(v):.3g}"


def _methods_table(result: Mapping, bt: Mapping[str, str]) -> str:
    """``result["methods"]`` as a table, with what "build s" means and where the lift came from."""
    from ..eval.reports import markdown_table

    rows = []
    for r in result["methods"]:
        sc = r["scores"]
        rows.append(
            [r["method"], r["run"]]
            + [f"{sc[b]['loc_pct']:.1f}" for b in BOXES]
            + [f"{sc[b]['miou_pct']:.1f}" for b in BOXES]
            + [f"{sc[b]['map_pct']:.1f}" for b in BOXES]
            + [_seconds(r["build_time_s"])]
        )
    out = [
        markdown_table(
            ["method", "run"]
            + [f"loc. % ({bt[b]})" for b in BOXES]
            + [f"mIoU % ({bt[b]})" for b in BOXES]
            + [f"mAP % ({bt[b]})" for b in BOXES]
            + ["build s"],
            rows,
            ["l", "l"] + ["r"] * (3 * len(BOXES) + 1),
        ),
        "\nbuild s: "
        + (
            "a field's training steps (`train_time_s` of its `train_report.json`); "
            if any(not r["training_free"] for r in result["methods"])
            else ""
        ),
    ]
    lifts = [r for r in result["runs"].values() if r.get("training_free")]
    for r in lifts:
        info = r["lift"]
        out.append(
            f"the lift's blending weights ({_seconds(info['blend_weights_s'])} s) plus averaging the bank's "
            f"features onto the Gaussians ({_seconds(info['lift_s'])} s) over {len(info['views'])} training "
            f"views: {info['about']}. "
        )
    blend = [(name, r["blend_cache_s"]) for name, r in result["runs"].items() if r.get("blend_cache_s") is not None]
    if blend:
        out.append(
            "A field's training precomputes the same blending weights before its first step (not in its "
            "build time): " + ", ".join(f"{n} {_seconds(v)} s" for n, v in blend) + ". "
        )
    out.append(
        "Wall times of this session's machine (load average in the header); a reused run keeps the times "
        "it was built in. The lift is answered as the 3-level field: LangSplat's level choice, or the "
        "oracle level.\n"
    )
    return "".join(out)


def _millions(v: Any) -> str:
    return "-" if v is None else f"{v / 1e6:.2f} M"


def _ms(v: Any) -> str:
    if v is None:
        return "-"
    ms = 1000 * float(v)
    return f"{ms:.1f}" if ms >= 10 else f"{ms:.3f}"


def _mb(v: Any) -> str:
    return "-" if v is None else f"{float(v):.1f}"


def _mode_table(rows: Sequence[tuple[str, Mapping, str]], bt: Mapping[str, str]) -> str:
    from ..eval.reports import markdown_table

    body = [
        [label] + [pct(score(e, m, b, "loc_accuracy")) for b in BOXES] + [pct(score(e, m, b)) for b in BOXES]
        for label, e, m in rows
    ]
    return markdown_table(
        ["method"] + [f"loc. % ({bt[b]})" for b in BOXES] + [f"mIoU % ({bt[b]})" for b in BOXES], body
    )


def _split_table(rows: Sequence[tuple[str, Mapping, str]], bt: Mapping[str, str]) -> str:
    from ..eval.reports import markdown_table

    body = []
    for label, e, m in rows:
        for b in BOXES:
            sp = e["split"][m][b]
            body.append(
                [
                    label,
                    bt[b],
                    pct(sp["simple"]["miou"]),
                    pct(sp["compound"]["miou"]),
                    pct(sp["simple"]["loc_accuracy"]),
                    pct(sp["compound"]["loc_accuracy"]),
                    sp["simple"]["pairs"],
                    sp["compound"]["pairs"],
                ]
            )
    return markdown_table(
        [
            "method",
            "box",
            "simple mIoU %",
            "compound mIoU %",
            "simple loc. %",
            "compound loc. %",
            "simple pairs",
            "compound pairs",
        ],
        body,
        ["l", "l"] + ["r"] * 6,
    )


def _delta_tables(ref: Mapping, ref_mode: str, cur: Mapping, cur_mode: str, bt: Mapping[str, str]) -> str:
    from ..eval.metrics import query_deltas
    from ..eval.reports import markdown_table

    out = []
    for b in BOXES:
        a = {q: v["iou"] for q, v in ref["per_query"][ref_mode][b].items()}
        c = {q: v["iou"] for q, v in cur["per_query"][cur_mode][b].items()}
        d = query_deltas(a, c, n=3)
        types = cur.get("query_types", {})
        rows = [
            [tag, x.query, types.get(x.query, "unknown"), pct(x.a), pct(x.b), signed_pts(x.delta)]
            for tag, items in (("top", d.top), ("bottom", d.bottom))
            for x in items
        ]
        out.append(f"{bt[b]}: mean delta {signed_pts(d.mean_delta)} points over {len(d.deltas)} queries\n\n")
        out.append(
            markdown_table(
                ["", "query", "type", "3-level IoU %", "N2F2 IoU %", "delta"], rows, ["l", "l", "l", "r", "r", "r"]
            )
        )
        out.append("\n")
    return "".join(out)


def _choice_table(ev: Mapping, modes: Sequence[str]) -> str:
    from ..eval.reports import markdown_table

    dims = [int(s.split("=")[1]) for s in ev["field"]["scale_labels"]]
    rows = []
    for m in modes:
        for b in BOXES:
            pairs = ev["scores"][m][b]["pairs"]
            seg = np.array([dims[p["seg_level"]] for p in pairs])
            rows.append(
                [
                    m,
                    b,
                    f"{np.median(seg):.0f}",
                    f"{np.mean(seg == dims[-1]) * 100:.0f}",
                    f"{np.mean(seg == dims[0]) * 100:.0f}",
                    f"{np.percentile(seg, 25):.0f}-{np.percentile(seg, 75):.0f}",
                ]
            )
    return markdown_table(
        ["mode", "box", "median d (segmentation)", "% pairs at d = D", "% pairs at the first scale", "interquartile d"],
        rows,
        ["l", "l", "r", "r", "r", "r"],
    )


def _cos_names(result: Mapping) -> list[str]:
    for r in result["runs"].values():
        if r.get("cosine"):
            return list(r["cosine"]["levels"])
    return []


def _cos_cells(cos: Optional[Mapping], key: str = "cosine") -> list[str]:
    """``key`` = "cosine" (mean over pixels) or "region_cosine" (mean over (view, region))."""
    if not cos:
        return []
    return [("-" if v.get(key) is None else f"{v[key]:.3f}") for v in cos["levels"].values()]


def _cosine_table(result: Mapping, variant_runs: Mapping[str, str]) -> str:
    from ..eval.reports import markdown_table

    names = _cos_names(result)
    rows = []
    for v, name in variant_runs.items():
        r = result["runs"][name]
        if r.get("cosine") and v in VARIANTS and VARIANTS[v].cosine:
            rows.append(
                [VARIANTS[v].title]
                + _cos_cells(r["cosine"])
                + _cos_cells(r["cosine"], "region_cosine")
                + [f"{r['final_loss']:.5f}"]
            )
    if not rows:
        return "Not computed.\n"
    # Pixel means weigh a level's regions by their area (at the group level the room, floor and
    # wall, is most of the image); region means weigh every (view, region) alike. Both are shown.
    return markdown_table(
        ["variant"]
        + [f"cos {n} (pixels)" for n in names]
        + [f"cos {n} (regions)" for n in names]
        + ["final train loss"],
        rows,
    )
