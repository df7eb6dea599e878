"""Reader for the HumanML3D on-disk format (KIT-ML has the same layout).

    <root>/new_joint_vecs/<id>.npy   (T, D) features      <root>/texts/<id>.txt  caption lines
    <root>/new_joints/<id>.npy       (T, J, 3) joints     <root>/Mean.npy, Std.npy  (D,)
    <root>/{train,val,test,train_val,all}.txt              one id per line

A caption line is `caption#word/POS word/POS ...#start#end` (seconds; 0/0 or nan = whole clip).
Motions are kept when min_length <= T < length_limit; a caption with a sub-span becomes an item
of its own when the span's length obeys the same rule (the reference loader's rules).

Problems with the data raise `DataError` naming the file and the fix, or, with
on_invalid="skip", are skipped and counted in a `LoadReport` that the caller logs.

One file per motion is what the format gives, not what the loader keeps: the first load packs
every new_joint_vecs/*.npy into <root>/.features-pack/<key>/ (one float32 file, memory-mapped,
and an index), so later loads open one file instead of tens of thousands and keep the features
in the page cache rather than in each process's own memory (`FeatureStore`). The key covers the
feature files' names, sizes, mtimes, ctimes and inodes (the dataset fingerprint's rule), so a
changed, added or removed file makes a new pack; a pack is written under a temporary name and
renamed into place, so a crash never leaves a half-written one. Where the dataset folder cannot
be written the files are read one by one, as before. The caption files are packed the same way,
parsed, into <root>/.captions-pack/<key>/index.json (`CaptionStore`).
"""

from __future__ import annotations

import functools
import hashlib
import json
import logging
import math
import os
import shutil
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mmm.atomic import atomic_write, file_lock
from mmm.data.arrays import DataError, load_array
from mmm.motion.features import FeatureLayout

log = logging.getLogger(__name__)

SPLITS = ("train", "val", "test", "train_val", "all")


@dataclass(frozen=True)
class Caption:
    text: str
    tokens: tuple[str, ...]  # "word/POS"
    start: float  # seconds; 0 and 0 mean the whole clip
    end: float

    @property
    def whole_clip(self) -> bool:
        return self.start == 0.0 and self.end == 0.0


@dataclass
class MotionItem:
    """One training item: a clip or a captioned sub-span of one."""

    name: str  # the clip id, or "<id>#<first frame>-<end frame>" for a sub-span
    motion_id: str
    features: np.ndarray  # (T, D) float32, not normalized
    captions: list[Caption]
    start: int = 0  # first frame of the span within the clip

    @property
    def length(self) -> int:
        return int(self.features.shape[0])


@dataclass
class LoadReport:
    """What a load kept and left out, by reason, with a few example files per reason."""

    kept_items: int = 0
    kept_clips: int = 0
    skipped: Counter = field(default_factory=Counter)
    examples: dict[str, list[str]] = field(default_factory=dict)

    def skip(self, reason: str, where: str) -> None:
        self.skipped[reason] += 1
        self.examples.setdefault(reason, [])
        if len(self.examples[reason]) < 3:
            self.examples[reason].append(where)

    def summary(self) -> str:
        lines = [f"kept {self.kept_items} items from {self.kept_clips} clips"]
        for reason, n in sorted(self.skipped.items()):
            lines.append(f"  left out {n}: {reason} (e.g. {', '.join(self.examples[reason])})")
        return "\n".join(lines)


def mirror_id(motion_id: str) -> str:
    """The id of the left/right mirrored copy (M<id>) of a clip, or of the original for a mirror."""
    return motion_id[1:] if motion_id.startswith("M") else "M" + motion_id


def parse_caption_line(line: str, path: str | Path = "<text>", lineno: int = 0) -> Caption:
    """Parse `caption#tokens#start#end` (split from the right: a '#' inside the caption is text);
    raises DataError naming file and line."""
    where = f"{path}:{lineno}"
    fields = line.rstrip("\r\n").rsplit("#", 3)
    if not line.strip():
        raise DataError(where, "empty caption line", "remove it or write 'caption#word/POS ...#0.0#0.0'")
    if len(fields) != 4:
        raise DataError(
            where,
            f"malformed caption line ({len(fields)} '#'-separated fields, expected 4): {line.strip()[:80]!r}",
            "write 'caption#word/POS ...#start#end'",
        )
    text, tokens, start_s, end_s = fields
    if not text.strip():
        raise DataError(where, "empty caption text", "every line needs a caption before the first '#'")
    try:
        start = float(start_s) if start_s.strip() else 0.0
        end = float(end_s) if end_s.strip() else 0.0
    except ValueError:
        raise DataError(
            where,
            f"start/end {start_s!r}/{end_s!r} are not numbers",
            "write seconds, or 0.0#0.0 for the whole clip",
        ) from None
    # NaN means "the whole clip" (the reference loader's rule, HumanML3D writes nan#nan); an
    # infinite bound has no frame to cut at.
    start = 0.0 if math.isnan(start) else start
    end = 0.0 if math.isnan(end) else end
    if math.isinf(start) or math.isinf(end):
        raise DataError(
            where,
            f"caption span {start_s.strip()}..{end_s.strip()} s is not finite",
            "write the span in seconds, or 0.0#0.0 for the whole clip",
        )
    if start < 0 or end < 0 or (end != 0.0 and end <= start):
        raise DataError(
            where,
            f"caption span {start}..{end} s is empty or negative",
            "use start < end, or 0.0#0.0 for the whole clip",
        )
    return Caption(text.strip(), tuple(tokens.split()), start, end)


FEATURE_SKELETONS = {
    263: "HumanML3D (data=humanml3d or synthetic; --skeleton t2m)",
    251: "KIT-ML (data=kit; --skeleton kit)",
}


def skeleton_hint(width: int) -> str:
    """What to choose for features `width` wide (HumanML3D 263, KIT-ML 251)."""
    if width in FEATURE_SKELETONS:
        return f"{width}-d features are {FEATURE_SKELETONS[width]}: choose that dataset config"
    return (
        "HumanML3D features are 263 wide (data=humanml3d), KIT-ML 251 (data=kit; --skeleton kit for mmm data)"
    )


def read_captions(path: str | Path) -> list[Caption]:
    path = Path(path)
    try:
        lines = path.read_text(encoding="utf-8-sig").splitlines()  # -sig: a byte-order mark is not text
    except FileNotFoundError:
        raise DataError(path, "caption file is missing", "every id in a split needs texts/<id>.txt") from None
    except (OSError, UnicodeDecodeError) as e:
        raise DataError(path, f"unreadable caption file ({e})", "rewrite it as UTF-8 text") from None
    # Blank lines (an editor's trailing newline) hold no caption: passed over, not counted as bad.
    numbered = [(i + 1, line) for i, line in enumerate(lines) if line.strip()]
    if not numbered:
        raise DataError(path, "caption file is empty", "write at least one caption line")
    return [parse_caption_line(line, path, lineno) for lineno, line in numbered]


DUPLICATE_ID = "id listed again in the split (kept once)"


def _unique(ids: list[str], report: LoadReport) -> list[str]:
    """`ids` in order without repeats; each repeat is counted in `report` (the reference loader
    keys its clips by id, so a repeat never counted twice there either)."""
    unique: dict[str, None] = {}
    for motion_id in ids:
        if motion_id in unique:
            report.skip(DUPLICATE_ID, motion_id)
        unique[motion_id] = None
    return list(unique)


def read_split(root: str | Path, split: str) -> list[str]:
    path = Path(root) / f"{split}.txt"
    if not path.exists():
        raise DataError(
            path, "split file is missing", f"expected {', '.join(s + '.txt' for s in SPLITS)} in {root}"
        )
    try:
        lines = path.read_text(encoding="utf-8-sig").splitlines()  # -sig: a byte-order mark is not an id
    except (OSError, UnicodeDecodeError) as e:
        raise DataError(path, f"unreadable split file ({e})", "write it as UTF-8, one id per line") from None
    ids = [line.strip() for line in lines if line.strip()]
    if not ids:
        raise DataError(path, "split file lists no ids", "write one id per line")
    # "000001.npy" would be looked up as new_joint_vecs/000001.npy.npy and reported missing.
    with_extension = [i for i in ids if i.lower().endswith((".npy", ".txt"))]
    if with_extension:
        raise DataError(
            path,
            f"{len(with_extension)} of {len(ids)} ids end in a file extension (e.g. "
            f"{', '.join(with_extension[:3])})",
            "write the ids without .npy/.txt, one per line (000001, not 000001.npy)",
        )
    return ids


def load_motion(path: str | Path, feature_dim: int) -> np.ndarray:
    """Features (T, D) float32 from a .npy file; raises DataError for anything unusable."""
    path = Path(path)
    try:
        arr = np.load(path, allow_pickle=False)
    except FileNotFoundError:
        raise DataError(
            path, "motion file is missing", "remove the id from the split or restore new_joint_vecs/<id>.npy"
        ) from None
    except (OSError, ValueError, EOFError) as e:
        raise DataError(
            path, f"unreadable .npy file ({e})", "regenerate it, or remove it and its id from the splits"
        ) from None
    if arr.dtype.kind not in "biuf":  # strings or bytes: np.isfinite below could not even look at them
        raise DataError(
            path,
            f"holds {arr.dtype} values, not numbers",
            "regenerate it, or remove it and its id from the splits",
        )
    if arr.ndim != 2 or arr.shape[1] != feature_dim:
        # (T, D) without T: one reason per width, not one per clip length, in the skip reports
        shape = f"(T, {arr.shape[1]})" if arr.ndim == 2 else str(arr.shape)
        raise DataError(
            path, f"wrong feature shape {shape}, expected (T, {feature_dim})", skeleton_hint(arr.shape[-1])
        )
    if not np.isfinite(arr).all():
        bad = int((~np.isfinite(arr)).any(axis=1).sum())
        raise DataError(
            path, f"NaN/Inf values ({bad} of {arr.shape[0]} frames)", "regenerate the file or remove the id"
        )
    return arr.astype(np.float32, copy=False)


PACK_DIR = ".features-pack"
PACK_FORMAT = 2  # 2: wrong feature shapes reported as (T, D)
CAPTION_PACK_DIR = ".captions-pack"
CAPTION_PACK_FORMAT = 2  # 2: blank lines passed over, captions split from the right
# Files changed less than this many seconds before a pack would be built are not packed yet: a
# rewrite within the file system's timestamp granularity could keep size, mtime and ctime.
PACK_SETTLE_S = 2.0
_unwritable_warned: set[str] = set()


def _scan(folder: Path, suffix: str, salt: str) -> tuple[str, list[str], float]:
    """(pack key, sorted ids, newest mtime/ctime) of the `suffix` files in `folder`; the key hashes
    `salt` and every file's name, size, mtime, ctime and inode."""
    entries = []
    newest = 0.0
    with os.scandir(folder) as it:
        for entry in it:
            if entry.name.endswith(suffix) and not entry.name.startswith("."):
                st = entry.stat()
                entries.append((entry.name, f"{st.st_size}:{st.st_mtime_ns}:{st.st_ctime_ns}:{st.st_ino}"))
                newest = max(newest, st.st_mtime, st.st_ctime)
    entries.sort()
    h = hashlib.sha256(f"{salt}\n".encode())
    for name, key in entries:
        h.update(f"{name}:{key}\n".encode())
    return h.hexdigest()[:16], [name[: -len(suffix)] for name, _ in entries], newest


def _scan_features(vec_dir: Path, feature_dim: int) -> tuple[str, list[str], float]:
    return _scan(vec_dir, ".npy", f"mmm-features-pack {PACK_FORMAT} float32 d={feature_dim}")


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:
        return True
    return True


def _publish(folder: Path, fill) -> None:
    """`fill(tmp)` writes a pack into a temporary folder beside `folder`, which is then renamed
    into place (never a half-written pack; another process's identical pack is kept)."""
    tmp = folder.with_name(f".tmp-{folder.name}-{os.getpid()}")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    try:
        fill(tmp)
        try:
            os.replace(tmp, folder)
        except OSError:
            if not (folder / "index.json").exists():
                raise
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _write_json(path: Path, value) -> None:
    with open(path, "w", encoding="utf-8") as fh:
        json.dump(value, fh)
        fh.flush()
        os.fsync(fh.fileno())


def _write_pack(vec_dir: Path, folder: Path, ids: list[str], feature_dim: int) -> None:
    """Read and check every feature file once; publish features.f32 and index.json as `folder`."""

    def fill(tmp: Path) -> None:
        offsets, packed, errors = [0], [], {}
        with open(tmp / "features.f32", "wb") as fh:
            for motion_id in ids:
                try:
                    arr = load_motion(vec_dir / f"{motion_id}.npy", feature_dim)
                except DataError as e:
                    errors[motion_id] = [e.problem, e.fix]
                    continue
                fh.write(np.ascontiguousarray(arr, dtype=np.float32).tobytes())
                packed.append(motion_id)
                offsets.append(offsets[-1] + arr.shape[0])
            fh.flush()
            os.fsync(fh.fileno())
        index = {
            "format": PACK_FORMAT,
            "feature_dim": feature_dim,
            "frames": offsets[-1],
            "ids": packed,
            "offsets": offsets,
            "errors": errors,
        }
        _write_json(tmp / "index.json", index)

    _publish(folder, fill)


def _write_caption_pack(text_dir: Path, folder: Path, ids: list[str]) -> None:
    """Read and parse every caption file once; publish index.json as `folder`: per id its lines as
    [text, tokens, start, end], or the error `read_captions` raised, its path kept relative
    (the line number) so the message stays right when the dataset folder moves."""

    def fill(tmp: Path) -> None:
        captions, errors = {}, {}
        for motion_id in ids:
            path = text_dir / f"{motion_id}.txt"
            try:
                captions[motion_id] = [
                    [c.text, " ".join(c.tokens), c.start, c.end] for c in read_captions(path)
                ]
            except DataError as e:
                errors[motion_id] = [e.path[len(str(path)) :], e.problem, e.fix]
        index = {"format": CAPTION_PACK_FORMAT, "captions": captions, "errors": errors}
        _write_json(tmp / "index.json", index)

    _publish(folder, fill)


def _clean_packs(parent: Path, keep: str) -> None:
    """Remove packs of other keys (stale) and temporaries whose writer no longer runs."""
    for entry in parent.iterdir():
        if entry.name == keep or not entry.is_dir():
            continue
        if entry.name.startswith(".tmp-"):
            try:
                pid = int(entry.name.rsplit("-", 1)[1])
            except ValueError:
                continue
            if _pid_alive(pid):
                continue
        shutil.rmtree(entry, ignore_errors=True)


def _pack(
    root: Path, pack_dir: str, key: str, newest: float, what: str, files: int, write
) -> tuple[Path | None, bool]:
    """(root/pack_dir/key, whether this call wrote it) once that pack exists, writing it with
    `write(folder)` under a lock when missing; (None, False) when the files changed less than
    PACK_SETTLE_S ago or the dataset folder cannot be written (warned once per folder): the caller
    then reads the files one by one."""
    folder = root / pack_dir / key
    if (folder / "index.json").exists():
        return folder, False
    if time.time() - newest < PACK_SETTLE_S:
        return None, False  # just written: read file by file this time
    built = False
    try:
        folder.parent.mkdir(exist_ok=True)
        with file_lock(folder.parent / ".lock"):
            if not (folder / "index.json").exists():
                log.info("packing the %s of %s (%d files) into %s", what, root, files, folder)
                write(folder)
                built = True
            _clean_packs(folder.parent, keep=key)
    except OSError as e:
        if str(folder.parent) not in _unwritable_warned:
            _unwritable_warned.add(str(folder.parent))
            log.warning("cannot pack the %s of %s (%s): reading them file by file", what, root, e)
        return None, False
    return folder, built


class FeatureStore:
    """Features (T, D) float32 of a dataset's motions by id: views into the memory-mapped pack
    (read-only arrays) where one exists or can be built, otherwise `load_motion` per file. Either
    way an unusable or missing file raises the DataError `load_motion` gives.

        store = FeatureStore(root, 263)
        features = store.load("000001")
    """

    def __init__(self, root: str | Path, feature_dim: int, pack: bool = True):
        self.root, self.feature_dim = Path(root), feature_dim
        self.vec_dir = self.root / "new_joint_vecs"
        self.folder: Path | None = None
        self._features: np.ndarray | None = None
        self._rows: dict[str, tuple[int, int]] = {}
        self._errors: dict[str, list[str]] = {}
        self.built = False  # this store wrote the pack
        if pack:
            self._open_or_build()

    @property
    def packed(self) -> bool:
        return self.folder is not None

    def _open_or_build(self) -> None:
        if not self.vec_dir.is_dir():
            return  # load_motion names the missing files
        try:
            key, ids, newest = _scan_features(self.vec_dir, self.feature_dim)
        except OSError:
            return
        if not ids:
            return
        folder, self.built = _pack(
            self.root,
            PACK_DIR,
            key,
            newest,
            "features",
            len(ids),
            lambda folder: _write_pack(self.vec_dir, folder, ids, self.feature_dim),
        )
        if folder is None:
            return
        try:
            self._open(folder)
        except (OSError, ValueError, KeyError) as e:
            log.warning("unusable feature pack %s (%s): reading the files one by one", folder, e)

    def _open(self, folder: Path) -> None:
        index = json.loads((folder / "index.json").read_text(encoding="utf-8"))
        if index["format"] != PACK_FORMAT or index["feature_dim"] != self.feature_dim:
            raise ValueError("another format or feature size")
        frames = int(index["frames"])
        if frames:
            expected = frames * self.feature_dim * 4
            size = (folder / "features.f32").stat().st_size
            if size != expected:
                raise ValueError(f"features.f32 holds {size} bytes, expected {expected}")
            mm = np.memmap(
                folder / "features.f32", dtype=np.float32, mode="r", shape=(frames, self.feature_dim)
            )
            self._features = np.asarray(mm)
        offsets = index["offsets"]
        self._rows = {m: (offsets[i], offsets[i + 1]) for i, m in enumerate(index["ids"])}
        self._errors = index["errors"]
        self.folder = folder

    def path(self, motion_id: str) -> Path:
        return self.root / "new_joint_vecs" / f"{motion_id}.npy"

    def load(self, motion_id: str) -> np.ndarray:
        """(T, D) float32 features of `motion_id`; DataError as `load_motion` raises it."""
        rows = self._rows.get(motion_id)
        if rows is not None:
            return self._features[rows[0] : rows[1]]
        error = self._errors.get(motion_id)
        if error is not None:
            raise DataError(self.path(motion_id), error[0], error[1])
        return load_motion(self.path(motion_id), self.feature_dim)

    def blocks(self, ids: list[str], block_frames: int = 1 << 16):
        """The features of `ids` that load, concatenated into (<= block_frames-ish, D) blocks, and
        the DataErrors of those that do not: yields (block or None, [DataError, ...])."""
        chunk, size, errors = [], 0, []
        for motion_id in ids:
            try:
                arr = self.load(motion_id)
            except DataError as e:
                errors.append(e)
                continue
            chunk.append(arr)
            size += arr.shape[0]
            if size >= block_frames:
                yield np.concatenate(chunk), errors
                chunk, size, errors = [], 0, []
        if chunk or errors:
            yield (np.concatenate(chunk) if chunk else None), errors


@functools.lru_cache(maxsize=2)
def _read_caption_pack(index_path: str) -> tuple[dict[str, tuple[Caption, ...]], dict[str, list[str]]]:
    """The parsed captions and the errors of a caption pack; kept for the next load of the same
    pack in this process (its key changes with any caption file, so it cannot go stale)."""
    with open(index_path, encoding="utf-8") as fh:
        index = json.load(fh)
    if index["format"] != CAPTION_PACK_FORMAT:
        raise ValueError(f"caption pack format {index['format']}, expected {CAPTION_PACK_FORMAT}")
    captions = {
        motion_id: tuple(Caption(text, tuple(tokens.split()), a, b) for text, tokens, a, b in lines)
        for motion_id, lines in index["captions"].items()
    }
    return captions, index["errors"]


class CaptionStore:
    """The captions of a dataset's motions by id, parsed once into <root>/.captions-pack/<key>/
    (one JSON file instead of one text file per motion; keyed, built and cleaned like the feature
    pack), otherwise `read_captions` per file. Either way the same captions and the same DataErrors.

        captions = CaptionStore(root).load("000001")
    """

    def __init__(self, root: str | Path, pack: bool = True):
        self.root = Path(root)
        self.text_dir = self.root / "texts"
        self.folder: Path | None = None
        self._captions: dict[str, tuple[Caption, ...]] = {}
        self._errors: dict[str, list[str]] = {}
        if pack and self.text_dir.is_dir():
            self._open_or_build()

    @property
    def packed(self) -> bool:
        return self.folder is not None

    def _open_or_build(self) -> None:
        try:
            key, ids, newest = _scan(self.text_dir, ".txt", f"mmm-captions-pack {CAPTION_PACK_FORMAT}")
        except OSError:
            return
        if not ids:
            return
        folder, _ = _pack(
            self.root,
            CAPTION_PACK_DIR,
            key,
            newest,
            "captions",
            len(ids),
            lambda folder: _write_caption_pack(self.text_dir, folder, ids),
        )
        if folder is None:
            return
        try:
            self._captions, self._errors = _read_caption_pack(str(folder / "index.json"))
            self.folder = folder
        except (OSError, ValueError, KeyError, TypeError) as e:
            log.warning("unusable caption pack %s (%s): reading the files one by one", folder, e)

    def path(self, motion_id: str) -> Path:
        return self.text_dir / f"{motion_id}.txt"

    def load(self, motion_id: str) -> list[Caption]:
        """The captions of `motion_id`; DataError as `read_captions` raises it."""
        captions = self._captions.get(motion_id)
        if captions is not None:
            return list(captions)
        error = self._errors.get(motion_id)
        if error is not None:
            raise DataError(f"{self.path(motion_id)}{error[0]}", error[1], error[2])
        return read_captions(self.path(motion_id))


def load_stats(root: str | Path, feature_dim: int) -> tuple[np.ndarray, np.ndarray]:
    root = Path(root)
    out = []
    for name in ("Mean.npy", "Std.npy"):
        path = root / name
        if not path.exists():
            raise DataError(
                path,
                "normalization statistics are missing",
                f"create them with `mmm data stats {root} --write`",
            )
        arr = load_array(
            path, "normalization statistics", f"recompute with `mmm data stats {root} --write`"
        ).astype(np.float32)
        if arr.shape != (feature_dim,):
            raise DataError(
                path,
                f"shape {arr.shape}, expected ({feature_dim},)",
                f"recompute with `mmm data stats {root} --write`"
                + (f", or {skeleton_hint(arr.shape[0])}" if arr.shape[0] in FEATURE_SKELETONS else ""),
            )
        if not np.isfinite(arr).all():
            raise DataError(path, "NaN/Inf values", f"recompute with `mmm data stats {root} --write`")
        out.append(arr)
    if (out[1] <= 0).any():
        raise DataError(
            root / "Std.npy", "zero or negative entries", f"recompute with `mmm data stats {root} --write`"
        )
    return out[0], out[1]


def compute_stats(
    root: str | Path, num_joints: int, ids: list[str] | None = None
) -> tuple[np.ndarray, np.ndarray, LoadReport]:
    """Mean and Std (D,) over every feature file (or `ids`), the reference way.

    Files with NaN/Inf are left out (as the reference does) and counted in the report.
    """
    root = Path(root)
    vec_dir = root / "new_joint_vecs"
    if ids is None:
        if not vec_dir.is_dir():
            raise DataError(vec_dir, "folder is missing", f"is {root} a dataset in the HumanML3D layout?")
        ids = sorted(p.stem for p in vec_dir.glob("*.npy"))
    report = LoadReport()
    feature_dim = 4 + (num_joints - 1) * 9 + num_joints * 3 + 4
    store = FeatureStore(root, feature_dim)
    # Two passes over blocks of frames in float64 (mean, then squared deviations): the numbers of
    # np.concatenate(...).mean/.std without holding every frame in memory at once.
    total = np.zeros(feature_dim, dtype=np.float64)
    frames = 0
    hint = ""  # another skeleton's features: say which to choose
    for block, errors in store.blocks(ids):
        for e in errors:
            report.skip(e.problem, e.path)
            if e.problem.startswith("wrong feature shape") and not hint:
                hint = f" ({e.fix})"
        if block is not None:
            total += block.sum(axis=0, dtype=np.float64)
            frames += block.shape[0]
    report.kept_clips = len(ids) - sum(report.skipped.values())
    if not frames:
        raise DataError(
            vec_dir, f"no usable feature files to compute statistics from{hint}", report.summary()
        )
    mean = total / frames
    squares = np.zeros(feature_dim, dtype=np.float64)
    for block, _ in store.blocks(ids):
        if block is not None:
            squares += np.square(block.astype(np.float64) - mean).sum(axis=0)
    std = np.sqrt(squares / frames)
    for group in FeatureLayout(num_joints).groups():
        std[group] = std[group].mean()
    report.kept_items = report.kept_clips
    return mean.astype(np.float32), std.astype(np.float32), report


def save_array_atomic(path: str | Path, array: np.ndarray) -> None:
    """np.save to a temporary name in the same folder, then rename: never a half-written file."""
    with atomic_write(path) as f:
        np.save(f, array)


def load_items(
    root: str | Path,
    split: str,
    *,
    feature_dim: int,
    fps: float,
    min_length: int,
    length_limit: int = 200,
    on_invalid: str = "error",
    ids: list[str] | None = None,
) -> tuple[list[MotionItem], LoadReport]:
    """Items of a split with their captions, by the reference loader's rules.

    on_invalid: "error" raises DataError at the first unusable file or line; "skip" leaves the
    clip out and counts it. Length-rule exclusions are always counted, never an error.
    """
    if on_invalid not in ("error", "skip"):
        raise ValueError(f"on_invalid must be 'error' or 'skip', got {on_invalid!r}")
    root = Path(root)
    ids = read_split(root, split) if ids is None else ids
    store, caption_store = FeatureStore(root, feature_dim), CaptionStore(root)
    report = LoadReport()
    items: list[MotionItem] = []
    for motion_id in _unique(ids, report):
        try:
            features = store.load(motion_id)
            captions = caption_store.load(motion_id)
        except DataError as e:
            if on_invalid == "error":
                raise DataError(
                    e.path,
                    e.problem,
                    f"{e.fix}; or set data.on_invalid=skip (mmm data check: --on-invalid skip) to leave such "
                    "clips out (they are counted)",
                ) from None
            report.skip(e.problem.split(" (")[0], e.path)
            continue
        T = features.shape[0]
        if not (min_length <= T < length_limit):
            report.skip(f"clip length outside [{min_length}, {length_limit}) frames", motion_id)
            continue
        whole = [c for c in captions if c.whole_clip]
        for c in captions:
            if c.whole_clip:
                continue
            a, b = int(c.start * fps), int(c.end * fps)
            span = features[a:b]
            if not (min_length <= len(span) < length_limit):
                report.skip(
                    f"caption sub-span length outside [{min_length}, {length_limit}) frames",
                    f"{motion_id} {c.start}-{c.end}s",
                )
                continue
            items.append(MotionItem(f"{motion_id}#{a}-{a + len(span)}", motion_id, span, [c], start=a))
        if whole:
            items.append(MotionItem(motion_id, motion_id, features, whole))
        report.kept_clips += 1
    report.kept_items = len(items)
    if not items:
        raise DataError(root / f"{split}.txt", f"no usable items in split {split!r}", report.summary())
    return items, report


def check_mirror_splits(root: str | Path) -> list[str]:
    """Ids whose mirrored copy is in a different train/val/test split (a leak between splits)."""
    where: dict[str, str] = {}
    for split in ("train", "val", "test"):
        if (Path(root) / f"{split}.txt").exists():
            for motion_id in read_split(root, split):
                where[motion_id] = split
    return sorted(i for i, s in where.items() if mirror_id(i) in where and where[mirror_id(i)] != s)


def load_clips(
    root: str | Path,
    split: str,
    *,
    feature_dim: int,
    min_length: int,
    on_invalid: str = "error",
) -> tuple[dict[str, np.ndarray], LoadReport]:
    """Whole clips (id -> (T, D) features) of a split with T >= min_length, captions not read.

    This is what the tokenizer trains on: the reference keeps every clip at least one window long.
    """
    root = Path(root)
    report = LoadReport()
    clips: dict[str, np.ndarray] = {}
    ids = _unique(read_split(root, split), report)
    store = FeatureStore(root, feature_dim)
    for motion_id in ids:
        try:
            features = store.load(motion_id)
        except DataError as e:
            if on_invalid == "error":
                raise DataError(
                    e.path,
                    e.problem,
                    f"{e.fix}; or set data.on_invalid=skip (mmm data check: --on-invalid skip) to leave such "
                    "clips out (they are counted)",
                ) from None
            report.skip(e.problem.split(" (")[0], e.path)
            continue
        if features.shape[0] < min_length:
            report.skip(f"clip shorter than {min_length} frames", motion_id)
            continue
        clips[motion_id] = features
    report.kept_clips = report.kept_items = len(clips)
    if not clips:
        raise DataError(
            root / f"{split}.txt",
            f"no clip of split {split!r} is at least {min_length} frames long",
            report.summary(),
        )
    return clips, report
