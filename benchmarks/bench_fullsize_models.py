"""Full-size SAM ViT-H + CLIP ViT-B/16 through ``n2f2 segments``: time per image by part, memory.

Runs ``n2f2 segments --segmenter sam --sam-model DIR --encoder clip --clip-model DIR`` on real
photos, with the model folders that ``benchmarks/make_fullsize_models.py`` writes (random
weights, real sizes; see there)::

    python benchmarks/make_fullsize_models.py /tmp/fullsize_models
    python benchmarks/bench_fullsize_models.py --models /tmp/fullsize_models [--device cuda] \\
        [--json fullsize_models.json]

The scene is made in a temporary folder: copies of the photos (default: two of the plush-dog
capture in ``shared/data``), a nerfstudio ``transforms.json`` with one plausible pinhole camera
(focal length 0.8 x the image width, principal point at the centre) and near-identity poses
(the second camera 10 cm to the right), and a wall of 3D Gaussians 2 m in front of the cameras,
because ``n2f2 segments`` lifts every segment to 3D with the Gaussians' rendered depth.

The command runs in a child process (``n2f2.cli.main``, as the ``n2f2`` script does), so its
peak resident memory (``getrusage``, whole process: both models' weights included) and CPU
time are its own. Inside it, the time of each image is split into the SAM image encoder, the
mask decoder (all point batches), SAM's post-processing (upsampling, stability, NMS, small
regions, packing), making CLIP's masked crops, the CLIP image model, and rendering the depth
that lifting uses; "other" is the rest of the image's share of ``n2f2 segments`` (lifting,
writing the record, reading the next image; for the last image, fitting the quantiles).
Random SAM weights leave only about a dozen segments per image, so CLIP is also timed on
``--clip-segments`` (default 100) box-shaped segments of the first image, the count a real
image gives. Times on CUDA are taken after synchronising the device;
``torch.cuda.max_memory_allocated`` is reported there. Prints a Markdown table, writes JSON.

On the CPU each model part is also printed beside its floor, measured in the same process right
after the run: its multiply-accumulates (counted from the model folders' configs: SAM ViT-H's
encoder 3.27 TMAC at 1024 x 1024, the decoder 1.79 GMAC a point prompt and 1,024 prompts an
image, CLIP ViT-B/16 17.6 GMAC a crop) at the fp32 rate of a [4096, 1280] x [1280, 5120]
``torch.matmul`` on the same threads, so the ratio reads the same on any CPU.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
SAM_DIRS = {"sam": "sam-vit-huge", "sam2": "sam2.1-hiera-tiny"}  # --segmenter -> its folder in --models
PLUSH_DOG = REPO.parent / "shared" / "data" / "plush-dog" / "images"
DEFAULT_IMAGES = [PLUSH_DOG / "IMG_3496.jpg", PLUSH_DOG / "IMG_3497.jpg"]


# ----------------------------------------------------------------------------- scene
def make_scene(root: Path, images: list[Path]) -> Path:
    """Copies of ``images``, a nerfstudio transforms.json, and a Gaussian wall (gaussians.ply)."""
    import torch
    from PIL import Image

    from n2f2.cameras import Camera
    from n2f2.data.nerfstudio import write_transforms
    from n2f2.gaussians import Gaussians, rgb_to_sh, write_ply

    (root / "images").mkdir(parents=True)
    cameras, names = [], []
    for i, src in enumerate(images):
        with Image.open(src) as im:
            W, H = im.size
        shutil.copy(src, root / "images" / src.name)
        f = 0.8 * W
        cameras.append(Camera(f, f, W / 2, H / 2, W, H, R=np.eye(3), t=np.array([-0.1 * i, 0.0, 0.0])))
        names.append(f"images/{src.name}")
    write_transforms(root, cameras, names)
    # A wall at z = 2 (OpenCV: in front of the cameras), wider than every view, gently curved so
    # depth varies across the image.
    W, H = cameras[0].width, cameras[0].height
    half_w, half_h = 2.0 * (W / 2) / cameras[0].fx + 0.3, 2.0 * (H / 2) / cameras[0].fy + 0.2
    xs, ys = np.meshgrid(np.arange(-half_w, half_w, 0.08), np.arange(-half_h, half_h, 0.08))
    means = np.stack([xs.ravel(), ys.ravel(), 2.0 + 0.2 * np.sin(2.0 * xs.ravel())], axis=1)
    n = len(means)
    rgb = torch.full((n, 1, 3), 0.5)
    g = Gaussians(torch.as_tensor(means, dtype=torch.float32), torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1),
                  torch.full((n, 3), float(np.log(0.06))), torch.full((n,), 4.0), rgb_to_sh(rgb))
    write_ply(root / "gaussians.ply", g)
    return root


# ----------------------------------------------------------------------------- arithmetic floors
def vit_layer_macs(tokens: int, d: int, mlp: int) -> int:
    """Multiply-accumulates of one transformer block's projections and MLP over ``tokens``."""
    return tokens * (4 * d * d + 2 * d * mlp)


def sam_encoder_macs(v: dict) -> int:
    """SAM's ViT image encoder at its input size: patch embedding, windowed blocks on the grid
    padded to a multiple of the window (``window_size`` 14: 64 x 64 -> 70 x 70), global blocks on
    the grid, attention products (QK^T and AV) of both, and the neck (1x1 then 3x3 conv)."""
    grid = v["image_size"] // v["patch_size"]
    d, mlp, w = v["hidden_size"], v["mlp_dim"], v["window_size"]
    padded = -(-grid // w) * w
    windows, n_win = (padded // w) ** 2, w * w
    macs = grid * grid * 3 * v["patch_size"] ** 2 * d
    for layer in range(v["num_hidden_layers"]):
        if layer in v["global_attn_indexes"]:
            macs += vit_layer_macs(grid * grid, d, mlp) + 2 * (grid * grid) ** 2 * d
        else:
            macs += vit_layer_macs(padded * padded, d, mlp) + windows * 2 * n_win * n_win * d
    c = v["output_channels"]
    return macs + grid * grid * (d * c + 9 * c * c)


def sam_decoder_macs_per_prompt(m: dict, prompt_tokens: int = 7) -> int:
    """SAM's mask decoder for one point prompt (multimask): the two-way transformer's image-side
    projections (keys and values of the 4096 image tokens for token-to-image attention, queries
    and output for image-to-token, in every layer, and the final attention's keys and values,
    at the downsampled attention width) and attention products, then the two transposed 2x2
    convolutions (64 -> 128 -> 256) and the masks' dot products; the prompt tokens' own
    projections and MLPs are negligible (7 tokens)."""
    d, L = m["hidden_size"], m["num_hidden_layers"]
    inner = d // m.get("attention_downsample_rate", 2)
    n, t = 64 * 64, prompt_tokens
    per_layer = 4 * n * d * inner + 2 * 2 * t * n * inner  # k, v (token->image); q, out (image->token); products
    final = 2 * n * d * inner + 2 * t * n * inner
    upscale = n * d * (d // 4) * 4 + (4 * n) * (d // 4) * (d // 8) * 4
    masks = 4 * (d // 8) * (16 * n)
    return L * per_layer + final + upscale + masks


def clip_image_macs(v: dict) -> int:
    """CLIP's vision tower on one crop: patch embedding, the blocks with their attention
    products, and the projection."""
    tokens = (v["image_size"] // v["patch_size"]) ** 2 + 1
    d, mlp = v["hidden_size"], v["intermediate_size"]
    macs = (tokens - 1) * 3 * v["patch_size"] ** 2 * d
    macs += v["num_hidden_layers"] * (vit_layer_macs(tokens, d, mlp) + 2 * tokens * tokens * d)
    return macs + d * v.get("projection_dim", 512)


def matmul_gflops(repeats: int = 5) -> float:
    """fp32 GFLOP/s of a [4096, 1280] x [1280, 5120] torch.matmul (ViT-H's MLP shape) on this
    process's threads, the median of ``repeats`` after one warm-up."""
    import torch

    a, b = torch.randn(4096, 1280), torch.randn(1280, 5120)
    torch.matmul(a, b)
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        torch.matmul(a, b)
        times.append(time.perf_counter() - t)
    return 2 * 4096 * 1280 * 5120 / float(np.median(times)) / 1e9


def floors(models: Path, gflops: float, prompts: int) -> dict:
    """Seconds each part's multiply-accumulates take at ``gflops``: the SAM encoder per image, the
    decoder per image (``prompts`` point prompts), CLIP per segment."""
    sam = json.loads((models / "sam-vit-huge" / "config.json").read_text())
    clip = json.loads((models / "clip-vit-b-16" / "config.json").read_text())
    macs = {"sam_image_encoder": sam_encoder_macs(sam["vision_config"]),
            "sam_mask_decoder": prompts * sam_decoder_macs_per_prompt(sam["mask_decoder_config"]),
            "clip_per_segment": clip_image_macs({**clip["vision_config"], "projection_dim": clip["projection_dim"]})}
    return {"gflops_fp32": gflops, "macs": macs, "seconds": {k: 2 * v / (gflops * 1e9) for k, v in macs.items()}}


# ----------------------------------------------------------------------------- child
def child(args: argparse.Namespace) -> int:
    """Run ``n2f2 segments`` in this process, timing each image's parts; write JSON."""
    import torch

    from n2f2.cli import main
    from n2f2.segments import setup
    from n2f2.segments.bank import SegmentAndEncode

    wall0 = time.perf_counter()
    records: list[dict] = []
    depth_s: dict[int, float] = {}
    marks: list[tuple[float, float]] = []  # (start, end) of each image's extraction
    original = SegmentAndEncode.extract
    original_depth = setup.depth_provider
    state = {"models_loaded_at": None}

    def depth_provider(*a, **k):
        provide = original_depth(*a, **k)

        def timed(i):
            t = time.perf_counter()
            out = provide(i)
            depth_s[i] = time.perf_counter() - t
            return out

        return timed

    def extract(self, index, stem, image):
        if state["models_loaded_at"] is None:
            state["models_loaded_at"] = time.perf_counter() - wall0
            state["encoder"], state["image"] = self.encoder, image
        clip_before = dict(self.encoder.timing)
        t0 = time.perf_counter()
        segs, emb = original(self, index, stem, image)
        total = time.perf_counter() - t0
        marks.append((t0, t0 + total))
        sam = dict(self.segmenter.last_timing)
        clip = {k: self.encoder.timing[k] - clip_before[k] for k in clip_before}
        records.append({"image": stem, "height": int(image.shape[0]), "width": int(image.shape[1]),
                        "segments": int(segs.num_segments), "layers": int(segs.layers.shape[0]),
                        "sam_counts": dict(self.segmenter.last_counts),
                        "sam_image_encoder_s": sam["image_encoder"], "sam_mask_decoder_s": sam["mask_decoder"],
                        "sam_postprocess_s": sam["postprocess"], "clip_crops_s": clip["crops"],
                        "clip_model_s": clip["model"], "clip_segments": int(clip["segments"]),
                        "index": int(index), "extract_s": total})
        return segs, emb

    SegmentAndEncode.extract = extract
    setup.depth_provider = depth_provider
    if args.device.startswith("cuda"):
        torch.cuda.reset_peak_memory_stats()
    argv = ["segments", str(args.scene), "--gaussians", str(args.scene / "gaussians.ply"), "--segmenter",
            args.segmenter, "--sam-model", str(args.models / SAM_DIRS[args.segmenter]), "--encoder", "clip",
            "--clip-model", str(args.models / "clip-vit-b-16"), "--out", str(args.bank), "--device", args.device,
            "--quiet"]
    rc = main(argv)
    end = time.perf_counter()
    wall = end - wall0
    clip_at_n = None
    if rc == 0 and args.clip_segments > 0:
        clip_at_n = time_clip(state["encoder"], state["image"], args.clip_segments)
    # The floors, measured in this process on its threads right after the run.
    from n2f2.segments.sam import SamSettings

    cpu_sam = args.device == "cpu" and args.segmenter == "sam"  # the counts are SAM ViT-H's
    floor = floors(args.models, matmul_gflops(), SamSettings().points_per_side ** 2) if cpu_sam else None
    # The rest of an image's share: from the end of its extraction to the start of the next
    # image's (the last: to the end of the command, which includes fitting the quantiles).
    for k, r in enumerate(records):
        until = marks[k + 1][0] if k + 1 < len(marks) else end
        r["depth_render_s"] = depth_s.get(r["index"], 0.0)
        r["other_s"] = until - marks[k][1] - r["depth_render_s"]
        r["total_s"] = r["extract_s"] + r["depth_render_s"] + r["other_s"]
    usage = resource.getrusage(resource.RUSAGE_SELF)
    bank = json.loads((args.bank / "bank.json").read_text())
    out = {"argv": ["n2f2"] + argv, "rc": rc, "wall_s": wall, "user_s": usage.ru_utime, "system_s": usage.ru_stime,
           "max_rss_mib": usage.ru_maxrss / 1024.0, "models_loaded_s": state["models_loaded_at"],
           "torch_threads": torch.get_num_threads(), "bank_timing": bank.get("timing"),
           "bank_counts": bank.get("counts"), "images": records, "clip_at_n": clip_at_n, "floor": floor}
    if args.device.startswith("cuda"):
        out["cuda_max_allocated_mib"] = torch.cuda.max_memory_allocated() / 2**20
        out["cuda_device"] = torch.cuda.get_device_name()
    Path(args.child_json).write_text(json.dumps(out, indent=2))
    return rc


def box_masks(height: int, width: int, n: int, seed: int = 0) -> np.ndarray:  # -> [n, H, W] bool
    """``n`` rectangles, 10-100 % of the image's height, of varied aspect, anywhere in it."""
    rng = np.random.default_rng(seed)
    masks = np.zeros((n, height, width), bool)
    for k in range(n):
        h = max(1, int(rng.uniform(0.1, 1.0) * height))
        w = max(1, min(width, int(h * width / height * rng.uniform(0.5, 1.5))))
        y, x = rng.integers(0, height - h + 1), rng.integers(0, width - w + 1)
        masks[k, y:y + h, x:x + w] = True
    return masks


def time_clip(encoder, image: np.ndarray,  # [H, W, 3] float
              n: int) -> dict:
    """CLIP on ``n`` box segments of ``image``, in chunks of 64 as ``n2f2 segments`` passes
    them: the cost at a real image's segment count, which random SAM weights do not give."""
    masks = box_masks(image.shape[0], image.shape[1], n)
    before = dict(encoder.timing)
    t = time.perf_counter()
    for start in range(0, n, 64):
        encoder.encode_segments(image, masks[start:start + 64])
    total = time.perf_counter() - t
    return {"segments": n, "total_s": total, "crops_s": encoder.timing["crops"] - before["crops"],
            "model_s": encoder.timing["model"] - before["model"]}


# ----------------------------------------------------------------------------- report
PARTS = [("SAM image encoder", "sam_image_encoder_s"), ("SAM mask decoder", "sam_mask_decoder_s"),
         ("SAM post-processing", "sam_postprocess_s"), ("CLIP crops", "clip_crops_s"),
         ("CLIP image model", "clip_model_s"), ("depth render (lifting)", "depth_render_s"),
         ("other (lifting, record, next image read)", "other_s"), ("**total per image**", "total_s")]


def table(result: dict) -> str:
    images = result["images"]
    head = "| part | " + " | ".join(f"{r['image']} ({r['width']}x{r['height']})" for r in images) + " | mean |"
    rows = [head, "|---|" + "---:|" * (len(images) + 1)]
    for label, key in PARTS:
        vals = [r[key] for r in images]
        rows.append(f"| {label} | " + " | ".join(f"{v:.1f} s" for v in vals) + f" | {np.mean(vals):.1f} s |")
    rows.append("| segments (CLIP crops) | " + " | ".join(str(r["segments"]) for r in images)
                + f" | {np.mean([r['segments'] for r in images]):.0f} |")
    lines = ["\n".join(rows), ""]
    c = images[0]["sam_counts"]
    lines.append(f"SAM masks, first image: {c['candidates']} candidates, {c['iou_kept']} above the IoU threshold, "
                 f"{c['stable']} stable, {c['after_nms']} after NMS, {c['final']} kept")
    lines.append(f"process: wall {result['wall_s']:.0f} s, user {result['user_s']:.0f} s, system "
                 f"{result['system_s']:.0f} s ({result['torch_threads']} torch threads); models loaded after "
                 f"{result['models_loaded_s']:.0f} s; peak RSS {result['max_rss_mib'] / 1024:.2f} GiB")
    n = result.get("clip_at_n")
    if n:
        per = n["total_s"] / n["segments"]
        lines.append(f"CLIP at {n['segments']} box segments of the first image: {n['total_s']:.1f} s (crops "
                     f"{n['crops_s']:.1f} s, model {n['model_s']:.1f} s), {per:.3f} s per segment")
    f = result.get("floor")
    if f:
        sec = f["seconds"]
        mean = {k: float(np.mean([r[k] for r in images])) for k in ("sam_image_encoder_s", "sam_mask_decoder_s")}
        rows = [f"| part | mean time | floor at {f['gflops_fp32']:.0f} GFLOP/s fp32 (same run) | ratio |",
                "|---|---:|---:|---:|"]
        for label, key, floor in (("SAM image encoder", "sam_image_encoder_s", sec["sam_image_encoder"]),
                                  ("SAM mask decoder", "sam_mask_decoder_s", sec["sam_mask_decoder"])):
            rows.append(f"| {label} | {mean[key]:.1f} s | {floor:.1f} s | {mean[key] / floor:.2f}x |")
        if n:
            model = n["model_s"] / n["segments"]
            rows.append(f"| CLIP per segment (model) | {model:.3f} s | {sec['clip_per_segment']:.3f} s | "
                        f"{model / sec['clip_per_segment']:.2f}x |")
            rows.append(f"| CLIP per segment (crops + model) | {per:.3f} s | {sec['clip_per_segment']:.3f} s | "
                        f"{per / sec['clip_per_segment']:.2f}x |")
        lines += ["", "\n".join(rows)]
    if "cuda_max_allocated_mib" in result:
        lines.append(f"CUDA ({result['cuda_device']}): max allocated {result['cuda_max_allocated_mib'] / 1024:.2f} GiB")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--models", type=Path, default=Path("/tmp/fullsize_models"),
                    help="folder with sam-vit-huge/ (or sam2.1-hiera-tiny/) and clip-vit-b-16/ "
                         "(make_fullsize_models.py)")
    ap.add_argument("--segmenter", choices=list(SAM_DIRS), default="sam",
                    help="sam: SAM ViT-H (with the floors); sam2: SAM 2.1 Hiera-tiny")
    ap.add_argument("--images", type=Path, nargs="+", default=DEFAULT_IMAGES, help="photos (same size)")
    ap.add_argument("--device", default="cpu", help="torch device (cpu, cuda)")
    ap.add_argument("--json", type=Path, default=Path("fullsize_models.json"), help="where to write the numbers")
    ap.add_argument("--keep", type=Path, default=None, help="keep the scene and bank in this folder")
    ap.add_argument("--clip-segments", type=int, default=100,
                    help="also time CLIP on this many box segments of the first image (0: skip)")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--scene", type=Path, help=argparse.SUPPRESS)
    ap.add_argument("--bank", type=Path, help=argparse.SUPPRESS)
    ap.add_argument("--child-json", type=Path, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        return child(args)

    for d in (SAM_DIRS[args.segmenter], "clip-vit-b-16"):
        if not (args.models / d / "config.json").is_file():
            sys.exit(f"{args.models / d}: no model; run benchmarks/make_fullsize_models.py {args.models} first")
    missing = [str(p) for p in args.images if not p.is_file()]
    if missing:
        sys.exit(f"missing images: {', '.join(missing)}")
    work = Path(tempfile.mkdtemp(prefix="n2f2-fullsize-")) if args.keep is None else args.keep
    try:
        scene = make_scene(work / "scene", list(args.images))
        child_json = work / "child.json"
        cmd = [sys.executable, str(Path(__file__).resolve()), "--child", "--scene", str(scene), "--bank",
               str(work / "bank"), "--child-json", str(child_json), "--models", str(args.models),
               "--device", args.device, "--clip-segments", str(args.clip_segments), "--segmenter", args.segmenter]
        t = time.perf_counter()
        proc = subprocess.run(cmd)
        if proc.returncode != 0:
            sys.exit(f"n2f2 segments failed (exit {proc.returncode})")
        result = json.loads(child_json.read_text())
        result["parent_wall_s"] = time.perf_counter() - t
    finally:
        if args.keep is None:
            shutil.rmtree(work, ignore_errors=True)
    import torch

    result.update({"device": args.device, "cpu_count": os.cpu_count(), "platform": platform.platform(),
                   "torch": torch.__version__, "load_average_after": os.getloadavg()})
    try:
        import transformers

        result["transformers"] = transformers.__version__
    except ImportError:
        pass
    print(table(result))
    args.json.write_text(json.dumps(result, indent=2))
    print(f"-> {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
