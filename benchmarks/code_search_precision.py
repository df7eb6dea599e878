"""The code search in float32 against bfloat16 (README, Stage 1: "Code search").

Tokenizes every clip of a split as stage 2's token cache does (whole clips cut to a multiple of 4,
same-length batches) with the tokenizer's code search, its decoder calls in each precision, the
precisions interleaved pass by pass after a warm-up batch. Prints per precision the median wall
time of a pass, the round trip's global and root-aligned MPJPE (mm) and the share of codes equal
to float32's, and writes them with the device, dtype, batch and model size as JSON.

    python benchmarks/code_search_precision.py [--tokenizer REF] [--data data/synthetic]
        [--split test] [--repeats 3] [--out outputs/bench/code_search_precision.json]
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from mmm.atomic import atomic_write_text
from mmm.data.humanml3d import read_split
from mmm.tokenizer.load import load_tokenizer

PRECISIONS = ("fp32", "bf16")


def load_clips(tokenizer, root: Path, split: str) -> dict[int, torch.Tensor]:
    """Normalized clips (N, T, D) of the split, by length T (a multiple of the downsampling)."""
    down = tokenizer.tokenizer.cfg.downsample
    mean, std = tokenizer.mean.numpy(), tokenizer.std.numpy()
    by_length: dict[int, list[np.ndarray]] = {}
    for motion_id in read_split(root, split):
        features = np.load(root / "new_joint_vecs" / f"{motion_id}.npy")
        n = features.shape[0] // down * down
        if n:
            by_length.setdefault(n, []).append((features[:n] - mean) / std)
    return {n: torch.from_numpy(np.stack(group).astype(np.float32)) for n, group in by_length.items()}


def batches(clips: dict[int, torch.Tensor], size: int):
    for _, x in sorted(clips.items()):
        for start in range(0, len(x), size):
            yield x[start : start + size]


@torch.no_grad()
def search_pass(tokenizer, clips, size: int) -> list[torch.Tensor]:
    return [tokenizer.encode(x) for x in batches(clips, size)]


@torch.no_grad()
def mpjpe(tokenizer, clips, codes: list[torch.Tensor], size: int) -> tuple[float, float]:
    """Global and root-aligned MPJPE (mm) of the decoded codes, frame-weighted."""
    total_global = total_aligned = frames = 0.0
    for x, c in zip(batches(clips, size), codes):
        real, rec = tokenizer.joints(x), tokenizer.joints(tokenizer.tokenizer.decode(c))
        total_global += float((real - rec).norm(dim=-1).mean(-1).sum())
        aligned = (real - real[..., :1, :]) - (rec - rec[..., :1, :])
        total_aligned += float(aligned.norm(dim=-1).mean(-1).sum())
        frames += x.shape[0] * x.shape[1]
    return total_global / frames * 1000.0, total_aligned / frames * 1000.0


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--tokenizer", default=None, help="stage-1 reference (default: the newest run)")
    p.add_argument("--tracking-uri", default="sqlite:///mlflow.db")
    p.add_argument("--data", default="data/synthetic")
    p.add_argument("--split", default="test")
    p.add_argument("--batch", type=int, default=64, help="clips per search call (tokenize_dataset's)")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--out", default="outputs/bench/code_search_precision.json")
    args = p.parse_args()
    tokenizer, _ = load_tokenizer(args.tokenizer, args.tracking_uri)
    tokenizer.eval()
    root = Path(args.data)
    clips = load_clips(tokenizer, root, args.split)
    configs = {name: replace(tokenizer.encode_cfg, precision=name) for name in PRECISIONS}
    warm = next(batches(clips, args.batch))
    for cfg in configs.values():
        tokenizer.encode_cfg = cfg
        tokenizer.encode(warm)
    times: dict[str, list[float]] = {name: [] for name in PRECISIONS}
    codes: dict[str, list[torch.Tensor]] = {}
    for _ in range(args.repeats):
        for name, cfg in configs.items():
            tokenizer.encode_cfg = cfg
            start = time.perf_counter()
            codes[name] = search_pass(tokenizer, clips, args.batch)
            times[name].append(time.perf_counter() - start)
    reference = torch.cat([c.flatten() for c in codes["fp32"]])
    results = {}
    for name in PRECISIONS:
        flat = torch.cat([c.flatten() for c in codes[name]])
        global_mm, aligned_mm = mpjpe(tokenizer, clips, codes[name], args.batch)
        results[name] = {
            "median_s": statistics.median(times[name]),
            "times_s": times[name],
            "mpjpe_global_mm": global_mm,
            "mpjpe_root_aligned_mm": aligned_mm,
            "codes_equal_to_fp32": float((flat == reference).float().mean()),
        }
        print(
            f"{name}: {results[name]['median_s']:.1f} s per pass (median of {args.repeats}), "
            f"global / root-aligned {global_mm:.1f} / {aligned_mm:.1f} mm, "
            f"codes equal to fp32 {results[name]['codes_equal_to_fp32']:.3f}"
        )
    print(f"bf16 speed-up: {results['fp32']['median_s'] / results['bf16']['median_s']:.2f}x")
    record = {
        "device": f"cpu: {platform.processor() or platform.machine()}, {torch.get_num_threads()} threads",
        "torch": torch.__version__,
        "tokenizer_parameters": sum(p.numel() for p in tokenizer.tokenizer.parameters()),
        "search": {"candidates": tokenizer.encode_cfg.candidates, "sweeps": tokenizer.encode_cfg.sweeps},
        "batch": args.batch,
        "clips": sum(len(x) for x in clips.values()),
        "data": str(root),
        "split": args.split,
        "results": results,
    }
    atomic_write_text(Path(args.out), json.dumps(record, indent=2))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
