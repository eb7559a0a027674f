"""Which ground-truth regions of a generated scene the trained field keeps apart, at which of its
scales, and how well each level of a decomposition holds them: a check of whether a region the
hierarchy misses is in the field at all.

    python benchmarks/field_regions.py RUN SCENE --pairs "sofa back/sofa seat" ... \
        [--decomposition DIR] [--regions NAME ...] [--out FILE.json]

SCENE is the generated scene RUN was trained on (``n2f2 demo`` writes ``regions/``, ``depth/``
and ``regions.json`` in it). Every Gaussian gets the ground-truth region of each kind (part,
object, group) that most of its sightings name: a sighting is a labelled view in which its centre
projects onto a pixel whose ground-truth depth is within 2 cm + 2 % of the centre's depth
(centres off every surface stay unlabelled, -1).

For each pair ``A/B`` of region names and every scale of the field, the field is read at the
labelled Gaussians (the unit features of :mod:`n2f2.hierarchy.build`): A and B count as apart at
a scale when the cosine distance between their mean features exceeds the sum of their members'
90th-percentile distances to their own mean. The report lists those scales and the largest
ratio of the two.

With ``--decomposition``, per level the best 3D IoU of each named region (``--regions``, default
the pairs' regions) against any node of the level, over the labelled Gaussians.

Prints Markdown; ``--out`` also writes the numbers as JSON."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

SPREAD_QUANTILE = 0.9
DEPTH_ABS, DEPTH_REL = 0.02, 0.02  # a sighting: |depth - z| < 2 cm + 2 % of the depth


def gaussian_regions(
    means: np.ndarray,  # [N, 3] Gaussian centres
    scene: Path,
) -> np.ndarray:  # -> [N, K] int64 region id per kind (regions.json's levels), -1 unlabelled
    """Majority ground-truth region of every Gaussian over its sightings (module docstring)."""
    from n2f2.data import load_scene
    from n2f2.eval.hierarchy import read_ground_truth

    gt = read_ground_truth(scene)
    views = load_scene(scene)
    stems = {Path(p).stem: cam for cam, p in zip(views.cameras, views.image_paths)}
    n, kinds = means.shape[0], len(gt.kinds)
    seen: list[list[np.ndarray]] = [[] for _ in range(kinds)]  # [M, 2] (Gaussian, region) sightings
    for stem in gt.stems:
        if stem not in stems or not (scene / "depth" / f"{stem}.npy").is_file():
            continue
        cam = stems[stem]
        ids = gt.region_map(stem)  # [K, H, W]
        depth = np.load(scene / "depth" / f"{stem}.npy")  # [H, W] z-depth
        h, w = ids.shape[1:]
        uv, z = cam.project(means)
        u = np.floor(uv[:, 0] * w / cam.width).astype(np.int64)
        v = np.floor(uv[:, 1] * h / cam.height).astype(np.int64)
        idx = np.flatnonzero((z > 0) & (u >= 0) & (u < w) & (v >= 0) & (v < h))
        d = depth[v[idx], u[idx]]
        idx = idx[np.abs(d - z[idx]) < DEPTH_ABS + DEPTH_REL * d]
        for k in range(kinds):
            r = ids[k, v[idx], u[idx]]
            seen[k].append(np.stack([idx[r >= 0], r[r >= 0]], 1))
    out = np.full((n, kinds), -1, dtype=np.int64)
    for k in range(kinds):
        if not seen[k]:
            continue
        pairs, counts = np.unique(np.concatenate(seen[k]), axis=0, return_counts=True)
        order = np.lexsort((-counts, pairs[:, 0]))  # per Gaussian, its most frequent region first
        pairs = pairs[order]
        first = np.r_[True, pairs[1:, 0] != pairs[:-1, 0]]
        out[pairs[first, 0], k] = pairs[first, 1]
    return out


def region_index(scene: Path, names: list[str]) -> dict[str, tuple[int, int]]:  # name -> (kind, id)
    """Each named region's kind (column of :func:`gaussian_regions`) and id; ValueError naming the
    file for a name the scene does not have."""
    from n2f2.eval.hierarchy import read_ground_truth

    by_name = {str(r["name"]): r for r in read_ground_truth(scene).regions.values()}
    missing = [n for n in names if n not in by_name]
    if missing:
        raise ValueError(f"{scene / 'regions.json'}: no region named {', '.join(map(repr, missing))}")
    return {n: (int(by_name[n]["level"]), int(by_name[n]["id"])) for n in names}


def scan_pairs(
    theta: torch.Tensor,  # [N, D] the field's features at the centres
    W: torch.Tensor,  # [E, D]
    scales: list[tuple[int, int]],  # the field's scales, coarse to fine
    labels: list[str],  # their names
    masks: dict[str, np.ndarray],  # region name -> [N] bool
    pairs: list[tuple[str, str]],
) -> list[dict]:
    from n2f2.hierarchy.build import scale_bases, unit_features

    rows: dict[tuple[str, str], list[tuple[str, float, float]]] = {p: [] for p in pairs}
    sel = {n: torch.from_numpy(m) for n, m in masks.items()}
    for scale, label in zip(scales, labels):
        z = unit_features(theta, scale, scale_bases(W, [scale])[0])
        mean = {n: torch.nn.functional.normalize(z[s].mean(0), dim=0) for n, s in sel.items()}
        spread = {n: float((1 - z[s] @ mean[n]).quantile(SPREAD_QUANTILE)) for n, s in sel.items()}
        for a, b in pairs:
            rows[(a, b)].append((label, float(1 - mean[a] @ mean[b]), spread[a] + spread[b]))
    out = []
    for (a, b), r in rows.items():
        ratios = [(label, dist / max(s, 1e-9)) for label, dist, s in r]
        best = max(ratios, key=lambda x: x[1])
        out.append(
            {
                "a": a,
                "b": b,
                "apart_at": [label for label, q in ratios if q > 1],
                "scales": len(r),
                "best_scale": best[0],
                "best_ratio": best[1],
            }
        )
    return out


def level_ious(
    gaussian_nodes: np.ndarray,  # [N, L]
    masks: dict[str, np.ndarray],  # region name -> [N] bool
    labelled: np.ndarray,  # [N] bool, the Gaussians any region kind labels
) -> dict[str, list[float]]:  # name -> [L] best IoU against any node of each level
    out = {}
    for name, m in masks.items():
        a = m[labelled]
        row = []
        for level in range(gaussian_nodes.shape[1]):
            col = gaussian_nodes[labelled, level]
            best = 0.0
            for k in np.unique(col[a]):
                b = col == k
                best = max(best, float((a & b).sum() / (a | b).sum()))
            row.append(best)
        out[name] = row
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=(__doc__ or "").split("\n\n")[0])
    p.add_argument("run", type=Path)
    p.add_argument("scene", type=Path)
    p.add_argument("--pairs", nargs="+", default=[], metavar="A/B")
    p.add_argument("--regions", nargs="+", default=None, metavar="NAME")
    p.add_argument("--decomposition", type=Path, default=None)
    p.add_argument("--out", type=Path, default=None)
    args = p.parse_args()

    from n2f2.field import gaussian_features, load_field
    from n2f2.field.variants import get_variant
    from n2f2.gaussians import read_ply

    pairs = []
    for s in args.pairs:
        if s.count("/") != 1:
            p.error(f"--pairs {s!r}: expected two region names joined by '/'")
        a, b = s.split("/")
        pairs.append((a.strip(), b.strip()))
    names = list(dict.fromkeys(args.regions or [n for pr in pairs for n in pr]))
    try:
        index = region_index(args.scene, list(dict.fromkeys(names + [n for pr in pairs for n in pr])))
    except ValueError as e:
        p.exit(2, f"{e}\n")
    g = read_ply(args.run / "gaussians.ply")
    means = g.means.detach().double().numpy()
    labels = gaussian_regions(means, args.scene)
    masks = {n: labels[:, kind] == rid for n, (kind, rid) in index.items()}
    report: dict = {
        "run": str(args.run),
        "scene": str(args.scene),
        "gaussians": int(means.shape[0]),
        "labelled": [int((labels[:, k] >= 0).sum()) for k in range(labels.shape[1])],
        "region_gaussians": {n: int(m.sum()) for n, m in masks.items()},
    }
    print(f"{args.run}: {means.shape[0]} Gaussians, labelled per kind {report['labelled']}")
    if pairs:
        fld, meta = load_field(args.run / "field.pt", "cpu")
        with torch.no_grad():
            theta = gaussian_features(fld, g.means).float()
        cfg = meta.get("config", {})
        variant = get_variant(str(cfg.get("variant", "nested")))
        step = int(cfg.get("step_size", 1))
        scales = variant.coarse_to_fine(theta.shape[1], step)
        scale_labels = variant.coarse_to_fine_labels(theta.shape[1], step)
        report["pairs"] = scan_pairs(theta, fld.W.detach().float(), scales, scale_labels, masks, pairs)
        print("\n| A / B | apart at (of all scales) | best scale | best ratio |\n|---|---|---|---:|")
        for r in report["pairs"]:
            at = ", ".join(s.removeprefix("d=") for s in r["apart_at"]) or "none"
            apart = f"{len(r['apart_at'])} of {r['scales']}: {at}"
            print(f"| {r['a']} / {r['b']} | {apart} | {r['best_scale']} | {r['best_ratio']:.2f} |")
    if args.decomposition is not None:
        tree = json.loads((args.decomposition / "tree.json").read_text())
        nodes = np.load(args.decomposition / "gaussian_nodes.npy")
        labelled = np.asarray((labels >= 0).any(axis=1))
        ious = level_ious(nodes, {n: masks[n] for n in names}, labelled)
        level_names = [str(lv.get("scale_label", i)) for i, lv in enumerate(tree.get("levels", []))]
        report["levels"] = level_names
        report["level_ious"] = ious
        print("\n| region | " + " | ".join(level_names) + " |\n|---|" + "---:|" * len(level_names))
        for n, row in ious.items():
            print(f"| {n} | " + " | ".join(f"{100 * x:.0f}" for x in row) + " |")
    if args.out is not None:
        args.out.write_text(json.dumps(report, indent=1) + "\n")


if __name__ == "__main__":
    main()
