"""The 3D viewer of ``n2f2 view``: the run's Gaussians drawn as splats in the browser (viser),
the training cameras as clickable frustums, and open-vocabulary queries that recolour the splats.
The splat arrays and the displays' colours are made in :mod:`n2f2.viewer.splat_colors`.

What travels to the browser, and when:

* Once, when the viewer starts: every Gaussian's centre, covariance ``R diag(s^2) R^T`` (from its
  scales and wxyz quaternion), degree-0 colour (``SH_C0 * dc + 0.5``) and opacity, in viser's
  splat buffer (32 bytes per Gaussian: 12 centre, 12 covariance as float16, 4 RGBA).
* Per query, per threshold or display change: colours only. viser's splat API has no message
  for the RGBA column alone (its ``rgbs`` / ``opacities`` setters resend the whole buffer), so a
  recolour is one assignment of a buffer whose geometry words are the ones sent at start:
  32 bytes per Gaussian on the wire (32 MB for 1M Gaussians), and nothing is recomputed.

Queries use the engine's 3D path (:meth:`n2f2.query.engine.QueryEngine.query_gaussians`): the
relevancy of every Gaussian from its own feature, no rendering. The per-Gaussian features (the
field at every centre, ``Theta~`` and the score caches) are computed once, in the background
when the viewer starts, and kept by the engine.

Display (the "colours" dropdown):

* ``heatmap``: turbo colour map of the relevancy, min-max normalised per query; with several
  queries each Gaussian shows its highest normalised relevancy.
* ``selection``: the Gaussians selected by any query keep their colours, the others are dimmed
  (darker and more transparent). Selection = the evaluation protocol's rule on the Gaussians'
  relevancy (min-max normalise, map to [-1, 1], clip, ``> threshold``; 0.4 is the protocol's
  value and what ``/api/selection`` uses with ``"threshold": null``).
* ``rgb``: the Gaussians' own colours.

"Render view" renders the browser's current camera on the server with the same fast path as the
JSON API (:meth:`n2f2.viewer.server.Viewer.query_view`) and shows, per query, the relevancy heatmap
and the segmentation mask with the localisation cross (:mod:`n2f2.query.outputs`), with the
numbers beside them: the point is ``n2f2 query``'s (:func:`n2f2.query.maps.localization_point`,
integer pixel (x, y) of the render), and a flat map gets its warning there, as a query's flat
relevancy over the Gaussians does in the status text.
"Export selection" writes the selected Gaussians as an INRIA PLY (and a
JSON of the query, mode, threshold and count) into the export folder given on the command line
(default: the run folder); the file name comes from the queries, never from a typed path.

When the run has a hierarchy (``n2f2 decompose``; ``n2f2 view --decomposition DIR``), the
"Hierarchy" folder colours the Gaussians by their node at a chosen level, shows the path of a
clicked Gaussian up to the root and exports a node (:mod:`n2f2.viewer.hierarchy`).
"""

from __future__ import annotations

import json
import math
import re
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Optional

import numpy as np

from ..cameras import Camera
from ..errors import InputError
from .splat_colors import (
    SELECTION_THRESHOLD,
    dimmed,
    heat_index,
    rgba_words,
    selection_mask,
    selection_scores,
    splat_arrays,
    turbo_lut,
)

SPLATS = "/gaussians"
DISPLAYS = ("heatmap", "selection", "rgb")


# ----------------------------------------------------------------------------- queries
def split_queries(text: str) -> list[str]:
    """``"teapot, red mug; plate"`` -> ``["teapot", "red mug", "plate"]`` (commas, semicolons
    and new lines separate queries; blanks are dropped)."""
    return [q.strip() for q in re.split(r"[,;\n]", text or "") if q.strip()]


# ----------------------------------------------------------------------------- cameras
def pose_of(camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """(wxyz [4], position [3]) of a camera's camera-to-world pose. viser's cameras and frustums
    use OpenCV axes too (+z forward, +y down), so no axis flip is needed."""
    import viser.transforms as vtf

    return vtf.SO3.from_matrix(camera.R.T).wxyz, camera.center


def camera_from_pose(
    wxyz: np.ndarray,  # [4] camera-to-world rotation, OpenCV axes
    position: np.ndarray,  # [3] camera centre
    fov: float,  # vertical field of view (radians)
    aspect: float,  # width / height
    width: int,  # pixels of the rendered image
) -> Camera:
    """An n2f2 pinhole camera (square pixels, centred principal point) for a browser view."""
    import viser.transforms as vtf

    width = max(8, int(width))
    height = max(8, int(round(width / max(aspect, 1e-3))))
    fy = 0.5 * height / math.tan(0.5 * float(fov))
    R_wc = vtf.SO3(np.asarray(wxyz, dtype=np.float64)).as_matrix()
    R = R_wc.T
    t = -R @ np.asarray(position, dtype=np.float64)
    return Camera(fy, fy, width / 2.0, height / 2.0, width, height, R=R, t=t)


def scene_up(scene: Any, fallback: np.ndarray) -> np.ndarray:  # -> [3] unit
    """The scene's up direction: ``scene.json``'s ``"up"`` (the demo scenes record it), else
    ``fallback`` (the mean up vector of the training cameras)."""
    root = getattr(scene, "root", None)
    if root is not None:
        meta = Path(root) / "scene.json"
        try:
            up = np.asarray(json.loads(meta.read_text()).get("up"), dtype=np.float64).reshape(3)
            if np.isfinite(up).all() and np.linalg.norm(up) > 0:
                return up / np.linalg.norm(up)
        except (OSError, ValueError, TypeError, AttributeError):
            pass
    return np.asarray(fallback, dtype=np.float64) / max(float(np.linalg.norm(fallback)), 1e-12)


# ----------------------------------------------------------------------------- the app
@dataclass
class QueryState:
    """The last query's relevancy over the Gaussians, and what its displays derive from it
    (computed once per query: a threshold change only compares)."""

    texts: list[str]
    mode: str
    relevancy: np.ndarray  # [Q, N] float32
    chosen: list[Optional[str]]  # chosen scale per query (explicit mode)
    seconds: float  # engine time
    _heat: Optional[np.ndarray] = None  # [N] uint32
    _scores: Optional[np.ndarray] = None  # [N] float32, see selection_scores

    @property
    def heat(self) -> np.ndarray:  # [N] uint32 RGBA words with alpha 0
        if self._heat is None:
            lut = np.zeros((256, 4), np.uint8)
            lut[:, :3] = turbo_lut()
            self._heat = rgba_words(lut)[heat_index(self.relevancy)]
        return self._heat

    def selected(self, threshold: float) -> np.ndarray:  # -> [N] bool
        if self._scores is None:
            self._scores = selection_scores(self.relevancy)
        return self._scores > threshold


@dataclass
class Timing:
    """Seconds of the last recolour, from the request to the buffer handed to viser."""

    relevancy: float = 0.0  # engine: relevancy of every Gaussian (0 for a pure recolour)
    colors: float = 0.0  # colour map / selection / RGBA packing
    send: float = 0.0  # buffer assignment + flush to the websocket
    total: float = 0.0
    bytes: int = 0  # size of the buffer sent


class SplatViewer:
    """The viser scene and GUI over a :class:`n2f2.viewer.server.Viewer` (its engine, lock and
    render cache are shared with the JSON API).

    Args:
        viewer: the Viewer of the run.
        server: a started ``viser.ViserServer``.
        export_dir: folder for "Export selection" (default: the run folder).
        warm: compute the per-Gaussian features in a background thread now, so the first query
            does not wait for them.
    """

    def __init__(self, viewer: Any, server: Any, export_dir: Optional[Path] = None, warm: bool = True):
        self.viewer = viewer
        self.engine = viewer.engine
        self.server = server
        run_dir = getattr(self.engine, "run_dir", None)
        self.export_dir = Path(export_dir) if export_dir is not None else Path(run_dir or ".")
        self.scene = viewer.scene
        # The viewers' modes this run answers (node only with a hierarchy that reads back).
        self.modes = list(viewer.modes)
        self.up = scene_up(self.scene, viewer.orbit.up)
        self._work = threading.Lock()  # one recolour / query at a time
        self._gen_lock = threading.Lock()
        self._generation = 0  # recolour requests; a superseded one is skipped
        self._quiet = False  # set while the app itself assigns a GUI value
        self.query: Optional[QueryState] = None
        self.timing = Timing()
        self.last_export: Optional[Path] = None
        self.ready = threading.Event()  # per-Gaussian features computed

        arrays = splat_arrays(self.engine.gaussians)
        self.num = int(arrays["centers"].shape[0])
        server.scene.set_up_direction(tuple(float(v) for v in self.up))
        self.splats = server.scene.add_gaussian_splats(SPLATS, **arrays)
        # The buffer as sent: its geometry words are reused by every recolour.
        self._base = np.array(self.splats.buffer, copy=True)  # [N, 8] uint32
        self.base_rgba = self._base[:, 7].copy().view(np.uint8).reshape(-1, 4)  # [N, 4] uint8
        self._base_words = rgba_words(self.base_rgba)  # [N] uint32
        self._alpha_words = self._base_words & np.uint32(0xFF000000)  # [N] uint32, opacity byte only
        self._dim_words: Optional[np.ndarray] = None  # [N] uint32, every Gaussian dimmed
        self.shown = "rgb"
        self.hierarchy: Any = None  # the HierarchyPanel when the run has a hierarchy
        self._add_frustums()
        self._set_initial_camera()
        self._add_gui(warm)
        if viewer.tree is not None:
            from .hierarchy import HierarchyPanel

            self.hierarchy = HierarchyPanel(self, viewer.tree)
        if warm:
            threading.Thread(target=self._warm, name="n2f2-warm", daemon=True).start()
        else:
            self.ready.set()

    # ------------------------------------------------------------------ scene
    def _add_frustums(self) -> None:
        cams = list(self.scene.cameras)
        centers = np.stack([c.center for c in cams])
        spread = float(np.median(np.linalg.norm(centers - self.viewer.orbit.center, axis=1))) or 1.0
        self.frustums = []
        for i, (cam, name) in enumerate(zip(cams, self.scene.image_names)):
            wxyz, pos = pose_of(cam)
            handle = self.server.scene.add_camera_frustum(
                f"/cameras/{i:04d}_{name}",
                fov=2.0 * math.atan(0.5 * cam.height / cam.fy),
                aspect=cam.width / cam.height,
                scale=0.06 * spread,
                thickness=1.5,
                thickness_units="screen",
                color=(40, 90, 200),
                wxyz=wxyz,
                position=pos,
            )
            handle.on_click(lambda event, i=i: self.move_to_view(event.client, i))
            self.frustums.append(handle)

    def _view_pose(self, i: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        """(wxyz, position, look-at point, vertical fov) of training view ``i``."""
        cam = self.scene.cameras[i]
        wxyz, pos = pose_of(cam)
        dist = float(np.linalg.norm(self.viewer.orbit.center - pos)) or 1.0
        return wxyz, pos, pos + cam.R[2] * dist, 2.0 * math.atan(0.5 * cam.height / cam.fy)

    def _set_initial_camera(self) -> None:
        _, pos, look, fov = self._view_pose(0)
        init = self.server.initial_camera
        init.position = tuple(pos)
        init.look_at = tuple(look)
        init.up = tuple(self.up)
        init.fov = fov

    def move_to_view(self, client: Any, i: int) -> None:
        """Put ``client``'s camera at training view ``i`` (what clicking its frustum does)."""
        if client is None:
            return
        wxyz, pos, _, fov = self._view_pose(i)
        with client.atomic():
            client.camera.wxyz = wxyz
            client.camera.position = pos
            client.camera.fov = fov
        self._set_status(f"view {i} ({self.scene.image_names[i]})")

    # ------------------------------------------------------------------ GUI
    def _add_gui(self, warm: bool) -> None:
        gui = self.server.gui
        limits = self.viewer.limits
        modes = self.modes
        with gui.add_folder("Query"):
            self.gui_text = gui.add_text(
                "Queries", "", hint=f"one or more, separated by commas or semicolons (at most {limits.max_queries})"
            )
            self.gui_mode = gui.add_dropdown(
                "Mode",
                modes,
                initial_value=modes[0],
                hint="composite: one relevancy per query (paper Sec. 3.3); explicit: the best scale per query",
            )
            self.gui_run = gui.add_button("Query", hint="relevancy of every Gaussian")
            self.gui_display = gui.add_dropdown(
                "Colours",
                list(DISPLAYS),
                initial_value="heatmap",
                hint="heatmap of the relevancy, the selection with the rest dimmed, or the Gaussians' own colours",
            )
            self.gui_threshold = gui.add_slider(
                "Threshold",
                0.0,
                0.99,
                0.01,
                SELECTION_THRESHOLD,
                hint="selection: normalised relevancy above this (0.4 = the evaluation protocol)",
            )
            self.gui_status = gui.add_markdown(
                "Computing per-Gaussian features…" if warm else f"{self.num:,} Gaussians. Type a query."
            )
        with gui.add_folder("Render view"):
            self.gui_render = gui.add_button(
                "Render view", hint="2D relevancy, mask and localisation of the current camera, rendered on the server"
            )
            self.gui_image = gui.add_image(np.zeros((8, 8, 3), np.uint8), label="relevancy | mask", visible=False)
            self.gui_numbers = gui.add_markdown("")
        with gui.add_folder("Export"):
            self.gui_export = gui.add_button("Export selection as PLY", hint=f"written into {self.export_dir}")
            self.gui_export_status = gui.add_markdown("")

        self.gui_run.on_click(lambda _: self._guarded(self.run_query))
        self.gui_mode.on_update(lambda _: self._guarded(self.run_query) if self.query is not None else None)
        self.gui_display.on_update(lambda _: None if self._quiet else self._guarded(self.recolour))
        self.gui_threshold.on_update(lambda _: self._guarded(self.recolour, coalesce=True))
        self.gui_render.on_click(lambda event: self._guarded(self.render_view, event.client))
        self.gui_export.on_click(lambda _: self._guarded(self.export_selection))

    def _guarded(self, fn: Any, *args: Any, coalesce: bool = False) -> Any:
        """Run a GUI action: one at a time; a coalescing one (slider drags) is skipped when a newer
        request of any kind is already waiting; a user error is shown, not raised."""
        with self._gen_lock:
            self._generation += 1
            mine = self._generation
        with self._work:
            if coalesce and mine != self._generation:
                return None
            try:
                return fn(*args)
            except InputError as e:
                self._set_status(f"**error:** {e}")
            except Exception as e:  # a GUI callback must not die silently
                self._set_status(f"**error:** internal error ({type(e).__name__}: {e})")
                raise
        return None

    def _set_status(self, text: str) -> None:
        self.gui_status.content = text

    def _warm(self) -> None:
        t0 = time.perf_counter()
        try:
            with self.viewer.lock:
                self.engine.gaussian_cache(self.modes[0])
            turbo_lut()  # imports matplotlib once, not in the first query
            selection_mask(np.zeros((1, 2), np.float32))
            self._set_status(
                f"Ready: {self.num:,} Gaussians (features in {time.perf_counter() - t0:.1f} s). Type a query."
            )
        except Exception as e:
            self._set_status(f"**error** preparing features: {type(e).__name__}: {e}")
        finally:
            self.ready.set()

    # ------------------------------------------------------------------ queries
    def parse_queries(self, text: str) -> list[str]:
        """The text box's queries, under the JSON API's limits."""
        from .server import ApiError

        texts = split_queries(text)
        if not texts:
            raise InputError(None, "type a query (several: separate them with commas or semicolons)")
        try:
            return self.viewer.parse_queries(texts)
        except ApiError as e:
            raise InputError(None, e.message) from None

    def run_query(self) -> Timing:
        """Relevancy of every Gaussian for the text box's queries, then recolour."""
        texts = self.parse_queries(self.gui_text.value)
        mode = str(self.gui_mode.value)
        t0 = time.perf_counter()
        with self.viewer.lock:
            result = self.engine.query_gaussians(texts, mode)
        rel = result.relevancy.float().cpu().numpy()
        self.query = QueryState(texts, mode, rel, result.chosen_labels, time.perf_counter() - t0)
        if self.hierarchy is not None:
            self.hierarchy.hide()  # the answer's colours, not the nodes'
        if self.gui_display.value == "rgb":
            self._quiet = True  # the dropdown's callback runs here, synchronously: skip it
            try:
                self.gui_display.value = "heatmap"
            finally:
                self._quiet = False
        return self.recolour(t0=t0)

    def colors(self) -> np.ndarray:  # [N] uint32 RGBA words for the current display
        nodes = self.hierarchy.colors() if self.hierarchy is not None else None
        if nodes is not None:
            return nodes
        q = self.query
        display = self.gui_display.value
        if q is None or display == "rgb":
            return self._base_words
        if display == "heatmap":
            return q.heat | self._alpha_words
        if self._dim_words is None:
            self._dim_words = rgba_words(dimmed(self.base_rgba, np.zeros(self.num, dtype=bool)))
        return np.where(q.selected(float(self.gui_threshold.value)), self._base_words, self._dim_words)

    def recolour(self, t0: Optional[float] = None) -> Timing:
        """Send the colours of the current display (one splat-buffer update, geometry unchanged)."""
        start = time.perf_counter() if t0 is None else t0
        t1 = time.perf_counter()
        words = self.colors()
        display = self.gui_display.value if self.query is not None else "rgb"
        if self.hierarchy is not None and self.hierarchy.showing:
            display = "nodes"
        buf = self._base.copy()
        buf[:, 7] = words
        t2 = time.perf_counter()
        self.splats.buffer = buf
        self.server.flush()
        t3 = time.perf_counter()
        self.shown = display
        self.timing = Timing(
            relevancy=(t1 - start), colors=t2 - t1, send=t3 - t2, total=t3 - start, bytes=int(buf.nbytes)
        )
        self._show_query_status()
        return self.timing

    def _show_query_status(self) -> None:
        from ..query.maps import flat_warning

        q = self.query
        if q is None:
            return
        n_sel = int(q.selected(float(self.gui_threshold.value)).sum())
        lines = [
            f"**{len(q.texts)} quer{'y' if len(q.texts) == 1 else 'ies'}** ({q.mode}): "
            f"{n_sel:,} of {self.num:,} Gaussians selected at threshold "
            f"{float(self.gui_threshold.value):.2f}."
        ]
        for text, rel, scale in zip(q.texts, q.relevancy, q.chosen):
            extra = f", scale {scale}" if scale else ""
            lines.append(f"- {text}: relevancy {float(rel.min()):.3f} to {float(rel.max()):.3f}{extra}")
            warning = flat_warning(rel, "the Gaussians")
            if warning is not None:
                lines.append(f"  **warning:** {warning}")
        t = self.timing
        lines.append(
            f"\n{1000 * t.total:.0f} ms to colours sent (relevancy {1000 * t.relevancy:.0f}, "
            f"colours {1000 * t.colors:.0f}, send {1000 * t.send:.0f} ms; {t.bytes / 2**20:.1f} MB)"
        )
        self._set_status("\n".join(lines))

    # ------------------------------------------------------------------ render view
    def render_camera(self, client: Any) -> Camera:
        """The n2f2 camera of a browser's view, at the training views' width."""
        cam = client.camera
        width = self.viewer.orbit.intrinsics.width
        return camera_from_pose(cam.wxyz, cam.position, cam.fov, cam.aspect, width)

    def render_view(self, client: Any = None) -> Optional[np.ndarray]:
        """Render the client's camera on the server; show per query [heatmap | mask + cross] and
        the numbers. Returns the image shown ([H, W, 3] uint8), None without a client."""
        from ..query.maps import flat_warning, localization_point
        from ..query.outputs import heatmap_overlay, mask_overlay, segment

        if client is None:
            clients = list(self.server.get_clients().values())
            if not clients:
                return None
            client = clients[0]
        camera = self.render_camera(client)
        p = np.round(np.concatenate([camera.center, camera.R.ravel()]), 4)
        key = f"client:{camera.width}x{camera.height}:{camera.fy:.3f}:" + ",".join(f"{v:g}" for v in p)
        q = self.query
        texts = q.texts if q is not None else []
        mode = q.mode if q is not None else str(self.gui_mode.value)
        t0 = time.perf_counter()
        labels: list = []
        if texts:
            view, result = self.viewer.query_view(key, camera, texts, mode)
            rel_all = result.relevancy.float().cpu().numpy()
            labels = result.chosen_labels
        else:
            view, _ = self.viewer.render(key, camera, mode)
            rel_all = np.zeros((0, camera.height, camera.width), np.float32)
        rgb = view.rgb.float().cpu().numpy()
        box = self.viewer.box_pixels(camera.width)
        threshold = float(self.gui_threshold.value)
        rows, lines, warnings = [], [], []
        for qi, text in enumerate(texts):
            rel = np.ascontiguousarray(rel_all[qi], dtype=np.float32)
            mask = segment(rel, box, threshold)
            x, y = localization_point(rel, box)
            rows.append(np.concatenate([heatmap_overlay(rgb, rel), mask_overlay(rgb, mask, (x, y))], axis=1))
            scale = labels[qi]
            lines.append(f"| {text} | {float(rel.max()):.3f} | ({x}, {y}) | {int(mask.sum())} | {scale or '-'} |")
            warning = flat_warning(rel)
            if warning is not None:
                warnings.append(f"**warning:** {text}: {warning}")
        image = np.concatenate(rows, axis=0) if rows else rgb
        image = (np.clip(image, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
        self.gui_image.image = image
        self.gui_image.visible = True
        ms = 1000 * (time.perf_counter() - t0)
        header = (
            f"{camera.width}x{camera.height} px, {ms:.0f} ms, mask threshold {threshold:.2f}, box {box} px\n\n"
            "| query | max relevancy | localisation (x, y) px | mask px | scale |\n|---|---|---|---|---|\n"
        )
        numbers = header + "\n".join(lines) + "".join(f"\n\n{w}" for w in warnings)
        self.gui_numbers.content = numbers if lines else f"RGB only (no query), {ms:.0f} ms"
        return image

    # ------------------------------------------------------------------ export
    def export_selection(self) -> Path:
        """Write the current selection (all queries, current threshold) as a PLY + JSON."""
        import torch

        from ..io import write_json
        from ..query.outputs import unique_slugs

        q = self.query
        if q is None:
            raise InputError(None, "run a query first: the export writes the Gaussians it selects")
        threshold = float(self.gui_threshold.value)
        mask = q.selected(threshold)
        name = "selection_" + "_".join(unique_slugs(q.texts))[:100]
        path = self.export_dir / f"{name}.ply"
        self.export_dir.mkdir(parents=True, exist_ok=True)
        with self.viewer.lock:
            n = self.engine.export_selection(torch.from_numpy(mask), path)
        write_json(
            path.with_suffix(".json"),
            {
                "queries": q.texts,
                "mode": q.mode,
                "threshold": threshold,
                "rule": "normalized_for_threshold(relevancy) > threshold, any query",
                "selected": n,
                "total": self.num,
                "ply": path.name,
            },
        )
        self.last_export = path
        self.gui_export_status.content = f"{n:,} Gaussians written to `{path}`"
        return path
