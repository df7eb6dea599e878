"""Stage-1 training speed and peak memory at the tiny and paper sizes.

    python benchmarks/stage1_speed.py [--sizes tiny paper] [--batch 64] [--steps 20] [--out FILE.json]

Each size runs in its own process (clean peak-memory figures): a full training step (forward,
losses, backward, AdamW, EMA codebook update) on random (batch, 64, 263) windows, after warm-up,
timed with the device synchronized; the median step time is reported with device, dtype, batch
and parameter count. Peak memory: max RSS of the process on CPU, max allocated on CUDA.
"""

from __future__ import annotations

import argparse
import json
import platform
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def measure(size: str, batch: int, steps: int, warmup: int, device: str) -> dict:
    import torch

    from mmm.config import compose
    from mmm.tokenizer.module import OptimConfig, TokenizerLossConfig, TokenizerModule
    from mmm.tokenizer.network import TokenizerConfig

    cfg = compose("train_stage1", [f"model={size}"]).model.tokenizer
    module = TokenizerModule(263, TokenizerConfig(**cfg), OptimConfig(), TokenizerLossConfig()).to(device)
    module.train()
    optimizer = torch.optim.AdamW(module.parameters(), lr=2e-4, betas=(0.9, 0.99))
    x = torch.randn(batch, 64, 263, device=device)

    def sync():
        if device.startswith("cuda"):
            torch.cuda.synchronize()

    times = []
    for i in range(warmup + steps):
        sync()
        t0 = time.perf_counter()
        loss = _loss(module, x)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        sync()
        if i >= warmup:
            times.append(time.perf_counter() - t0)
    median = statistics.median(times)
    peak = torch.cuda.max_memory_allocated() / 2**20 if device.startswith("cuda") else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return {
        "size": size, "device": torch.cuda.get_device_name() if device.startswith("cuda") else f"cpu ({platform.processor() or platform.machine()}, {torch.get_num_threads()} threads)",
        "dtype": "float32", "batch": batch, "window": 64, "params_M": round(sum(p.numel() for p in module.parameters()) / 1e6, 2),
        "codes": module.quantizer.num_codes, "median_step_s": round(median, 4), "iters_per_s": round(1 / median, 2),
        "samples_per_s": round(batch / median, 1), "peak_memory_MiB": round(peak, 1), "steps_timed": steps, "warmup": warmup,
        "torch": torch.__version__,
    }


def _loss(module, x):
    out = module.tokenizer(x)
    parts = module.losses(out.reconstruction, x)
    return parts["recon"] + 0.5 * parts["position"] + 0.02 * out.commit_loss


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", nargs="+", default=["tiny", "paper"])
    parser.add_argument("--batch", type=int, default=64)
    parser.add_argument("--steps", type=int, default=10)
    parser.add_argument("--warmup", type=int, default=3)
    parser.add_argument("--device", default="cuda" if _cuda() else "cpu")
    parser.add_argument("--out", default="outputs/bench/stage1_speed.json")
    parser.add_argument("--one", default=None, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.one:  # child process: one size, print JSON
        print(json.dumps(measure(args.one, args.batch, args.steps, args.warmup, args.device)))
        return
    results = []
    for size in args.sizes:
        cmd = [sys.executable, __file__, "--one", size, "--batch", str(args.batch), "--steps", str(args.steps), "--warmup", str(args.warmup), "--device", args.device]
        out = subprocess.run(cmd, capture_output=True, text=True, check=True, cwd=REPO)
        results.append(json.loads(out.stdout.strip().splitlines()[-1]))
        r = results[-1]
        print(f"{size:6s} {r['params_M']:6.2f}M params  batch {r['batch']}  {r['iters_per_s']:7.2f} it/s  {r['samples_per_s']:8.1f} samples/s  peak {r['peak_memory_MiB']:.0f} MiB  ({r['device']})")
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(results, indent=2))
    print(f"wrote {args.out}")


def _cuda() -> bool:
    import torch

    return torch.cuda.is_available()


if __name__ == "__main__":
    main()
