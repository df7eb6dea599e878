"""`make stress`: what concurrency and crashes do to the package's files, tried for real.

In a fresh folder (outputs/stress, or --workdir) it trains a tiny pipeline on a small synthetic
dataset (the champion everything else uses), then:

1. N `mmm generate` calls against `models:/mmm-text2motion@champion` with a cold model cache, as
   many at once as memory allows (each process peaks at ~0.8 GB: torch, MLflow and the model; 50
   at once need ~40 GB), all started together up to that bound: every call must exit 0 with a
   complete sample, and the cache must hold complete files only (no temporary file left);
2. two promotions racing, several rounds: a weaker and a stronger text-to-motion candidate promoted
   at the same moment; the champion must always end on the stronger one (lower FID);
3. a stage-1 training SIGKILLed three times while it writes `last.ckpt` (a test hook holds each
   save open before its rename), resumed with `--resume last` each time: every resume must start
   from a complete checkpoint and the training must reach its last step.

It prints what it tried, the figures, and exits 1 if anything was lost or corrupted. JSON in
<workdir>/stress.json.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch

MMM = [sys.executable, "-m", "mmm.cli"]
GENERATE_GIB = (
    0.8  # peak resident memory of one `mmm generate` process (measured: 764 MB with the tiny model)
)
TINY_S1 = [
    "model.tokenizer.width=16",
    "model.tokenizer.num_codes=32",
    "trainer.log_every_n_steps=1",
    "callbacks.preview_clips=0",
    "callbacks.usage_plot=false",
]
TINY_S2 = [
    "model.transformer.embed_dim=32",
    "model.transformer.num_heads=2",
    "model.transformer.num_layers=2",
    "callbacks.preview_captions=0",
]
PROTOCOL = [
    "protocol.batch_size=8",
    "protocol.replications=2",
    "protocol.mm_texts=2",
    "protocol.mm_generations=3",
    "protocol.mm_times=2",
    "protocol.diversity_times=10",
    "protocol.max_batches=null",
]
PIPELINE = {
    "evaluator": [
        "model.hidden_dim=16",
        "model.embed_dim=32",
        "model.text_hidden_dim=32",
        "trainer.max_steps=20",
        "trainer.val_check_interval=20",
        "retrieval.batch_size=8",
    ],
    "stage1": [*TINY_S1, "trainer.max_steps=60", "trainer.val_check_interval=60"],
    "stage2": [*TINY_S2, "trainer.max_steps=60", "trainer.val_check_interval=60"],
    "length": ["model.hidden_dim=16", "trainer.max_steps=10", "trainer.val_check_interval=10"],
    "evaluate": PROTOCOL,
    "promote": PROTOCOL,
}


def run(args: list[str], cwd: Path, **kw) -> subprocess.CompletedProcess:
    return subprocess.run(args, cwd=cwd, capture_output=True, text=True, **kw)


def check(ok: bool, what: str, failures: list[str]) -> None:
    print(f"  {'ok  ' if ok else 'FAIL'} {what}")
    if not ok:
        failures.append(what)


def common(work: Path) -> list[str]:
    return [
        f"data.root={work}/data",
        "data.synthesize.num_clips=80",
        "data.batch_size=8",
        f"logger.tracking_uri=sqlite:///{work}/mlflow.db",
        f"logger.artifact_root={work}/art",
    ]


def champion_pipeline(work: Path) -> float:
    started = time.perf_counter()
    overrides = [f"overrides.{step}=[{','.join(items)}]" for step, items in PIPELINE.items()]
    done = run([*MMM, "pipeline", "full", *common(work), f"state_file={work}/state.json", *overrides], work)
    if done.returncode != 0:
        sys.exit(f"the setup pipeline failed:\n{done.stderr[-3000:]}")
    return time.perf_counter() - started


def concurrent_generate(work: Path, n: int, at_once: int | None, failures: list[str]) -> dict:
    import psutil

    available = psutil.virtual_memory().available / 2**30
    at_once = min(n, at_once or max(2, int(available * 0.8 / GENERATE_GIB)))
    print(
        f"\n[1] {n} `mmm generate` against the champion, cold model cache, {at_once} at once "
        f"({available:.1f} GiB available)"
    )
    shutil.rmtree(work / "outputs" / "cache", ignore_errors=True)
    env = {**os.environ, "MLFLOW_TRACKING_URI": f"sqlite:///{work}/mlflow.db"}
    started = time.perf_counter()
    waiting, running, codes, errors = list(range(n)), {}, {}, []
    while waiting or running:
        while waiting and len(running) < at_once:
            k = waiting.pop(0)
            running[k] = subprocess.Popen(
                [
                    *MMM,
                    "generate",
                    "--text",
                    f"a person walks forward {k}",
                    "--length",
                    "40",
                    "--seed",
                    str(k),
                    "--tracking-uri",
                    f"sqlite:///{work}/mlflow.db",
                    "--out",
                    str(work / "gen" / str(k)),
                ],
                cwd=work,
                env=env,
                stdout=subprocess.DEVNULL,
                stderr=subprocess.PIPE,
                text=True,
            )
        for k, p in list(running.items()):
            if p.poll() is not None:
                err = p.stderr.read()
                codes[k] = p.returncode
                if p.returncode:
                    errors.append(err.strip().splitlines()[-1] if err.strip() else f"exit {p.returncode}")
                del running[k]
        time.sleep(0.1)
    codes = list(codes.values())
    seconds = time.perf_counter() - started
    complete = sum(
        (work / "gen" / str(k) / "0" / "joints.npy").is_file()
        and np.load(work / "gen" / str(k) / "0" / "joints.npy").shape == (40, 22, 3)
        for k in range(n)
    )
    cache = work / "outputs" / "cache"
    leftovers = (
        [
            str(p.relative_to(cache))
            for p in cache.rglob("*")
            if p.name.startswith(".download") or p.name.endswith(".tmp") or ".tmp-" in p.name
        ]
        if cache.exists()
        else []
    )
    check(
        codes.count(0) == n,
        f"{codes.count(0)} of {n} exited 0" + (f" (first error: {errors[0]})" if errors else ""),
        failures,
    )
    check(complete == n, f"{complete} of {n} samples complete, (40, 22, 3) joints", failures)
    check(not leftovers, f"no temporary file left in the model cache ({len(leftovers)} found)", failures)
    print(f"  {seconds:.1f} s for all {n} ({seconds / n:.2f} s per call on {os.cpu_count()} cores)")
    return {
        "calls": n,
        "at_once": at_once,
        "exit_0": codes.count(0),
        "complete": complete,
        "cache_leftovers": leftovers,
        "seconds": round(seconds, 1),
    }


def racing_promotions(work: Path, rounds: int, failures: list[str]) -> dict:
    print(f"\n[2] two text-to-motion promotions racing, {rounds} rounds")
    candidates = {}
    for name, steps in (("weak", 2), ("strong", 200)):
        done = run(
            [
                *MMM,
                "train",
                "stage2",
                *common(work),
                *TINY_S2,
                f"trainer.max_steps={steps}",
                f"trainer.val_check_interval={steps}",
                f"output_dir={work}/outputs/stage2-{name}",
                f"logger.run_name=stress-{name}",
            ],
            work,
        )
        if done.returncode != 0:
            sys.exit(f"training the {name} candidate failed:\n{done.stderr[-3000:]}")
        import mlflow

        client = mlflow.MlflowClient(f"sqlite:///{work}/mlflow.db")
        experiment = client.get_experiment_by_name("mmm-stage2")
        candidates[name] = client.search_runs(
            [experiment.experiment_id], f"attributes.run_name = 'stress-{name}'"
        )[0].info.run_id
    results = []
    for r in range(rounds):
        order = ["weak", "strong"] if r % 2 == 0 else ["strong", "weak"]
        procs = {
            name: subprocess.Popen(
                [*MMM, "promote", "text2motion", f"candidate={candidates[name]}", *common(work), *PROTOCOL],
                cwd=work,
                stdout=subprocess.DEVNULL,
                stderr=subprocess.PIPE,
                text=True,
            )
            for name in order
        }
        codes = {name: p.wait(timeout=1800) for name, p in procs.items()}
        client = mlflow.MlflowClient(f"sqlite:///{work}/mlflow.db")
        champion = client.get_model_version_by_alias("mmm-text2motion", "champion")
        fids = {}
        for version in client.search_model_versions("name = 'mmm-text2motion'"):
            if version.run_id in candidates.values() and "metric.generated/fid" in version.tags:
                fids.setdefault(version.run_id, float(version.tags["metric.generated/fid"]))
        best = min(fids, key=fids.get) if fids else None
        results.append(
            {"round": r, "exit": codes, "champion_run": champion.run_id, "best_run": best, "fids": fids}
        )
        check(
            all(c == 0 for c in codes.values()) and champion.run_id == best,
            f"round {r}: both exited {sorted(codes.values())}, champion is the lower-FID candidate "
            f"({'strong' if champion.run_id == candidates['strong'] else 'weak' if champion.run_id == candidates['weak'] else 'other'}; "  # noqa: E501
            f"FIDs {', '.join(f'{k[:6]} {v:.4f}' for k, v in fids.items())})",
            failures,
        )
    return {"rounds": results, "candidates": candidates}


def killed_training(work: Path, kills: int, failures: list[str]) -> dict:
    print(f"\n[3] a stage-1 training SIGKILLed {kills} times during checkpoint saves, resumed each time")
    out = work / "outputs" / "stage1-killed"
    steps = 2 * (kills + 2)
    train = [
        *MMM,
        "train",
        "stage1",
        *common(work),
        *TINY_S1,
        f"trainer.max_steps={steps}",
        "trainer.val_check_interval=2",
        "trainer.enable_progress_bar=false",
        f"output_dir={out}",
    ]
    env = {**os.environ, "MMM_TEST_CHECKPOINT_SAVE_DELAY": "2"}
    events = []
    for k in range(kills):
        proc = subprocess.Popen(
            [*train, *(["--resume", "last"] if k else [])],
            cwd=work,
            env=env,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
        )
        before = _last_step(out)
        caught = False
        deadline = time.monotonic() + 600
        while time.monotonic() < deadline and proc.poll() is None:
            # a save in progress after the one that was complete when this process started
            if list(out.glob("*/checkpoints/.last.ckpt.*.tmp")) and (_last_step(out) or 0) > (before or 0):
                os.kill(proc.pid, signal.SIGKILL)
                caught = True
                break
            time.sleep(0.05)
        proc.wait(timeout=120)
        kept = _last_step(out)
        events.append({"kill": k + 1, "caught_during_save": caught, "last_ckpt_step": kept})
        check(
            caught and kept is not None,
            f"kill {k + 1}: during a save; last.ckpt still loads (step {kept})",
            failures,
        )
    done = run([*train, "--resume", "last"], work, env={**os.environ})
    final = _last_step(out)
    check(
        done.returncode == 0 and final == steps,
        f"the last resume finished: exit {done.returncode}, last.ckpt at step {final} of {steps}",
        failures,
    )
    folders = [p.name for p in out.iterdir() if p.is_dir()]
    check(len(folders) == 1, f"one run folder for the whole training ({len(folders)})", failures)
    return {"kills": events, "final_step": final, "steps": steps}


def _last_step(out: Path) -> int | None:
    found = list(out.glob("*/checkpoints/last.ckpt"))
    if not found:
        return None
    try:
        return int(torch.load(found[0], map_location="cpu", weights_only=True)["global_step"])
    except Exception as e:  # a corrupt last.ckpt is exactly what this measures
        print(f"  last.ckpt does not load: {e}")
        return -1


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--workdir", default="outputs/stress")
    parser.add_argument("--calls", type=int, default=50)
    parser.add_argument(
        "--at-once",
        type=int,
        default=None,
        help="generate calls running together (default: what memory allows)",
    )
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--kills", type=int, default=3)
    args = parser.parse_args()
    work = Path(args.workdir).resolve()
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    print(f"stress test in {work}: setting up a tiny champion")
    setup = champion_pipeline(work)
    print(f"  pipeline in {setup:.0f} s")
    failures: list[str] = []
    report = {
        "setup_seconds": round(setup, 1),
        "cpu_count": os.cpu_count(),
        "generate": concurrent_generate(work, args.calls, args.at_once, failures),
        "promotions": racing_promotions(work, args.rounds, failures),
        "killed_training": killed_training(work, args.kills, failures),
    }
    report["failures"] = failures
    (work / "stress.json").write_text(json.dumps(report, indent=1))
    verdict = (
        "nothing lost or corrupted" if not failures else f"{len(failures)} FAILED: " + "; ".join(failures)
    )
    print(f"\n{verdict} ({work / 'stress.json'})")
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
