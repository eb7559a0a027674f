"""A PNG overview of a demo scene: RGB and the part / object / group ids of a few views, with a
legend of the regions' captions."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ...io import atomic_path


def id_colors(ids: np.ndarray) -> np.ndarray:
    """Distinct colours [..., 3] float in [0, 1] for integer ids (black for -1), stable per id:
    n2f2's one id palette (region ids here, the hierarchy's node ids)."""
    golden = 0.618033988749895
    hue = (np.asarray(ids, dtype=np.float64) * golden + 0.11) % 1.0
    sat = 0.55 + 0.35 * ((np.asarray(ids) * 7) % 3) / 2
    val = 0.95 - 0.25 * ((np.asarray(ids) * 5) % 2)
    import matplotlib.colors as mcolors

    rgb = mcolors.hsv_to_rgb(np.stack([hue, sat, val], axis=-1))
    return np.where((np.asarray(ids) < 0)[..., None], 0.0, rgb)


def write_contact_sheet(scene_dir: str | Path, out_png: str | Path, max_views: int = 8) -> Path:
    """A PNG grid: one column per view (spread over the scene), rows = RGB and the part,
    object and group ids coloured per region, with a legend of region captions per level."""
    import json

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Patch

    from ...errors import InputError
    from ..scene import read_scene_meta

    scene_dir = Path(scene_dir)
    try:
        reg_info = json.loads((scene_dir / "regions.json").read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise InputError(scene_dir / "regions.json", f"cannot read regions ({e})") from None
    images = sorted((scene_dir / "images").glob("*.png"))
    if not images:
        raise InputError(scene_dir / "images", "no images")
    count = min(max_views, len(images))
    pick = np.unique(np.linspace(0, len(images) - 1, count).round().astype(int))
    levels = reg_info["levels"]
    from PIL import Image

    rows = 1 + len(levels)
    fig, axes = plt.subplots(
        rows,
        len(pick) + 1,
        figsize=(1.9 * len(pick) + 3.6, 1.55 * rows),
        gridspec_kw={"width_ratios": [1] * len(pick) + [1.9]},
        squeeze=False,
    )
    seen_per_level = [set() for _ in levels]
    for col, i in enumerate(pick):
        stem = images[i].stem
        with Image.open(images[i]) as im:
            axes[0, col].imshow(np.asarray(im.convert("RGB")))
        axes[0, col].set_title(f"{stem} (view {i})", fontsize=6)
        reg = np.load(scene_dir / "regions" / f"{stem}.npy")
        for lv in range(len(levels)):
            axes[lv + 1, col].imshow(id_colors(reg[lv]), interpolation="nearest")
            seen_per_level[lv].update(int(x) for x in np.unique(reg[lv]) if x >= 0)
    for r in range(rows):
        for c in range(len(pick) + 1):
            axes[r, c].set_xticks([])
            axes[r, c].set_yticks([])
        axes[r, 0].set_ylabel("rgb" if r == 0 else f"{levels[r - 1]} ids", fontsize=7)
        axes[r, -1].axis("off")
    by_id = {r["id"]: r for r in reg_info["regions"]}
    for lv in range(len(levels)):
        handles = [
            # matplotlib takes an RGB array as a colour; its ColorType alias lists only tuples and strings.
            Patch(color=id_colors(np.array(rid)), label=by_id[rid]["caption"])  # pyright: ignore[reportArgumentType]
            for rid in sorted(seen_per_level[lv])
        ]
        axes[lv + 1, -1].legend(
            handles=handles,
            loc="center left",
            fontsize=5,
            frameon=False,
            ncol=1 + len(handles) // 8,
            handlelength=1.0,
            borderaxespad=0,
        )
    try:
        layout = read_scene_meta(scene_dir).get("layout", "tabletop")
    except InputError:
        layout = "?"
    axes[0, -1].text(
        0.0, 0.5, f"{scene_dir.name} ({layout})\n{len(images)} views\nblack = no region", fontsize=7, va="center"
    )
    fig.tight_layout(pad=0.3)
    out_png = Path(out_png)
    with atomic_path(out_png) as tmp:
        fig.savefig(tmp, dpi=150, format="png")
    plt.close(fig)
    return out_png
