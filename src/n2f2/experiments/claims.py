"""The paper's claims the bench can test, with verdicts: paired differences over (frame, query)
pairs with their standard error, so that a difference within noise is called so; and ratios
for convergence, memory and query speed."""

from __future__ import annotations

import math
from typing import Any, Callable, Mapping, Optional, Union

import numpy as np

from ..eval.runner import BOXES
from .variants import PAPER_STEPS


def tag(T: Union[float, str]) -> str:
    """The evaluation name of composite temperature ``T`` (``T1`` = the paper's, ``Tuniform`` =
    infinity, n2f2's default)."""
    return f"T{temperature_label(T)}"


def temperature_label(T: Union[float, str]) -> str:
    """``T`` as the bench prints it: a number, or "uniform" for infinity (JSON has no infinity,
    so a bench result records it as "uniform")."""
    return "uniform" if T == "uniform" or math.isinf(float(T)) else f"{float(T):g}"


# The evaluation name of the nested run's composite with n2f2's default weights (the mean of the
# normalised scale features, query/composite.py); the bench's other rows use the paper's Eq. 6.
UNIT = "unit"

# The evaluation name of the nested run scored with the paper's per-Gaussian rendering of test
# views (QueryConfig.render = "gaussians"; the others are rendered deferred).
PAPER_RENDER = "gaussians"


def signed_pts(d: float, se: float = math.nan) -> str:
    """A difference of scores in points (x100, signed), with its standard error when known."""
    if d is None or not np.isfinite(d):
        return "n/a"
    s = f"{100 * d:+.1f}"
    return s + (f" ± {100 * se:.1f}" if np.isfinite(se) else "")


def score(ev: Mapping, mode: str, box: str, key: str = "miou") -> float:
    """One score (``key``: miou, loc_accuracy) of an evaluation for ``mode`` under ``box``."""
    return float(ev["scores"][mode][box][key])


def paired_difference(ev_a: Mapping, mode_a: str, ev_b: Mapping, mode_b: str, box: str, key: str = "iou") -> dict:
    """Mean of ``a - b`` over the (frame, query) pairs both scored, and its standard error
    (``key`` = "iou" for segmentation, "hit" for localization)."""
    pa = {(p["frame"], p["category"]): float(p[key]) for p in ev_a["scores"][mode_a][box]["pairs"]}
    pb = {(p["frame"], p["category"]): float(p[key]) for p in ev_b["scores"][mode_b][box]["pairs"]}
    shared = sorted(set(pa) & set(pb))
    d = np.array([pa[k] - pb[k] for k in shared], dtype=np.float64)
    if d.size == 0:
        return {"delta": math.nan, "se": math.nan, "pairs": 0}
    se = float(d.std(ddof=1) / math.sqrt(d.size)) if d.size > 1 else math.nan
    return {"delta": float(d.mean()), "se": se, "pairs": int(d.size)}


def _verdict(delta: float, se: float, expect_positive: bool = True) -> str:
    """ "holds" / "does not hold", with "(within noise)" when |delta| < 2 standard errors."""
    if not np.isfinite(delta):
        return "n/a"
    ok = delta >= 0 if expect_positive else delta <= 0
    noise = np.isfinite(se) and abs(delta) < 2 * se
    return ("holds" if ok else "does not hold") + (" (within noise)" if noise and delta != 0 else "")


def evaluate_claims(result: Mapping, runs: Mapping[str, dict], variant_runs: Mapping[str, str]) -> list[dict]:
    """Each claim of the paper the bench can test (per box and metric where it is a score), with
    the number measured here (``here``, in points for scores) and a verdict."""
    claims: list[dict] = []

    def ev(variant: str, tag: str = "T1") -> Optional[Mapping]:
        name = variant_runs.get(variant)
        return runs[name]["evals"].get(tag) if name else None

    def add(
        claim: str,
        paper: str,
        box: str,
        metric: str,
        delta: float,
        se: float,
        pairs: Optional[int],
        verdict: str,
        here: Optional[str] = None,
        **extra: Any,
    ) -> None:
        claims.append(
            {
                "claim": claim,
                "paper": paper,
                "box": box,
                "metric": metric,
                "delta": delta,
                "se": se,
                "pairs": pairs,
                "here": here if here is not None else signed_pts(delta, se) + " pts",
                "verdict": verdict,
                **extra,
            }
        )

    def compare(
        claim: str,
        paper: str,
        a: Optional[Mapping],
        ma: str,
        b: Optional[Mapping],
        mb: str,
        similar: Optional[tuple[str, str]] = None,
    ) -> None:
        if a is None or b is None or ma not in a["scores"] or mb not in b["scores"] or (a is b and ma == mb):
            return  # not run, or the same run (two paper settings that map to one k at this D)
        for box in BOXES:
            for metric, key in (("mIoU", "iou"), ("loc.", "hit")):
                d = paired_difference(a, ma, b, mb, box, key)
                verdict = _similar(d["delta"], d["se"], similar) if similar else _verdict(d["delta"], d["se"])
                add(claim, paper, box, metric, d["delta"], d["se"], d["pairs"], verdict)

    nested = ev("nested")
    compare("composite >= explicit (Table 3)", "+0.7 mIoU, +0.9 loc.", nested, "composite", nested, "explicit")
    compare(
        "oracle >= composite (oracle = upper bound, Table 3)",
        "+2.9 mIoU, +2.7 loc.",
        nested,
        "oracle",
        nested,
        "composite",
    )
    compare("oracle >= explicit (by construction)", "+3.6 mIoU, +3.6 loc.", nested, "oracle", nested, "explicit")
    compare(
        "N2F2 explicit (D scales) >= 3-level LangSplat-like (Sec. 4.3)",
        "explicit beats LangSplat",
        nested,
        "explicit",
        ev("levels"),
        "levels",
    )
    compare("N2F2 composite >= 3-level LangSplat-like", "+ (Tables 1, 2)", nested, "composite", ev("levels"), "levels")
    compare("nested >= non-nested (appendix)", "+2.0 mIoU, +2.5 loc.", nested, "composite", ev("flat"), "composite")
    for k in PAPER_STEPS[1:]:
        compare(f"k=1 >= k={k} (Table 6)", "k=1 best, monotone", nested, "composite", ev(f"k{k}"), "composite")
    compare(
        "TriPlane+MLP ~ PE+MLP accuracy (appendix)",
        "similar final performance",
        nested,
        "composite",
        ev("mlp"),
        "composite",
        similar=("TriPlane+MLP", "PE+MLP"),
    )
    for T in result["config"]["temperatures"]:
        if T != 1.0:
            compare(
                f"composite T=1 (paper) >= T={temperature_label(T)}",
                "T=1 is the paper's",
                nested,
                "composite",
                ev("nested", tag(T)),
                "composite",
            )
    lv = ev("levels")
    if nested is not None and lv is not None:
        for box in BOXES:
            g = compound_gain(nested, "composite", lv, "levels", box)
            add(
                "compound queries gain most over the 3-level field (Table 7)",
                "gain on compound > on simple",
                box,
                "mIoU",
                g["delta"],
                g["se"],
                g["pairs"],
                _verdict(g["delta"], g["se"]),
                here=f"{signed_pts(g['delta'], g['se'])} pts (compound {signed_pts(g['compound'])}, "
                f"simple {signed_pts(g['simple'])})",
            )
    _efficiency_claims(result, variant_runs, add)
    return claims


def compound_gain(ev_a: Mapping, mode_a: str, ev_b: Mapping, mode_b: str, box: str) -> dict:
    """(a - b) on compound queries minus (a - b) on simple queries, over the pairs both scored, with
    the standard error of that difference of two independent means."""
    types = ev_a.get("query_types", {})
    pa = {(p["frame"], p["category"]): p["iou"] for p in ev_a["scores"][mode_a][box]["pairs"]}
    pb = {(p["frame"], p["category"]): p["iou"] for p in ev_b["scores"][mode_b][box]["pairs"]}
    diffs = {
        k: np.array([pa[q] - pb[q] for q in sorted(set(pa) & set(pb)) if types.get(q[1]) == k], np.float64)
        for k in ("simple", "compound")
    }
    if any(d.size < 2 for d in diffs.values()):
        return {
            "delta": math.nan,
            "se": math.nan,
            "pairs": int(sum(d.size for d in diffs.values())),
            "simple": math.nan,
            "compound": math.nan,
        }
    se = math.sqrt(sum(d.var(ddof=1) / d.size for d in diffs.values()))
    return {
        "delta": float(diffs["compound"].mean() - diffs["simple"].mean()),
        "se": se,
        "pairs": int(sum(d.size for d in diffs.values())),
        "simple": float(diffs["simple"].mean()),
        "compound": float(diffs["compound"].mean()),
    }


def _similar(delta: float, se: float, names: tuple[str, str], tolerance: float = 0.02) -> str:
    """Verdict of a "similar" claim (``delta`` = first - second): within noise (2 SE) or within
    ``tolerance`` (2 points)."""
    if not np.isfinite(delta):
        return "n/a"
    if abs(delta) <= tolerance or (np.isfinite(se) and abs(delta) < 2 * se):
        return "holds (similar)"
    return f"does not hold ({names[0] if delta > 0 else names[1]} better)"


def _efficiency_claims(result: Mapping, variant_runs: Mapping[str, str], add: Callable[..., None]) -> None:
    """Convergence and memory of the two backbones, and query speed (ratios, not paired scores)."""
    runs = result["runs"]
    if "nested" in variant_runs and "mlp" in variant_runs:
        tri, mlp = runs[variant_runs["nested"]], runs[variant_runs["mlp"]]
        conv = convergence({"tri": tri["curve"], "mlp": mlp["curve"]})
        if conv.get("tri") and conv.get("mlp"):
            ratio = conv["mlp"] / conv["tri"]
            add(
                "TriPlane+MLP converges faster than PE+MLP (appendix)",
                "20x fewer steps",
                "-",
                "steps",
                ratio,
                math.nan,
                None,
                "holds" if ratio > 1 else "does not hold",
                here=f"{ratio:.1f}x (steps to loss {conv['target_loss']:.5f}: {conv['tri']} vs {conv['mlp']})",
            )
        mt, mm = tri.get("memory") or {}, mlp.get("memory") or {}
        if mt.get("activation_peak_mb") and mm.get("activation_peak_mb"):
            total_t = mt["parameter_adam_grad_mb"] + mt["activation_peak_mb"]
            total_m = mm["parameter_adam_grad_mb"] + mm["activation_peak_mb"]
            paper = result.get("paper_size_parameters") or {}
            at_paper = (
                f"; parameters at paper size {paper['triplane'] / max(paper['mlp'], 1):.0f}x"
                if paper.get("triplane") and paper.get("mlp")
                else ""
            )
            add(
                "PE+MLP needs less training memory than TriPlane+MLP (appendix)",
                "2.3x less",
                "-",
                "MB",
                total_t / total_m,
                math.nan,
                None,
                "holds" if total_m < total_t else "does not hold",
                here=f"{total_t / total_m:.1f}x (params+grad+Adam+activations {total_t:.0f} vs {total_m:.0f} MB"
                f"{at_paper})",
            )
    tm = result.get("timing")
    if tm:
        rows = {r["mode"]: r for r in tm["rows"]}
        n = tm["rows"][0]["num_queries"]
        comp = rows.get("composite")
        if comp and "explicit" in rows:
            ratio = rows["explicit"]["per_query_s"] / comp["per_query_s"]
            add(
                "composite queries faster than explicit scale selection (Sec. 4.3)",
                "~5x",
                "-",
                "time",
                ratio,
                math.nan,
                None,
                "holds" if ratio > 1 else "does not hold",
                here=f"{ratio:.0f}x per query (at {n} queries)",
            )
        if comp and "levels" in rows:
            ratio = rows["levels"][f"total_{n}_s"] / comp[f"total_{n}_s"]
            add(
                f"N2F2 total time for {n} queries < 3-level field's (Table 4)",
                "1.7x faster",
                "-",
                "time",
                ratio,
                math.nan,
                None,
                "holds" if ratio > 1 else "does not hold",
                here=f"{ratio:.1f}x (render + {n} queries)",
            )


# ------------------------------------------------------------------------------ backbone
def convergence(curves: Mapping[str, Mapping]) -> dict:
    """Steps to reach the higher of the runs' final losses (a level every run reaches), per run,
    on the trainer's logged loss curve (means over ``log_every`` steps)."""
    finals = {n: c["loss"][-1] for n, c in curves.items() if c and c.get("loss")}
    if not finals:
        return {}
    target = max(finals.values())
    out = {"target_loss": target}
    for n, c in curves.items():
        steps = [s for s, l in zip(c["step"], c["loss"]) if l <= target]
        out[n] = steps[0] if steps else None
    return out
