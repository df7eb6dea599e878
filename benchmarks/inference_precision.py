"""Inference speed and faithfulness per precision (issue 16): fp32 | bf16 | int8 against the
pre-change float32 path.

    python benchmarks/inference_precision.py [--size paper] [--repeats 5] [--threads 2]
        [--out outputs/bench/inference_precision.json]
    python benchmarks/inference_precision.py --faithfulness-only --model models:/mmm-text2motion@champion \\
        --tracking-uri sqlite:///mlflow.db        # a trained model's faithfulness (real text encoder)

Speed (random weights of the size: speed does not depend on their values; text encoding excluded,
the text embeddings are made once, outside the timings; sampling plus the VQ decode are timed):
    b1_196     batch 1 at 196 frames
    b1_40      batch 1 at 40 frames
    mixed32    32 sentences of lengths spread over 40..196, one at a time (batch 1): time per sentence
    b32_196    batch 32 at 196 frames: time per sentence
for the variants
    before     the pre-change path: float32, the plain decoding loop (`sample_tokens(...,
               reference=True)`: text keys/values and the head at every position on every pass) and
               one VQ decoder call per distinct length
    fp32 | bf16 | int8   the package's path at that precision (mmm.generation.precision).
    fp32-compiled | bf16-compiled | int8-compiled   the same through torch.compile with static
               length buckets (mmm.generation.compiled; `--variants ... int8-compiled`); their
               warm-up compiles every shape of the case and is reported as `warmup_s`.
Variants run interleaved (before, fp32, bf16, int8, before, ...) after one warm-up each, so that a
load shared with other processes falls on all alike; medians, spreads (min, max, IQR) and the
speed-up against `before` per repeat (its median) are reported, with `uptime`'s load averages.

Faithfulness against fp32 (same inputs, same seed): top-1 agreement of the logits at masked
positions of partly masked sequences, and the share of identical decoded codes.

Writes JSON and a plot of time per sentence against length (batch 1) per precision.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time
from collections import defaultdict
from pathlib import Path

import numpy as np
import torch

from mmm.cli.common import DEFAULT_TRACKING_URI

VARIANTS = ("before", "fp32", "bf16", "int8")
# torch.compile with static length buckets (mmm.generation.compiled): opt-in, each compiles its
# shapes in the warm-up (which then runs every call of the case once).
COMPILED = ("fp32-compiled", "bf16-compiled", "int8-compiled")
MIXED_LENGTHS = np.linspace(40, 196, 32).round().astype(int).tolist()
# Figures of the paper (RTX A5000), beside ours in the README; no GPU figure is measured here.
PAPER = {"aits_s": 0.081, "40_frames_s": 0.018, "device": "NVIDIA RTX A5000"}


class FakeTextEncoder:
    """CLIP-sized embeddings (sentence 512, 77 words of 512): text encoding is not timed."""

    name, identity, sentence_dim, word_dim, max_words = "fake-clip", "fake-clip-0", 512, 512, 77

    def encode(self, texts):
        from mmm.text import TextEmbedding

        g = torch.Generator().manual_seed(len(texts))
        n = len(texts)
        mask = torch.zeros(n, 77, dtype=torch.bool)
        for i in range(n):
            mask[i, : 6 + i % 12] = True
        return TextEmbedding(torch.randn(n, 512, generator=g), torch.randn(n, 77, 512, generator=g), mask, 0)


def build_model(size: str):
    from mmm.config import compose
    from mmm.generation.model import TextToMotion
    from mmm.optim import OptimConfig
    from mmm.tokenizer.configs import TokenizerLossConfig
    from mmm.tokenizer.module import TokenizerModule
    from mmm.tokenizer.network import TokenizerConfig
    from mmm.transformer.network import MaskedMotionTransformer, TransformerConfig

    cfg = compose("train_stage2", [f"model={size}"]).model
    torch.manual_seed(0)
    tokenizer = TokenizerModule(263, TokenizerConfig(**cfg.tokenizer), OptimConfig(), TokenizerLossConfig())
    text = FakeTextEncoder()
    transformer = MaskedMotionTransformer(
        tokenizer.tokenizer.codebook.detach().normal_(),
        TransformerConfig(**cfg.transformer),
        text.sentence_dim,
        text.word_dim,
    )
    return TextToMotion(tokenizer, transformer, text, {"size": size})


def decode_before(model, codes):
    """The pre-change VQ decode: one decoder call per distinct length."""
    groups = defaultdict(list)
    for i, c in enumerate(codes):
        groups[len(c)].append(i)
    out = [None] * len(codes)
    for length, members in groups.items():
        batch = torch.as_tensor(np.stack([codes[i] for i in members]), dtype=torch.long)
        x = model.tokenizer.tokenizer.decode(batch) * model.tokenizer.std + model.tokenizer.mean
        for i, f in zip(members, x.cpu().numpy()):
            out[i] = f
    return out


class Runner:
    def __init__(self, model):
        from mmm.generation.compiled import CompiledDecoding, default_compile_mode
        from mmm.generation.precision import inference_copy

        self.model = model
        self.copies = {p: inference_copy(model.transformer, p) for p in ("fp32", "bf16", "int8")}
        mode = default_compile_mode(model.device)
        for p in ("fp32", "bf16", "int8"):
            self.copies[f"{p}-compiled"] = CompiledDecoding(self.copies[p], mode=mode)

    @torch.no_grad()
    def generate(self, variant: str, emb, frames: list[int], seed: int = 0):
        """(codes, passes) of one batch; the timed unit (sampling and VQ decode)."""
        from mmm.generation.sampler import SamplingConfig, frames_to_codes, sample_tokens

        lengths = frames_to_codes(torch.tensor(frames), self.model.unit)
        transformer = self.model.transformer if variant == "before" else self.copies[variant]
        result = sample_tokens(
            transformer,
            emb,
            lengths,
            SamplingConfig(),
            generator=torch.Generator().manual_seed(seed),
            reference=variant == "before",
        )
        codes = [result.tokens[i, : int(n)].numpy() for i, n in enumerate(lengths)]
        if variant == "before":
            decode_before(self.model, codes)
        else:
            self.model.decode(codes)
        return codes, result.forward_passes


def load() -> list[float]:
    return [round(x, 2) for x in os.getloadavg()]


CASES = ("b1_196", "b1_40", "mixed32", "b32_196")


def speed(runner: Runner, variants, repeats: dict, cases=CASES, warmup: bool = True) -> dict:
    """Each case: `repeats[case]` rounds; in each, every call (one batch) runs every variant in
    turn, so the variants share the same moments of the machine's load."""
    text = runner.model.text_encoder
    all_cases = {
        "b1_196": [(text.encode(["a"]), [196])],
        "b1_40": [(text.encode(["a"]), [40])],
        "mixed32": [(text.encode(["a"]), [n]) for n in MIXED_LENGTHS],
        "b32_196": [(text.encode(["a"] * 32), [196] * 32)],
    }
    report = {}
    for case in cases:
        calls = all_cases[case]
        sentences = sum(len(frames) for _, frames in calls)
        times = {v: [] for v in variants}
        per_length = {v: defaultdict(list) for v in variants}
        passes = {}
        warmup_s = {}
        if warmup:
            for v in variants:
                t0 = time.perf_counter()
                for call in calls if v in COMPILED else calls[:1]:
                    runner.generate(v, *call)
                warmup_s[v] = round(time.perf_counter() - t0, 1)
        started = time.perf_counter()
        for _ in range(repeats.get(case, 1)):
            total = dict.fromkeys(variants, 0.0)
            for emb, frames in calls:
                for v in variants:
                    t0 = time.perf_counter()
                    _, passes[v] = runner.generate(v, emb, frames)
                    seconds = time.perf_counter() - t0
                    total[v] += seconds
                    if len(frames) == 1:
                        per_length[v][frames[0]].append(seconds)
            for v in variants:
                times[v].append(total[v] / sentences)
        entry = {
            "sentences": sentences,
            "batch": len(calls[0][1]),
            "frames": sorted({n for _, frames in calls for n in frames}),
            "load_after": load(),
            "wall_s": round(time.perf_counter() - started, 1),
            "variants": {},
        }
        for v in variants:
            t = sorted(times[v])
            q = np.percentile(t, [25, 75]).tolist()
            row = {
                "precision": "fp32" if v == "before" else v.split("-")[0],
                "path": "pre-change (plain loop, per-length decode)"
                if v == "before"
                else "package, compiled (static length buckets)"
                if v in COMPILED
                else "package",
                "warmup_s": warmup_s.get(v),
                "median_s_per_sentence": statistics.median(t),
                "min_s": t[0],
                "max_s": t[-1],
                "iqr_s": q[1] - q[0],
                "repeats": len(t),
                "passes_last_batch": passes[v],
            }
            if "before" in times and v != "before":
                ratios = [b / x for b, x in zip(times["before"], times[v])]
                row["speedup_vs_before_median"] = statistics.median(ratios)
                row["speedup_vs_before_range"] = [min(ratios), max(ratios)]
                if case == "mixed32":  # per sentence, same moment: the ratio's spread over sentences
                    per = [
                        statistics.median(per_length["before"][n]) / statistics.median(per_length[v][n])
                        for n in per_length[v]
                    ]
                    row["speedup_per_sentence_median"] = statistics.median(per)
                    row["speedup_per_sentence_range"] = [min(per), max(per)]
            if case == "mixed32":
                row["per_length_s"] = {str(n): statistics.median(s) for n, s in sorted(per_length[v].items())}
            entry["variants"][v] = row
            print(
                f"{case:8s} {v:6s} {row['median_s_per_sentence'] * 1000:9.1f} ms/sentence"
                + (f"  x{row['speedup_vs_before_median']:.2f}" if "speedup_vs_before_median" in row else ""),
                flush=True,
            )
        report[case] = entry
    return report


@torch.no_grad()
def faithfulness(runner: Runner, embed, lengths_frames: list[int], variants, seeds=(0, 1, 2)) -> dict:
    """Against fp32, for each of `variants` (fp32 always): top-1 agreement of logits at masked
    positions, share of identical codes."""
    from mmm.generation.sampler import frames_to_codes

    model = runner.model
    lengths = frames_to_codes(torch.tensor(lengths_frames), model.unit)
    emb = embed(len(lengths_frames))
    B, M = len(lengths), int(lengths.max()) + 1
    t = model.transformer
    g = torch.Generator().manual_seed(123)
    # Partly masked sequences (a random share of each row masked, the rest random codes), END, PAD.
    tokens = torch.randint(0, t.num_codes, (B, M), generator=g)
    share = torch.rand(B, 1, generator=g)
    tokens = torch.where(torch.rand(B, M, generator=g) < share, torch.full_like(tokens, t.mask_id), tokens)
    positions = torch.arange(M)[None]
    tokens = torch.where(positions == lengths[:, None], torch.full_like(tokens, t.end_id), tokens)
    tokens = torch.where(positions > lengths[:, None], torch.full_like(tokens, t.pad_id), tokens)
    masked = (tokens == t.mask_id).flatten().nonzero().squeeze(1)
    variants = ["fp32"] + [v for v in variants if v not in ("before", "fp32")]
    copies = {p: runner.copies[p] for p in variants}
    logits = {}
    for p, copy in copies.items():
        context = copy.text_context(emb.sentence, emb.words, emb.word_mask)
        logits[p] = copy.forward_cached(tokens, context, head_rows=masked)
    codes = {p: [runner.generate(p, emb, lengths_frames, seed)[0] for seed in seeds] for p in copies}
    out = {}
    for p in copies:
        same = [
            np.mean(np.concatenate([a == b for a, b in zip(c, r)])) for c, r in zip(codes[p], codes["fp32"])
        ]
        out[p] = {
            "top1_agreement": float((logits[p].argmax(-1) == logits["fp32"].argmax(-1)).float().mean()),
            "max_abs_logit_diff": float((logits[p] - logits["fp32"]).abs().max()),
            "identical_codes_share": float(np.mean(same)),
            "positions": int(len(masked)),
            "seeds": list(seeds),
        }
        print(f"faithfulness {p}: {out[p]}", flush=True)
    return out


def plot(report: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.5), dpi=110)
    for v, row in report["speed"]["mixed32"]["variants"].items():
        curve = row.get("per_length_s") or {}
        xs = [int(k) for k in curve]
        label = "fp32 before (plain loop)" if v == "before" else v
        ax.plot(xs, list(curve.values()), marker="o", markersize=3, label=label)
    ax.axhline(PAPER["aits_s"], color="grey", linestyle="--", linewidth=1, label="paper AITS (RTX A5000)")
    ax.set_xlabel("motion length (frames)")
    ax.set_ylabel("seconds per sentence (batch 1)")
    ax.set_yscale("log")
    ax.set_title(f"{report['size']} size, {report['device']}", fontsize=9)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--size", default="paper")
    parser.add_argument("--repeats", type=int, default=5, help="rounds of b1_196 and b1_40")
    parser.add_argument("--long-repeats", type=int, default=1, help="rounds of mixed32 and b32_196")
    parser.add_argument("--cases", nargs="+", default=list(CASES), choices=CASES)
    parser.add_argument("--no-faithfulness", action="store_true")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=VARIANTS + COMPILED)
    parser.add_argument("--faithfulness-only", action="store_true", help="skip the speed cases")
    parser.add_argument(
        "--model", default=None, help="a trained model (models:/..., run id, path): faithfulness"
    )
    parser.add_argument("--tracking-uri", default=DEFAULT_TRACKING_URI)
    parser.add_argument("--out", default="outputs/bench/inference_precision.json")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    report = {
        "device": f"cpu ({platform.machine()}, {torch.get_num_threads()} threads, "
        f"{torch.backends.cpu.get_cpu_capability()})",
        "torch": torch.__version__,
        "size": args.size,
        "load_before": load(),
        "paper": PAPER,
        "timed": "sampling + VQ decode; text encoding excluded",
    }
    if args.model:
        from mmm.generation.model import TextToMotion

        model = TextToMotion.load(args.model, args.tracking_uri)
        report["size"] = f"trained model {args.model}"
        prompts = [
            "a person walks forward",
            "someone jumps twice",
            "a person waves with the right hand",
            "the man squats down",
            "a person runs forward quickly",
            "a person turns left",
            "someone kicks with the left foot",
            "a person sits down",
        ]

        def embed(n):
            return model.encode_text([prompts[i % len(prompts)] for i in range(n)])

    else:
        model = build_model(args.size)

        def embed(n):
            return model.text_encoder.encode(["a"] * n)

    runner = Runner(model)
    if not args.faithfulness_only:
        repeats = {"b1_196": args.repeats, "b1_40": args.repeats}
        repeats.update({"mixed32": args.long_repeats, "b32_196": args.long_repeats})
        report["speed"] = speed(runner, args.variants, repeats, args.cases)
    if not args.no_faithfulness:
        frames = np.linspace(40, 196, 8).round().astype(int).tolist()
        report["faithfulness"] = faithfulness(runner, embed, frames, args.variants)
    report["load_after"] = load()
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(report, indent=2))
    print(f"wrote {out}")
    if "mixed32" in report.get("speed", {}):
        plot(report, out.with_suffix(".png"))
        print(f"wrote {out.with_suffix('.png')}")


if __name__ == "__main__":
    main()
