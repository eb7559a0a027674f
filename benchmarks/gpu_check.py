"""The GPU path end to end, in one command (about 8 minutes on one H100 or H200).

Three steps, each a child process timed on its own, with the GPU's peak memory in use during it
(``nvidia-smi``, polled every 0.25 s: the CUDA context included):

1. ``cuda_tests``: the test suite's CUDA tests (``pytest -m "not slow" -k cuda``).
2. ``demo``: ``n2f2 demo --preset paper --device cuda`` (generated scene, gsplat fit, segments,
   field training, evaluation); the per-stage seconds of its ``stages.json`` files are copied.
3. ``sam_clip``: full-size SAM ViT-H + CLIP ViT-B/16 with random weights
   (``make_fullsize_models.py``, unless ``--models`` holds them) through ``n2f2 segments`` on
   five photos (``bench_fullsize_models.py``): seconds per part and per photo, peak memory.

Writes ``OUT/gpu_check.json`` (and each step's log beside it) and prints a summary::

    bash benchmarks/gpu_check.sh [--out DIR] [--photos DIR] [--models DIR]
    bash benchmarks/gpu_check.sh --dry-run     # the same steps on the CPU at toy sizes

``--dry-run`` checks the script where no GPU is: ``--device cpu``, the demo at 4 views of 64 x 48
with the cpu preset and 100 steps per stage, and tiny random SAM and CLIP models instead of the
full-size ones, on the photos shrunk to 192 x 128.
"""

from __future__ import annotations

import argparse
import glob
import json
import os
import platform
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
N2F2 = [sys.executable, "-c", "import sys; from n2f2.cli import main; sys.exit(main())"]
PHOTO_DIRS = [REPO.parent / "shared" / "data" / "plush-dog" / "images", REPO / ".gpu_photos"]


class GpuMemory:
    """The peak of ``nvidia-smi``'s memory.used (MiB) while the ``with`` block runs; None
    without nvidia-smi."""

    def __init__(self, period: float = 0.25) -> None:
        self.period, self.peak, self._stop = period, None, threading.Event()
        self._thread = threading.Thread(target=self._poll, daemon=True)

    def _read(self):
        try:
            out = subprocess.run(["nvidia-smi", "--query-gpu=memory.used", "--format=csv,noheader,nounits"],
                                 capture_output=True, text=True, timeout=5)
            return max(float(v) for v in out.stdout.split()) if out.returncode == 0 and out.stdout.split() else None
        except (OSError, ValueError, subprocess.TimeoutExpired):
            return None

    def _poll(self) -> None:
        while not self._stop.is_set():
            used = self._read()
            if used is not None:
                self.peak = used if self.peak is None else max(self.peak, used)
            self._stop.wait(self.period)

    def __enter__(self):
        if shutil.which("nvidia-smi"):
            self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join()


def run_step(name: str, cmd: list, out: Path, timeout: float, env=None) -> dict:
    """Run ``cmd``, its output into ``out/<name>.log``; seconds, exit status, peak GPU memory."""
    log = out / f"{name}.log"
    print(f"[{name}] {' '.join(map(str, cmd[:3]))} ... (log: {log})", flush=True)
    start = time.perf_counter()
    with GpuMemory() as mem, open(log, "w") as f:
        try:
            rc = subprocess.run([str(c) for c in cmd], stdout=f, stderr=subprocess.STDOUT, timeout=timeout,
                                cwd=REPO, env=env).returncode
        except subprocess.TimeoutExpired:
            rc = "timeout"
    seconds = round(time.perf_counter() - start, 1)
    tail = log.read_text(errors="replace").strip().splitlines()[-3:]
    print(f"[{name}] rc {rc}, {seconds} s, peak GPU memory {mem.peak} MiB", flush=True)
    return {"rc": rc, "seconds": seconds, "peak_gpu_memory_mib": mem.peak, "log": log.name, "tail": tail}


def stage_seconds(folder: Path) -> dict:
    """``{"<run>/<stage>": seconds}`` from every ``stages.json`` under ``folder``."""
    found = {}
    for path in sorted(glob.glob(str(folder / "**" / "stages.json"), recursive=True)):
        rel = Path(path).parent.relative_to(folder).as_posix()
        for stage, rec in json.loads(Path(path).read_text()).items():
            found[f"{rel}/{stage}" if rel != "." else stage] = rec.get("seconds")
    return found


def tiny_models(folder: Path) -> Path:
    """Tiny random SAM and CLIP folders under the names the full-size ones have (dry run)."""
    import torch
    from transformers import CLIPConfig, CLIPModel, CLIPTokenizer, SamConfig, SamModel

    torch.manual_seed(0)
    sam = SamConfig(
        vision_config=dict(image_size=64, patch_size=16, hidden_size=32, output_channels=16, num_hidden_layers=2,
                           num_attention_heads=2, mlp_dim=64, global_attn_indexes=[1], window_size=2,
                           num_pos_feats=8),
        prompt_encoder_config=dict(hidden_size=16, image_size=64, patch_size=16, mask_input_channels=4),
        mask_decoder_config=dict(hidden_size=16, num_hidden_layers=2, num_attention_heads=2, mlp_dim=32,
                                 iou_head_hidden_dim=16),
    )
    model = SamModel(sam)
    sys.path.insert(0, str(REPO / "benchmarks"))
    from make_fullsize_models import calibrate_sam  # masks that pass SAM's filters, as at full size

    calibrate_sam(model, iou_center=0.75)  # the tiny model: IoUs above 0.7
    model.mask_decoder.upscale_conv2.weight.data.mul_(1e3)  # and logits far from 0, so masks are stable
    model.save_pretrained(folder / "sam-vit-huge")
    clip = CLIPConfig(
        text_config=dict(vocab_size=8, hidden_size=32, intermediate_size=64, num_hidden_layers=2,
                         num_attention_heads=2, max_position_embeddings=77, bos_token_id=0, eos_token_id=1,
                         pad_token_id=1),
        vision_config=dict(image_size=32, patch_size=8, hidden_size=32, intermediate_size=64, num_hidden_layers=2,
                           num_attention_heads=2),
        projection_dim=16)
    CLIPModel(clip).save_pretrained(folder / "clip-vit-b-16")
    CLIPTokenizer().save_pretrained(folder / "clip-vit-b-16")
    return folder


def photos(given) -> list[Path]:
    for folder in [Path(given)] if given else PHOTO_DIRS:
        found = sorted(p for p in Path(folder).glob("*") if p.suffix.lower() in (".jpg", ".jpeg", ".png"))
        if len(found) >= 5:
            return found[:5]
    sys.exit(f"need 5 photos of one size: pass --photos DIR (looked in {', '.join(map(str, PHOTO_DIRS))})")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--dry-run", action="store_true", help="the same steps on the CPU at toy sizes")
    ap.add_argument("--out", type=Path, default=REPO / "gpu_check_out", help="output folder (default: %(default)s)")
    ap.add_argument("--photos", default=None, help="folder with the photos (the first 5 are used)")
    ap.add_argument("--models", type=Path, default=None, help="full-size model folders (default: made in OUT)")
    args = ap.parse_args(argv)

    import torch

    dry = args.dry_run
    if not dry and not torch.cuda.is_available():
        sys.exit("no CUDA device: run with --dry-run to check the script on the CPU")
    device = "cpu" if dry else "cuda"
    out = args.out.resolve()
    if out.exists():
        shutil.rmtree(out)
    out.mkdir(parents=True)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(REPO / "src"), os.environ.get("PYTHONPATH")])),
           "PYTHONUNBUFFERED": "1"}
    result: dict = {
        "dry_run": dry, "device": "cpu" if dry else torch.cuda.get_device_name(), "torch": torch.__version__,
        "cuda": torch.version.cuda, "python": platform.python_version(), "cpu_count": os.cpu_count(), "steps": {},
    }
    start = time.perf_counter()
    steps = result["steps"]

    steps["cuda_tests"] = run_step("cuda_tests", [sys.executable, "-m", "pytest", "tests/test_render.py", "-k", "cuda",
                                                  "-p", "no:cacheprovider", "-rs"], out, 300, env)

    demo = [*N2F2, "demo", "--out", out / "demo", "--device", device, "--quiet"]
    toy = ["--preset", "cpu", "--views", "4", "--width", "64", "--height", "48", "--fit-steps", "100",
           "--train-steps", "100"]
    demo += toy if dry else ["--preset", "paper"]
    steps["demo"] = run_step("demo", demo, out, 420, env)
    steps["demo"]["stages_s"] = stage_seconds(out / "demo")

    models = args.models
    if dry:
        models = tiny_models(out / "models")
    elif models is None:
        models = out / "models"
        steps["make_models"] = run_step("make_models", [sys.executable, REPO / "benchmarks/make_fullsize_models.py",
                                                        models], out, 300, env)
    images = photos(args.photos)
    if dry:  # the tiny models at a small size: same code, seconds on a CPU
        from PIL import Image

        small = out / "photos"
        small.mkdir()
        for p in images:
            Image.open(p).convert("RGB").resize((192, 128)).save(small / f"{p.stem}.png")
        images = sorted(small.glob("*.png"))
    bench = out / "sam_clip.json"
    steps["sam_clip"] = run_step("sam_clip", [sys.executable, REPO / "benchmarks/bench_fullsize_models.py", "--models",
                                              models, "--device", device, "--json", bench, "--clip-segments",
                                              "4" if dry else "100", "--images", *images], out, 480, env)
    if bench.is_file():
        b = json.loads(bench.read_text())
        keys = ("sam_image_encoder_s", "sam_mask_decoder_s", "sam_postprocess_s", "clip_crops_s", "clip_model_s",
                "total_s", "segments")
        steps["sam_clip"]["per_photo"] = [{k: r.get(k) for k in ("image", *keys)} for r in b.get("images", [])]
        steps["sam_clip"]["clip_at_n"] = b.get("clip_at_n")
        steps["sam_clip"]["cuda_max_allocated_mib"] = b.get("cuda_max_allocated_mib")
        steps["sam_clip"]["max_rss_mib"] = b.get("max_rss_mib")
    if dry:
        shutil.rmtree(out / "models", ignore_errors=True)
    result["total_s"] = round(time.perf_counter() - start, 1)
    (out / "gpu_check.json").write_text(json.dumps(result, indent=2))
    failed = [k for k, s in steps.items() if s["rc"] != 0]
    print(f"gpu_check: {len(steps) - len(failed)} of {len(steps)} steps passed in {result['total_s']} s"
          + (f"; failed: {', '.join(failed)}" if failed else "") + f" -> {out / 'gpu_check.json'}")
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
