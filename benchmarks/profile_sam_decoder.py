"""SAM mask decoder on CPU: ``SamModel``'s own forward (the reference) against
:class:`n2f2.segments.sam.FastSamDecoder`, and both against an arithmetic floor.

The decoder is full size (``SamConfig()``'s mask decoder, the same for every SAM size: width
256, 2 two-way blocks, 8 heads, MLP 2048, 64 x 64 image tokens) with random weights, fed a
random image embedding [1, 256, 64, 64] and random point prompts, ``--prompts`` (64, SAM's
``points_per_batch``) at a time. The vision encoder is cut to one layer: it is not timed.

The floor is a ``torch.matmul`` of two 2048 x 2048 float32 matrices, repeated to the same
multiply-accumulate count as one batch through the reference decoder (``reference_macs``,
counted from the config: every projection, attention product, MLP, the two transposed
convolutions and the mask products; ~1.78 GMAC a prompt), timed in the same run with the same
threads. ``fast_macs`` counts the fast path the same way (~0.81 GMAC a prompt: it skips work
rather than only doing it faster, so it can beat the floor).

    python benchmarks/profile_sam_decoder.py [--batches 2] [--repeats 3] [--profile]

Each timing is the median of ``--repeats`` runs (after a warm-up) of ``--batches`` batches,
reported per batch. On a shared machine they are indicative only. ``--profile`` also prints
``torch.profiler`` tables (self CPU time by op) of one batch of each path.
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import time
from typing import Callable

import torch


def cpu_name() -> str:
    """``lscpu``'s model name (or /proc/cpuinfo's)."""
    try:
        out = subprocess.run(["lscpu"], capture_output=True, text=True, check=True).stdout
        for line in out.splitlines():
            if line.startswith("Model name:"):
                return line.split(":", 1)[1].strip()
    except (OSError, subprocess.CalledProcessError):
        pass
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return "unknown CPU"


def _sizes(config) -> dict[str, int]:
    dec = config.mask_decoder_config
    C = dec.hidden_size
    side = config.prompt_encoder_config.image_embedding_size
    return {
        "C": C,
        "N": side * side,  # image tokens
        "Ci": C // dec.attention_downsample_rate,  # cross-attention width
        "H": dec.num_attention_heads,
        "mlp": dec.mlp_dim,
        "L": dec.num_hidden_layers,
        "T": 1 + (dec.num_multimask_outputs + 1) + 2,  # IoU token, mask tokens, point, padding point
        "masks": dec.num_multimask_outputs + 1,
    }


def _upscale_macs(s: dict[str, int]) -> int:
    C, N = s["C"], s["N"]
    # kernel 2, stride 2: each input token meets 4 kernel taps once
    return N * C * (C // 4) * 4 + 4 * N * (C // 4) * (C // 8) * 4


def _token_side_macs(s: dict[str, int]) -> int:
    """Projections, self-attention and MLP of the T prompt tokens (small next to the image side)."""
    C, Ci, T, mlp = s["C"], s["Ci"], s["T"], s["mlp"]
    per_block = 4 * T * C * C + 2 * T * T * C + 2 * T * C * Ci + 2 * T * C * mlp + 2 * T * C * Ci + T * C * Ci
    return s["L"] * per_block + 2 * T * C * Ci + 4 * (2 * C * C + C * C // 8) + 2 * C * C


def reference_macs(config) -> int:
    """Multiply-accumulates per prompt of ``SamModel``'s mask decoder (multimask, one point)."""
    s = _sizes(config)
    C, N, Ci, T = s["C"], s["N"], s["Ci"], s["T"]
    t2i = 2 * N * C * Ci + 2 * T * N * Ci  # image keys and values, scores and output
    i2t = 2 * N * C * Ci + 2 * N * T * Ci  # image queries and output projection, scores and output
    final = 2 * N * C * Ci + 2 * T * N * Ci
    masks = s["masks"] * 16 * N * (C // 8)
    return s["L"] * (t2i + i2t) + final + _upscale_macs(s) + masks + _token_side_macs(s)


def fast_macs(config) -> int:
    """The same count for :class:`FastSamDecoder` (block 0's image projections shared, later
    image-side projections folded into the token rows, only the 3 multimask outputs)."""
    s = _sizes(config)
    C, N, Ci, T, H = s["C"], s["N"], s["Ci"], s["T"], s["H"]
    block0 = 2 * T * N * Ci + T * N * Ci + N * H * T * C  # shared K/V/Q; low-rank image update
    later = 4 * N * H * T * C + 2 * T * N * Ci  # 2 logits, values, update; positional parts
    n_out = s["masks"] + 1
    final = 2 * N * H * n_out * C + n_out * N * Ci
    masks = (s["masks"] - 1) * 16 * N * (C // 8)
    return block0 + (s["L"] - 1) * later + final + _upscale_macs(s) + masks + _token_side_macs(s)


def median_time(fn: Callable[[], object], repeats: int) -> float:
    fn()  # warm-up
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times)


def profile_table(fn: Callable[[], object], rows: int = 15) -> str:
    from torch.profiler import ProfilerActivity, profile

    with profile(activities=[ProfilerActivity.CPU]) as prof:
        fn()
    return prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=rows)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--batches", type=int, default=2, help="batches of prompts per timing")
    ap.add_argument("--prompts", type=int, default=64, help="prompts per batch (SAM's points_per_batch)")
    ap.add_argument("--repeats", type=int, default=3, help="timings per path; the median is reported")
    ap.add_argument("--threads", type=int, default=0, help="torch threads (0: torch's default)")
    ap.add_argument("--profile", action="store_true", help="print torch.profiler tables of one batch")
    args = ap.parse_args()
    if args.threads > 0:
        torch.set_num_threads(args.threads)

    from transformers import SamConfig, SamModel

    from n2f2.segments.sam import FastSamDecoder, reference_decode

    torch.manual_seed(0)
    config = SamConfig()
    config.vision_config.num_hidden_layers = 1  # the encoder is not timed
    model = SamModel(config).eval()
    embedding = torch.randn(1, config.vision_config.output_channels, 64, 64)
    points = [torch.rand(args.prompts, 2) * config.vision_config.image_size for _ in range(args.batches)]

    ref_macs, new_macs = reference_macs(config), fast_macs(config)
    batch_macs = ref_macs * args.prompts
    n = 2048
    reps = max(1, round(batch_macs / n**3))
    a, b = torch.randn(n, n), torch.randn(n, n)

    def floor() -> None:
        for _ in range(reps):
            torch.matmul(a, b)

    def reference() -> None:
        for p in points:
            reference_decode(model, embedding, p)

    def fast() -> None:
        decoder = FastSamDecoder(model, embedding)  # per image: included in the time
        for p in points:
            decoder(p)

    print(f"CPU: {cpu_name()}; torch {torch.__version__}, {torch.get_num_threads()} threads")
    print(f"decoder MACs per prompt: reference {ref_macs / 1e9:.3f} G, fast path {new_macs / 1e9:.3f} G")
    print(
        f"{args.batches} batches of {args.prompts} prompts, median of {args.repeats} (indicative on a shared machine)"
    )
    with torch.inference_mode():
        ref_iou, ref_masks = reference_decode(model, embedding, points[0][:8])
        new_iou, new_masks = FastSamDecoder(model, embedding)(points[0][:8])
        print(
            f"max |difference| on 8 prompts: IoU {(ref_iou - new_iou).abs().max():.2e}, "
            f"logits {(ref_masks - new_masks).abs().max():.2e} (logits up to {ref_masks.abs().max():.2e})"
        )
        t_floor = median_time(floor, args.repeats) * batch_macs / (reps * n**3)
        t_ref = median_time(reference, args.repeats) / args.batches
        t_fast = median_time(fast, args.repeats) / args.batches
        t_floor2 = median_time(floor, args.repeats) * batch_macs / (reps * n**3)
    t_floor = min(t_floor, t_floor2)
    rate = batch_macs / t_floor / 1e9
    print(f"floor (matmul, {batch_macs / 1e9:.0f} GMAC): {t_floor:7.2f} s/batch  ({rate:.1f} GMAC/s)")
    print(f"reference (SamModel):      {t_ref:7.2f} s/batch  {t_ref / t_floor:5.2f} x floor")
    print(f"fast (FastSamDecoder):     {t_fast:7.2f} s/batch  {t_fast / t_floor:5.2f} x floor")
    print(f"reference / fast: {t_ref / t_fast:.2f}")
    if args.profile:
        with torch.inference_mode():
            print("\nreference, one batch:")
            print(profile_table(lambda: reference_decode(model, embedding, points[0])))
            decoder = FastSamDecoder(model, embedding)
            decoder(points[0][:4])
            print("fast path, one batch:")
            print(profile_table(lambda: decoder(points[0])))


if __name__ == "__main__":
    main()
