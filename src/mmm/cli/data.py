"""Data commands: convert, data synth/stats/check/preview, render."""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

from mmm.cli.common import CLIError, load_npy, refuse_existing, save_npy
from mmm.cli.options import option_error
from mmm.generation.settings import SamplingValueError, check_seed

SKELETON_NAMES = ["t2m", "kit"]
LENGTH_LIMIT = 200  # data.length_limit of every conf/data/*.yaml


def add_convert(sub) -> None:
    convert = sub.add_parser("convert", help="joint positions <-> 263-d features")
    convert.add_argument("direction", choices=["joints-to-features", "features-to-joints"])
    convert.add_argument(
        "input", help="(T, 22, 3) joints or (T, 263) features .npy (KIT-ML: (T, 21, 3) or (T, 251))"
    )
    convert.add_argument("output", nargs="?", help=".npy to write (or give it as --out)")
    convert.add_argument("--out", default=None, help="the .npy to write, as the other commands take it")
    convert.add_argument("--no-retarget", action="store_true", help="keep the motion's own bone lengths")
    convert.add_argument("--overwrite", action="store_true", help="replace an existing output file")
    convert.set_defaults(func=cmd_convert)


def add_data(sub) -> None:
    data = sub.add_parser("data", help="datasets: synthesize, statistics, checks, previews")
    data = data.add_subparsers(dest="data_command", required=True)
    synth = data.add_parser("synth", help="generate the synthetic text-motion dataset")
    synth.add_argument("--out", required=True)
    synth.add_argument("--num-clips", type=int, default=1500)
    synth.add_argument("--seed", type=int, default=0)
    synth.add_argument(
        "--train-paraphrases",
        type=int,
        default=3,
        help="whole-clip captions per training clip (3, every clip's own, or more: extra paraphrases)",
    )
    synth.add_argument(
        "--extra-train-clips",
        type=int,
        default=0,
        help="more clips after --num-clips, all in the training split: val and test stay those of "
        "--num-clips alone",
    )
    synth.add_argument(
        "--extra-composite-fraction",
        type=float,
        default=None,
        help="share of two-action clips among the --extra-train-clips (default: a third, as in the others)",
    )
    synth.add_argument(
        "--workers",
        type=int,
        default=None,
        help="processes drawing clips (default: one per CPU core, at most 4); the files are the same for any",
    )
    synth.add_argument("--overwrite", action="store_true", help="replace an existing dataset folder")
    synth.set_defaults(func=cmd_data_synth)

    stats = data.add_parser("stats", help="Mean/Std of a dataset computed the reference way")
    stats.add_argument("root")
    stats.add_argument("--skeleton", choices=SKELETON_NAMES, default="t2m")
    stats.add_argument(
        "--write",
        action="store_true",
        help="write Mean.npy and Std.npy into the dataset "
        "(--evaluator-style: evaluator_style/{mean,std}.npy)",
    )
    stats.add_argument(
        "--evaluator-style",
        action="store_true",
        help="the released recipe's statistics: "
        "root (dims 0-3) and foot-contact (last 4) Std divided by --feat-bias",
    )
    stats.add_argument("--feat-bias", type=float, default=25.0)
    stats.set_defaults(func=cmd_data_stats)

    check = data.add_parser("check", help="load every split and report what is kept and left out")
    check.add_argument("root")
    check.add_argument("--skeleton", choices=SKELETON_NAMES, default="t2m")
    check.add_argument("--min-length", type=int, default=None)
    check.add_argument("--on-invalid", choices=["error", "skip"], default="skip")
    check.set_defaults(func=cmd_data_check)

    preview = data.add_parser(
        "preview", help="render a few clips of a dataset (one per action when labelled)"
    )
    preview.add_argument("root")
    preview.add_argument("--out", required=True)
    preview.add_argument("--count", type=int, default=6)
    preview.add_argument("--split", default="test")
    preview.set_defaults(func=cmd_data_preview)


def add_render(sub) -> None:
    render = sub.add_parser("render", help="stick-figure GIF/MP4/PNG of motions side by side")
    render.add_argument(
        "inputs", nargs="+", help=".npy files of joints (T, 22, 3) or features (T, 263); KIT-ML: 21 and 251"
    )
    render.add_argument("--out", required=True, help="FILE.gif, FILE.mp4 or FILE.png (contact sheet)")
    render.add_argument(
        "--caption",
        action="append",
        help="one per input, in order (default: a generated sample's caption from its meta.json, else "
        "the file name)",
    )
    render.add_argument("--fps", type=float, default=None)
    render.add_argument("--overwrite", action="store_true", help="replace an existing --out file")
    render.set_defaults(func=cmd_render)


def cmd_convert(args: argparse.Namespace) -> None:
    from mmm.motion.features import joints_to_features, recover_from_ric
    from mmm.motion.skeleton import skeleton_for

    if (args.output is None) == (args.out is None):
        raise CLIError(
            "give the .npy to write once: `mmm convert DIRECTION IN.npy OUT.npy` or "
            "`mmm convert DIRECTION IN.npy --out OUT.npy`"
        )
    args.output = args.output or args.out
    refuse_existing(args.output, args.overwrite, "output path")
    arr = load_npy(args.input)
    if not np.isfinite(arr).all():
        raise CLIError(f"{args.input}: contains NaN/Inf values; fix the motion first")
    if args.direction == "joints-to-features":
        if arr.ndim != 3 or arr.shape[1:] not in ((22, 3), (21, 3)) or arr.shape[0] < 2:
            raise CLIError(
                f"{args.input}: shape {arr.shape}, expected joints (T, 22, 3) or (T, 21, 3) with T >= 2"
            )
        skeleton = skeleton_for(arr.shape[1])
        out = joints_to_features(arr.astype(np.float32), skeleton, retarget=not args.no_retarget)
    else:
        if arr.ndim != 2 or arr.shape[1] not in (263, 251) or arr.shape[0] < 1:
            raise CLIError(f"{args.input}: shape {arr.shape}, expected features (T, 263) or (T, 251)")
        out = recover_from_ric(arr.astype(np.float32))
    bad = np.flatnonzero(~np.isfinite(out.reshape(len(out), -1)).all(axis=1))
    if bad.size:  # never write a file that every later command would refuse
        raise CLIError(
            f"{args.input}: converting it gave NaN/Inf in {bad.size} of {len(out)} frames (first: {bad[0]}); "
            "the skeleton is degenerate there (e.g. every joint on one vertical line, so no facing, or "
            "zero-length bones): check that it holds (T, joints, xyz) positions in metres, y up"
        )
    save_npy(args.output, out.astype(np.float32))


def cmd_data_synth(args: argparse.Namespace) -> None:
    try:
        check_seed(args.seed)
    except SamplingValueError as e:
        raise option_error(e) from None
    if args.train_paraphrases < 3:
        raise CLIError(f"--train-paraphrases {args.train_paraphrases}: every clip has three; give 3 or more")
    if args.extra_train_clips < 0:
        raise CLIError(f"--extra-train-clips {args.extra_train_clips}: give 0 or more")
    if args.workers is not None and args.workers < 1:
        raise CLIError(f"--workers {args.workers}: give 1 or more processes")
    # imported here: keeps `mmm --help` and the refusals above fast (the generator needs torch)
    from mmm.data.synthetic.generate import COMPOSITE_FRACTION, generate_dataset

    fraction = COMPOSITE_FRACTION if args.extra_composite_fraction is None else args.extra_composite_fraction
    if not 0.0 <= fraction <= 1.0:
        raise CLIError(f"--extra-composite-fraction {fraction}: give a share between 0 and 1")
    summary = generate_dataset(
        args.out,
        num_clips=args.num_clips,
        seed=args.seed,
        overwrite=args.overwrite,
        train_paraphrases=args.train_paraphrases,
        extra_train_clips=args.extra_train_clips,
        extra_composite_fraction=fraction,
        workers=args.workers,
    )
    print(summary)


def cmd_data_stats(args: argparse.Namespace) -> None:
    from mmm.data.arrays import load_array
    from mmm.data.humanml3d import compute_stats, save_array_atomic
    from mmm.data.normalization import evaluator_style_std
    from mmm.motion.features import FeatureLayout
    from mmm.motion.skeleton import SKELETONS

    if not (math.isfinite(args.feat_bias) and args.feat_bias > 0):
        raise CLIError(
            f"--feat-bias {args.feat_bias:g} is not allowed: the root and foot-contact Std are divided by "
            "it, so it must be a finite number above 0 (the released MMM uses 25)"
        )
    root = Path(args.root)
    num_joints = SKELETONS[args.skeleton].num_joints
    mean, std, report = compute_stats(root, num_joints)
    print(f"{root}: statistics over {report.kept_clips} files")
    if report.skipped:
        print(report.summary())
    layout = FeatureLayout(num_joints)
    names = ("root yaw vel", "root xz vel", "root height", "positions", "rotations", "velocities", "contacts")
    if args.evaluator_style:
        scaled = evaluator_style_std(std, num_joints, args.feat_bias)
        print(
            f"evaluator-style: the root and foot-contact Std divided by {args.feat_bias:g} "
            "(what the released MMM normalizes with)"
        )
        print(f"{'group':14s} {'mean(avg)':>10s} {'std':>10s} {'scaled std':>10s}")
        for name, sl in zip(names, layout.groups()):
            print(f"{name:14s} {mean[sl].mean():10.4f} {std[sl][0]:10.4f} {scaled[sl][0]:10.4f}")
        if args.write:
            folder = root / "evaluator_style"
            folder.mkdir(exist_ok=True)
            save_array_atomic(folder / "mean.npy", mean)
            save_array_atomic(folder / "std.npy", usable_std(scaled, names, layout))
            print(
                f"wrote {folder / 'mean.npy'} and {folder / 'std.npy'} "
                f"(stage 1: normalization.statistics=files normalization.dir={folder})"
            )
        return
    have = (root / "Mean.npy").exists() and (root / "Std.npy").exists()
    fix = f"delete it and write it again with `mmm data stats {root} --write`"
    old_mean = load_array(root / "Mean.npy", "saved Mean", fix) if have else None
    old_std = load_array(root / "Std.npy", "saved Std", fix) if have else None
    if have and (old_mean.shape != mean.shape or old_std.shape != std.shape):
        print(
            f"the saved Mean.npy {old_mean.shape} and Std.npy {old_std.shape} are not of this dataset's "
            f"{mean.shape} (another skeleton? --skeleton kit for 251-d KIT-ML): not compared"
            + ("; --write replaces them" if not args.write else "")
        )
        have = False
    saved = f" {'saved std':>10s} {'max|dmean|':>10s}" if have else ""
    print(f"{'group':14s} {'mean(avg)':>10s} {'std':>10s}" + saved)
    for name, sl in zip(names, layout.groups()):
        row = f"{name:14s} {mean[sl].mean():10.4f} {std[sl][0]:10.4f}"
        if have:
            row += f" {old_std[sl][0]:10.4f} {np.abs(old_mean[sl] - mean[sl]).max():10.2e}"
        print(row)
    if args.write:
        save_array_atomic(root / "Mean.npy", mean)
        save_array_atomic(root / "Std.npy", usable_std(std, names, layout))
        print(f"wrote {root / 'Mean.npy'} and {root / 'Std.npy'}")


def usable_std(std: np.ndarray, names, layout) -> np.ndarray:
    """`std` with its zero entries (a feature constant over the whole dataset, e.g. foot contacts
    that never change) set to 1, each group named on stderr: a constant feature then normalizes
    to 0, where a zero Std would divide by zero (and every loader refuses it)."""
    zero = std <= 0
    if not zero.any():
        return std
    for name, sl in zip(names, layout.groups()):
        dims = np.flatnonzero(zero[sl]) + (sl.start or 0)
        if dims.size:
            print(
                f"warning: Std is 0 for {name} (dims {dims[0]}-{dims[-1]}): constant over the dataset; "
                "written as 1, so it normalizes to 0",
                file=sys.stderr,
            )
    return np.where(zero, 1.0, std).astype(std.dtype)


def cmd_data_check(args: argparse.Namespace) -> None:
    from mmm.data.humanml3d import DataError, check_mirror_splits, load_items, load_stats
    from mmm.motion.skeleton import SKELETONS

    sk = SKELETONS[args.skeleton]
    if args.min_length is not None and not 1 <= args.min_length < LENGTH_LIMIT:
        raise CLIError(
            f"--min-length {args.min_length} is not allowed: 1 or more frames, below the length limit "
            f"{LENGTH_LIMIT} (clips this long or longer are left out, as in HumanML3D)"
        )
    min_length = args.min_length if args.min_length is not None else (24 if sk.name == "kit" else 40)
    root = Path(args.root)
    load_stats(root, sk.feature_dim)
    # Every split is checked and reported, so one run names every problem, not only the first.
    unusable: list[tuple[str, DataError]] = []
    for split in ("train", "val", "test"):
        try:
            _, report = load_items(
                root,
                split,
                feature_dim=sk.feature_dim,
                fps=sk.fps,
                min_length=min_length,
                length_limit=LENGTH_LIMIT,
                on_invalid=args.on_invalid,
            )
        except DataError as e:
            unusable.append((split, e))
            print(f"{split}: cannot be used (below)")
            continue
        print(f"{split}: {report.summary()}")
    if unusable:  # the mirror check reads every split file again
        print("mirrored ids in a different split from their original: not checked (a split cannot be used)")
    else:
        leaks = check_mirror_splits(root)
        print(
            f"mirrored ids in a different split from their original: {len(leaks)}"
            + (f" (e.g. {', '.join(leaks[:5])})" if leaks else "")
        )
    if len(unusable) == 1:
        raise unusable[0][1]
    if unusable:
        one_line = {split: "; ".join(line.strip() for line in str(e).splitlines()) for split, e in unusable}
        raise CLIError(
            f"{len(unusable)} of 3 splits cannot be used: "
            + " | ".join(f"{split}: {message}" for split, message in one_line.items())
        )


def cmd_data_preview(args: argparse.Namespace) -> None:
    from mmm.data.preview import preview_dataset

    if args.count < 1:
        raise CLIError(f"--count {args.count} is not allowed: 1 or more clips to render")
    for path in preview_dataset(args.root, args.out, count=args.count, split=args.split):
        print(f"wrote {path}")


def cmd_render(args: argparse.Namespace) -> None:
    from mmm.render import render_files

    if args.fps is not None and not (math.isfinite(args.fps) and 0 < args.fps <= 1000):
        raise CLIError(f"--fps {args.fps} is not allowed: frames per second, more than 0 and at most 1000")
    refuse_existing(args.out, args.overwrite, "--out")
    for path in render_files(args.inputs, args.out, captions=args.caption or None, fps=args.fps):
        print(f"wrote {path}")
