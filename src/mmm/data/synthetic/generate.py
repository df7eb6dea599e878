"""Write the synthetic dataset in the HumanML3D on-disk layout.

    <out>/new_joint_vecs/<id>.npy  float32 (T, 263)   features (joints_to_features, no retargeting)
    <out>/new_joints/<id>.npy      float32 (T, 22, 3) recover_from_ric(features)
    <out>/texts/<id>.txt           caption lines `caption#tokens#start#end`
    <out>/labels/<id>.json         {"fps": 20, "num_frames": T, "parts": [{action, params, start, end}]}
    <out>/train.txt val.txt test.txt train_val.txt all.txt, Mean.npy, Std.npy
    <out>/synthesis.json           {"num_clips", "seed", "train_paraphrases", "extra_train_clips",
                                    "extra_composite_fraction"}

Ids are 000000, 000001, ... and M<id> for the left/right mirrored copy (same split). Clip i is
drawn from its own random stream seeded by (seed, i), so a dataset is a pure function of
(num_clips, seed, train_paraphrases, extra_train_clips, extra_composite_fraction): the same
arguments give byte-identical files.

`extra_train_clips` > 0 draws that many more clips after the first `num_clips` (their own streams,
ids num_clips, num_clips + 1, ...) and puts them all in the training split: the val and test
splits, and every file of the first `num_clips` clips, stay those of the dataset without them, so
models trained on more data are measured on the same held-out clips. Mean.npy/Std.npy are over all
clips, as always. `extra_composite_fraction` is the share of two-action clips among those extra
clips (a third, as in the first `num_clips`, by default): more compositions to learn from without
changing a held-out clip.

Every clip has three whole-clip paraphrases; `train_paraphrases` > 3 gives the training split's
clips more, drawn from a second stream seeded by (seed, i, 1) and appended after the clip's own
lines, so the motions, the val and test splits and the first lines stay those of the default.
"""

from __future__ import annotations

import json
import multiprocessing
import os
import shutil
import time
from collections import Counter, deque
from collections.abc import Iterator
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from tqdm.auto import tqdm

from mmm.data.arrays import DataError
from mmm.data.synthetic.actions import PartSpec, make_pose
from mmm.data.synthetic.adherence import check_motion
from mmm.data.synthetic.animations import Infeasible
from mmm.data.synthetic.body import pose_to_joints
from mmm.data.synthetic.captions import clip_captions, extra_paraphrases, mirror_caption_line, mirror_params
from mmm.data.synthetic.constants import FPS
from mmm.data.synthetic.table import ACTIONS
from mmm.motion.features import FeatureLayout, joints_to_features, recover_from_ric, reference_std
from mmm.motion.skeleton import T2M_SKELETON

MAX_ROWS = 196
MIN_ROWS = 40
COMPOSITE_FRACTION = 1 / 3
SYNTHESIS_FILE = "synthesis.json"
CHUNK = 32  # clips whose first tries share one forward-kinematics call
POOL_MIN_CHUNKS = 8  # fewer chunks are drawn in this process: starting workers costs seconds
SPLITS = {"val": 0.05, "test": 0.15}  # the rest is train
_ACTIONS = tuple(ACTIONS)
_P = np.array([ACTIONS[a].weight for a in _ACTIONS]) / sum(spec.weight for spec in ACTIONS.values())


def sample_params(rng: np.random.Generator, action: str) -> dict:
    """Label parameters of an action, named as in the spec's Labels section."""
    return ACTIONS[action].sample_params(rng)


def duration_range(action: str, params: dict, options: dict | None = None) -> tuple[float, float]:
    """Seconds an action may last (2-6 s, longer minimum where it needs the time)."""
    return ACTIONS[action].duration(params, options or {})


def sample_clip_spec(
    rng: np.random.Generator, composite_fraction: float = COMPOSITE_FRACTION
) -> list[PartSpec]:
    """One or two parts (two different actions chained with probability `composite_fraction`)."""
    composite = rng.random() < composite_fraction
    for _ in range(50):
        actions = [str(rng.choice(_ACTIONS, p=_P)) for _ in range(2 if composite else 1)]
        if composite and actions[0] == actions[1]:
            continue
        params = [sample_params(rng, a) for a in actions]
        options = [ACTIONS[a].sample_options(rng, i < len(actions) - 1) for i, a in enumerate(actions)]
        ranges = [duration_range(a, p, o) for a, p, o in zip(actions, params, options)]
        budget = MAX_ROWS / FPS
        if sum(r[0] for r in ranges) > budget:
            continue
        frames = []
        used = 0.0
        for i, (lo, hi) in enumerate(ranges):
            rest = sum(r[0] for r in ranges[i + 1 :])
            d = rng.uniform(lo, min(hi, budget - used - rest))
            rows = int(round(d * FPS))
            frames.append(rows)
            used += rows / FPS
        if sum(frames) > MAX_ROWS or min(frames) < MIN_ROWS:
            continue
        return [PartSpec(a, p, f, o or None) for a, p, f, o in zip(actions, params, frames, options)]
    raise RuntimeError("could not sample a clip specification")


@dataclass
class Clip:
    """One generated clip and its mirrored copy."""

    features: np.ndarray  # (T, 263) float32
    joints: np.ndarray  # (T, 22, 3) float32, recovered from the features
    captions: list[str]
    label: dict
    m_features: np.ndarray
    m_joints: np.ndarray
    m_captions: list[str]
    m_label: dict
    attempts: int
    stands_up: list[bool]  # per label part: whether a sit part ends standing up again


_LAYOUT = FeatureLayout(T2M_SKELETON.num_joints)
_PERM = np.array(T2M_SKELETON.mirror_permutation)


def mirror_features(feats: np.ndarray) -> np.ndarray:
    """Features (T, 263) of the left/right mirrored motion, computed in feature space.

    Every step of joints_to_features is equivariant under the mirror M = diag(-1, 1, 1) with the
    left/right joints swapped (its left/right-symmetric rest directions, facing vector, Gaussian
    smoothing, shortest-arc IK), so: yaw velocity and x components change sign, joints are
    permuted, each joint rotation R becomes M R M (6-D columns (x, -y, -z), (-x, y, z)) and the
    contact channels swap feet. Equal to joints_to_features(mirror_joints(joints)) to float
    precision (a test checks it), at a fraction of the cost.
    """
    out = feats.copy()
    L = _LAYOUT
    out[:, L.root_yaw] *= -1
    out[:, 1] *= -1
    pos = feats[:, L.positions].reshape(-1, 21, 3)[:, _PERM[1:] - 1].copy()
    pos[..., 0] *= -1
    out[:, L.positions] = pos.reshape(-1, 63)
    flip = np.array([1, -1, -1, -1, 1, 1], dtype=feats.dtype)
    rot = feats[:, L.rotations].reshape(-1, 21, 6)[:, _PERM[1:] - 1] * flip
    out[:, L.rotations] = rot.reshape(-1, 126)
    vel = feats[:, L.velocities].reshape(-1, 22, 3)[:, _PERM].copy()
    vel[..., 0] *= -1
    out[:, L.velocities] = vel.reshape(-1, 66)
    out[:, L.contacts] = feats[:, L.contacts][:, [2, 3, 0, 1]]
    return out


def _recover(feats: np.ndarray) -> np.ndarray:
    return recover_from_ric(torch.from_numpy(feats)).numpy().astype(np.float32)


def _attempt(rng: np.random.Generator, composite_fraction: float):
    """One try at a clip: its specification and pose, or None when it cannot be animated."""
    specs = sample_clip_spec(rng, composite_fraction)
    try:
        quats, root, parts = make_pose(specs, rng)
    except Infeasible:
        return None
    return specs, quats, root, parts


def _finish(rng: np.random.Generator, specs, world: np.ndarray, parts, attempts: int) -> Clip | None:
    """Features, captions and labels of a clip, or None when it fails its own labels."""
    floor = world[..., 1].min()
    canon = world[:-1].copy()  # the checks are invariant to horizontal placement and facing
    canon[..., 1] -= floor
    if not check_motion(canon, parts).passed:
        return None
    feats = joints_to_features(torch.from_numpy(world), retarget=False).numpy().astype(np.float32)
    joints = _recover(feats)
    m_feats = mirror_features(feats)
    m_joints = _recover(m_feats)
    m_parts = [dict(p, params=mirror_params(p["params"])) for p in parts]
    if not (check_motion(joints, parts).passed and check_motion(m_joints, m_parts).passed):
        return None
    stands_up = [bool((s.options or {}).get("stand_up", False)) for s in specs]
    captions = clip_captions(rng, parts, stands_up)
    label = {"fps": int(FPS), "num_frames": int(feats.shape[0]), "parts": parts}
    m_label = {"fps": int(FPS), "num_frames": int(m_feats.shape[0]), "parts": m_parts}
    return Clip(
        feats,
        joints,
        captions,
        label,
        m_feats,
        m_joints,
        [mirror_caption_line(c) for c in captions],
        m_label,
        attempts=attempts,
        stands_up=stands_up,
    )


def _complete(
    rng: np.random.Generator,
    first,
    first_world,
    attempts: int,
    index: int,
    seed: int,
    max_attempts: int,
    composite_fraction: float,
) -> Clip:
    """Finish a clip from its first try (already posed); retry from the same stream if needed."""
    clip = _finish(rng, first[0], first_world, first[3], attempts) if first is not None else None
    while clip is None:
        attempts += 1
        if attempts > max_attempts:
            raise RuntimeError(f"clip {index} (seed {seed}) failed its own labels {max_attempts} times")
        tried = _attempt(rng, composite_fraction)
        if tried is not None:
            specs, quats, root, parts = tried
            clip = _finish(rng, specs, pose_to_joints(quats, root), parts, attempts)
    return clip


def generate_clip(
    seed: int, index: int, max_attempts: int = 30, composite_fraction: float = COMPOSITE_FRACTION
) -> Clip:
    """Clip `index` of the dataset with this seed (deterministic); retried until it satisfies its
    labels (also mirrored, on the joints recovered from the saved features)."""
    rng = np.random.default_rng([int(seed), int(index)])
    first = _attempt(rng, composite_fraction)
    world = pose_to_joints(first[1], first[2]) if first is not None else None
    return _complete(rng, first, world, 1, index, seed, max_attempts, composite_fraction)


def _generate_chunk(
    seed: int, indices: range, composite_fractions: list[float], max_attempts: int = 30
) -> list[Clip]:
    """generate_clip for several indices (one composite fraction each), with one forward-kinematics
    call for all first tries."""
    rngs = [np.random.default_rng([int(seed), int(i)]) for i in indices]
    firsts = [_attempt(rng, f) for rng, f in zip(rngs, composite_fractions)]
    posed = [f for f in firsts if f is not None]
    worlds = iter([])
    if posed:
        joints = pose_to_joints(np.concatenate([f[1] for f in posed]), np.concatenate([f[2] for f in posed]))
        cuts = np.cumsum([f[1].shape[0] for f in posed])[:-1]
        worlds = iter(np.split(joints, cuts))
    clips = []
    for rng, first, index, fraction in zip(rngs, firsts, indices, composite_fractions):
        world = next(worlds) if first is not None else None
        clips.append(_complete(rng, first, world, 1, index, seed, max_attempts, fraction))
    return clips


def _single_thread() -> None:
    torch.set_num_threads(1)


def _generate_all(seed: int, composite_fractions: list[float], workers: int) -> Iterator[Clip]:
    """Every clip, in index order, drawn in chunks of CHUNK; with workers > 1 by that many
    processes, a few chunks ahead of the caller (each clip has its own random stream, so the
    clips are those of one process)."""
    total = len(composite_fractions)
    chunks = [range(lo, min(lo + CHUNK, total)) for lo in range(0, total, CHUNK)]
    if workers <= 1 or len(chunks) < POOL_MIN_CHUNKS:
        for chunk in chunks:
            yield from _generate_chunk(seed, chunk, composite_fractions[chunk.start : chunk.stop])
        return
    # spawn, not fork: the caller may hold OpenMP threads (a forked child can hang on them)
    context = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(workers, mp_context=context, initializer=_single_thread) as pool:
        pending: deque = deque()
        try:
            for chunk in chunks:
                pending.append(
                    pool.submit(_generate_chunk, seed, chunk, composite_fractions[chunk.start : chunk.stop])
                )
                if len(pending) > 2 * workers:  # bounded: clips are written as they come
                    yield from pending.popleft().result()
            while pending:
                yield from pending.popleft().result()
        finally:
            for future in pending:
                future.cancel()


def split_ids(num_clips: int, seed: int) -> dict[str, list[str]]:
    """Clip ids (without mirrors) per split, 80/5/15 by clip."""
    order = np.random.default_rng([int(seed), 2**31 - 1]).permutation(num_clips)
    n_val = int(round(SPLITS["val"] * num_clips))
    n_test = int(round(SPLITS["test"] * num_clips))
    if num_clips >= 3:  # tiny datasets still get one clip in each split
        n_val, n_test = max(n_val, 1), max(n_test, 1)
    ids = [f"{i:06d}" for i in order]
    return {
        "val": sorted(ids[:n_val]),
        "test": sorted(ids[n_val : n_val + n_test]),
        "train": sorted(ids[n_val + n_test :]),
    }


class _Moments:
    """Mean and population variance per dimension, merged clip by clip (Chan et al.)."""

    def __init__(self, dim: int):
        self.n = 0
        self.mean = np.zeros(dim)
        self.m2 = np.zeros(dim)

    def add(self, x: np.ndarray) -> None:
        x = x.astype(np.float64)
        n_b = x.shape[0]
        mean_b = x.mean(axis=0)
        m2_b = ((x - mean_b) ** 2).sum(axis=0)
        n = self.n + n_b
        delta = mean_b - self.mean
        self.mean = self.mean + delta * n_b / n
        self.m2 = self.m2 + m2_b + delta * delta * self.n * n_b / n
        self.n = n

    def stats(self) -> tuple[np.ndarray, np.ndarray]:
        """Mean and Std the reference way (group-averaged Std), via reference_std."""
        std = np.sqrt(np.maximum(self.m2 / self.n, 0.0))
        # Two rows whose mean and population std are exactly these: reference_std then only
        # applies its group averaging.
        mean, std = reference_std(np.stack([self.mean + std, self.mean - std]), T2M_SKELETON.num_joints)
        return mean, std


def _settings(
    num_clips: int, seed: int, train_paraphrases: int, extra_train_clips: int, extra_composite_fraction: float
) -> dict:
    """What makes a synthetic dataset, as synthesis.json records it."""
    return {
        "num_clips": int(num_clips),
        "seed": int(seed),
        "train_paraphrases": int(train_paraphrases),
        "extra_train_clips": int(extra_train_clips),
        "extra_composite_fraction": float(extra_composite_fraction),
    }


def check_synthesis(
    root,
    num_clips: int,
    seed: int,
    train_paraphrases: int,
    extra_train_clips: int = 0,
    extra_composite_fraction: float = COMPOSITE_FRACTION,
) -> None:
    """Refuse a synthetic dataset folder generated with other settings than the config asks for
    (a folder without synthesis.json predates it, or is not synthetic: nothing to compare)."""
    path = Path(root) / SYNTHESIS_FILE
    if not path.exists():
        return
    try:
        made = json.loads(path.read_text())
    except ValueError as e:
        raise DataError(path, f"unreadable ({e})", "delete the dataset folder to regenerate it") from None
    asked = _settings(num_clips, seed, train_paraphrases, extra_train_clips, extra_composite_fraction)
    made.setdefault("extra_train_clips", 0)  # written before the options existed
    made.setdefault("extra_composite_fraction", COMPOSITE_FRACTION)
    differ = {k: (made.get(k), v) for k, v in asked.items() if made.get(k) != v}
    if differ:
        what = ", ".join(f"{k} {m} (asked {a})" for k, (m, a) in differ.items())
        raise DataError(
            root,
            f"synthetic dataset made with {what}",
            "point data.root at another folder for these settings, or delete this one to regenerate it",
        )


def _prepare_out(out: Path, overwrite: bool) -> None:
    if out.exists() and not out.is_dir():
        raise FileExistsError(f"{out} exists and is not a folder; choose another output folder")
    if out.is_dir() and any(out.iterdir()) and not overwrite:
        raise FileExistsError(
            f"{out} already exists and is not empty; pass overwrite=True (mmm data synth --overwrite) "
            f"to replace it, or choose another output folder"
        )
    if out.is_dir() and any(out.iterdir()) and not (out / SYNTHESIS_FILE).is_file():
        # --overwrite replaces what this command made, never a folder of someone's own files
        raise FileExistsError(
            f"{out} holds files but no synthetic dataset (no {SYNTHESIS_FILE}); overwrite only replaces a "
            "dataset `mmm data synth` made: choose another output folder, or empty this one yourself"
        )


# A clip and its mirror on disk: the default dataset's 1,500 clips take 804 MB (`du -s`, file
# blocks included), about 0.54 MB each.
BYTES_PER_CLIP = 540_000


def _check_disk(out: Path, clips: int) -> None:
    """Refuse a dataset that cannot fit on the disk it is written to, before anything is drawn."""
    place = next(p for p in (out, *out.parents) if p.exists())
    free = shutil.disk_usage(place).free
    if clips * BYTES_PER_CLIP > free:
        raise ValueError(
            f"{clips} clips need about {clips * BYTES_PER_CLIP / 1e9:,.1f} GB on disk (about "
            f"{BYTES_PER_CLIP / 1e6:.2f} MB per clip with its mirror), but {place} has {free / 1e9:,.1f} GB "
            "free: ask for fewer clips or write to another disk"
        )


def _add_paraphrases(clip: Clip, seed: int, index: int, whole: int) -> int:
    """Append whole-clip paraphrases to clip (and its mirror) until it has `whole`; returns how
    many it was short of that (the templates ran out)."""
    existing = [c for c in clip.captions if c.endswith("#0.0#0.0")]  # the whole-clip lines, not the parts'
    want = whole - len(existing)
    more = extra_paraphrases(
        np.random.default_rng([int(seed), int(index), 1]), clip.label["parts"], clip.stands_up, want, existing
    )
    clip.captions = clip.captions + more
    clip.m_captions = clip.m_captions + [mirror_caption_line(c) for c in more]
    return want - len(more)


def generate_dataset(
    out_dir,
    num_clips: int = 1500,
    seed: int = 0,
    progress: bool = True,
    overwrite: bool = False,
    train_paraphrases: int = 3,
    extra_train_clips: int = 0,
    extra_composite_fraction: float = COMPOSITE_FRACTION,
    workers: int | None = None,
) -> dict:
    """Generate `num_clips` clips plus their mirrors into out_dir, and `extra_train_clips` more
    (a share `extra_composite_fraction` of them two-action clips) that all go to the training
    split; returns a summary.

    workers: processes drawing clips (None: one per CPU core, at most 4; the files are the same
    for any number).

    Written into a temporary sibling folder that replaces out_dir only when complete, so a crash
    never leaves a half-written dataset. Refuses a non-empty out_dir unless overwrite=True.
    """
    if int(num_clips) < 1:
        raise ValueError(f"num_clips must be >= 1, got {num_clips}")
    if int(train_paraphrases) < 3:
        raise ValueError(f"train_paraphrases must be >= 3 (every clip has three), got {train_paraphrases}")
    if int(extra_train_clips) < 0:
        raise ValueError(f"extra_train_clips must be >= 0, got {extra_train_clips}")
    if not 0.0 <= float(extra_composite_fraction) <= 1.0:
        raise ValueError(f"extra_composite_fraction must be within [0, 1], got {extra_composite_fraction}")
    if workers is None:
        cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
        workers = min(4, cores or 1)
    if int(workers) < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    total = int(num_clips) + int(extra_train_clips)
    _check_disk(Path(out_dir), total)
    extra = [float(extra_composite_fraction)] * int(extra_train_clips)
    fractions = [COMPOSITE_FRACTION] * int(num_clips) + extra  # per clip index
    splits = split_ids(int(num_clips), seed)
    splits["train"] = splits["train"] + [f"{i:06d}" for i in range(int(num_clips), total)]
    out = Path(out_dir)
    _prepare_out(out, overwrite)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.parent / f".{out.name}.tmp-{os.getpid()}"
    if tmp.exists():
        shutil.rmtree(tmp)
    start = time.perf_counter()
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        for sub in ("new_joint_vecs", "new_joints", "texts", "labels"):
            (tmp / sub).mkdir(parents=True)
        moments = _Moments(T2M_SKELETON.feature_dim)
        actions: Counter = Counter()
        composites = attempts = frames = short = 0
        train = set(splits["train"])
        bar = tqdm(total=total, desc="synthesizing clips", unit="clip", disable=not progress)
        for i, clip in enumerate(_generate_all(seed, fractions, int(workers))):
            bar.update(1)
            cid = f"{i:06d}"
            if train_paraphrases > 3 and cid in train:
                short += _add_paraphrases(clip, seed, i, int(train_paraphrases))
            for motion_id, feats, joints, captions, label in (
                (cid, clip.features, clip.joints, clip.captions, clip.label),
                ("M" + cid, clip.m_features, clip.m_joints, clip.m_captions, clip.m_label),
            ):
                np.save(tmp / "new_joint_vecs" / f"{motion_id}.npy", feats)
                np.save(tmp / "new_joints" / f"{motion_id}.npy", joints)
                (tmp / "texts" / f"{motion_id}.txt").write_text("\n".join(captions) + "\n")
                (tmp / "labels" / f"{motion_id}.json").write_text(json.dumps(label) + "\n")
                moments.add(feats)
            actions.update(p["action"] for p in clip.label["parts"])
            composites += len(clip.label["parts"]) > 1
            attempts += clip.attempts - 1
            frames += clip.features.shape[0]
        bar.close()
        mean, std = moments.stats()
        np.save(tmp / "Mean.npy", mean.astype(np.float32))
        np.save(tmp / "Std.npy", std.astype(np.float32))
        with_mirrors = {k: sorted(v + ["M" + i for i in v]) for k, v in splits.items()}
        with_mirrors["train_val"] = sorted(with_mirrors["train"] + with_mirrors["val"])
        with_mirrors["all"] = sorted(with_mirrors["train_val"] + with_mirrors["test"])
        for name, ids in with_mirrors.items():
            (tmp / f"{name}.txt").write_text("".join(f"{i}\n" for i in ids))
        made = _settings(num_clips, seed, train_paraphrases, extra_train_clips, extra_composite_fraction)
        (tmp / SYNTHESIS_FILE).write_text(json.dumps(made) + "\n")
        _prepare_out(out, overwrite)
        if out.exists():
            trash = out.parent / f".{out.name}.old-{os.getpid()}"
            os.replace(out, trash)
            os.replace(tmp, out)
            shutil.rmtree(trash)
        else:
            os.replace(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    finally:
        torch.set_num_threads(threads)
    return {
        "out": str(out),
        "clips": total,
        "motions": 2 * total,
        "composites": composites,
        "frames": 2 * frames,
        "actions": dict(sorted(actions.items())),
        "splits": {k: len(v) for k, v in with_mirrors.items() if k in ("train", "val", "test")},
        "retries": attempts,
        "train_paraphrases": int(train_paraphrases),
        "extra_train_clips": int(extra_train_clips),
        "extra_composite_fraction": float(extra_composite_fraction),
        "paraphrases_short": short,
        "seconds": round(time.perf_counter() - start, 2),
    }


__all__ = [
    "Clip",
    "check_synthesis",
    "duration_range",
    "generate_clip",
    "generate_dataset",
    "mirror_features",
    "sample_clip_spec",
    "sample_params",
    "split_ids",
]
