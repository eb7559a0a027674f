"""``n2f2 view RUN_DIR``: the 3D viewer (viser, ``--port``) and the JSON API with the 2D page
(FastAPI, ``--api-port``) in one process, over one query engine."""

from __future__ import annotations

import argparse
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Optional

from ..config import add_config_options, config_overrides, field_default
from ..validate import nonneg_float, port_number
from .settings import API_PORT, HOST, VIEWER_PORT, ViewerLimits

if TYPE_CHECKING:
    from .server import Viewer
    from .splats import SplatViewer

LOCAL_HOSTS = ("127.0.0.1", "localhost", "::1")
LIMIT_FLAGS = ("max_queries", "max_body_bytes")  # the ViewerLimits fields that are flags of `n2f2 view`


@dataclass
class RunningViewer:
    """Both servers of ``n2f2 view``, started; :meth:`stop` shuts them down."""

    viewer: Viewer  # engine, lock, render cache
    viser: Any  # viser.ViserServer
    splats: SplatViewer
    api: Optional[Any] = None  # uvicorn.Server of the JSON API, None with --no-api
    api_thread: Optional[threading.Thread] = None

    @property
    def url(self) -> str:
        return f"http://{_url_host(self.viser.get_host())}:{self.viser.get_port()}"

    @property
    def api_url(self) -> Optional[str]:
        if self.api is None:
            return None
        return f"http://{_url_host(self.api.config.host)}:{self.api_port}"

    @property
    def api_port(self) -> Optional[int]:
        """The bound port (the requested one, or the one the OS chose for port 0)."""
        if self.api is None:
            return None
        for server in getattr(self.api, "servers", []) or []:
            for sock in server.sockets:
                return int(sock.getsockname()[1])
        return int(self.api.config.port)

    def stop(self) -> None:
        if self.api is not None:
            self.api.should_exit = True
            if self.api_thread is not None:
                self.api_thread.join(timeout=10)
        self.viser.stop()


def _url_host(host: str) -> str:
    return f"[{host}]" if ":" in host else host


def launch(
    run_dir: str | Path,
    *,
    host: str = HOST,
    port: int = VIEWER_PORT,
    api_port: Optional[int] = API_PORT,
    scene: Optional[str] = None,
    limits: Any = None,
    export_dir: Optional[str | Path] = None,
    warm: bool = True,
    full_res: bool = False,
    box_size: Any = None,
    decomposition: Optional[str | Path] = None,
) -> RunningViewer:
    """Load the run once and start the 3D viewer on ``port`` and (unless ``api_port`` is None)
    the JSON API on ``api_port``; returns when both accept connections. Port 0 = any free port.
    Views render at the downscale the run was trained at, or at the images' size with ``full_res``.
    ``box_size``: the protocol's mean filter (pixels or "scaled"; None: LangSplat's 30 px, as
    ``n2f2 query``'s) of the masks, the localisation and explicit mode's scale choice.
    ``decomposition``: the run's hierarchy (``n2f2 decompose``'s folder; None: RUN/decomposition
    when it exists), for the 3D viewer's hierarchy panel and the node mode; one given here must
    read back, or the viewer does not start."""
    import viser

    from ..errors import InputError
    from ..query.engine import QueryConfig, QueryEngine
    from .server import Viewer, api_server
    from .splats import SplatViewer

    config = QueryConfig(box_size=box_size, decomposition=None if decomposition is None else str(decomposition))
    engine = QueryEngine.from_run(run_dir, scene=scene, full_res=full_res, config=config)
    viewer = Viewer(engine, limits or ViewerLimits())
    if decomposition is not None and viewer.tree is None:
        _ = engine.tree  # the InputError saying what is missing
        raise InputError(Path(decomposition), viewer.tree_error or "cannot read the hierarchy")
    api = thread = None
    if api_port is not None:
        api = api_server(viewer, host=host, port=api_port)
        thread = threading.Thread(target=api.run, name="n2f2-api", daemon=True)
        thread.start()
        deadline = time.time() + 60
        while not api.started:
            if not thread.is_alive() or time.time() > deadline:
                api.should_exit = True
                raise InputError(
                    None,
                    f"cannot serve the JSON API on {host}:{api_port} "
                    "(port in use? choose another with --api-port, or --no-api)",
                )
            time.sleep(0.05)
    server = viser.ViserServer(host=host, port=port, label=f"n2f2 · {Path(run_dir).name}", verbose=False)
    try:
        splats = SplatViewer(viewer, server, export_dir=Path(export_dir) if export_dir else None, warm=warm)
    except BaseException:
        server.stop()
        if api is not None:
            api.should_exit = True
        raise
    return RunningViewer(viewer, server, splats, api, thread)


def _cmd_view(args: argparse.Namespace) -> int:
    if args.host not in LOCAL_HOSTS:
        print(
            f"warning: serving on {args.host}: the viewer has no authentication; "
            "anyone who can reach this address can query the scene"
        )
    limits = ViewerLimits(
        **config_overrides(args, ViewerLimits, LIMIT_FLAGS), render_cache_bytes=int(args.cache_mb * 2**20)
    )
    running = launch(
        args.run_dir,
        host=args.host,
        port=args.port,
        api_port=None if args.no_api else args.api_port,
        scene=args.scene,
        limits=limits,
        export_dir=args.export_dir,
        full_res=args.full_res,
        box_size=args.box_size,
        decomposition=args.decomposition,
    )
    if running.viewer.tree_error:
        print(f"warning: the run's hierarchy is not offered: {running.viewer.tree_error}")
    print(
        f"n2f2 viewer: 3D view on {running.url}"
        + ("" if running.api_url is None else f"; JSON API and 2D page on {running.api_url}")
        + "  (Ctrl+C to stop)"
    )
    try:
        while running.api_thread is None or running.api_thread.is_alive():
            time.sleep(0.5)
    except KeyboardInterrupt:
        pass
    finally:
        running.stop()
    return 0


def register(subparsers) -> None:
    from ..query.commands import add_decomposition_option, add_full_res_option, box_size_arg

    p = subparsers.add_parser(
        "view",
        help="start the local viewer on a trained run: 3D splats in the browser + JSON API",
        description="Serve the run's Gaussians as splats in the browser (viser, --port): click a "
        "camera frustum to jump to a training view, type queries to recolour the Gaussians "
        "by relevancy or dim everything outside the selection, render the current view's "
        "2D relevancy / mask / localisation on the server, export the selection as PLY; with the run's "
        "hierarchy (n2f2 decompose), colour the Gaussians by node per level, click one for its path, "
        "export a node. "
        "Beside it, on --api-port, the JSON API (POST /api/query, /api/render, "
        "/api/selection; GET /api/scene) and the 2D page at /.",
    )
    p.add_argument("run_dir", help="a trained run folder (field.pt, gaussians.ply)")
    p.add_argument(
        "--port",
        type=port_number,
        default=VIEWER_PORT,
        help=f"3D viewer port (default: {VIEWER_PORT}; the next free one if taken)",
    )
    p.add_argument(
        "--api-port", type=port_number, default=API_PORT, help=f"JSON API and 2D page port (default: {API_PORT})"
    )
    p.add_argument("--no-api", action="store_true", help="serve only the 3D viewer")
    p.add_argument("--host", default=HOST, help=f"bind address of both (default: {HOST}, this machine only)")
    p.add_argument("--scene", default=None, help="scene folder, if not the one recorded in the run")
    add_full_res_option(p)
    add_decomposition_option(p)  # the hierarchy panel and the node mode
    p.add_argument("--export-dir", default=None, help="where 'Export selection' writes (default: the run folder)")
    cache_mb = field_default(ViewerLimits, "render_cache_bytes") / 2**20
    p.add_argument(
        "--cache-mb",
        type=nonneg_float,
        default=cache_mb,
        help=f"memory for cached renders, least recently used out first (default: {cache_mb:g}; 0: none)",
    )
    add_config_options(p, ViewerLimits, LIMIT_FLAGS)  # None: ViewerLimits' own value
    p.add_argument(
        "--box-size",
        type=box_size_arg,
        default=None,
        help="protocol mean-filter size in pixels for masks and localisation, or 'scaled' = round(30 W / 986) "
        "(default 30, LangSplat's, as n2f2 query's: the same view and query give the same point)",
    )
    p.set_defaults(func=_cmd_view)
