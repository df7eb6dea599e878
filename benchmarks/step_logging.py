"""What the training steps' on-step logging costs, measured inside a real training run.

    python benchmarks/step_logging.py stage1 trainer.max_steps=300 refine.steps=100 logger=none
    python benchmarks/step_logging.py stage2 stage1=PATH trainer.max_steps=300 logger=none
    python benchmarks/step_logging.py evaluator trainer.max_steps=200 logger=none registry.register=false

The arguments after the kind are `mmm train <kind>`'s. The run's training steps alternate between
computing and logging their on-step values (what every step did before
mmm.step_logging) and not (what the steps Lightning does not write now do), so a busy
machine slows both alike. Reported: the median `training_step` time of each half after 20
warm-up steps, and their difference, the time the gating saves on each step it skips; the
optimizer step and backward, which logging does not touch, are outside the timed part.
"""

from __future__ import annotations

import argparse
import importlib
import platform
import statistics
import time

import torch

MODULES = {
    "stage1": ("mmm.tokenizer.module", "TokenizerModule"),
    "stage2": ("mmm.transformer.module", "MaskedTransformerModule"),
    "evaluator": ("mmm.evaluation.contrastive_module", "ContrastiveEvaluatorModule"),
    "length": ("mmm.generation.length_module", "LengthEstimatorModule"),
}
WARMUP = 20


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("kind", choices=sorted(MODULES))
    parser.add_argument("overrides", nargs="*", help="mmm train <kind>'s key=value overrides")
    args = parser.parse_args()
    module_path, class_name = MODULES[args.kind]
    namespace = importlib.import_module(module_path)
    cls = getattr(namespace, class_name)
    calls = {"n": 0}

    def alternate(_module) -> bool:
        calls["n"] += 1
        return calls["n"] % 2 == 0

    namespace.logged_step = alternate  # the name the module's training_step calls
    times: dict[bool, list[float]] = {True: [], False: []}
    step = cls.training_step

    def timed(self, *a, **kw):
        logs = (calls["n"] + 1) % 2 == 0  # what alternate() answers inside this call
        started = time.perf_counter()
        out = step(self, *a, **kw)
        times[logs].append(time.perf_counter() - started)
        return out

    cls.training_step = timed
    from mmm.cli.app import main as mmm_main

    status = mmm_main(["train", args.kind, *args.overrides])
    if status:
        return status
    logged, skipped = (times[flag][WARMUP:] for flag in (True, False))
    if not logged or not skipped:
        raise SystemExit(f"too few steps to compare: give more than {2 * WARMUP} (trainer.max_steps=...)")
    med = {flag: statistics.median(ts) * 1e3 for flag, ts in ((True, logged), (False, skipped))}
    print(
        f"{args.kind}: training_step {med[True]:.2f} ms logging, {med[False]:.2f} ms not "
        f"(medians of {len(logged)} and {len(skipped)} steps): {med[True] - med[False]:.2f} ms saved per "
        f"skipped step; cpu {platform.processor() or platform.machine()}, {torch.get_num_threads()} threads"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
