"""Memory of the JSON API's render cache while orbiting: peak RSS against the configured bound.

    python benchmarks/bench_viewer_cache.py --run RUN_DIR [--views 200] [--width 640 --height 480]
                                            [--cache-mb 256] [--mode composite|explicit]

Loads the run as ``n2f2 view`` does, resizes the scene's cameras to ``--width x --height``
(same field of view; orbit cameras take the intrinsics of view 0), serves the JSON API
(:func:`n2f2.viewer.server.api_server`) on a free loopback port in this process, and asks for
``--views`` distinct orbit cameras one after another (``POST /api/query`` with one query, so
each request renders and caches a view in ``--mode``). A sampling thread reads this process's
resident memory (``/proc/self/status`` VmRSS) every 20 ms.

Prints the baseline (run loaded, per-Gaussian features and text encoder ready, the compiled
rasterizer loaded by one 16x16 render), the peak, the cache's own byte count and entries at the end, one entry's size, and
what the previous 32-entry count bound would have held at this size.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import socket
import threading
import time
import urllib.request

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # as the CLI does for `n2f2 view`
os.environ.setdefault("HF_HUB_OFFLINE", "1")


def rss_mb() -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


class PeakRss:
    """Peak of VmRSS sampled every ``interval`` seconds in a background thread."""

    def __init__(self, interval: float = 0.02):
        self.peak = rss_mb()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, args=(interval,), daemon=True)
        self._thread.start()

    def _run(self, interval: float) -> None:
        while not self._stop.wait(interval):
            self.peak = max(self.peak, rss_mb())

    def stop(self) -> float:
        self._stop.set()
        self._thread.join()
        return max(self.peak, rss_mb())


def resized(scene, width: int, height: int):
    """The scene with every camera resampled to ``width x height`` (same field of view)."""
    from n2f2.cameras import Camera

    cams = []
    for c in scene.cameras:
        sx, sy = width / c.width, height / c.height
        cams.append(Camera(c.fx * sx, c.fy * sy, c.cx * sx, c.cy * sy, width, height, R=c.R, t=c.t))
    return dataclasses.replace(scene, cameras=cams, _cache={})


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--run", required=True, help="a trained run folder")
    ap.add_argument("--scene", default=None, help="its scene folder, if not the recorded one")
    ap.add_argument("--views", type=int, default=200, help="distinct orbit cameras (default 200)")
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--cache-mb", type=float, default=256.0, help="render cache bound (default 256)")
    ap.add_argument("--mode", default="composite", choices=("composite", "explicit"))
    args = ap.parse_args()

    import torch

    from n2f2.query.engine import QueryEngine
    from n2f2.viewer.server import Viewer, ViewerLimits, api_server

    engine = QueryEngine.from_run(args.run, scene=args.scene)
    engine.scene = resized(engine.scene, args.width, args.height)
    limits = ViewerLimits(render_cache_bytes=int(args.cache_mb * 2**20))
    viewer = Viewer(engine, limits)
    with viewer.lock:  # per-field data every render needs, the encoder and the compiled
        engine.encode(["teapot"])  # rasterizer (loaded by a first, 16x16 render): the model's own size
        _ = engine.theta_tilde if args.mode == "composite" else engine.theta
        engine.render_view(engine.scene.cameras[0].scaled(16, 16), modes=[args.mode], rgb=True)
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    server = api_server(viewer, "127.0.0.1", port)
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    while not server.started:
        time.sleep(0.05)
    url = f"http://127.0.0.1:{port}/api/query"
    baseline = rss_mb()
    print(f"{engine.gaussians.num:,} Gaussians, D = {engine.dim}, {args.width}x{args.height}, mode {args.mode}, "
          f"cache bound {args.cache_mb:.0f} MB, torch threads {torch.get_num_threads()}")
    print(f"baseline RSS (run loaded, features, encoder and rasterizer ready): {baseline:.0f} MB")

    sampler = PeakRss()
    t0 = time.perf_counter()
    times = []
    for i in range(args.views):
        body = {"queries": ["teapot"], "mode": args.mode,
                "camera": {"orbit": {"azimuth": 360.0 * i / args.views, "elevation": 15.0 + 20.0 * (i % 3),
                                     "radius": 3.0}}}
        req = urllib.request.Request(url, data=json.dumps(body).encode(), headers={"Content-Type": "application/json"})
        t = time.perf_counter()
        with urllib.request.urlopen(req, timeout=600) as resp:
            assert resp.status == 200
            resp.read()
        times.append(time.perf_counter() - t)
        if (i + 1) % 25 == 0:
            print(f"  {i + 1} views, RSS {rss_mb():.0f} MB (peak {sampler.peak:.0f}), cache "
                  f"{viewer._renders.nbytes / 2**20:.0f} MB in {len(viewer._renders)} entries", flush=True)
    wall = time.perf_counter() - t0
    peak = sampler.stop()
    server.should_exit = True
    thread.join(timeout=10)

    cache = viewer._renders
    entry = cache.nbytes / max(len(cache), 1)
    print(f"{args.views} views in {wall:.0f} s ({1000 * wall / args.views:.0f} ms per request, "
          f"median {1000 * sorted(times)[len(times) // 2]:.0f} ms)")
    print(f"cache at the end: {len(cache)} entries, {cache.nbytes / 2**20:.0f} MB "
          f"(bound {args.cache_mb:.0f} MB; one entry {entry / 2**20:.1f} MB)")
    print(f"peak RSS {peak:.0f} MB = baseline {baseline:.0f} MB + {peak - baseline:.0f} MB "
          f"(bound {args.cache_mb:.0f} MB: cached renders and the request in flight)")
    print(f"the previous 32-entry bound would have held {32 * entry / 2**20:.0f} MB of renders at this size")


if __name__ == "__main__":
    main()
