"""Data at scale: loaders, caches and token/text pipelines on HumanML3D- and Motion-X-sized data.

    python benchmarks/data_scale.py [--num-clips 15000 40000] [--root outputs/bench/data]
                                    [--workers 0 1 2] [--epoch-limit-s 240] [--no-rerun]
                                    [--skip STEP ...] [--only STEP ...]
                                    [--out outputs/bench/data_scale.json]

For each size a synthetic dataset of that many clips (twice as many motions with the mirrors) is
generated into <root>/synthetic-<clips>-seed<seed> (generation timed; an existing dataset of the
same size and seed is reused, and the JSON says so), then every step runs in a fresh process, so
its peak memory is its own:

  load_files         the loader as the format gives it: every .npy and .txt file read one by one
  pack               the feature pack built from scratch (new_joint_vecs/*.npy -> one memory-mapped
                     file, what every later load reads; see mmm.data.humanml3d.FeatureStore)
  load               index (splits), captions, arrays, and the items of train/val/test as stage 2
                     loads them
  stats              Mean/Std over every feature file (`mmm data stats`)
  stage1_cli         `mmm train stage1 ... trainer.max_steps=1`, cold (the dataset fingerprint is
                     hashed for the first time): the tiny tokenizer whose near-random weights
                     tokenize the data below
  tokenize           every motion of train/val/test through that tokenizer (the token cache, cold)
  captions           the caption-embedding cache (MiniLM, the default text encoder), cold
  stage1_loader,     the training dataloaders alone, one epoch (capped by --epoch-limit-s), no
  stage2_loader      model, at each --workers count: samples/s
  stage1_cli_cached, `mmm train stage1|stage2 ... trainer.max_steps=1` with every cache warm:
  stage2_cli_cached  seconds from the command's start to the end of its first optimizer step, and
                     to its exit

--only STEP ... measures just those steps (and what they need) and keeps the other figures of the
same size from the existing --out; --skip STEP ... leaves steps out.

Peak memory: ru_maxrss of the step's process (it counts pages of memory-mapped files the step
touched, which the kernel can drop: shared page cache, not the process's own) and the peak of its
anonymous memory (RssAnon, sampled every 20 ms: what the process really holds). The tiny models'
training throughput at batch 64 comes from benchmarks/train_speed.py's JSON when it has it, else
it is measured now the same way; the loaders' goal (>= 10x what the models consume) is checked
against the stricter of that and the README's uncontended figures. Timings are on a shared
machine: the JSON records the cores and `uptime` load averages.
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
import threading
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
GiB = 2**30
# The tiny models' training samples/s at batch 64 in the README's training-speed table (steps/s
# x 64, measured uncontended on the 2-core machine): the loaders' goal is 10x the stricter of
# these and what the models do now.
README_TINY_SAMPLES_PER_S = {"stage1": 6.84 * 64, "stage2": 4.77 * 64}


# ---------------------------------------------------------------- measuring inside a step


class AnonPeak:
    """The peak of this process's anonymous resident memory (RssAnon), sampled in a thread."""

    def __init__(self, interval: float = 0.02):
        self.interval, self.peak, self._stop = interval, 0, threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    @staticmethod
    def now() -> int:
        try:
            for line in Path("/proc/self/status").read_text().splitlines():
                if line.startswith("RssAnon:"):
                    return int(line.split()[1]) * 1024
        except OSError:
            pass
        return 0

    def _run(self) -> None:
        while not self._stop.is_set():
            self.peak = max(self.peak, self.now())
            self._stop.wait(self.interval)

    def stop(self) -> int:
        self._stop.set()
        self._thread.join()
        self.peak = max(self.peak, self.now())
        return self.peak


def _mib(n: float) -> float:
    return round(n / 2**20, 1)


def _memory(anon: AnonPeak) -> dict:
    return {
        "peak_rss_MiB": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
        "peak_anon_MiB": _mib(anon.stop()),
    }


def _data_cfg(data: Path, clips: int, workers: int = 0):
    from mmm.data.configs import DataConfig, SynthConfig

    return DataConfig(root=str(data), num_workers=workers, synthesize=SynthConfig(num_clips=clips))


def _splits(data: Path) -> list[str]:
    return [s for s in ("train", "val", "test") if (data / f"{s}.txt").exists()]


def step_load_files(data: Path, clips: int, **_) -> dict:
    """The per-file loader (what the format gives): every split's ids, captions and arrays."""
    from mmm.data import humanml3d as h

    t0 = time.perf_counter()
    ids = sorted({i for s in _splits(data) for i in h.read_split(data, s)})
    t_index = time.perf_counter() - t0
    t0 = time.perf_counter()
    captions = sum(len(h.read_captions(data / "texts" / f"{i}.txt")) for i in ids)
    t_captions = time.perf_counter() - t0
    t0 = time.perf_counter()
    arrays = [h.load_motion(data / "new_joint_vecs" / f"{i}.npy", 263) for i in ids]
    t_arrays = time.perf_counter() - t0
    frames = sum(a.shape[0] for a in arrays)
    return {
        "motions": len(ids),
        "frames": frames,
        "captions": captions,
        "index_s": round(t_index, 2),
        "captions_s": round(t_captions, 2),
        "arrays_s": round(t_arrays, 2),
        "seconds": round(t_index + t_captions + t_arrays, 2),
        "arrays_GiB": round(sum(a.nbytes for a in arrays) / GiB, 2),
    }


def step_pack(data: Path, clips: int, **_) -> dict:
    from mmm.data import humanml3d as h

    shutil.rmtree(data / h.PACK_DIR, ignore_errors=True)
    shutil.rmtree(data / h.CAPTION_PACK_DIR, ignore_errors=True)
    t0 = time.perf_counter()
    store = h.FeatureStore(data, 263)
    seconds = time.perf_counter() - t0
    t0 = time.perf_counter()
    captions = h.CaptionStore(data)
    captions_s = time.perf_counter() - t0
    if not (store.packed and captions.packed):
        raise RuntimeError(f"no pack was built in {data}")
    return {
        "seconds": round(seconds, 2),
        "captions_s": round(captions_s, 2),
        "pack": str(store.folder),
        "caption_pack": str(captions.folder),
        "built": store.built,
    }


def step_load(data: Path, clips: int, **_) -> dict:
    """The packed loader: index, captions, arrays, then the items of every split as stage 2 loads
    them (DataConfig.items) and the whole clips stage 1 loads (load_clips)."""
    from mmm.data import humanml3d as h

    t0 = time.perf_counter()
    ids = sorted({i for s in _splits(data) for i in h.read_split(data, s)})
    t_index = time.perf_counter() - t0
    t0 = time.perf_counter()
    caption_store = h.CaptionStore(data)
    n_captions = sum(len(caption_store.load(i)) for i in ids)
    t_captions = time.perf_counter() - t0
    t0 = time.perf_counter()
    store = h.FeatureStore(data, 263)
    arrays = [store.load(i) for i in ids]
    t_arrays = time.perf_counter() - t0
    cfg = _data_cfg(data, clips)
    t0 = time.perf_counter()
    items = {s: cfg.items(s)[0] for s in _splits(data)}
    t_items = time.perf_counter() - t0
    t0 = time.perf_counter()
    for s in ("train", "val"):
        h.load_clips(data, s, feature_dim=263, min_length=64)
    t_clips = time.perf_counter() - t0
    return {
        "packed": store.packed and caption_store.packed,
        "motions": len(ids),
        "frames": sum(a.shape[0] for a in arrays),
        "captions": n_captions,
        "items": {s: len(v) for s, v in items.items()},
        "index_s": round(t_index, 2),
        "captions_s": round(t_captions, 2),
        "arrays_s": round(t_arrays, 2),
        "seconds": round(t_index + t_captions + t_arrays, 2),
        "items_all_splits_s": round(t_items, 2),
        "clips_train_val_s": round(t_clips, 2),
    }


def step_stats(data: Path, clips: int, **_) -> dict:
    import numpy as np

    from mmm.data.humanml3d import compute_stats

    t0 = time.perf_counter()
    mean, std, report = compute_stats(data, 22)
    seconds = time.perf_counter() - t0
    ref_mean, ref_std = np.load(data / "Mean.npy"), np.load(data / "Std.npy")
    return {
        "seconds": round(seconds, 2),
        "files": report.kept_clips,
        "max_abs_diff_vs_generator_mean": float(np.abs(mean - ref_mean).max()),
        "max_rel_diff_vs_generator_std": float((np.abs(std - ref_std) / ref_std).max()),
    }


def _epoch(loader, limit_s: float, count) -> dict:
    t0 = time.perf_counter()
    first = None
    samples = batches = 0
    complete = True
    for batch in loader:
        if first is None:
            first = time.perf_counter() - t0
        samples += count(batch)
        batches += 1
        if time.perf_counter() - t0 > limit_s:
            complete = False
            break
    seconds = time.perf_counter() - t0
    return {
        "samples": samples,
        "batches": batches,
        "batches_per_epoch": len(loader),
        "epoch_complete": complete,
        "seconds": round(seconds, 2),
        "first_batch_s": round(first or 0.0, 2),
        "samples_per_s": round(samples / seconds, 1) if seconds else None,
    }


def step_stage1_loader(data: Path, clips: int, workers: int, limit_s: float, **_) -> dict:
    from mmm.data.datamodule import TokenizerDataModule

    dm = TokenizerDataModule(_data_cfg(data, clips, workers))
    t0 = time.perf_counter()
    dm.setup("fit")
    setup = time.perf_counter() - t0
    loader = dm.train_dataloader()
    out = _epoch(loader, limit_s, lambda b: b.shape[0])
    return {"workers": workers, "setup_s": round(setup, 2), "windows": len(dm.datasets["train"]), **out}


def _tokenizer(ckpt: str):
    from mmm.tokenizer.load import load_tokenizer

    return load_tokenizer(ckpt, "sqlite:///:memory:")


def _token_folder(data: Path, cache: Path, identity: str) -> tuple[Path, float]:
    from mmm.data.tokens import token_cache_folder
    from mmm.fingerprint import dataset_fingerprint

    t0 = time.perf_counter()
    fingerprint = dataset_fingerprint(data)
    return token_cache_folder(cache / "tokens", identity, fingerprint), time.perf_counter() - t0


def step_tokenize(data: Path, clips: int, cache: Path, ckpt: str, **_) -> dict:
    from mmm.data.tokens import tokenize_dataset

    tokenizer, source = _tokenizer(ckpt)
    folder, t_fp = _token_folder(data, cache, source.identity)
    shutil.rmtree(folder, ignore_errors=True)
    t0 = time.perf_counter()
    tokens = tokenize_dataset(tokenizer, data, folder, meta={"tokenizer": source.identity}, progress=False)
    seconds = time.perf_counter() - t0
    t0 = time.perf_counter()
    n = len(tokens)  # reading the cache back (what stage-2 setup does)
    read = time.perf_counter() - t0
    return {
        "seconds": round(seconds, 2),
        "motions": n,
        "fingerprint_s": round(t_fp, 2),
        "read_back_s": round(read, 2),
        "folder": str(folder),
    }


def _all_captions(data: Path, clips: int) -> list[str]:
    cfg = _data_cfg(data, clips)
    captions = set()
    for s in _splits(data):
        captions.update(c.text for item in cfg.items(s)[0] for c in item.captions)
    return sorted(captions)


def step_captions(data: Path, clips: int, cache: Path, **_) -> dict:
    from mmm.text.encoders import TextConfig, build_text

    t0 = time.perf_counter()
    captions = _all_captions(data, clips)
    t_collect = time.perf_counter() - t0
    encoder, caption_cache = build_text(TextConfig(cache_dir=str(cache / "text")))
    shutil.rmtree(caption_cache.folder, ignore_errors=True)
    encoder, caption_cache = build_text(TextConfig(cache_dir=str(cache / "text")))
    t0 = time.perf_counter()
    counts = caption_cache.build(encoder, captions, progress=False)
    seconds = time.perf_counter() - t0
    return {
        "seconds": round(seconds, 2),
        "captions": len(captions),
        "captions_per_s": round(len(captions) / seconds, 1),
        "collect_s": round(t_collect, 2),
        "added": counts["added"],
        "folder": str(caption_cache.folder),
    }


def step_stage2_loader(data: Path, clips: int, cache: Path, ckpt: str, workers: int, limit_s: float, **_):
    from mmm.data.datamodule import TokenTextDataModule
    from mmm.text.encoders import TextConfig, build_text

    t0 = time.perf_counter()
    tokenizer, source = _tokenizer(ckpt)
    encoder, caption_cache = build_text(TextConfig(cache_dir=str(cache / "text")))
    dm = TokenTextDataModule(
        _data_cfg(data, clips, workers),
        0,
        tokenizer,
        source.identity,
        encoder,
        caption_cache,
        str(cache / "tokens"),
    )
    dm.prepare_data()  # every cache warm: reads them
    t_prepare = time.perf_counter() - t0
    t0 = time.perf_counter()
    dm.setup("fit")
    setup = time.perf_counter() - t0
    out = _epoch(dm.train_dataloader(), limit_s, lambda b: b["tokens"].shape[0])
    return {
        "workers": workers,
        "prepare_s": round(t_prepare, 2),
        "setup_s": round(setup, 2),
        "items": len(dm.datasets["train"]),
        **out,
    }


# The real CLI (`mmm ...`, its entry point) with one global hook: the end of the first optimizer
# step is written to $MMM_BENCH_FIRST_STEP as seconds since the Unix epoch.
_CLI_LAUNCHER = """
import os, sys, time
import torch

def _first_step(optimizer, args, kwargs):
    path = os.environ["MMM_BENCH_FIRST_STEP"]
    if not os.path.exists(path):
        with open(path, "w") as fh:
            fh.write(repr(time.time()))

from torch.optim.optimizer import register_optimizer_step_post_hook
register_optimizer_step_post_hook(_first_step)
from mmm.cli import main
sys.argv = ["mmm", *sys.argv[1:]]
sys.exit(main())
"""


def step_cli(data: Path, clips: int, cache: Path, ckpt: str, stage: str, **_) -> dict:
    """The real CLI with trainer.max_steps=1 (and one validation batch, so a checkpoint is
    written): seconds from the command's start to the end of its first training step, and to its
    exit; peak memory of the CLI process."""
    runs = cache / f"runs-{stage}"
    args = [
        "train",
        stage,
        f"data.root={data}",
        f"data.synthesize.num_clips={clips}",
        "trainer.max_steps=1",
        "trainer.val_check_interval=1",
        "trainer.limit_val_batches=0.05",
        "logger=none",
        f"output_dir={runs}",
    ]
    if stage == "stage2":
        args += [
            f"stage1={ckpt}",
            f"token_cache_dir={cache / 'tokens'}",
            f"text.cache_dir={cache / 'text'}",
            "callbacks.preview_captions=0",
            "callbacks.adherence_captions=0",
        ]
    marker = cache / f".first-step-{stage}-{os.getpid()}"
    marker.unlink(missing_ok=True)
    env = dict(os.environ, MMM_BENCH_FIRST_STEP=str(marker))
    start = time.time()
    t0 = time.perf_counter()
    proc = subprocess.run(
        [sys.executable, "-c", _CLI_LAUNCHER, *args], cwd=REPO, env=env, capture_output=True, text=True
    )
    total = time.perf_counter() - t0
    if proc.returncode != 0:
        raise RuntimeError(f"mmm {' '.join(args)} failed ({proc.returncode}):\n{proc.stderr[-3000:]}")
    first_step = float(marker.read_text()) - start if marker.exists() else None
    marker.unlink(missing_ok=True)
    ckpts = sorted(runs.glob("*/checkpoints/*.ckpt"), key=lambda p: p.stat().st_mtime)
    return {
        "command": "mmm " + " ".join(args),
        "to_first_step_s": round(first_step, 2) if first_step is not None else None,
        "to_exit_s": round(total, 2),
        "checkpoint": str(ckpts[-1]) if ckpts else None,
        "peak_rss_MiB": round(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024, 1),
    }


def child(args) -> None:
    anon = AnonPeak()
    kwargs = json.loads(args.child_args)
    out = globals()[f"step_{args.child}"](
        Path(kwargs.pop("data")), **{**kwargs, "cache": Path(kwargs.get("cache", "."))}
    )
    mem = _memory(anon)
    if args.child == "cli":
        mem = {"peak_rss_MiB": out.pop("peak_rss_MiB"), "peak_anon_MiB": None}
    print(json.dumps({**out, **mem}))


# ---------------------------------------------------------------- the parent


def run_step(name: str, **kwargs) -> dict:
    kwargs = {k: str(v) if isinstance(v, Path) else v for k, v in kwargs.items()}
    cmd = [sys.executable, __file__, "--child", name, "--child-args", json.dumps(kwargs)]
    out = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True)
    if out.returncode != 0:
        raise RuntimeError(f"step {name} failed:\n{out.stderr[-4000:]}")
    result = json.loads(out.stdout.strip().splitlines()[-1])
    print(f"  {name:14s} {json.dumps(result)[:300]}", flush=True)
    return result


def du(path: Path, exclude: tuple[str, ...] = ()) -> float:
    total = 0
    for dirpath, dirnames, filenames in os.walk(path):
        dirnames[:] = [d for d in dirnames if d not in exclude]
        for f in filenames:
            try:
                total += os.lstat(os.path.join(dirpath, f)).st_blocks * 512
            except OSError:
                pass
    return round(total / GiB, 3)


def load_average() -> dict:
    text = subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()
    one, five, fifteen = os.getloadavg()
    return {
        "uptime": text,
        "load_1m": round(one, 2),
        "load_5m": round(five, 2),
        "load_15m": round(fifteen, 2),
    }


def ensure_dataset(folder: Path, clips: int, seed: int) -> dict:
    """Generate the dataset (timed, in a child for its peak memory), or reuse one of the same size
    and seed."""
    record = folder.with_name(folder.name + ".generation.json")
    synthesis = folder / "synthesis.json"
    if synthesis.exists() and (folder / "all.txt").exists():
        made = json.loads(synthesis.read_text())
        if made.get("num_clips") == clips and made.get("seed") == seed:
            previous = json.loads(record.read_text()) if record.exists() else {}
            return {"reused": True, "generated_earlier": previous}
        raise SystemExit(f"{folder} holds another dataset ({made}); choose another --root")
    code = (
        "import json,resource,sys,time\n"
        "from mmm.data.synthetic.generate import generate_dataset\n"
        "t0=time.perf_counter()\n"
        f"generate_dataset({str(folder)!r}, num_clips={clips}, seed={seed}, progress=False)\n"
        "print(json.dumps({'seconds': round(time.perf_counter()-t0, 1), 'peak_rss_MiB': "
        "round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss/1024, 1)}))\n"
    )
    print(f"generating {clips} clips into {folder} ...", flush=True)
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, check=True)
    result = {"num_clips": clips, "seed": seed, **json.loads(out.stdout.strip().splitlines()[-1])}
    record.write_text(json.dumps(result))
    return {"reused": False, **result}


def step_model_speed(data: Path, stage: int, size: str, batch: int, steps: int = 6, **_) -> dict:
    """Training step time of one stage at `size` on random inputs of the real shapes, as
    benchmarks/train_speed.py measures it (float32)."""
    sys.path.insert(0, str(REPO / "benchmarks"))
    from train_speed import measure

    return measure(stage, size, batch, steps, 2, "cpu", ["32-true"])[0]


def model_speeds(path: Path) -> dict:
    """The tiny models' training samples/s at batch 64: from `path` (train_speed.py's JSON) where
    it has them, else measured now."""
    rows = json.loads(path.read_text()) if path.exists() else []
    speeds = {
        f"stage{r['stage']}": r["samples_per_s"]
        for r in rows
        if r.get("size") == "tiny" and r.get("batch") == 64 and r.get("precision", "32-true") == "32-true"
    }
    sources = {k: f"{path}" for k in speeds}
    for stage in (1, 2):
        if f"stage{stage}" not in speeds:
            r = run_step("model_speed", data=".", stage=stage, size="tiny", batch=64)
            speeds[f"stage{stage}"] = r["samples_per_s"]
            sources[f"stage{stage}"] = "measured now (train_speed.py's approach)"
    return {**speeds, "source": sources}


STEP_NAMES = (
    "load_files",
    "pack",
    "load",
    "stats",
    "stage1_cli",
    "tokenize",
    "captions",
    "stage1_loader",
    "stage2_loader",
    "stage1_cli_cached",
    "stage2_cli_cached",
)


def measure_size(clips: int, args, previous: dict | None = None) -> dict:
    """Every step at one size; with --only, just those steps, the others kept from `previous`
    (the same size in the existing JSON)."""
    root = Path(args.root)
    data = root / f"synthetic-{clips}-seed{args.seed}"
    cache = root / f"cache-{clips}-seed{args.seed}"
    cache.mkdir(parents=True, exist_ok=True)
    res: dict = dict(previous or {})
    res.update({"clips": clips, "dataset": str(data), "cache": str(cache)})
    if not (args.only and "generation" in res):
        res["generation"] = ensure_dataset(data, clips, args.seed)
    res["load_average_start"] = load_average()
    common = {"data": data, "clips": clips, "cache": cache}

    def wanted(name: str) -> bool:
        if name in args.skip:
            return False
        return not args.only or name in args.only or name not in res

    if wanted("load_files"):
        res["load_files"] = run_step("load_files", **common)
    if wanted("pack"):
        res["pack"] = run_step("pack", **common)
    if wanted("load"):
        res["load"] = run_step("load", **common)
    if wanted("stats"):
        res["stats"] = run_step("stats", **common)
    if wanted("stage1_cli") or not (res.get("stage1_cli") or {}).get("checkpoint"):
        res["stage1_cli"] = run_step("cli", **common, ckpt="", stage="stage1")
    ckpt = res["stage1_cli"]["checkpoint"]
    if wanted("tokenize"):
        res["tokenize"] = run_step("tokenize", **common, ckpt=ckpt)
    if wanted("captions"):
        res["captions"] = run_step("captions", **common, ckpt=ckpt)
    for stage in ("stage1", "stage2"):
        if f"{stage}_loader" in args.skip:
            continue
        if (
            not args.only
            or f"{stage}_loader" in args.only
            or any(f"{stage}_loader_w{w}" not in res for w in args.workers)
        ):
            for w in args.workers:
                res[f"{stage}_loader_w{w}"] = run_step(
                    f"{stage}_loader", **common, ckpt=ckpt, workers=w, limit_s=args.epoch_limit_s
                )
    if not args.no_rerun:
        # Everything cached now (dataset fingerprint, feature pack, tokens, caption embeddings).
        for stage in ("stage1", "stage2"):
            if wanted(f"{stage}_cli_cached"):
                res[f"{stage}_cli_cached"] = run_step("cli", **common, ckpt=ckpt, stage=stage)
    res["disk_GiB"] = {
        "dataset": du(data, exclude=(".features-pack", ".captions-pack")),
        "feature_pack": du(data / ".features-pack"),
        "caption_pack": du(data / ".captions-pack"),
        "new_joint_vecs": du(data / "new_joint_vecs"),
        "token_cache": du(Path(res["tokenize"]["folder"])) if "tokenize" in res else None,
        "caption_cache": du(Path(res["captions"]["folder"])) if "captions" in res else None,
    }
    res["load_average_end"] = load_average()
    return res


def goals(res: dict, speed: dict) -> dict:
    out = {}
    load = res["load"]
    out["load_under_60s"] = max(load["seconds"], load["items_all_splits_s"]) < 60
    out["load_under_4GiB"] = max(load["peak_anon_MiB"], 0) < 4096
    for stage in ("stage1", "stage2"):
        rates = [res[k]["samples_per_s"] for k in res if k.startswith(f"{stage}_loader_w")]
        # The stricter of the models' rate measured now and the README's uncontended figure.
        model = max(speed.get(stage) or 0, README_TINY_SAMPLES_PER_S[stage])
        if rates:
            out[f"{stage}_loader_10x_model"] = max(rates) >= 10 * model
            out[f"{stage}_loader_x_model"] = round(max(rates) / model, 1)
    for stage in ("stage1", "stage2"):
        rerun = (res.get(f"{stage}_cli_cached") or {}).get("to_first_step_s")
        if rerun is not None:
            out[f"{stage}_cached_rerun_under_20s"] = rerun < 20
    return out


def table(results: list[dict], speed: dict) -> str:
    cols = [f"{r['clips']:,} clips ({r['load']['motions']:,} motions)" for r in results]
    rows = []

    def row(name, fn):
        cells = []
        for r in results:
            try:
                cells.append(fn(r))
            except (KeyError, TypeError):
                cells.append("-")
        rows.append(f"| {name} | " + " | ".join(cells) + " |")

    def t_mem(step, key="seconds"):
        return lambda r: (
            f"{r[step][key]:.1f} s, {r[step]['peak_anon_MiB'] / 1024:.2f} GiB anon / "
            f"{r[step]['peak_rss_MiB'] / 1024:.2f} GiB RSS"
        )

    row(
        "generation",
        lambda r: (
            f"{r['generation']['seconds']:.0f} s"
            if not r["generation"]["reused"]
            else f"reused ({r['generation']['generated_earlier'].get('seconds', '?')} s earlier)"
        ),
    )
    row("load, file by file (index + captions + arrays)", t_mem("load_files"))
    row("feature pack, built once", t_mem("pack"))
    row("caption pack, built once", lambda r: f"{r['pack']['captions_s']:.1f} s")
    row("load, packed (index + captions + arrays)", t_mem("load"))
    row(
        "items of train/val/test (stage-2 setup), packed",
        lambda r: f"{r['load']['items_all_splits_s']:.1f} s",
    )
    row("Mean/Std", t_mem("stats"))
    for stage, unit in (("stage1", "windows"), ("stage2", "items")):
        for w in (0, 1, 2):
            row(
                f"{stage} loader, {w} workers (samples/s)",
                lambda r, stage=stage, w=w: (
                    f"{r[f'{stage}_loader_w{w}']['samples_per_s']:,.0f}"
                    + ("" if r[f"{stage}_loader_w{w}"]["epoch_complete"] else " (part of an epoch)")
                    + f", {r[f'{stage}_loader_w{w}']['peak_anon_MiB'] / 1024:.2f} GiB anon"
                ),
            )
    row("tokenize every motion (tiny)", t_mem("tokenize"))
    row(
        "caption-embedding cache (MiniLM)",
        lambda r: f"{r['captions']['captions']:,} captions, {t_mem('captions')(r)}",
    )
    row(
        "`mmm train stage1` max_steps=1, cold: first step",
        lambda r: f"{r['stage1_cli']['to_first_step_s']:.1f} s",
    )
    row(
        "`mmm train stage1` cached rerun: first step",
        lambda r: (
            f"{r['stage1_cli_cached']['to_first_step_s']:.1f} s "
            f"(exit {r['stage1_cli_cached']['to_exit_s']:.0f} s)"
        ),
    )
    row(
        "`mmm train stage2` cached rerun: first step",
        lambda r: (
            f"{r['stage2_cli_cached']['to_first_step_s']:.1f} s "
            f"(exit {r['stage2_cli_cached']['to_exit_s']:.0f} s)"
        ),
    )
    row(
        "disk: dataset / feature pack / caption pack / tokens / caption embeddings",
        lambda r: (
            " / ".join(
                "-" if r["disk_GiB"].get(k) is None else f"{r['disk_GiB'][k]:.3g}"
                for k in ("dataset", "feature_pack", "caption_pack", "token_cache", "caption_cache")
            )
            + " GiB"
        ),
    )
    head = "| step | " + " | ".join(cols) + " |\n|---|" + "---|" * len(cols)
    foot = (
        f"\nTiny models at batch 64 consume {speed.get('stage1', '?')} (stage 1) and "
        f"{speed.get('stage2', '?')} (stage 2) samples/s ({speed.get('source')})."
    )
    return head + "\n" + "\n".join(rows) + "\n" + foot


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--num-clips", nargs="+", type=int, default=[15000, 40000])
    parser.add_argument("--root", default="outputs/bench/data")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--workers", nargs="+", type=int, default=[0, 1, 2])
    parser.add_argument("--epoch-limit-s", type=float, default=240.0, help="cap on each loader's epoch")
    parser.add_argument("--no-rerun", action="store_true", help="skip the cached `mmm train` reruns")
    parser.add_argument("--skip", nargs="*", default=[], choices=STEP_NAMES, help="steps left out")
    parser.add_argument(
        "--only",
        nargs="*",
        default=[],
        choices=STEP_NAMES,
        help="measure only these steps (and what they need), keeping the others from the existing --out",
    )
    parser.add_argument("--train-speed", default="outputs/bench/train_speed.json")
    parser.add_argument("--out", default="outputs/bench/data_scale.json")
    parser.add_argument("--child", default=None, help=argparse.SUPPRESS)
    parser.add_argument("--child-args", default="{}", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        child(args)
        return
    import torch

    out = Path(args.out)
    old_report = json.loads(out.read_text()) if args.only and out.exists() else {}
    speed = old_report.get("tiny_models_samples_per_s") or model_speeds(Path(args.train_speed))
    report = {
        "machine": {
            "cores": os.cpu_count(),
            "torch_threads": torch.get_num_threads(),
            "platform": platform.platform(),
            "python": platform.python_version(),
            "torch": torch.__version__,
            "memory_GiB": round(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / GiB, 1),
            "load_average_start": load_average(),
        },
        "tiny_models_samples_per_s": speed,
        "sizes": [],
    }
    out.parent.mkdir(parents=True, exist_ok=True)
    previous = {}
    if old_report:
        previous = {r["clips"]: r for r in old_report.get("sizes", [])}
        report["sizes"] = [r for r in old_report.get("sizes", []) if r["clips"] not in args.num_clips]
    for clips in args.num_clips:
        print(f"== {clips} clips", flush=True)
        res = measure_size(clips, args, previous.get(clips))
        res["goals"] = goals(res, speed)
        report["sizes"].append(res)
        out.write_text(json.dumps(report, indent=2))  # after every size: a partial run keeps what it measured
    report["machine"]["load_average_end"] = load_average()
    out.write_text(json.dumps(report, indent=2))
    print()
    print(f"python benchmarks/data_scale.py {' '.join(sys.argv[1:])}")
    print(table(report["sizes"], speed))
    for r in report["sizes"]:
        print(f"goals at {r['clips']} clips: {json.dumps(r['goals'])}")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
