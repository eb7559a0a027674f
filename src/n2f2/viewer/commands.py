"""``n2f2 view RUN_DIR``: start the local viewer."""

from __future__ import annotations

import argparse


def _cmd_view(args: argparse.Namespace) -> int:
    from .server import ViewerLimits, serve

    if args.host not in ("127.0.0.1", "localhost", "::1"):
        print(f"warning: serving on {args.host}: the viewer has no authentication; "
              "anyone who can reach this address can query the scene")
    limits = ViewerLimits(max_body_bytes=args.max_body_bytes, max_queries=args.max_queries)
    serve(args.run_dir, host=args.host, port=args.port, scene=args.scene, limits=limits)
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "view", help="start the local web viewer on a trained run",
        description="Serve a web page to orbit the scene, type queries and see relevancy, "
                    "segmentation, localization and the 3D selection; plus a JSON API "
                    "(POST /api/query, /api/render, /api/selection; GET /api/scene).")
    p.add_argument("run_dir", help="a trained run folder (field.pt, gaussians.ply)")
    p.add_argument("--port", type=int, default=7007, help="port (default: 7007)")
    p.add_argument("--host", default="127.0.0.1", help="bind address (default: 127.0.0.1, this machine only)")
    p.add_argument("--scene", default=None, help="scene folder, if not the one recorded in the run")
    p.add_argument("--max-queries", type=int, default=8, help="queries per request (default: 8)")
    p.add_argument("--max-body-bytes", type=int, default=16384, help="request size cap (default: 16384)")
    p.set_defaults(func=_cmd_view)
