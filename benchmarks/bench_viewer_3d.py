"""Per-query latency of the 3D viewer: from "query submitted" to the new splat colours delivered
to a browser's websocket.

    python benchmarks/bench_viewer_3d.py --gaussians 1000000          # synthetic run, D = 128
    python benchmarks/bench_viewer_3d.py --run RUN_DIR                # an existing trained run

Without ``--run`` it writes a synthetic run into ``--out`` (default: a temporary folder): a small
demo scene (6 views, for the cameras), ``--gaussians`` random Gaussians spread over the scene's
box (SH degree 0) and a feature field with the default architecture (``FieldConfig()``:
TriPlane 128^2 x 32, MLP 256, D = 128) and random weights, including W; its text encoder is the
demo's (all-MiniLM-L6-v2), so queries are encoded for real. Relevancy values are meaningless;
the work per query is the real one.

It then starts the viewer as ``n2f2 view`` does (:func:`n2f2.viewer.commands.launch`, JSON API
off), connects a plain websocket client speaking viser's protocol (it stands in for the browser
and receives every byte the browser would), and prints:

* one-time costs: splat conversion, the initial splat buffer reaching the client, and the
  per-Gaussian features the engine computes once (field at every centre, Theta~, score cache);
* per query (a new text each time, so the text encoder runs): relevancy (engine), colours,
  buffer handed to viser, and the time until the client has received the new buffer;
* a threshold change in the "selection" display (recolour only), and one explicit-mode query.

Set ``OMP_WAIT_POLICY=PASSIVE`` as ``n2f2 view`` does (the CLI sets it for the viewer); on a
shared machine spin-waiting OpenMP threads make every torch call several times slower.
"""

from __future__ import annotations

import argparse
import os
import resource
import tempfile
import threading
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # as the CLI does for `n2f2 view`
os.environ.setdefault("HF_HUB_OFFLINE", "1")

import numpy as np  # noqa: E402

QUERIES = ["teapot", "lid of the teapot", "red mug", "bag of cookies", "plate of fruit", "sofa cushion",
           "floor lamp", "the handle of the mug"]


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def make_synthetic_run(out: Path, num: int, seed: int = 0) -> Path:
    """A run folder (field.pt, gaussians.ply) with ``num`` random Gaussians over a demo scene."""
    import torch

    from n2f2.data.synthetic import generate_demo_scene
    from n2f2.field import FieldConfig, NestedField, save_field
    from n2f2.gaussians import write_ply
    from n2f2.gaussians.model import Gaussians

    scene = out / "scene"
    if not (scene / "scene.json").is_file():
        generate_demo_scene(scene, num_views=6, width=80, height=60, seed=seed, show_progress=False)
    run = out / "run"
    run.mkdir(parents=True, exist_ok=True)
    g = torch.Generator().manual_seed(seed)
    lo, hi = torch.tensor([-3.0, -3.0, 0.0]), torch.tensor([3.0, 3.0, 1.4])
    means = lo + (hi - lo) * torch.rand(num, 3, generator=g)
    gaussians = Gaussians(means, torch.randn(num, 4, generator=g), torch.full((num, 3), -4.0) +
                          0.3 * torch.randn(num, 3, generator=g), torch.randn(num, generator=g),
                          torch.randn(num, 1, 3, generator=g))
    write_ply(run / "gaussians.ply", gaussians)
    torch.manual_seed(seed)
    field = NestedField(FieldConfig(), 384, lo.numpy(), hi.numpy())
    with torch.no_grad():
        field.W.normal_(0.0, 0.05)  # the trained W is not zero; a zero W gives relevancy 0.5 everywhere
    save_field(run / "field.pt", field, {"encoder_spec": {"name": "captions", "embed_dim": 384},
                                         "scene": str(scene)})
    return run


class SocketClient:
    """A websocket client of the viser server that records (arrival time, size) of every frame."""

    def __init__(self, port: int):
        import viser
        from websockets.sync.client import connect

        self.ws = connect(f"ws://127.0.0.1:{port}", subprotocols=[f"viser-v{viser.__version__}"],
                          max_size=None, compression=None, open_timeout=60)
        self.frames: list[tuple[float, int]] = []
        self.cond = threading.Condition()
        threading.Thread(target=self._receive, daemon=True).start()

    def _receive(self) -> None:
        try:
            for message in self.ws:
                with self.cond:
                    self.frames.append((time.perf_counter(), len(message)))
                    self.cond.notify_all()
        except Exception:
            pass

    def wait_for(self, min_bytes: int, after: float, timeout: float = 120.0) -> float:
        """Arrival time of the first frame of at least ``min_bytes`` that came after ``after``."""
        deadline = time.perf_counter() + timeout
        with self.cond:
            while True:
                for t, n in self.frames:
                    if t >= after and n >= min_bytes:
                        return t
                left = deadline - time.perf_counter()
                if left <= 0:
                    raise TimeoutError(f"no frame of {min_bytes} bytes within {timeout} s")
                self.cond.wait(left)

    def close(self) -> None:
        self.ws.close()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--run", default=None, help="an existing trained run (default: build a synthetic one)")
    ap.add_argument("--scene", default=None, help="scene folder of --run, if not the recorded one")
    ap.add_argument("--gaussians", type=int, default=1_000_000, help="synthetic run size (default 1000000)")
    ap.add_argument("--out", default=None, help="where to write the synthetic run (default: a temp folder)")
    ap.add_argument("--queries", type=int, default=5, help="distinct queries to time (default 5)")
    args = ap.parse_args()

    import torch

    from n2f2.viewer.commands import launch
    from n2f2.viewer.splat_colors import splat_arrays, turbo_lut

    print(f"torch threads {torch.get_num_threads()}, OMP_WAIT_POLICY={os.environ.get('OMP_WAIT_POLICY')}")
    tmp = None
    if args.run is None:
        if args.out is None:
            tmp = tempfile.TemporaryDirectory(prefix="bench_viewer_3d_")
        out = Path(args.out or tmp.name)
        t = time.perf_counter()
        run = make_synthetic_run(out, args.gaussians)
        print(f"synthetic run ({args.gaussians:,} Gaussians, D = 128) written in "
              f"{time.perf_counter() - t:.1f} s: {run}")
    else:
        run = Path(args.run)

    t = time.perf_counter()
    running = launch(run, port=0, api_port=None, scene=args.scene, warm=False)
    t_launch = time.perf_counter() - t
    s = running.splats
    engine = running.viewer.engine
    n = s.num
    t = time.perf_counter()
    splat_arrays(engine.gaussians)
    t_convert = time.perf_counter() - t
    print(f"viewer started in {t_launch:.1f} s (engine load + splats + frustums; the splat conversion "
          f"alone {t_convert:.2f} s) for {n:,} Gaussians, field D = {engine.dim}, step {engine.step}")

    t = time.perf_counter()
    client = SocketClient(running.viser.get_port())
    arrived = client.wait_for(32 * n, after=0.0)
    print(f"initial splat buffer ({32 * n / 2**20:.1f} MB) received {arrived - t:.2f} s after connecting")

    # One-time per-Gaussian work (what the viewer's background warm-up does).
    with running.viewer.lock:
        t0 = time.perf_counter()
        engine.encode(engine.config.negatives + engine.config.canonical)
        t1 = time.perf_counter()
        _ = engine.theta
        t2 = time.perf_counter()
        _ = engine.theta_tilde
        t3 = time.perf_counter()
        engine.gaussian_cache("composite")
        t4 = time.perf_counter()
    turbo_lut()  # the colour map (imports matplotlib), as the viewer's warm-up does
    s.ready.set()
    print(f"one-time: text encoder {t1 - t0:.2f} s, field at {n:,} centres {t2 - t1:.2f} s, Theta~ "
          f"{t3 - t2:.2f} s, composite score cache {t4 - t3:.2f} s; peak RSS {peak_rss_mb():.0f} MB")

    def timed_query(text: str, mode: str = "composite") -> tuple[float, float, object]:
        if s.gui_mode.value != mode:
            t_switch = time.perf_counter()
            s.gui_mode.value = mode  # re-runs the last query in the new mode (not timed)
            client.wait_for(32 * n, after=t_switch)  # its colours must not count as this query's
        s.gui_text.value = text
        t0 = time.perf_counter()
        s.gui_run.value = True  # the Query button's callback, synchronously
        t_server = time.perf_counter() - t0
        t_client = client.wait_for(32 * n, after=t0) - t0
        return t_server, t_client, s.timing

    print(f"\nper query (composite), {n:,} Gaussians, {32 * n / 2**20:.1f} MB per recolour:")
    received = []
    for text in QUERIES[: args.queries]:
        t_server, t_client, tm = timed_query(text)
        received.append(t_client)
        print(f"  {text!r:28s} relevancy {1000 * tm.relevancy:6.0f} ms, colours {1000 * tm.colors:5.0f} ms, "
              f"buffer to viser {1000 * tm.send:5.0f} ms | server {1000 * t_server:6.0f} ms, "
              f"received by the client {1000 * t_client:6.0f} ms")
    print(f"  median received: {1000 * float(np.median(received)):.0f} ms, max {1000 * max(received):.0f} ms")

    s.gui_display.value = "selection"
    t0 = time.perf_counter()
    s.gui_threshold.value = 0.6
    t_server = time.perf_counter() - t0
    t_client = client.wait_for(32 * n, after=t0) - t0
    print(f"threshold change (selection display): colours {1000 * s.timing.colors:.0f} ms, server "
          f"{1000 * t_server:.0f} ms, received {1000 * t_client:.0f} ms")
    s.gui_display.value = "heatmap"

    t0 = time.perf_counter()
    with running.viewer.lock:
        engine.gaussian_cache("explicit")
    t_cache = time.perf_counter() - t0
    t_server, t_client, tm = timed_query("wooden table", mode="explicit")
    print(f"explicit mode: one-time score cache {t_cache:.1f} s; query relevancy {1000 * tm.relevancy:.0f} ms, "
          f"received {1000 * t_client:.0f} ms; peak RSS {peak_rss_mb():.0f} MB")

    client.close()
    running.stop()
    if tmp is not None:
        tmp.cleanup()


if __name__ == "__main__":
    main()
