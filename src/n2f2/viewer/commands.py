"""``n2f2 view RUN_DIR``: the 3D viewer (viser, ``--port``) and the JSON API with the 2D page
(FastAPI, ``--api-port``) in one process, over one query engine."""

from __future__ import annotations

import argparse
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Optional

from ..validate import nonneg_float, port_number, positive_int

if TYPE_CHECKING:
    from .server import Viewer
    from .splats import SplatViewer

LOCAL_HOSTS = ("127.0.0.1", "localhost", "::1")


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
    host: str = "127.0.0.1",
    port: int = 7007,
    api_port: Optional[int] = 7008,
    scene: Optional[str] = None,
    limits: Any = None,
    export_dir: Optional[str | Path] = None,
    warm: bool = True,
) -> RunningViewer:
    """Load the run once and start the 3D viewer on ``port`` and (unless ``api_port`` is None)
    the JSON API on ``api_port``; returns when both accept connections. Port 0 = any free port."""
    import viser

    from ..errors import InputError
    from ..query.engine import QueryEngine
    from .server import Viewer, ViewerLimits, api_server
    from .splats import SplatViewer

    engine = QueryEngine.from_run(run_dir, scene=scene)
    viewer = Viewer(engine, limits or ViewerLimits())
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
    from .server import ViewerLimits

    if args.host not in LOCAL_HOSTS:
        print(
            f"warning: serving on {args.host}: the viewer has no authentication; "
            "anyone who can reach this address can query the scene"
        )
    limits = ViewerLimits(
        max_body_bytes=args.max_body_bytes, max_queries=args.max_queries, render_cache_bytes=int(args.cache_mb * 2**20)
    )
    running = launch(
        args.run_dir,
        host=args.host,
        port=args.port,
        api_port=None if args.no_api else args.api_port,
        scene=args.scene,
        limits=limits,
        export_dir=args.export_dir,
    )
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
    p = subparsers.add_parser(
        "view",
        help="start the local viewer on a trained run: 3D splats in the browser + JSON API",
        description="Serve the run's Gaussians as splats in the browser (viser, --port): click a "
        "camera frustum to jump to a training view, type queries to recolour the Gaussians "
        "by relevancy or dim everything outside the selection, render the current view's "
        "2D relevancy / mask / localisation on the server, export the selection as PLY. "
        "Beside it, on --api-port, the JSON API (POST /api/query, /api/render, "
        "/api/selection; GET /api/scene) and the 2D page at /.",
    )
    p.add_argument("run_dir", help="a trained run folder (field.pt, gaussians.ply)")
    p.add_argument(
        "--port", type=port_number, default=7007, help="3D viewer port (default: 7007; the next free one if taken)"
    )
    p.add_argument("--api-port", type=port_number, default=7008, help="JSON API and 2D page port (default: 7008)")
    p.add_argument("--no-api", action="store_true", help="serve only the 3D viewer")
    p.add_argument("--host", default="127.0.0.1", help="bind address of both (default: 127.0.0.1, this machine only)")
    p.add_argument("--scene", default=None, help="scene folder, if not the one recorded in the run")
    p.add_argument("--export-dir", default=None, help="where 'Export selection' writes (default: the run folder)")
    p.add_argument(
        "--cache-mb",
        type=nonneg_float,
        default=512,
        help="memory for cached renders, least recently used out first (default: 512; 0: none)",
    )
    p.add_argument("--max-queries", type=positive_int, default=8, help="queries per request (default: 8)")
    p.add_argument("--max-body-bytes", type=positive_int, default=16384, help="request size cap (default: 16384)")
    p.set_defaults(func=_cmd_view)
