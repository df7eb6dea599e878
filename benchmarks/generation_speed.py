"""Generation speed: time per sentence against length, batch throughput, AITS, and a long sequence.

    python benchmarks/generation_speed.py [--sizes tiny paper] [--repeats 5]
        [--out outputs/bench/generation_speed.json]

For each model size (random weights of that size: speed does not depend on their values; the
text encoder is the real MiniLM, whose time is included as it is part of inference):
- time per sentence for lengths 40, 60, ..., 196 frames at batch 1 and batch 32 (Figure 11);
- AITS: the mean time per sentence at batch 1 over lengths spread like a test set (40..196);
- the time of a 10.873-minute motion (13,047 frames at 20 fps) from many prompts, generated
  as segments in one batch, transitions in one pass, and one decode (the paper: 1.65 s).
Timed with the device synchronized, after warm-up, medians of repeats, excluding model loading, at
`--precision` (default: the device's default, int8 on CPU; recorded as `dtype`), through
torch.compile with `--compile` (recorded as `compiled`; each shape compiles during its warm-up).
Paper (RTX A5000): AITS 0.081 s; 0.018 s for 40 frames; 1.65 s for the 10.873-minute motion.
Writes JSON (device, dtype, batch, model size with every figure) and a plot of the curve.
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import time
from pathlib import Path

import numpy as np
import torch

PROMPTS = [
    "a person walks forward",
    "someone jumps twice",
    "a person waves with the right hand",
    "the man squats down",
    "a person runs forward quickly",
    "a person turns left",
    "someone kicks with the left foot",
    "a person sits down",
]
PAPER = {"aits_s": 0.081, "40_frames_s": 0.018, "long_10.873min_s": 1.65, "device": "NVIDIA RTX A5000"}


def build_model(size: str, device: str, precision: str | None, compiled: bool = False):
    from mmm.config import compose
    from mmm.generation.model import TextToMotion
    from mmm.optim import OptimConfig
    from mmm.text import build_text_encoder
    from mmm.tokenizer.configs import TokenizerLossConfig
    from mmm.tokenizer.module import TokenizerModule
    from mmm.tokenizer.network import TokenizerConfig
    from mmm.transformer.network import MaskedMotionTransformer, TransformerConfig

    cfg = compose("train_stage2", [f"model={size}"]).model
    torch.manual_seed(0)
    tokenizer = TokenizerModule(263, TokenizerConfig(**cfg.tokenizer), OptimConfig(), TokenizerLossConfig())
    text = build_text_encoder("minilm")
    transformer = MaskedMotionTransformer(
        tokenizer.tokenizer.codebook.detach().normal_(),
        TransformerConfig(**cfg.transformer),
        text.sentence_dim,
        text.word_dim,
    )
    model = TextToMotion(
        tokenizer, transformer, text, {"size": size}, device=device, precision=precision, compiled=compiled
    )
    params = sum(p.numel() for p in transformer.parameters()) + sum(p.numel() for p in tokenizer.parameters())
    return model, params


def timed(fn, repeats: int, warmup: int = 1) -> float:
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)  # generate() synchronizes the device itself
    return statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--sizes", nargs="+", default=["tiny"])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--lengths", default="40,60,80,100,120,140,160,180,196")
    parser.add_argument("--batches", default="1,32,128")
    parser.add_argument("--long-minutes", type=float, default=10.873, help="0 skips the long sequence")
    parser.add_argument("--no-aits", action="store_true", help="skip the AITS spread")
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument(
        "--precision", default=None, choices=["fp32", "bf16", "int8"], help="default: the device's default"
    )
    parser.add_argument(
        "--compile",
        action="store_true",
        help="decode through torch.compile (CUDA graphs on a GPU); every shape compiles in the warm-up",
    )
    parser.add_argument("--out", default="outputs/bench/generation_speed.json")
    args = parser.parse_args()
    lengths = [int(x) for x in args.lengths.split(",")]
    batches = [int(x) for x in args.batches.split(",")]
    device_name = (
        torch.cuda.get_device_name()
        if args.device.startswith("cuda")
        else f"cpu ({platform.machine()}, {torch.get_num_threads()} threads)"
    )
    from mmm.generation.precision import default_precision

    precision = args.precision or default_precision(args.device)
    report = {
        "device": device_name,
        "dtype": precision,
        "compiled": args.compile,
        "torch": torch.__version__,
        "paper": PAPER,
        "sizes": {},
    }
    # CUDA graphs are recorded on a shape's second call and replayed from the third.
    warmup = 2 if args.compile else 1
    for size in args.sizes:
        model, params = build_model(size, args.device, precision, args.compile)
        entry = {"params_M": round(params / 1e6, 2), "per_sentence_s": {}, "sentences_per_s": {}}
        for batch in batches:
            curve = {}
            for frames in lengths:
                texts = [PROMPTS[i % len(PROMPTS)] for i in range(batch)]
                seconds = timed(lambda: model.generate(texts, [frames] * batch, seed=0), args.repeats, warmup)
                curve[frames] = seconds / batch
                print(
                    f"{size} batch {batch:3d} {frames:4d} frames: {seconds / batch * 1000:8.1f} ms per "
                    "sentence",
                    flush=True,
                )
            entry["per_sentence_s"][str(batch)] = curve
            entry["sentences_per_s"][str(batch)] = round(batch / (np.mean(list(curve.values())) * batch), 2)
        # AITS: batch 1, lengths spread evenly over 40..196 like a test set, mean time per sentence.
        if not args.no_aits:
            spread = np.linspace(40, 196, 9).round().astype(int).tolist()
            per = [
                timed(
                    lambda n=n: model.generate([PROMPTS[n % len(PROMPTS)]], [n], seed=0),
                    max(1, args.repeats // 2),
                    warmup,
                )
                for n in spread
            ]
            entry["aits_s"] = round(float(np.mean(per)), 4)
            print(f"{size}: AITS {entry['aits_s']:.4f} s", flush=True)
        if args.long_minutes <= 0:
            report["sizes"][size] = entry
            continue
        # The long sequence: segments of 196 frames joined by 2-code (8-frame) transitions.
        total = int(round(args.long_minutes * 60 * model.fps))
        count = max(1, int(np.ceil((total + 8) / (196 + 8))))
        texts = [PROMPTS[i % len(PROMPTS)] for i in range(count)]
        frames = [196] * count
        result = {}

        def run_long():
            result["out"] = model.generate_long(texts, frames, seed=0)

        seconds = timed(run_long, max(1, args.repeats // 2), warmup)
        produced = result["out"].features[0].shape[0]
        entry["long"] = {
            "prompts": count,
            "frames": produced,
            "minutes": round(produced / model.fps / 60, 3),
            "seconds": round(seconds, 3),
            "forward_passes": result["out"].forward_passes,
        }
        print(
            f"{size}: {produced} frames ({produced / model.fps / 60:.2f} min) from {count} prompts in "
            f"{seconds:.2f} s",
            flush=True,
        )
        report["sizes"][size] = entry
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(report, indent=2))
    plot(report, out.with_suffix(".png"))
    print(f"wrote {out} and {out.with_suffix('.png')}")


def plot(report: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.5), dpi=110)
    for size, entry in report["sizes"].items():
        for batch, curve in entry["per_sentence_s"].items():
            xs = [int(k) for k in curve]
            ax.plot(xs, [curve[k] for k in curve], marker="o", label=f"{size}, batch {batch}")
    ax.axhline(PAPER["aits_s"], color="grey", linestyle="--", linewidth=1, label="paper AITS (RTX A5000)")
    ax.set_xlabel("motion length (frames)")
    ax.set_ylabel("seconds per sentence")
    ax.set_yscale("log")
    compiled = ", compiled" if report.get("compiled") else ""
    ax.set_title(f"time per sentence ({report['device']}, {report['dtype']}{compiled})", fontsize=9)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


if __name__ == "__main__":
    main()
