"""The live viewer: a FastAPI app serving one page and a small JSON API over a trained run.

API (all JSON; errors are ``{"error": "..."}`` with a 4xx/5xx status, never a traceback):

* ``GET  /api/scene`` -> views (index, name, size, orbit parameters), modes, encoder description,
  limits.
* ``POST /api/render`` ``{"camera": CAMERA}`` -> ``{"rgb_png": base64, "width", "height",
  "cached", "timing_ms"}``.
* ``POST /api/query`` ``{"queries": [str, ...], "camera": CAMERA, "mode": MODE}`` (MODE: one of
  ``/api/scene``'s ``modes``, default composite; ``node`` only when the run has a hierarchy)
  -> ``{"rgb_png", "width", "height", "mode", "box_size", "timing_ms", "results": [{"query",
  "max_relevancy", "localization": [x, y], "mask_area", "mask_png", "overlay_png",
  "relevancy_png", "chosen_scale"}]}``, and ``"warning"`` in a result whose relevancy is flat over
  the view (:func:`n2f2.query.maps.flat_warning`, the line ``n2f2 query`` prints).
  ``localization`` is ``n2f2 query``'s point (:func:`n2f2.query.maps.localization_point`):
  integer pixel indices (x = column, y = row) of the view as rendered, the pixel's centre at
  ``(x + 0.5, y + 0.5)``; a training view renders at the size ``n2f2 query`` renders it (same
  ``--full-res``), so the point equals
  query.json's for the same view, query, mode and ``box_size`` (the protocol's mean filter in
  pixels: ``QueryConfig.box_size`` of the engine, LangSplat's 30 by default, as ``n2f2 query``).
  ``mask_png`` is the protocol's segmentation mask as a white-on-transparent PNG;
  ``overlay_png`` / ``relevancy_png`` are ``n2f2 query``'s heatmap (:mod:`n2f2.query.outputs`)
  over the RGB / alone. In mode ``node`` a result also holds ``nodes`` (the answer's node ids,
  the best first) and ``level``, and its map is their rendered coverage.
* ``POST /api/selection`` ``{"query": str, "mode": ..., "threshold": float|null}`` -> the selected
  Gaussians as an INRIA 3DGS PLY (``application/octet-stream``), count in ``X-Selected-Gaussians``.

``CAMERA`` is ``{"view": int}`` (a training view) or ``{"orbit": {"azimuth": deg, "elevation":
deg, "radius": r}}`` around the scene's orbit centre (see :class:`OrbitFrame`).

Safety: binds 127.0.0.1 unless told otherwise; request bodies are capped (``max_body_bytes``),
as are the number and length of queries; nothing in a request is ever used as a file path. Every
malformed request gets a JSON error with a 4xx status, also those the HTTP parser refuses before
the app sees them (a non-numeric Content-Length, a garbled request line: see
:func:`json_error_protocol`). Renders are cached per camera in an LRU bounded in bytes
(``ViewerLimits.render_cache_bytes`` in :mod:`n2f2.viewer.settings`, ``n2f2 view --cache-mb``;
:mod:`n2f2.viewer.cache`).
"""

from __future__ import annotations

import base64
import io
import json
import math
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Optional

import numpy as np
from fastapi import Request  # module level: FastAPI resolves the handlers' string annotations here

from ..cameras import Camera, look_at
from ..errors import InputError, N2F2Error
from ..heap import return_freed_blocks
from ..query.modes import QUERY_MODES
from .cache import ByteLRU, compact_tensors, tensor_bytes
from .settings import API_PORT, HOST, ViewerLimits

STATIC_DIR = Path(__file__).parent / "static"
VIEWER_MODES = tuple(m.name for m in QUERY_MODES.values() if m.viewer)  # what the viewers can offer


class ApiError(Exception):
    def __init__(self, status: int, message: str):
        super().__init__(message)
        self.status = status
        self.message = message


# ----------------------------------------------------------------------------- orbit cameras
@dataclass(frozen=True)
class OrbitFrame:
    """Spherical coordinates around the scene: centre = the point closest (least squares) to
    all training cameras' optical axes; up = the mean of the cameras' up vectors (-y in OpenCV
    camera axes), so it works for any capture, not only z-up scenes."""

    center: np.ndarray  # [3]
    up: np.ndarray  # [3] unit
    x_axis: np.ndarray  # [3] unit, azimuth 0
    y_axis: np.ndarray  # [3] unit, azimuth 90
    intrinsics: Camera  # intrinsics source for novel views (training view 0)

    @staticmethod
    def from_cameras(cameras: list[Camera]) -> "OrbitFrame":
        centers = np.stack([c.center for c in cameras])
        dirs = np.stack([c.R[2] for c in cameras])  # optical axes in world space
        A = np.zeros((3, 3))
        b = np.zeros(3)
        for o, d in zip(centers, dirs):
            P = np.eye(3) - np.outer(d, d)
            A += P
            b += P @ o
        center = np.linalg.lstsq(A, b, rcond=None)[0]
        up = -np.mean([c.R[1] for c in cameras], axis=0)
        up /= max(np.linalg.norm(up), 1e-12)
        ref = centers[0] - center
        x_axis = ref - up * (ref @ up)
        if np.linalg.norm(x_axis) < 1e-9:
            x_axis = np.cross(up, [1.0, 0.0, 0.0])
        x_axis /= np.linalg.norm(x_axis)
        y_axis = np.cross(up, x_axis)
        return OrbitFrame(center, up, x_axis, y_axis, cameras[0])

    def orbit_of(self, camera: Camera) -> dict:
        rel = camera.center - self.center
        radius = float(np.linalg.norm(rel))
        elevation = math.degrees(math.asin(float(np.clip(rel @ self.up / max(radius, 1e-12), -1, 1))))
        azimuth = math.degrees(math.atan2(float(rel @ self.y_axis), float(rel @ self.x_axis)))
        return {"azimuth": azimuth, "elevation": elevation, "radius": radius}

    def camera(self, azimuth: float, elevation: float, radius: float) -> Camera:
        az, el = math.radians(azimuth), math.radians(elevation)
        direction = math.cos(el) * (math.cos(az) * self.x_axis + math.sin(az) * self.y_axis) + math.sin(el) * self.up
        R, t = look_at(self.center + radius * direction, self.center, self.up)
        k = self.intrinsics
        return Camera(k.fx, k.fy, k.cx, k.cy, k.width, k.height, R=R, t=t)


def finite_number(value: Any) -> Optional[float]:
    """``value`` as a float when it is a finite JSON number (not a bool), else None; an integer
    too large for a float is None too (``float(10**400)`` raises OverflowError)."""
    if not isinstance(value, (int, float)) or isinstance(value, bool):
        return None
    try:
        v = float(value)
    except OverflowError:
        return None
    return v if math.isfinite(v) else None


# ----------------------------------------------------------------------------- image helpers
def png_base64(image: np.ndarray) -> str:
    """uint8 or [0, 1] float array [H, W] / [H, W, 3|4] -> base64 PNG."""
    from PIL import Image

    if image.dtype != np.uint8:
        image = (np.clip(image, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    buf = io.BytesIO()
    Image.fromarray(image).save(buf, format="PNG")
    return base64.b64encode(buf.getvalue()).decode("ascii")


# ----------------------------------------------------------------------------- the viewer state
class Viewer:
    """Holds the query engine and a per-camera render cache. One lock serialises the engine
    (PyTorch on 2 cores gains nothing from running queries concurrently)."""

    def __init__(self, engine: Any, limits: ViewerLimits = ViewerLimits(), box_size: Any = None):
        from ..query.maps import LANGSPLAT_BOX_SIZE

        self.engine = engine
        # Mean filter of the protocol's mask / localization rules (pixels or "scaled"). None: the
        # engine's QueryConfig.box_size, whose own None is LangSplat's 30 px, as `n2f2 query`'s:
        # one default, so the viewer and the command give the same mask and point.
        if box_size is None:
            box_size = getattr(getattr(engine, "config", None), "box_size", None)
        self.box_size = LANGSPLAT_BOX_SIZE if box_size is None else box_size
        self.limits = limits
        self.scene = engine.scene
        if self.scene is None:
            raise InputError(getattr(engine, "run_dir", None), "the viewer needs the run's scene (its cameras)")
        self.orbit = OrbitFrame.from_cameras(list(self.scene.cameras))
        self.tree, self.tree_error = self._read_tree()
        self.modes = tuple(
            m for m in VIEWER_MODES if m in engine.modes() and (self.tree is not None or not QUERY_MODES[m].needs_tree)
        )
        self.lock = threading.Lock()
        # The field's W is shared by every cache (and the engine): it is not a render's cost.
        self._shared = frozenset({engine.W.untyped_storage().data_ptr()}) if hasattr(engine, "W") else frozenset()
        self._renders = ByteLRU(limits.render_cache_bytes, lambda cache: tensor_bytes(cache, exclude=self._shared))

    def _read_tree(self) -> tuple[Any, Optional[str]]:
        """(the run's hierarchy, None) when it has one that reads back; (None, why not) when its
        folder is stale or broken; (None, None) without one. Read once, here: the node mode and
        the 3D viewer's hierarchy panel are offered only with a tree."""
        tree_dir = getattr(self.engine, "_tree_dir", lambda: None)()
        if tree_dir is None:
            return None, None
        try:
            return self.engine.tree, None
        except InputError as e:
            return None, str(e)

    def box_pixels(self, width: int) -> int:
        """The protocol's mean-filter size in pixels for a render ``width`` pixels wide."""
        from ..query.maps import resolve_box_size

        return resolve_box_size(self.box_size, width)

    def encoder_description(self) -> str:
        """The text encoder's description, from the field's metadata when it records one (no
        need to load the encoder, which another thread may be loading under the lock)."""
        spec = (getattr(self.engine, "meta", None) or {}).get("encoder_spec") or {}
        if spec.get("description"):
            return str(spec["description"])
        with self.lock:
            return str(getattr(self.engine.encoder, "description", ""))

    # -------------------------------------------------------------- parsing
    def parse_camera(self, body: Any) -> tuple[str, Any]:
        """Validate a CAMERA object -> (cache key, view index or Camera)."""
        if not isinstance(body, dict):
            raise ApiError(422, '\'camera\' must be an object: {"view": int} or {"orbit": {...}}')
        if "view" in body:
            view = body["view"]
            if not isinstance(view, int) or isinstance(view, bool):
                raise ApiError(422, "'camera.view' must be an integer view index")
            n = len(self.scene.cameras)
            if not 0 <= view < n:
                raise ApiError(404, f"unknown view {view}: the scene has views 0..{n - 1}")
            return f"view:{view}", view
        if "orbit" in body:
            orbit = body["orbit"]
            if not isinstance(orbit, dict):
                raise ApiError(422, "'camera.orbit' must be an object")
            vals = []
            for key in ("azimuth", "elevation", "radius"):
                v = finite_number(orbit.get(key))
                if v is None:
                    raise ApiError(422, f"'camera.orbit.{key}' must be a finite number")
                vals.append(v)
            az, el, r = vals
            if not -89.0 <= el <= 89.0 or not 0.0 < r <= 1e4:
                raise ApiError(422, "orbit elevation must be in [-89, 89] degrees and radius in (0, 1e4]")
            key = f"orbit:{az:.2f}:{el:.2f}:{r:.4f}"
            return key, self.orbit.camera(az, el, r)
        raise ApiError(422, "'camera' needs 'view' or 'orbit'")

    def parse_queries(self, value: Any) -> list[str]:
        if isinstance(value, str):
            value = [value]
        if not isinstance(value, list) or not value:
            raise ApiError(422, "'queries' must be a non-empty list of strings")
        if len(value) > self.limits.max_queries:
            raise ApiError(413, f"too many queries: at most {self.limits.max_queries} per request")
        out = []
        for q in value:
            if not isinstance(q, str) or not q.strip():
                raise ApiError(422, "every query must be a non-empty string")
            if len(q) > self.limits.max_query_chars:
                raise ApiError(413, f"query too long: at most {self.limits.max_query_chars} characters")
            out.append(q.strip())
        return out

    def parse_mode(self, value: Any) -> str:
        mode = value if value is not None else "composite"
        if mode not in VIEWER_MODES:
            raise ApiError(422, f"unknown mode {mode!r}: use one of {', '.join(VIEWER_MODES)}")
        if mode not in self.modes:
            if QUERY_MODES[mode].needs_tree:
                raise ApiError(
                    422,
                    self.tree_error
                    or f"mode {mode!r} needs the run's hierarchy: run `n2f2 decompose RUN` first "
                    "(or give `n2f2 view --decomposition DIR`)",
                )
            raise ApiError(422, f"mode {mode!r} is not available for this field")
        return mode

    # -------------------------------------------------------------- work
    def render(self, key: str, view: Any, mode: str = "composite") -> tuple[Any, bool]:
        """Render (or fetch from the LRU cache) what ``mode`` needs for a camera."""
        with self.lock:
            return self._render_locked(key, view, mode)

    def _render_locked(self, key: str, view: Any, mode: str) -> tuple[Any, bool]:
        # Cached per (camera, mode): the explicit mode's per-scale caches cost about 3x the
        # composite one's (416 vs 127 ms on a demo view), so they are made only when asked for.
        key = f"{key}|{mode}"
        cache = self._renders.get(key)
        if cache is not None:
            return cache, True
        # Room for the render in flight first, so that the cache and the request together stay
        # within the bound (the evicted renders are freed before the new one allocates).
        self._renders.reserve(self.engine.view_cache_bytes(view, [mode], rgb=True) + self.limits.render_transient_bytes)
        cache = self.engine.render_view(view, modes=[mode], rgb=True)
        compact_tensors(cache, self._shared)
        self._renders.put(key, cache)
        return cache, False

    def query_view(self, key: str, view: Any, texts: list[str], mode: str) -> tuple[Any, Any]:
        """Render (or reuse) a camera and answer ``texts`` in it under one hold of the lock:
        -> (ViewCache, QueryResult)."""
        with self.lock:
            cache, _ = self._render_locked(key, view, mode)
            return cache, self.engine.query(cache, texts, mode=mode)

    def render_and_query(self, key: str, view: Any, texts: list[str], mode: str) -> tuple[Any, list[dict]]:
        """A query request's engine work under one hold of the lock, so that concurrent requests
        finish one after another: with two holds (render, then query) every queued render ran
        before any query, and all 50 requests of a burst finished together at its end. The PNG
        encoding runs outside the lock."""
        with self.lock:
            cache, _ = self._render_locked(key, view, mode)
            result = self.engine.query(cache, texts, mode=mode)
            # Node mode: which nodes answered (cheap: one score per node).
            answers = self.engine.node_answers(texts) if QUERY_MODES[mode].needs_tree else []
        results = self._results(cache, texts, result)
        for rec, answer in zip(results, answers):
            rec["nodes"], rec["level"] = answer.nodes, answer.level
        return cache, results

    def _results(self, view_cache: Any, texts: list[str], result: Any) -> list[dict]:
        """Per query: the protocol's mask and localization and the heatmap overlay, the same
        functions ``n2f2 query`` writes its files with (:mod:`n2f2.query.outputs`), as PNGs."""
        from ..query.maps import LANGSPLAT_THRESHOLD, flat_warning, localization_point
        from ..query.outputs import heatmap_overlay, relevancy_colors, segment

        rel = result.relevancy.float().cpu().numpy()  # [Q, H, W]
        rgb = view_cache.rgb.float().cpu().numpy()  # [H, W, 3]
        labels = result.chosen_labels
        out = []
        for qi, text in enumerate(texts):
            r = np.ascontiguousarray(rel[qi], dtype=np.float32)
            box = self.box_pixels(r.shape[1])
            mask = segment(r, box, LANGSPLAT_THRESHOLD)
            x, y = localization_point(r, box)
            heat = relevancy_colors(r)
            mask_rgba = np.zeros(mask.shape + (4,), np.uint8)
            mask_rgba[mask] = (255, 255, 255, 255)
            rec = {
                "query": text,
                "max_relevancy": float(r.max()),
                "localization": [x, y],
                "mask_area": int(mask.sum()),
                "mask_png": png_base64(mask_rgba),
                "overlay_png": png_base64(heatmap_overlay(rgb, r, heat)),
                "relevancy_png": png_base64(heat),
                "chosen_scale": labels[qi],
            }
            warning = flat_warning(r)
            if warning is not None:
                rec["warning"] = warning
            out.append(rec)
        return out

    def selection_ply(self, text: str, mode: str, threshold: Optional[float]) -> tuple[bytes, int]:
        with self.lock:
            mask = self.engine.select(text, threshold=threshold, mode=mode)
            n = int(mask.sum())
            if n == 0:
                raise ApiError(404, f"no Gaussian is selected by {text!r}; lower the threshold")
            with tempfile.TemporaryDirectory() as tmp:
                path = Path(tmp) / "selection.ply"
                self.engine.export_selection(mask, path)
                return path.read_bytes(), n


# ----------------------------------------------------------------------------- the app
def create_app(viewer: Viewer):
    from fastapi import FastAPI
    from fastapi.exceptions import RequestValidationError
    from fastapi.responses import FileResponse, JSONResponse, Response
    from fastapi.staticfiles import StaticFiles
    from starlette.exceptions import HTTPException as StarletteHTTPException

    app = FastAPI(title="n2f2 viewer", docs_url=None, redoc_url=None, openapi_url=None)
    limits = viewer.limits

    def error(status: int, message: str) -> JSONResponse:
        return JSONResponse({"error": message}, status_code=status)

    @app.exception_handler(ApiError)
    async def _api_error(_: Request, exc: ApiError):
        return error(exc.status, exc.message)

    @app.exception_handler(N2F2Error)
    async def _user_error(_: Request, exc: N2F2Error):
        return error(422, str(exc))

    @app.exception_handler(StarletteHTTPException)
    async def _http_error(_: Request, exc: StarletteHTTPException):
        return error(exc.status_code, str(exc.detail))

    @app.exception_handler(RequestValidationError)
    async def _validation_error(_: Request, exc: RequestValidationError):
        return error(422, "invalid request")

    @app.exception_handler(Exception)
    async def _internal_error(_: Request, exc: Exception):  # never leak a traceback
        return error(500, f"internal error ({type(exc).__name__})")

    async def json_body(request: Request) -> dict:
        """Read at most ``max_body_bytes`` (also when Content-Length lies or is absent)."""
        declared = request.headers.get("content-length")
        if declared is not None:
            digits = declared.strip()
            if not (digits.isascii() and digits.isdigit()):
                raise ApiError(400, "bad Content-Length header")
            if int(declared) > limits.max_body_bytes:
                raise ApiError(413, f"request body too large: at most {limits.max_body_bytes} bytes")
        body = bytearray()
        async for chunk in request.stream():
            body.extend(chunk)
            if len(body) > limits.max_body_bytes:
                raise ApiError(413, f"request body too large: at most {limits.max_body_bytes} bytes")
        try:
            data = json.loads(body.decode("utf-8"))
        except RecursionError:
            raise ApiError(400, "request body is nested too deeply") from None
        except ValueError:  # bad UTF-8, bad JSON, or an integer literal past Python's digit limit
            raise ApiError(400, "request body is not valid JSON") from None
        if not isinstance(data, dict):
            raise ApiError(400, "request body must be a JSON object")
        return data

    @app.get("/")
    def index():
        return FileResponse(STATIC_DIR / "index.html")

    app.mount("/static", StaticFiles(directory=STATIC_DIR), name="static")

    @app.get("/api/scene")
    def scene_info():
        scene = viewer.scene
        views = [
            {"index": i, "name": name, "width": cam.width, "height": cam.height, "orbit": viewer.orbit.orbit_of(cam)}
            for i, (name, cam) in enumerate(zip(scene.image_names, scene.cameras))
        ]
        return {
            "views": views,
            "modes": list(viewer.modes),
            "encoder": viewer.encoder_description(),
            "limits": {
                "max_queries": limits.max_queries,
                "max_query_chars": limits.max_query_chars,
                "max_body_bytes": limits.max_body_bytes,
            },
        }

    # Plain (sync) handlers run in FastAPI's thread pool, so the event loop stays free while
    # the engine works; the Viewer's lock keeps the engine single-threaded.
    @app.post("/api/render")
    async def render(request: Request):
        data = await json_body(request)
        key, view = viewer.parse_camera(data.get("camera", {"view": 0}))
        from starlette.concurrency import run_in_threadpool

        t0 = time.perf_counter()
        cache, cached = await run_in_threadpool(viewer.render, key, view)
        rgb = cache.rgb.float().cpu().numpy()
        return {
            "rgb_png": png_base64(rgb),
            "width": cache.width,
            "height": cache.height,
            "cached": cached,
            "timing_ms": 1000 * (time.perf_counter() - t0),
        }

    @app.post("/api/query")
    async def query(request: Request):
        from starlette.concurrency import run_in_threadpool

        data = await json_body(request)
        texts = viewer.parse_queries(data.get("queries"))
        mode = viewer.parse_mode(data.get("mode"))
        key, view = viewer.parse_camera(data.get("camera", {"view": 0}))
        t0 = time.perf_counter()
        cache, results = await run_in_threadpool(viewer.render_and_query, key, view, texts, mode)
        return {
            "rgb_png": png_base64(cache.rgb.float().cpu().numpy()),
            "width": cache.width,
            "height": cache.height,
            "mode": mode,
            "box_size": viewer.box_pixels(cache.width),
            "results": results,
            "timing_ms": 1000 * (time.perf_counter() - t0),
        }

    @app.post("/api/selection")
    async def selection(request: Request):
        from starlette.concurrency import run_in_threadpool

        data = await json_body(request)
        text = viewer.parse_queries(data.get("query"))[0]
        mode = viewer.parse_mode(data.get("mode"))
        threshold = data.get("threshold")
        if threshold is not None:
            threshold = finite_number(threshold)
            if threshold is None or not 0.0 <= threshold <= 1.0:
                raise ApiError(422, "'threshold' must be a number in [0, 1] or null")
        payload, n = await run_in_threadpool(viewer.selection_ply, text, mode, threshold)
        return Response(
            payload,
            media_type="application/octet-stream",
            headers={"Content-Disposition": 'attachment; filename="selection.ply"', "X-Selected-Gaussians": str(n)},
        )

    return app


def json_error_protocol() -> type:
    """uvicorn's h11 protocol, answering the requests its parser refuses (a non-numeric
    Content-Length, a garbled request line or header) with a JSON error body instead of
    uvicorn's plain text, so every malformed request gets ``{"error": ...}`` and a 4xx."""
    from uvicorn.protocols.http.h11_impl import H11Protocol

    class JsonErrorH11Protocol(H11Protocol):
        def send_400_response(self, msg: str) -> None:
            import h11

            body = json.dumps({"error": f"malformed HTTP request ({msg.rstrip('.')})"}).encode()
            headers = [
                (b"content-type", b"application/json"),
                (b"content-length", str(len(body)).encode()),
                (b"connection", b"close"),
            ]
            for data in (
                self.conn.send(h11.Response(status_code=400, headers=headers, reason=b"Bad Request")),
                self.conn.send(h11.Data(data=body)),
                self.conn.send(h11.EndOfMessage()),
            ):
                if data:
                    self.transport.write(data)
            self.transport.close()

    return JsonErrorH11Protocol


def api_server(viewer: Viewer, host: str = HOST, port: int = API_PORT) -> Any:
    """A ``uvicorn.Server`` for the JSON API (and the 2D page) of ``viewer``; ``server.run()``
    blocks, so callers run it in a thread beside the 3D viewer."""
    import uvicorn

    # Resident memory follows the view cache: glibc's dynamic thresholds, raised by loading a
    # run, kept a render's freed bands in the heap (~66 MB above the cache; ~15 MB with this).
    return_freed_blocks()

    config = uvicorn.Config(create_app(viewer), host=host, port=port, log_level="warning", http=json_error_protocol())
    return uvicorn.Server(config)
