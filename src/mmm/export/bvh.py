"""BVH export of joint-position motions (HumanML3D 22 joints, KIT-ML 21 joints) and a BVH parser.

A motion here is joint positions (T, J, 3); BVH stores a rigid hierarchy of offsets plus one
rotation per joint and frame, so `write_bvh` turns positions into rotations:

* Bones are rigid in BVH. Generated motions do not keep bone lengths exactly constant (each joint
  is predicted on its own), so each bone gets its median length over the motion and keeps its
  direction of every frame. `BVHInfo.max_deviation_m` reports how far this moves any joint; the
  file encodes exactly the rigidified positions (`BVHInfo.rigid_joints`), to print precision.
* A BVH joint has one rotation for all of its children, but the pelvis (hips + spine) and spine3
  (neck + collars) have children whose bones move independently (KIT: root and chest). Such a joint gets one
  zero-offset carrier joint per child (`pelvis_to_left_hip`, ...) whose rotation orients that
  bone. A joint with a single child carries its bone's rotation itself; a leaf keeps its parent's
  rotation and ends in an `End Site` along its rest direction.
* The root's rotation is the body's heading about +Y (from hips and shoulders). Each bone's
  global rotation turns its rest direction onto its direction in the frame by a shortest arc;
  every BVH joint's local rotation is inv(global of its BVH parent) · its own global, written as
  Z-X-Y Euler angles in degrees (R = Rz · Rx · Ry, the channel order `Zrotation Xrotation
  Yrotation`). Positions fix a bone's direction but not its twist; the frame the shortest arc is
  taken in decides the twist (`arcs`):
  - "parent" (default): the arc is taken in the frame of the BVH parent, global = G_parent ·
    qbetween(rest, G_parent⁻¹ · bone). Local rotations are pure swings, and they only become
    ill-defined when a bone points opposite its rest direction relative to its parent (an arm
    straight overhead), which makes the smoothest animation: on the reference clip 012314 no
    local rotation steps more than 54° between frames, against 172° for "world".
  - "heading": the arc is taken in the body's heading frame (turns with the body).
  - "world": global = qbetween(rest, bone) in world coordinates. Its twist flips whenever a bone
    points opposite its rest direction in the world, e.g. the hips and feet of a body facing −Z.
  All three encode the same positions.

Units are metres (KIT's millimetres are converted with `Skeleton.unit_scale`), y is up and the
body faces +Z, as in the data; Blender's BVH importer reads these files with its defaults
(checked with bpy 5.0.1: pose-bone heads match `read_bvh` to 1e-6 m).
"""

from __future__ import annotations

import math
import os
import uuid
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from mmm.motion.features import recover_from_ric
from mmm.motion.quaternion import qbetween, qinv, qmul, qrot, quat_about_y, quat_to_matrix
from mmm.motion.skeleton import SKELETONS, Skeleton, skeleton_for

ROOT_CHANNELS = ("Xposition", "Yposition", "Zposition", "Zrotation", "Xrotation", "Yrotation")
JOINT_CHANNELS = ("Zrotation", "Xrotation", "Yrotation")
END_SITE_LENGTH = 0.05  # metres: the End Site marks the tip of a leaf bone (hand, toe, head top)
_LOCK_EPS = 1e-13  # cos(x) below this is gimbal lock for the Z-X-Y extraction (costs < 4e-13)


# ---------------------------------------------------------------------------------------------
# Euler angles
# ---------------------------------------------------------------------------------------------


def _axis_matrix(axis: str, angle: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) about one coordinate axis by `angle` (...) radians."""
    c, s = np.cos(angle), np.sin(angle)
    one, zero = np.ones_like(angle), np.zeros_like(angle)
    rows = {
        "X": ((one, zero, zero), (zero, c, -s), (zero, s, c)),
        "Y": ((c, zero, s), (zero, one, zero), (-s, zero, c)),
        "Z": ((c, -s, zero), (s, c, zero), (zero, zero, one)),
    }[axis]
    return np.stack([np.stack(row, axis=-1) for row in rows], axis=-2)


def euler_to_matrix(angles: np.ndarray, order: str = "ZXY") -> np.ndarray:
    """Rotation matrices (..., 3, 3) from Euler angles (..., len(order)) in radians.

    BVH semantics: the angles are listed in channel order and R = R_order[0] · R_order[1] · ...,
    e.g. order "ZXY" gives R = Rz(a0) · Rx(a1) · Ry(a2), acting on column vectors.
    """
    angles = np.asarray(angles, dtype=np.float64)
    out = np.broadcast_to(np.eye(3), angles.shape[:-1] + (3, 3)).copy()
    for i, axis in enumerate(order.upper()):
        out = out @ _axis_matrix(axis, angles[..., i])
    return out


def matrix_to_euler_zxy(R: np.ndarray) -> np.ndarray:
    """Z-X-Y Euler angles (..., 3) = (z, x, y) in radians with R = Rz(z) · Rx(x) · Ry(y).

    R = [[cz·cy − sz·sx·sy, −sz·cx, cz·sy + sz·sx·cy],
         [sz·cy + cz·sx·sy,  cz·cx, sz·sy − cz·sx·cy],
         [−cx·sy,            sx,    cx·cy           ]].
    y comes from the last row, then z and x from M = R · Ry(y)ᵀ = Rz(z) · Rx(x). Because z and x
    are read from M, the angles reproduce R to rounding even where y is ill-determined: near
    gimbal lock (x = ±90°, the bottom row's first and last entries vanish) an error δ in y costs
    only cos(x)·δ. At the lock itself y is set to 0 and z takes the whole turn about the
    vertical of the locked frame. x lies in [−90°, 90°].
    """
    R = np.asarray(R, dtype=np.float64)
    r20, r21, r22 = R[..., 2, 0], R[..., 2, 1], R[..., 2, 2]
    locked = np.hypot(r20, r22) < _LOCK_EPS
    y = np.where(locked, 0.0, np.arctan2(-r20, r22))
    cy, sy = np.cos(y), np.sin(y)
    m00 = R[..., 0, 0] * cy + R[..., 0, 2] * sy
    m10 = R[..., 1, 0] * cy + R[..., 1, 2] * sy
    m22 = -r20 * sy + r22 * cy
    z = np.arctan2(m10, m00)
    x = np.arctan2(r21, m22)
    return np.stack((z, x, y), axis=-1)


def _continuous_zxy(angles: np.ndarray) -> np.ndarray:
    """Make Z-X-Y angles (T, N, 3) continuous in time without changing any rotation.

    Each frame picks, per joint, between the two equivalent triples (z, x, y) and
    (z + π, π − x, y + π) the one closer to the previous frame, then shifts every angle by the
    multiple of 2π nearest the previous value. Keyframe interpolation (e.g. Blender playing the
    file at another frame rate) then turns the short way instead of flipping.
    """
    out = angles.copy()
    two_pi = 2.0 * math.pi

    def nearest(a: np.ndarray, ref: np.ndarray) -> np.ndarray:
        return a - two_pi * np.round((a - ref) / two_pi)

    for t in range(1, out.shape[0]):
        prev = out[t - 1]
        a = nearest(out[t], prev)
        alt = out[t] + np.array([math.pi, 0.0, math.pi])
        alt[..., 1] = math.pi - out[t][..., 1]
        b = nearest(alt, prev)
        use_b = np.abs(b - prev).sum(-1) < np.abs(a - prev).sum(-1)
        out[t] = np.where(use_b[..., None], b, a)
    return out


# ---------------------------------------------------------------------------------------------
# The BVH hierarchy of a skeleton
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Node:
    name: str
    parent: int  # index into the node list, -1 for the root
    joint: int | None  # skeleton joint the node sits at (None for a carrier)
    bone: int | None  # skeleton joint c whose bone parent(c) -> c this node's rotation orients
    offset_joint: int | None  # skeleton joint whose rest offset is the node's OFFSET
    end_site: bool  # a leaf: ends in an End Site along its rest direction


def _children(skeleton: Skeleton) -> list[list[int]]:
    children: list[list[int]] = [[] for _ in range(skeleton.num_joints)]
    for child, parent in enumerate(skeleton.parents):
        if parent >= 0:
            children[parent].append(child)
    return children


def _root_of(skeleton: Skeleton) -> int:
    roots = [j for j, p in enumerate(skeleton.parents) if p < 0]
    if len(roots) != 1:
        raise ValueError(f"skeleton {skeleton.name!r} has {len(roots)} roots; a BVH needs exactly one")
    return roots[0]


def _bvh_nodes(skeleton: Skeleton) -> list[_Node]:
    """The BVH joints of a skeleton in file (depth-first) order, carriers included.

    The root rotates with the heading, so each of its bones gets a carrier; so does each bone of
    any other joint with several children. A joint with one child orients that child's bone.
    """
    children = _children(skeleton)
    names = skeleton.joint_names
    nodes: list[_Node] = []

    def add_joint(j: int, parent_node: int) -> None:
        kids = children[j]
        is_root = parent_node < 0
        carries = kids[0] if (len(kids) == 1 and not is_root) else None
        nodes.append(_Node(names[j], parent_node, j, carries, None if is_root else j, end_site=not kids))
        me = len(nodes) - 1
        if carries is not None:
            add_joint(carries, me)
            return
        for c in kids:
            nodes.append(_Node(f"{names[j]}_to_{names[c]}", me, None, c, None, end_site=False))
            add_joint(c, len(nodes) - 1)

    add_joint(_root_of(skeleton), -1)
    return nodes


def bvh_joint_names(skeleton: Skeleton) -> tuple[str, ...]:
    """Names of the BVH joints `write_bvh` writes for `skeleton`, in file order (carriers included)."""
    return tuple(node.name for node in _bvh_nodes(skeleton))


# ---------------------------------------------------------------------------------------------
# Writing
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class BVHInfo:
    """What `write_bvh` wrote. Lengths and positions in metres.

    max_deviation_m: the largest distance between a joint of the input motion (in metres) and the
    same joint of the rigidified motion the file encodes (bones at their median length); where it
    happened: max_deviation_joint, max_deviation_frame. rigid_joints (T, J, 3): those rigidified
    positions in skeleton joint order, which `read_bvh(path).positions(skeleton.joint_names)`
    reproduces to print precision.
    """

    path: Path
    skeleton: str
    num_frames: int
    fps: float
    frame_time: float
    joint_names: tuple[str, ...]  # BVH joints in file order, carriers included
    num_channels: int  # values per frame line: 6 + 3 × (joints − 1)
    bone_lengths: np.ndarray = field(repr=False)  # (J,) median length of the bone into each joint
    max_deviation_m: float = 0.0
    max_deviation_joint: str = ""
    max_deviation_frame: int = 0
    mean_deviation_m: float = 0.0
    rigid_joints: np.ndarray = field(default=None, repr=False)

    @property
    def num_joints(self) -> int:
        return len(self.joint_names)

    def as_dict(self) -> dict:
        """Scalars for logging (e.g. as run metrics or tags)."""
        return {
            "path": str(self.path),
            "skeleton": self.skeleton,
            "num_frames": self.num_frames,
            "fps": self.fps,
            "num_joints": self.num_joints,
            "num_channels": self.num_channels,
            "max_deviation_m": self.max_deviation_m,
            "max_deviation_joint": self.max_deviation_joint,
            "max_deviation_frame": self.max_deviation_frame,
            "mean_deviation_m": self.mean_deviation_m,
        }


def _resolve_skeleton(skeleton: Skeleton | str | None, num_joints: int, path: Path) -> Skeleton:
    if skeleton is None:
        try:
            return skeleton_for(num_joints)
        except ValueError as err:
            raise ValueError(f"cannot write {path}: {err}") from None
    if isinstance(skeleton, str):
        if skeleton.lower() not in SKELETONS:
            raise ValueError(
                f"cannot write {path}: unknown skeleton {skeleton!r}; use one of {sorted(SKELETONS)}"
            )
        return SKELETONS[skeleton.lower()]
    return skeleton


def _as_joint_array(joints, path: Path) -> np.ndarray:
    if isinstance(joints, torch.Tensor):
        joints = joints.detach().cpu().numpy()
    arr = np.asarray(joints)
    if arr.dtype == object or not (
        np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)
    ):
        raise ValueError(
            f"cannot write {path}: joints must be a numeric array (T, J, 3), got dtype {arr.dtype}"
        )
    if arr.ndim != 3 or arr.shape[-1] != 3:
        hint = ""
        if arr.ndim == 2:
            hint = (
                " (a single pose? pass joints[None])"
                if arr.shape[-1] == 3
                else " (features? write them with features_to_bvh, or recover_from_ric first)"
            )
        raise ValueError(f"cannot write {path}: joints must have shape (T, J, 3), got {arr.shape}{hint}")
    if arr.shape[0] < 1:
        raise ValueError(
            f"cannot write {path}: the motion has no frames, shape {arr.shape}; pass at least 1 frame"
        )
    arr = arr.astype(np.float64)
    bad = ~np.isfinite(arr)
    if bad.any():
        frames = np.unique(np.nonzero(bad)[0])
        raise ValueError(
            f"cannot write {path}: joints of shape {arr.shape} contain NaN or inf in {len(frames)} frame(s) "
            f"(first: {frames[:5].tolist()}); drop or repair those frames before exporting"
        )
    return arr


def _unit_directions(bones: torch.Tensor, rest: torch.Tensor) -> torch.Tensor:
    """Unit bone directions (T, 3); zero-length frames reuse the nearest earlier (else later) direction."""
    norms = bones.norm(dim=-1)
    valid = norms > 1e-9
    if not bool(valid.any()):
        return rest.expand_as(bones).clone()
    idx = torch.arange(bones.shape[0])
    last_valid = torch.cummax(torch.where(valid, idx, torch.full_like(idx, -1)), dim=0).values
    first_valid = int(idx[valid][0])
    src = torch.where(last_valid >= 0, last_valid, torch.full_like(idx, first_valid))
    return bones[src] / norms[src].unsqueeze(-1)


def _headings(positions: torch.Tensor, skeleton: Skeleton) -> torch.Tensor:
    """Heading angle (T,) about +Y of the facing direction from hips and shoulders (0 faces +Z).

    across = (R_hip − L_hip) + (R_shoulder − L_shoulder), forward = up × across = (a_z, 0, −a_x).
    A frame whose across vector is vertical keeps the previous frame's heading (0 at the start).
    """
    r_hip, l_hip, r_sh, l_sh = skeleton.face_joints
    across = positions[:, r_hip] - positions[:, l_hip] + positions[:, r_sh] - positions[:, l_sh]
    fwd_x, fwd_z = across[:, 2], -across[:, 0]
    angle = torch.atan2(fwd_x, fwd_z)
    ok = torch.hypot(fwd_x, fwd_z) > 1e-9
    if not bool(ok.all()):
        idx = torch.arange(angle.shape[0])
        last = torch.cummax(torch.where(ok, idx, torch.full_like(idx, -1)), dim=0).values
        angle = torch.where(last >= 0, angle[last.clamp_min(0)], torch.zeros_like(angle))
    return angle


def _fmt(values: np.ndarray, decimals: int) -> str:
    return " ".join(f"{v:.{decimals}f}" for v in values)


def write_bvh(
    joints,
    path,
    skeleton: Skeleton | str | None = None,
    fps: float | None = None,
    *,
    decimals: int = 6,
    end_site_length: float = END_SITE_LENGTH,
    arcs: str = "parent",
) -> BVHInfo:
    """Write joint positions (T, J, 3) as a BVH file; returns a `BVHInfo`.

    skeleton: a `Skeleton`, its name ("t2m", "humanml3d", "kit") or None to pick it from J
    (22: HumanML3D, 21: KIT-ML). fps: the skeleton's by default (20 / 12.5). Coordinates are in
    the skeleton's units (KIT: millimetres) and written in metres. decimals: digits after the
    point for offsets, positions and angles (6: 1e-6 m, 1e-6°). end_site_length: metres from
    a leaf joint to its End Site. arcs: "parent", "heading" or "world", the frame each bone's
    shortest-arc rotation is taken in (module docstring); the positions are the same for all.
    The file is written under a temporary name and renamed, so a reader never sees half a file.
    """
    path = Path(path)
    arr = _as_joint_array(joints, path)
    skeleton = _resolve_skeleton(skeleton, arr.shape[1], path)
    if arr.shape[1] != skeleton.num_joints:
        raise ValueError(
            f"cannot write {path}: joints of shape {arr.shape} have {arr.shape[1]} joints but skeleton "
            f"{skeleton.name!r} has {skeleton.num_joints}; pass the matching skeleton (or None to pick it "
            "from J)"
        )
    fps = float(skeleton.fps if fps is None else fps)
    if not math.isfinite(fps) or fps <= 0:
        raise ValueError(f"cannot write {path}: fps must be a positive number, got {fps}")
    if arcs not in ("parent", "heading", "world"):
        raise ValueError(f"cannot write {path}: arcs must be 'parent', 'heading' or 'world', got {arcs!r}")

    pos = torch.from_numpy(arr) * float(skeleton.unit_scale)  # metres
    T, J = pos.shape[:2]
    parents = skeleton.parents
    root = _root_of(skeleton)
    rest = torch.tensor(skeleton.rest_directions, dtype=torch.float64)

    # Rigidify: every bone keeps its direction of each frame at its median length.
    order = [root]
    children = _children(skeleton)
    for j in order:
        order.extend(children[j])
    lengths = np.zeros(J)
    dirs = torch.zeros(T, J, 3, dtype=torch.float64)
    rigid = torch.zeros_like(pos)
    rigid[:, root] = pos[:, root]
    for j in order[1:]:
        bones = pos[:, j] - pos[:, parents[j]]
        lengths[j] = float(np.median(bones.norm(dim=-1).numpy()))
        dirs[:, j] = _unit_directions(bones, rest[j])
        rigid[:, j] = rigid[:, parents[j]] + lengths[j] * dirs[:, j]
    deviation = (rigid - pos).norm(dim=-1)  # (T, J)
    flat = int(deviation.argmax())

    # Global rotations of the BVH joints, then local = inv(parent global) · global.
    nodes = _bvh_nodes(skeleton)
    heading = quat_about_y(_headings(pos, skeleton))
    globals_: list[torch.Tensor] = []
    locals_: list[torch.Tensor] = []
    for node in nodes:
        if node.parent < 0:
            g = heading
        elif node.bone is not None:
            c = node.bone
            frame = {"world": None, "heading": heading, "parent": globals_[node.parent]}[arcs]
            if frame is None:
                g = qbetween(rest[c].expand(T, 3), dirs[:, c])
            else:  # the shortest arc seen from `frame`, turned with it
                g = qmul(frame, qbetween(rest[c].expand(T, 3), qrot(qinv(frame), dirs[:, c])))
        else:  # a leaf keeps its parent's orientation
            g = globals_[node.parent]
        globals_.append(g)
        locals_.append(g if node.parent < 0 else qmul(qinv(globals_[node.parent]), g))
    matrices = quat_to_matrix(torch.stack(locals_, dim=1)).numpy()  # (T, N, 3, 3)
    euler = np.degrees(_continuous_zxy(matrix_to_euler_zxy(matrices)))  # (T, N, 3) z, x, y

    # The text.
    lines = ["HIERARCHY"]
    depth_of: list[int] = []
    zero = _fmt(np.zeros(3), decimals)

    def close_to(depth: int) -> None:
        while len(stack) > depth:
            stack.pop()
            lines.append("\t" * len(stack) + "}")

    stack: list[int] = []
    for i, node in enumerate(nodes):
        depth = 0 if node.parent < 0 else depth_of[node.parent] + 1
        depth_of.append(depth)
        close_to(depth)
        ind = "\t" * depth
        lines.append(f"{ind}{'ROOT' if node.parent < 0 else 'JOINT'} {node.name}")
        lines.append(f"{ind}{{")
        offset = (
            zero
            if node.offset_joint is None
            else _fmt((rest[node.offset_joint] * lengths[node.offset_joint]).numpy(), decimals)
        )
        lines.append(f"{ind}\tOFFSET {offset}")
        channels = ROOT_CHANNELS if node.parent < 0 else JOINT_CHANNELS
        lines.append(f"{ind}\tCHANNELS {len(channels)} {' '.join(channels)}")
        stack.append(i)
        if node.end_site:
            tip = _fmt((rest[node.joint] * float(end_site_length)).numpy(), decimals)
            lines += [f"{ind}\tEnd Site", f"{ind}\t{{", f"{ind}\t\tOFFSET {tip}", f"{ind}\t}}"]
    close_to(0)

    frame_time = 1.0 / fps
    lines += ["MOTION", f"Frames: {T}", f"Frame Time: {frame_time:.10g}"]
    values = np.concatenate((pos[:, root].numpy(), euler.reshape(T, -1)), axis=1)  # (T, C)
    num_channels = 3 + 3 * len(nodes)
    assert values.shape[1] == num_channels
    fmt = " ".join([f"%.{decimals}f"] * num_channels)
    lines += [fmt % tuple(row) for row in values.tolist()]
    text = "\n".join(lines) + "\n"

    _write_atomic(path, text)
    return BVHInfo(
        path=path,
        skeleton=skeleton.name,
        num_frames=T,
        fps=fps,
        frame_time=frame_time,
        joint_names=tuple(n.name for n in nodes),
        num_channels=num_channels,
        bone_lengths=lengths,
        max_deviation_m=float(deviation.max()),
        max_deviation_joint=skeleton.joint_names[flat % J],
        max_deviation_frame=flat // J,
        mean_deviation_m=float(deviation.mean()),
        rigid_joints=rigid.numpy(),
    )


def _write_atomic(path: Path, text: str) -> None:
    """Write under a temporary name in the same folder, then rename over `path` (atomic on POSIX)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.{uuid.uuid4().hex[:8]}.tmp")
    try:
        with open(tmp, "x", encoding="utf-8", newline="\n") as fh:  # the umask's usual permissions
            fh.write(text)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def features_to_bvh(
    features, path, skeleton: Skeleton | str | None = None, fps: float | None = None, **kwargs
) -> BVHInfo:
    """Write a motion given as (de-normalized) features (T, 263 or 251) as BVH via `recover_from_ric`."""
    if isinstance(features, torch.Tensor):
        features = features.detach().cpu().numpy()
    feats = np.asarray(features, dtype=np.float64)
    if feats.ndim != 2:
        raise ValueError(f"cannot write {path}: features must have shape (T, D), got {feats.shape}")
    return write_bvh(recover_from_ric(feats), path, skeleton, fps, **kwargs)


# ---------------------------------------------------------------------------------------------
# Reading
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class BVHMotion:
    """A parsed BVH file. Positions are in the file's units (metres for files of `write_bvh`).

    names, parents, offsets (J, 3), channels: the joints in file order; joints (T, J, 3): their
    positions by forward kinematics of the hierarchy and the channels; end_sites: joint name ->
    End Site offset, end_positions (T, E, 3) in the same order; motion (T, C): the raw channel
    values (angles in degrees).
    """

    path: Path
    names: tuple[str, ...]
    parents: tuple[int, ...]
    offsets: np.ndarray
    channels: tuple[tuple[str, ...], ...]
    end_sites: dict[str, np.ndarray]
    fps: float
    frame_time: float
    motion: np.ndarray = field(repr=False)
    joints: np.ndarray = field(repr=False)
    end_positions: np.ndarray = field(repr=False)

    @property
    def num_frames(self) -> int:
        return self.motion.shape[0]

    @property
    def num_joints(self) -> int:
        return len(self.names)

    def channel_index(self, joint: str, channel: str) -> int:
        """Column of `motion` holding `channel` (e.g. "Zrotation") of `joint`."""
        start = 0
        for name, chans in zip(self.names, self.channels):
            if name == joint:
                return start + chans.index(channel)
            start += len(chans)
        raise KeyError(joint)

    def positions(self, names) -> np.ndarray:
        """Positions (T, len(names), 3) of the named joints, e.g. a skeleton's joint_names."""
        index = {n: i for i, n in enumerate(self.names)}
        missing = [n for n in names if n not in index]
        if missing:
            raise ValueError(f"{self.path}: no joints named {missing}; the file has {list(self.names)}")
        return self.joints[:, [index[n] for n in names]]


_ROTATION_AXES = {"Xrotation": "X", "Yrotation": "Y", "Zrotation": "Z"}
_POSITION_AXES = {"Xposition": 0, "Yposition": 1, "Zposition": 2}


class _Tokens:
    def __init__(self, lines: list[tuple[int, str]], path: Path):
        self.items = [(no, tok) for no, line in lines for tok in line.split()]
        self.pos = 0
        self.path = path

    def error(self, message: str) -> ValueError:
        where = f"line {self.items[self.pos][0]}" if self.pos < len(self.items) else "end of HIERARCHY"
        return ValueError(f"{self.path}: malformed BVH at {where}: {message}")

    def peek(self) -> str | None:
        return self.items[self.pos][1] if self.pos < len(self.items) else None

    def next(self, what: str) -> str:
        if self.pos >= len(self.items):
            raise self.error(f"expected {what}, the hierarchy ended (truncated file?)")
        tok = self.items[self.pos][1]
        self.pos += 1
        return tok

    def expect(self, word: str) -> None:
        tok = self.next(repr(word))
        if tok != word:
            self.pos -= 1
            raise self.error(f"expected {word!r}, found {tok!r}")

    def floats(self, n: int, what: str) -> list[float]:
        out = []
        for _ in range(n):
            tok = self.next(what)
            try:
                out.append(float(tok))
            except ValueError:
                self.pos -= 1
                raise self.error(f"expected a number for {what}, found {tok!r}") from None
        return out


def _parse_hierarchy(tokens: _Tokens):
    names: list[str] = []
    parents: list[int] = []
    offsets: list[list[float]] = []
    channels: list[tuple[str, ...]] = []
    end_sites: dict[str, np.ndarray] = {}

    def joint(parent: int) -> None:
        name = tokens.next("a joint name")
        if name == "{":
            tokens.pos -= 1
            raise tokens.error("a joint has no name")
        index = len(names)
        names.append(name)
        parents.append(parent)
        tokens.expect("{")
        tokens.expect("OFFSET")
        offsets.append(tokens.floats(3, f"the OFFSET of {name}"))
        chans: tuple[str, ...] = ()
        if tokens.peek() == "CHANNELS":
            tokens.next("CHANNELS")
            count = tokens.next("a channel count")
            if not count.isdigit():
                tokens.pos -= 1
                raise tokens.error(f"expected the channel count of {name}, found {count!r}")
            chans = tuple(tokens.next(f"a channel of {name}") for _ in range(int(count)))
            unknown = [c for c in chans if c not in _ROTATION_AXES and c not in _POSITION_AXES]
            if unknown:
                raise tokens.error(f"unknown channel(s) {unknown} of {name}")
        channels.append(chans)
        while True:
            tok = tokens.next(f"JOINT, End Site or '}}' closing {name}")
            if tok == "}":
                return
            if tok == "JOINT":
                joint(index)
            elif tok == "End":
                tokens.expect("Site")
                tokens.expect("{")
                tokens.expect("OFFSET")
                end_sites[name] = np.array(tokens.floats(3, f"the End Site OFFSET of {name}"))
                tokens.expect("}")
            else:
                tokens.pos -= 1
                raise tokens.error(f"expected JOINT, End Site or '}}' in {name}, found {tok!r}")

    tokens.expect("HIERARCHY")
    while tokens.peek() is not None:
        tokens.expect("ROOT")
        joint(-1)
    if not names:
        raise tokens.error("no ROOT joint")
    return names, parents, np.array(offsets, dtype=np.float64).reshape(-1, 3), channels, end_sites


def _forward_kinematics(parents, offsets, channels, motion):
    """Positions (T, J, 3) and global rotation matrices (T, J, 3, 3) of a parsed BVH.

    Position channels give a joint's translation from its parent in addition to its OFFSET
    (files of `write_bvh` have a zero root OFFSET, where every reading of the convention agrees).
    """
    T = motion.shape[0]
    positions = np.zeros((T, len(parents), 3))
    rotations = np.zeros((T, len(parents), 3, 3))
    column = 0
    for j, (parent, chans) in enumerate(zip(parents, channels)):
        local_t = np.broadcast_to(offsets[j], (T, 3)).copy()
        rot_axes, rot_cols = [], []
        for c in chans:
            if c in _POSITION_AXES:
                local_t[:, _POSITION_AXES[c]] += motion[:, column]
            else:
                rot_axes.append(_ROTATION_AXES[c])
                rot_cols.append(column)
            column += 1
        if rot_axes:
            local_r = euler_to_matrix(np.radians(motion[:, rot_cols]), "".join(rot_axes))
        else:
            local_r = np.broadcast_to(np.eye(3), (T, 3, 3))
        if parent < 0:
            positions[:, j] = local_t
            rotations[:, j] = local_r
        else:
            positions[:, j] = positions[:, parent] + np.einsum("tij,tj->ti", rotations[:, parent], local_t)
            rotations[:, j] = rotations[:, parent] @ local_r
    return positions, rotations


def read_bvh(path) -> BVHMotion:
    """Parse a BVH file and compute its joint positions by forward kinematics.

    Any channel order is accepted (rotations compose in channel order, R = R1 · R2 · R3, angles in
    degrees). A truncated file, a frame line with the wrong number of values, or a `Frames:`
    count that does not match the frame lines raises ValueError naming the file and the line.
    """
    path = Path(path)
    try:
        raw = path.read_text(encoding="utf-8", errors="replace")
    except OSError as err:
        raise ValueError(f"cannot read BVH {path}: {err}") from None
    lines = raw.splitlines()
    motion_at = next((i for i, line in enumerate(lines) if line.strip() == "MOTION"), None)
    if motion_at is None:
        raise ValueError(f"{path}: not a complete BVH file: no MOTION section (truncated file?)")
    tokens = _Tokens([(i + 1, line) for i, line in enumerate(lines[:motion_at])], path)
    names, parents, offsets, channels, end_sites = _parse_hierarchy(tokens)
    num_channels = sum(len(c) for c in channels)

    def header(index: int, key: str) -> str:
        if index >= len(lines):
            raise ValueError(f"{path}: truncated BVH: missing the '{key}' line after MOTION")
        line = lines[index].strip()
        if not line.startswith(key):
            raise ValueError(
                f"{path}: malformed BVH at line {index + 1}: expected '{key} ...', found {line[:60]!r}"
            )
        return line[len(key) :].strip()

    frames_text = header(motion_at + 1, "Frames:")
    time_text = header(motion_at + 2, "Frame Time:")
    try:
        num_frames = int(frames_text)
        frame_time = float(time_text)
    except ValueError:
        raise ValueError(
            f"{path}: malformed BVH: 'Frames: {frames_text}' / 'Frame Time: {time_text}' are not numbers"
        ) from None
    if num_frames < 0 or not (frame_time > 0 and math.isfinite(frame_time)):
        raise ValueError(f"{path}: malformed BVH: Frames: {num_frames}, Frame Time: {frame_time}")

    first = motion_at + 3
    rows = []
    for offset, line in enumerate(lines[first:]):
        if not line.strip():
            continue
        line_no = first + offset + 1
        if len(rows) == num_frames:
            raise ValueError(
                f"{path}: line {line_no}: more frame lines than 'Frames: {num_frames}' declares; "
                "fix the Frames: count or remove the extra lines"
            )
        parts = line.split()
        if len(parts) != num_channels:
            raise ValueError(
                f"{path}: line {line_no} (frame {len(rows)}) has {len(parts)} values, expected "
                f"{num_channels} "
                f"(the channels of {len(names)} joints in the hierarchy); the file is corrupt or truncated"
            )
        try:
            rows.append([float(p) for p in parts])
        except ValueError:
            raise ValueError(f"{path}: line {line_no} (frame {len(rows)}) has a non-numeric value") from None
    if len(rows) != num_frames:
        raise ValueError(
            f"{path}: truncated BVH: 'Frames: {num_frames}' declares {num_frames} frames but only "
            f"{len(rows)} frame lines follow"
        )
    motion = np.array(rows, dtype=np.float64).reshape(num_frames, num_channels)
    positions, rotations = _forward_kinematics(parents, offsets, channels, motion)
    index = {n: i for i, n in enumerate(names)}
    end_positions = (
        np.stack(
            [
                positions[:, index[n]] + np.einsum("tij,j->ti", rotations[:, index[n]], off)
                for n, off in end_sites.items()
            ],
            axis=1,
        )
        if end_sites
        else np.zeros((num_frames, 0, 3))
    )
    fps = 1.0 / frame_time
    if abs(fps - round(fps, 6)) < 1e-6:
        fps = round(fps, 6)
    return BVHMotion(
        path=path,
        names=tuple(names),
        parents=tuple(parents),
        offsets=offsets,
        channels=tuple(channels),
        end_sites=end_sites,
        fps=fps,
        frame_time=frame_time,
        motion=motion,
        joints=positions,
        end_positions=end_positions,
    )


__all__ = [
    "END_SITE_LENGTH",
    "BVHInfo",
    "BVHMotion",
    "bvh_joint_names",
    "euler_to_matrix",
    "features_to_bvh",
    "matrix_to_euler_zxy",
    "read_bvh",
    "write_bvh",
]
