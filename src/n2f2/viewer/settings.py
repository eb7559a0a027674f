"""Settings of ``n2f2 view``: its ports and address and the servers' limits. Light to import
(no web framework): the command line reads its defaults from here."""

from __future__ import annotations

from dataclasses import dataclass

from ..config import option
from ..validate import positive_int

VIEWER_PORT = 7007  # the 3D viewer (viser), ``--port``
API_PORT = 7008  # the JSON API and the 2D page, ``--api-port``
HOST = "127.0.0.1"  # bind address of both: this machine only


@dataclass(frozen=True)
class ViewerLimits:
    """Bounds on what a request may ask and on the render cache. Fields declared with option()
    are flags of ``n2f2 view``."""

    max_body_bytes: int = option(16 * 1024, help="request size cap", type=positive_int)
    max_queries: int = option(8, help="queries per request", type=positive_int)
    max_query_chars: int = 200
    # Bytes of cached renders (LRU), the render in flight included: before a view is rendered,
    # old entries make room for what it will keep plus ``render_transient_bytes``. One 640x480
    # view of a D = 128 field keeps ~160 MB in composite mode and ~470 MB in explicit mode; a
    # render larger than the bound is not cached. ``n2f2 view --cache-mb`` sets it in MiB.
    render_cache_bytes: int = 512 * 2**20
    # Working memory of one render and its answer beyond what the view keeps: the rasterizer's
    # bands (``rasterize_in_bands``, ~16 MB), the score cache's blocks (~32 MB) and the
    # per-query maps and PNGs (measured on a 640x480 view, D = 128: ~60 MB rendering, ~30 MB
    # answering one query; see docs/measurements.md).
    render_transient_bytes: int = 96 * 2**20
