"""The scene's hierarchy (``n2f2 decompose``) in the 3D viewer: colour the splats by their node at
one level, click a Gaussian to see its path up to the root, export a node as a PLY.

The parts a test can call without a browser are plain functions: :func:`level_colors` (a stable
colour per node, :func:`n2f2.hierarchy.views.palette`), :func:`pick_gaussian` (the Gaussian a
click's ray hits), :func:`path_records` / :func:`path_markdown` (what the panel shows of it) and
:func:`export_node`. :class:`HierarchyPanel` wires them to viser's GUI and scene clicks.

Which Gaussian a click hits: viser hands the click over as a ray (camera centre and direction in
world space), not as a splat. Along that ray each Gaussian's largest density is at the point of
smallest Mahalanobis distance ``m``; its opacity there is ``alpha = o exp(-m^2 / 2)`` (cut at 3
sigma and 1/255, as 3DGS cuts its splats). Composited front to back (by the depth of that point),
the Gaussian with the largest weight ``alpha T`` is the one that gives the pixel most of its
colour: the one the user sees there.
"""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Any, Optional

import numpy as np

from ..errors import InputError
from .splat_colors import dimmed, rgba_words

SIGMA_CUT = 3.0  # a Gaussian reaches this many standard deviations along a click's ray
ALPHA_MIN = 1.0 / 255.0  # and contributes at least this opacity there (3DGS's cut)


# ----------------------------------------------------------------------------- colours
def level_colors(
    gaussian_nodes: np.ndarray,  # [N, L] node of every Gaussian at every level
    level: int,
) -> np.ndarray:  # -> [N, 3] uint8
    """Every Gaussian's colour at ``level``: the palette colour of its node there (the same colour
    the node has in ``n2f2 decompose``'s per-view PNGs)."""
    from ..hierarchy.views import palette

    uniq, inverse = np.unique(gaussian_nodes[:, level], return_inverse=True)
    return palette(uniq)[inverse.reshape(-1)]


def level_words(
    gaussian_nodes: np.ndarray,  # [N, L]
    level: int,
    alpha_words: np.ndarray,  # [N] uint32, the splats' own opacity byte only
) -> np.ndarray:  # -> [N] uint32 RGBA words of viser's splat buffer
    """:func:`level_colors` packed as splat-buffer words, each Gaussian keeping its opacity."""
    rgba = np.zeros((gaussian_nodes.shape[0], 4), np.uint8)
    rgba[:, :3] = level_colors(gaussian_nodes, level)
    return rgba_words(rgba) | alpha_words


# ----------------------------------------------------------------------------- picking
def whitening(
    quats: np.ndarray,  # [N, 4] wxyz, any norm
    scales: np.ndarray,  # [N, 3] standard deviations along the local axes
) -> np.ndarray:  # -> [N, 3, 3] float32 A_i = diag(1 / s_i) R_i^T
    """Per Gaussian the map from world offsets to its unit-variance frame: ``|A_i (x - c_i)|`` is
    the Mahalanobis distance of ``x`` from the Gaussian."""
    import torch

    from ..gaussians.model import quat_to_rotmat

    R = quat_to_rotmat(torch.as_tensor(np.asarray(quats, dtype=np.float32))).numpy()  # [N, 3, 3]
    inv = 1.0 / np.maximum(np.asarray(scales, dtype=np.float32), 1e-12)  # [N, 3]
    return (R.transpose(0, 2, 1) * inv[:, :, None]).astype(np.float32)


def pick_gaussian(
    centers: np.ndarray,  # [N, 3]
    whiten: np.ndarray,  # [N, 3, 3] from :func:`whitening`
    opacities: np.ndarray,  # [N] in [0, 1]
    origin: Any,  # [3] ray origin (the camera centre)
    direction: Any,  # [3] ray direction, any norm
) -> Optional[int]:
    """The Gaussian that gives a click's pixel most of its colour (module docstring), None when
    the ray hits none."""
    o = np.asarray(origin, dtype=np.float64).reshape(3)
    d = np.asarray(direction, dtype=np.float64).reshape(3)
    d = d / max(float(np.linalg.norm(d)), 1e-12)
    rel = np.asarray(centers, dtype=np.float64) - o  # [N, 3]
    # Cheap cut first: the Euclidean distance to the ray against 3 sigma of the widest axis.
    along = rel @ d  # [N]
    perp2 = np.einsum("ij,ij->i", rel, rel) - along**2
    # Row i of A = diag(1 / s) R^T has norm 1 / s_i: the largest sigma is 1 / the smallest row norm.
    widest = 1.0 / np.maximum(np.linalg.norm(whiten, axis=2).min(axis=1), 1e-12)  # [N]
    near = np.nonzero(perp2 <= (SIGMA_CUT * widest) ** 2)[0]
    if near.size == 0:
        return None
    A = whiten[near].astype(np.float64)  # [n, 3, 3]
    o_l = np.einsum("nij,nj->ni", A, -rel[near])  # ray origin in each Gaussian's frame
    d_l = np.einsum("nij,j->ni", A, d)  # ray direction in each Gaussian's frame
    dd = np.maximum(np.einsum("ni,ni->n", d_l, d_l), 1e-30)
    t = -np.einsum("ni,ni->n", o_l, d_l) / dd  # depth of the densest point along the ray
    m2 = np.maximum(np.einsum("ni,ni->n", o_l, o_l) - t * t * dd, 0.0)
    alpha = np.minimum(np.asarray(opacities, dtype=np.float64)[near] * np.exp(-0.5 * m2), 0.99)
    hit = (t > 0) & (m2 <= SIGMA_CUT**2) & (alpha >= ALPHA_MIN)
    if not hit.any():
        return None
    idx, t, alpha = near[hit], t[hit], alpha[hit]
    order = np.argsort(t, kind="stable")
    a = alpha[order]
    T = np.concatenate([[1.0], np.cumprod(1.0 - a)[:-1]])  # transmittance in front of each
    return int(idx[order][int(np.argmax(a * T))])


# ----------------------------------------------------------------------------- paths
def path_records(tree: Any, node: int) -> list[dict]:
    """``node`` and its ancestors up to the root (``tree.path(node)``, the node first), each as
    ``{"node", "level", "last_level", "scale_label", "last_scale_label", "gaussians", "text",
    "relevancy"}`` from ``tree.json`` (a node spans the levels ``level .. last_level`` unsplit)."""
    labels = [lv.get("scale_label") for lv in tree.tree["levels"]]
    out = []
    for k in tree.path(int(node)):
        rec = tree.tree["nodes"][k]
        level = int(rec["level"])
        last = int(tree.last_levels[k])
        out.append(
            {
                "node": int(k),
                "level": level,
                "last_level": last,
                "scale_label": labels[level],
                "last_scale_label": labels[last],
                "gaussians": int(rec["gaussians"]),
                "text": rec.get("text"),
                "relevancy": rec.get("relevancy"),
            }
        )
    return out


def path_markdown(gaussian: int, records: list[dict]) -> str:
    """What the panel shows of a clicked Gaussian: one line per node of its path, its node at the
    current level first, the root last (a node's text only when ``tree.json`` has one)."""
    lines = [f"**Gaussian {gaussian:,}**, from its node up to the root:"]
    for r in records:
        text = ""
        if r["text"] is not None:
            rel = f" ({r['relevancy']:.3f})" if r["relevancy"] is not None else ""
            text = f" · “{r['text']}”{rel}"
        span = f"level {r['level']} ({r['scale_label']})"
        if r["last_level"] != r["level"]:
            span = f"levels {r['level']}–{r['last_level']} ({r['scale_label']}–{r['last_scale_label']})"
        lines.append(f"- {span}: node **{r['node']}**, {r['gaussians']:,} Gaussians{text}")
    return "\n".join(lines)


# ----------------------------------------------------------------------------- export
def node_mask(tree: Any, node: int) -> np.ndarray:  # -> [N] bool
    """The Gaussians of ``node``: those whose node at its level is ``node``."""
    level = int(tree.tree["nodes"][int(node)]["level"])
    return tree.gaussian_nodes[:, level] == int(node)


def export_node(engine: Any, tree: Any, node: int, folder: Path) -> tuple[Path, int]:
    """Write ``node``'s Gaussians as an INRIA PLY ``node_<id>_level_<l>.ply`` in ``folder`` (``l``:
    its first level), and a JSON beside it (the node, the levels it spans, its path and text);
    -> (the PLY's path, Gaussians written).
    The file name comes from the node's id, never from anything typed."""
    import torch

    from ..io import write_json

    node = int(node)
    level = int(tree.tree["nodes"][node]["level"])
    path = Path(folder) / f"node_{node}_level_{level}.ply"
    Path(folder).mkdir(parents=True, exist_ok=True)
    n = engine.export_selection(torch.from_numpy(node_mask(tree, node)), path)
    write_json(
        path.with_suffix(".json"),
        {
            "node": node,
            "level": level,
            "last_level": int(tree.last_levels[node]),
            "path": tree.path(node),
            "text": tree.tree["nodes"][node].get("text"),
            "gaussians": n,
            "decomposition": str(tree.root),
            "ply": path.name,
        },
    )
    return path, n


# ----------------------------------------------------------------------------- GUI
class HierarchyPanel:
    """The "Hierarchy" folder of the 3D viewer and its scene click, over a
    :class:`n2f2.viewer.splats.SplatViewer` (whose recolour, lock and status it uses).

    "Colour by node" with the "Granularity" slider (0 = the coarsest level) colours every
    Gaussian by its node at that level; unticked, the viewer's own display comes back. A click
    picks a Gaussian (:func:`pick_gaussian`); the panel shows its path from its node at the
    current level to the root, and the other nodes are dimmed while the node colours show.
    "Export node" writes that node (:func:`export_node`) into the viewer's export folder."""

    def __init__(self, splats: Any, tree: Any):
        self.splats = splats
        self.tree = tree
        self.gaussian: Optional[int] = None  # the clicked Gaussian
        self.last_export: Optional[Path] = None
        self._words: dict[int, np.ndarray] = {}  # level -> [N] uint32 node colours
        self._whiten: Optional[np.ndarray] = None  # [N, 3, 3], made on the first click
        self._pick_lock = threading.Lock()
        self._add_gui()
        splats.server.scene.on_click()(self._on_click)

    @property
    def level(self) -> int:
        return int(round(float(self.gui_level.value)))

    @property
    def showing(self) -> bool:
        return bool(self.gui_show.value)

    @property
    def node(self) -> Optional[int]:
        """The clicked Gaussian's node at the current level."""
        if self.gaussian is None:
            return None
        return int(self.tree.gaussian_nodes[self.gaussian, self.level])

    def _add_gui(self) -> None:
        gui = self.splats.server.gui
        L = self.tree.num_levels
        with gui.add_folder("Hierarchy"):
            self.gui_show = gui.add_checkbox(
                "Colour by node", False, hint="each Gaussian in its node's colour; untick for the usual colours"
            )
            self.gui_level = gui.add_slider(
                "Granularity",
                0,
                L - 1,
                1,
                0,
                marks=tuple(range(L)),
                hint="the level whose nodes colour the Gaussians: 0 = the coarsest",
            )
            self.gui_level_text = gui.add_markdown(self._level_text())
            self.gui_path = gui.add_markdown("Click a Gaussian to see its path up to the root.")
            self.gui_export = gui.add_button(
                "Export node", hint=f"the clicked node as a PLY in {self.splats.export_dir}"
            )
            self.gui_export_status = gui.add_markdown("")
        self.gui_show.on_update(lambda _: None if self.splats._quiet else self.splats._guarded(self.splats.recolour))
        self.gui_level.on_update(
            lambda _: None if self.splats._quiet else self.splats._guarded(self.set_level, self.level, coalesce=True)
        )
        self.gui_export.on_click(lambda _: self.splats._guarded(self.export))

    def _level_text(self) -> str:
        lv = self.tree.tree["levels"][self.level]
        return f"level {self.level} of 0..{self.tree.num_levels - 1}: {lv['nodes']} nodes, scale {lv['scale_label']}"

    def words(self, level: Optional[int] = None) -> np.ndarray:  # -> [N] uint32
        """The node colours at ``level`` (default: the slider's), cached per level."""
        level = self.level if level is None else int(level)
        if level not in self._words:
            self._words[level] = level_words(self.tree.gaussian_nodes, level, self.splats._alpha_words)
        return self._words[level]

    def colors(self) -> Optional[np.ndarray]:  # -> [N] uint32, None when the node colours are off
        """The splat colours while "Colour by node" is on: every Gaussian in its node's colour,
        the nodes other than the clicked one dimmed; None when it is off."""
        if not self.showing:
            return None
        words = self.words()
        node = self.node
        if node is None:
            return words
        rgba = words.view(np.uint8).reshape(-1, 4)
        return rgba_words(dimmed(rgba, self.tree.gaussian_nodes[:, self.level] == node))

    def set_level(self, level: int) -> Any:
        """Show the nodes of ``level`` (what moving the slider does; it also ticks the box)."""
        s = self.splats
        if self.level != int(level):
            s._quiet = True
            try:
                self.gui_level.value = int(level)
            finally:
                s._quiet = False
        if not self.showing:
            s._quiet = True  # the checkbox's callback would recolour a second time
            try:
                self.gui_show.value = True
            finally:
                s._quiet = False
        self.gui_level_text.content = self._level_text()
        self._show_path()
        return s.recolour()

    def hide(self) -> None:
        """Back to the viewer's own colours (untick the box, without a recolour of its own)."""
        if self.showing:
            self.splats._quiet = True
            try:
                self.gui_show.value = False
            finally:
                self.splats._quiet = False

    # ------------------------------------------------------------------ clicks
    def _on_click(self, event: Any) -> None:
        self.splats._guarded(self.pick, event.ray_origin, event.ray_direction)

    def pick(self, origin: Any, direction: Any) -> Optional[int]:
        """Select the Gaussian a ray from ``origin`` along ``direction`` hits (None: a click on
        empty space clears the selection); recolour when the node colours show."""
        g = self.splats.engine.gaussians
        with self._pick_lock:
            if self._whiten is None:
                self._whiten = whitening(g.quats.detach().cpu().numpy(), g.scales.detach().cpu().numpy())
        centers = g.means.detach().cpu().numpy()
        hit = pick_gaussian(centers, self._whiten, g.opacities.detach().cpu().numpy(), origin, direction)
        self.select(hit)
        return hit

    def select(self, gaussian: Optional[int]) -> None:
        """Make ``gaussian`` the clicked one (None: none) and show its path."""
        self.gaussian = None if gaussian is None else int(gaussian)
        self._show_path()
        if self.showing:
            self.splats.recolour()

    def _show_path(self) -> None:
        node = self.node
        if self.gaussian is None or node is None:
            self.gui_path.content = "Click a Gaussian to see its path up to the root."
            return
        self.gui_path.content = path_markdown(self.gaussian, path_records(self.tree, node))

    # ------------------------------------------------------------------ export
    def export(self) -> Path:
        """Write the clicked Gaussian's node at the current level (:func:`export_node`)."""
        node = self.node
        if node is None:
            raise InputError(None, "click a Gaussian first: 'Export node' writes its node at the current level")
        with self.splats.viewer.lock:
            path, n = export_node(self.splats.engine, self.tree, node, self.splats.export_dir)
        self.last_export = path
        self.gui_export_status.content = f"node {node} (level {self.level}): {n:,} Gaussians written to `{path}`"
        return path
