"""Training speed and peak memory of both stages at the tiny and paper sizes.

    python benchmarks/train_speed.py [--stages 1 2] [--sizes tiny paper] [--batch1 64] [--batch2 64]
                                     [--steps 10] [--precisions 32-true bf16-mixed]
                                     [--set model.transformer.embed_dim=256 ...]
                                     [--out outputs/bench/train_speed.json]

Each (stage, size) runs in its own process (clean peak-memory figures): a full training step
(forward, loss, backward, AdamW; for stage 1 also the EMA codebook update; for stage 2 the
training corruption) on random inputs of the real shapes, after warm-up, with the device
synchronized; the median step time is reported with device, dtype, batch and parameter count.
Peak memory: max RSS of the process on CPU, max allocated on CUDA. On CPU the paper sizes use a
smaller batch (--paper-cpu-batch) so a step takes seconds, not minutes; the batch is recorded.
Precisions as Lightning names them (`trainer.precision`): 32-true, and bf16-mixed (the forward
and loss under bfloat16 autocast, float32 weights and optimizer, as Lightning runs it). Several
precisions are timed in one process, their steps interleaved, so that a busy machine slows them
alike and their ratio (`speedup_vs_32-true`) holds; peak memory is then the process's, for all.
`--set` changes the sizes' configs (the quality recipe's transformer: `--sizes tiny --set
model.transformer.embed_dim=256 model.transformer.num_heads=8`); the rows record it.
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


def _device_name(device: str) -> str:
    import torch

    if device.startswith("cuda"):
        return torch.cuda.get_device_name()
    return f"cpu ({platform.machine()}, {torch.get_num_threads()} threads)"


def _stage1(size: str, batch: int, device: str, overrides: list[str]):
    import torch

    from mmm.config import compose
    from mmm.optim import OptimConfig
    from mmm.tokenizer.configs import TokenizerLossConfig
    from mmm.tokenizer.module import TokenizerModule
    from mmm.tokenizer.network import TokenizerConfig

    cfg = compose("train_stage1", [f"model={size}", *overrides]).model.tokenizer
    module = (
        TokenizerModule(263, TokenizerConfig(**cfg), OptimConfig(), TokenizerLossConfig()).to(device).train()
    )
    x = torch.randn(batch, 64, 263, device=device)

    def loss():
        out = module.tokenizer(x)
        parts = module.losses(out.reconstruction, x)
        return parts["recon"] + 0.5 * parts["position"] + 0.02 * out.commit_loss

    return module, loss, {"window": 64, "codes": module.quantizer.num_codes}


def _stage2(size: str, batch: int, device: str, overrides: list[str]):
    import torch

    from mmm.config import compose
    from mmm.optim import OptimConfig
    from mmm.transformer.configs import CorruptionConfig
    from mmm.transformer.module import MaskedTransformerModule, corrupt
    from mmm.transformer.network import TransformerConfig

    cfg = compose("train_stage2", [f"model={size}", *overrides]).model
    K, C = cfg.tokenizer.num_codes, cfg.tokenizer.code_dim
    module = MaskedTransformerModule(
        torch.randn(K, C),
        TransformerConfig(**cfg.transformer),
        OptimConfig(),
        CorruptionConfig(cond_drop=0.1),
        384,
        384,
    )
    module = module.to(device).train()
    M = cfg.transformer.max_tokens
    lengths = torch.full((batch,), M - 1, device=device)  # the longest motions (196 frames): the worst case
    tokens = torch.randint(0, K, (batch, M), device=device)
    tokens[:, M - 1] = K
    batch_dict = {
        "tokens": tokens,
        "lengths": lengths,
        "sentence": torch.randn(batch, 384, device=device),
        "words": torch.randn(batch, 16, 384, device=device),
        "word_mask": torch.ones(batch, 16, dtype=torch.bool, device=device),
    }

    def loss():  # what training_step computes, without the logging
        c = corrupt(tokens, lengths, K, module.corruption_cfg)
        drop = torch.rand(batch, device=device) < module.corruption_cfg.cond_drop
        logits = module.transformer(
            c.inputs, batch_dict["sentence"], batch_dict["words"], batch_dict["word_mask"], drop, None
        )
        return module.loss(logits, tokens, c)

    return module, loss, {"tokens": M, "codes": K}


def measure(
    stage: int, size: str, batch: int, steps: int, warmup: int, device: str, precisions, overrides=()
) -> list:
    import contextlib

    import torch

    module, loss_fn, extra = (_stage1 if stage == 1 else _stage2)(size, batch, device, list(overrides))
    optimizer = torch.optim.AdamW([p for p in module.parameters() if p.requires_grad], lr=2e-4, foreach=True)

    def sync():
        if device.startswith("cuda"):
            torch.cuda.synchronize()

    def autocast(precision: str):
        if precision == "bf16-mixed":
            return torch.autocast(device.split(":")[0], dtype=torch.bfloat16)
        if precision != "32-true":
            raise SystemExit(f"--precisions {precision!r}: use 32-true or bf16-mixed")
        return contextlib.nullcontext()

    times: dict[str, list[float]] = {p: [] for p in precisions}
    for i in range(warmup + steps):
        for precision in precisions:
            sync()
            t0 = time.perf_counter()
            with autocast(precision):
                loss = loss_fn()
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
            sync()
            if i >= warmup:
                times[precision].append(time.perf_counter() - t0)
    peak = (
        torch.cuda.max_memory_allocated() / 2**20
        if device.startswith("cuda")
        else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    )
    base = statistics.median(times[precisions[0]])
    rows = []
    for precision in precisions:
        median = statistics.median(times[precision])
        rows.append(
            {
                "stage": stage,
                "size": size,
                "overrides": list(overrides),
                "device": _device_name(device),
                "dtype": "float32" if precision == "32-true" else "bfloat16 autocast, float32 weights",
                "precision": precision,
                "batch": batch,
                "params_M": round(sum(p.numel() for p in module.parameters()) / 1e6, 2),
                **extra,
                "median_step_s": round(median, 4),
                "spread_s": [round(min(times[precision]), 4), round(max(times[precision]), 4)],
                "iters_per_s": round(1 / median, 3),
                "samples_per_s": round(batch / median, 1),
                f"speedup_vs_{precisions[0]}": round(base / median, 3),
                "peak_memory_MiB": round(peak, 1),
                "steps_timed": steps,
                "warmup": warmup,
                "torch": torch.__version__,
            }
        )
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--stages", nargs="+", type=int, default=[1, 2])
    parser.add_argument("--sizes", nargs="+", default=["tiny", "paper"])
    parser.add_argument("--batch1", type=int, default=64)
    parser.add_argument("--batch2", type=int, default=64)
    parser.add_argument("--paper-cpu-batch", type=int, default=8)
    parser.add_argument("--steps", type=int, default=10)
    parser.add_argument("--warmup", type=int, default=3)
    parser.add_argument("--device", default=None)
    parser.add_argument("--precisions", nargs="+", default=["32-true"])
    parser.add_argument("--set", nargs="+", default=[], metavar="KEY=VALUE", help="config overrides")
    parser.add_argument("--out", default="outputs/bench/train_speed.json")
    parser.add_argument(
        "--one", nargs=3, default=None, help=argparse.SUPPRESS
    )  # stage size batch, in a child
    args = parser.parse_args()
    import torch

    device = args.device or ("cuda" if torch.cuda.is_available() else "cpu")
    if args.one:
        stage, size, batch = int(args.one[0]), args.one[1], int(args.one[2])
        rows = measure(stage, size, batch, args.steps, args.warmup, device, args.precisions, args.set)
        print(json.dumps(rows))
        return
    results = []
    for stage in args.stages:
        for size in args.sizes:
            batch = args.batch1 if stage == 1 else args.batch2
            if size == "paper" and device == "cpu":
                batch = min(batch, args.paper_cpu_batch)
            cmd = [
                sys.executable,
                __file__,
                "--one",
                str(stage),
                size,
                str(batch),
                "--steps",
                str(args.steps),
                "--warmup",
                str(args.warmup),
                "--device",
                device,
                "--precisions",
                *args.precisions,
                *(["--set", *args.set] if args.set else []),
            ]
            out = subprocess.run(cmd, capture_output=True, text=True, check=True, cwd=REPO)
            for r in json.loads(out.stdout.strip().splitlines()[-1]):
                results.append(r)
                print(
                    f"stage {stage} {size:6s} {r['params_M']:7.2f}M params  batch {r['batch']:3d}  "
                    f"{r['precision']:10s} {r['iters_per_s']:8.3f} it/s  {r['samples_per_s']:8.1f} samples/s "
                    f"x{r[f'speedup_vs_{args.precisions[0]}']:.2f}  peak {r['peak_memory_MiB']:.0f} MiB  "
                    f"({r['device']})",
                    flush=True,
                )
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(results, indent=2))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
