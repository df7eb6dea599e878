"""Fast stick-figure rendering of motions with Pillow: GIF, MP4 (when ffmpeg exists) and PNG sheets.

Conventions (motion-format.md): y is up, the body faces +Z at frame 0 and +X is the body's left.

What a panel shows:
    - a perspective camera at a fixed world direction, in front of the body's start facing (+Z)
      and to its left (+X) by `CAMERA_AZIMUTH_DEG`, looking down by `CAMERA_ELEVATION_DEG`, so one
      sees the face side, left/right and depth. The camera follows the root's x/z (Gaussian-
      smoothed over time) so the figure stays centred, while the floor grid is drawn in world
      coordinates: a moving body scrolls the floor, and sliding feet slide against the grid.
    - the floor (a disc of grid lines around the camera's target), the root's path on the floor
      (the whole path faint, the part walked so far solid), the figure's shadow,
    - the 5 kinematic chains as polylines, farthest first: left limbs in blues, right limbs in
      reds/oranges, the spine in near-black, a head disc with a short stroke towards the face,
    - the caption as a title (word-wrapped to the panel width), a frame counter at the bottom.
      A motion shorter than the longest one holds its last frame, drawn in grey, marked "done".

Frames are drawn directly in palette ("P") mode with one fixed palette, which keeps GIF writing
free of colour quantization (the slow part of GIF encoding) and lets tests count exact colours;
`PALETTE` maps the role names below to their RGB colours.

Inputs: joints (T, J, 3) for J = 22 (HumanML3D) or 21 (KIT-ML), or features (T, 263)/(T, 251)
(de-normalized; converted with `recover_from_ric`), as numpy arrays or torch tensors. KIT-ML
coordinates are millimetres and are scaled to metres (`Skeleton.unit_scale`).
"""

from __future__ import annotations

import functools
import json
import logging
import math
import os
import shutil
import subprocess
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw, ImageFont

from mmm.motion.features import recover_from_ric
from mmm.motion.skeleton import Skeleton, skeleton_for

log = logging.getLogger(__name__)

CAMERA_AZIMUTH_DEG = 35.0  # from +Z towards +X (the body's left at frame 0)
CAMERA_ELEVATION_DEG = 22.0  # looking down
CAMERA_DISTANCE = 4.2  # metres from the look-at point
CAMERA_TARGET_HEIGHT = 0.8  # metres above the floor
VIEW_HEIGHT = 2.5  # metres visible vertically at the look-at distance
FOLLOW_SIGMA_S = 0.4  # Gaussian smoothing of the followed root path, seconds
GRID_SPACING = 0.5  # metres
GRID_RADIUS = 3.0  # metres around the camera's target
NEAR = 0.3  # metres: nearer points are clipped / clamped
# A GIF is assembled in memory (Pillow keeps every frame), about 0.22 MB per 320-pixel panel and
# frame: render_files draws at most this many panel frames (5 minutes of one motion at 20 fps).
MAX_PANEL_FRAMES = 6000

# Palette roles (index = position). Index 0 is the background.
_ROLES: tuple[tuple[str, tuple[int, int, int]], ...] = (
    ("background", (250, 250, 252)),
    ("floor", (232, 234, 240)),
    ("grid", (186, 190, 204)),
    ("path_faint", (196, 208, 236)),
    ("path", (82, 104, 168)),
    ("shadow", (208, 210, 218)),
    ("left_leg", (22, 82, 204)),
    ("left_arm", (66, 150, 250)),
    ("right_leg", (206, 34, 34)),
    ("right_arm", (250, 128, 40)),
    ("spine", (40, 40, 48)),
    ("head", (255, 222, 170)),
    ("text", (24, 24, 30)),
    ("muted_text", (120, 120, 130)),
    ("done_limb", (150, 150, 158)),
    ("done_spine", (118, 118, 126)),
    ("done_head", (214, 214, 220)),
    ("done_mark", (190, 40, 40)),
    ("separator", (160, 160, 170)),
    ("start", (60, 160, 80)),
)
_TEXT_ROLES = ("text", "muted_text", "done_mark")
_TEXT_LEVELS = 4  # anti-aliased text: blends of the background and the text colour
_ROLES = _ROLES + tuple(
    (
        f"{role}_{k}",
        tuple(round(b + (c - b) * k / _TEXT_LEVELS) for b, c in zip(_ROLES[0][1], dict(_ROLES)[role])),
    )
    for role in _TEXT_ROLES
    for k in range(1, _TEXT_LEVELS)
)
COLOR = {name: i for i, (name, _) in enumerate(_ROLES)}
PALETTE: dict[str, tuple[int, int, int]] = dict(_ROLES)
_PALETTE_BYTES = [c for _, rgb in _ROLES for c in rgb] + [0, 0, 0] * (256 - len(_ROLES))

_JOINT_SHAPES = (
    "(T, 22, 3) joints or (T, 263) features (HumanML3D), or (T, 21, 3) joints or (T, 251) features (KIT-ML)"
)


# ----------------------------------------------------------------------------------------------
# Inputs
# ----------------------------------------------------------------------------------------------


def _to_numpy(x) -> np.ndarray:
    try:
        import torch  # optional here: rendering works without it
    except ImportError:  # pragma: no cover - torch is a dependency
        torch = None
    if torch is not None and isinstance(x, torch.Tensor):
        return x.detach().to("cpu", torch.float64).numpy()
    return np.asarray(x)


def as_joints(motion, name: str = "motion") -> tuple[np.ndarray, Skeleton]:
    """Joints (T, J, 3) float64 in metres and the skeleton of one motion (joints or features).

    Raises ValueError naming `name`, the offending value and the expected shapes.
    """
    try:
        arr = _to_numpy(motion)
    except Exception as e:  # e.g. ragged lists
        raise ValueError(f"{name}: cannot be read as an array ({e}); expected {_JOINT_SHAPES}") from e
    if arr.dtype == object or not (
        np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)
    ):
        raise ValueError(f"{name}: has dtype {arr.dtype}, not numbers; expected {_JOINT_SHAPES}")
    shape = tuple(arr.shape)
    if arr.ndim == 3 and shape[2] == 3 and shape[1] in (22, 21):
        kind = "joints"
    elif arr.ndim == 2 and shape[1] in (263, 251):
        kind = "features"
    else:
        raise ValueError(f"{name}: got shape {shape}; expected {_JOINT_SHAPES}")
    if shape[0] == 0:
        raise ValueError(
            f"{name}: empty motion, shape {shape} has 0 frames; expected {_JOINT_SHAPES} with T >= 1"
        )
    arr = arr.astype(np.float64, copy=False)
    finite = np.isfinite(arr)
    if not finite.all():
        bad = ~finite.reshape(shape[0], -1).all(axis=1)
        frames = np.flatnonzero(bad)
        raise ValueError(
            f"{name}: {int((~finite).sum())} NaN/Inf values in {kind} of shape {shape} "
            f"(frames {frames[:5].tolist()}{'...' if len(frames) > 5 else ''}); "
            "render only finite motions (check the model output / de-normalization)"
        )
    skeleton = skeleton_for(shape[1])
    joints = recover_from_ric(arr) if kind == "features" else arr
    joints = np.asarray(joints, dtype=np.float64) * skeleton.unit_scale
    if not np.isfinite(joints).all():
        raise ValueError(
            f"{name}: features of shape {shape} give NaN/Inf joint positions (overflow in "
            "recover_from_ric); render only finite, de-normalized features"
        )
    return joints, skeleton


def _split_motions(motions) -> list:
    """A list of single motions from a list/tuple, one motion, or a batch array/tensor."""
    if isinstance(motions, (list, tuple)):
        if len(motions) == 0:
            raise ValueError("no motions given: expected one motion or a list of motions")
        return list(motions)
    shape = tuple(getattr(motions, "shape", ()))
    if len(shape) == 4 and shape[-1] == 3:  # (B, T, J, 3)
        return [motions[i] for i in range(shape[0])]
    if len(shape) == 3 and shape[-1] != 3:  # (B, T, D)
        return [motions[i] for i in range(shape[0])]
    return [motions]


def _split_captions(captions, n: int) -> list[str]:
    if captions is None:
        return [""] * n
    if isinstance(captions, str):
        captions = [captions]
    captions = ["" if c is None else str(c) for c in captions]
    if len(captions) != n:
        raise ValueError(
            f"got {len(captions)} captions for {n} motions; pass one caption per motion (or None)"
        )
    return captions


# ----------------------------------------------------------------------------------------------
# Camera
# ----------------------------------------------------------------------------------------------


def _smooth_path(xz: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian smoothing over time (T, 2); odd reflection at the ends keeps straight paths exact."""
    T = len(xz)
    if sigma <= 0 or T < 2:
        return xz.copy()
    radius = int(math.ceil(3 * sigma))
    t = np.arange(-radius, radius + 1)
    kernel = np.exp(-0.5 * (t / sigma) ** 2)
    kernel /= kernel.sum()
    padded = np.pad(xz, ((radius, radius), (0, 0)), mode="reflect", reflect_type="odd")
    out = np.empty_like(xz)
    for c in range(xz.shape[1]):
        out[:, c] = np.convolve(padded[:, c], kernel, mode="valid")
    return out


@dataclass
class _Camera:
    """A camera per frame: positions (T, 3), one fixed orientation, pinhole intrinsics."""

    eye: np.ndarray  # (T, 3)
    rot: np.ndarray  # (3, 3): rows right, up, forward
    focal: float
    cx: float
    cy: float

    def to_camera(self, points: np.ndarray, t: np.ndarray | int | None = None) -> np.ndarray:
        """Camera coordinates (..., 3) of world points (..., 3); `t` picks the frame(s) of eye."""
        eye = self.eye if t is None else self.eye[t]
        if t is None:
            rel = points - eye.reshape(eye.shape[:1] + (1,) * (points.ndim - 2) + (3,))
        else:
            rel = points - eye
        return rel @ self.rot.T

    def to_pixels(self, cam: np.ndarray) -> np.ndarray:
        """Pixels (..., 2) of camera-space points (..., 3); depths clamped at NEAR."""
        z = np.maximum(cam[..., 2], NEAR)
        return np.stack(
            (self.cx + self.focal * cam[..., 0] / z, self.cy - self.focal * cam[..., 1] / z), axis=-1
        )


def _make_camera(joints: np.ndarray, fps: float, width: int, height: int, top: int) -> _Camera:
    az, el = math.radians(CAMERA_AZIMUTH_DEG), math.radians(CAMERA_ELEVATION_DEG)
    back = np.array([math.sin(az) * math.cos(el), math.sin(el), math.cos(az) * math.cos(el)])
    forward = -back
    right = np.cross(forward, [0.0, 1.0, 0.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    target = np.zeros((len(joints), 3))
    target[:, [0, 2]] = _smooth_path(joints[:, 0, [0, 2]], FOLLOW_SIGMA_S * fps)
    target[:, 1] = CAMERA_TARGET_HEIGHT
    eye = target + CAMERA_DISTANCE * back
    view_h = height - top
    focal = min(view_h, width) * CAMERA_DISTANCE / VIEW_HEIGHT
    return _Camera(
        eye=eye, rot=np.stack((right, up, forward)), focal=focal, cx=width / 2.0, cy=top + view_h * 0.5
    )


# ----------------------------------------------------------------------------------------------
# Drawing
# ----------------------------------------------------------------------------------------------


@functools.lru_cache(maxsize=32)
def _font(size: int) -> ImageFont.ImageFont | ImageFont.FreeTypeFont:
    try:
        return ImageFont.load_default(size)
    except Exception:  # no FreeType: the fixed bitmap font
        return ImageFont.load_default()


def _fitting_prefix(text: str, font, width: float) -> int:
    """How many leading characters of `text` fit in `width` pixels (at least 1; all when the whole
    text fits). A galloping search: prefixes of 1, 2, 4, ... characters until one is too wide,
    then bisection, so no prefix longer than twice the answer is ever measured and a
    20,000-character word costs about as much as a short one."""
    fits, too_wide = 0, None
    n = 1
    while n < len(text):
        if font.getlength(text[:n]) > width:
            too_wide = n
            break
        fits, n = n, n * 2
    if too_wide is None:
        if font.getlength(text) <= width:
            return len(text)
        too_wide = len(text)
    while too_wide - fits > 1:
        middle = (fits + too_wide) // 2
        if font.getlength(text[:middle]) <= width:
            fits = middle
        else:
            too_wide = middle
    return max(fits, 1)


def _wrap(text: str, font, width: float, max_lines: int) -> list[str]:
    """Greedy word wrap to `width` pixels, a word wider than that broken by characters; at most
    `max_lines` lines, the last ending with an ellipsis when the text is cut. Wrapping stops once
    a line past `max_lines` is known to exist, so the text's length beyond what is shown costs
    nothing."""
    lines: list[str] = []
    line = ""
    for word in text.split():
        if len(lines) > max_lines:
            break
        trial = f"{line} {word}" if line else word
        if font.getlength(trial) <= width:
            line = trial
            continue
        if line:
            lines.append(line)
        line = word
        while len(lines) <= max_lines:  # a word too wide for a line of its own: cut by characters
            cut = _fitting_prefix(line, font, width)
            if cut >= len(line):
                break
            lines.append(line[:cut])
            line = line[cut:]
    if line and len(lines) <= max_lines:
        lines.append(line)
    if len(lines) > max_lines:
        last = lines[max_lines - 1]
        while last and font.getlength(last + "…") > width:
            last = last[:-1]
        lines = lines[: max_lines - 1] + [last.rstrip() + "…"]
    return lines


@dataclass
class _Style:
    width: int
    height: int
    font: object
    small_font: object
    line_h: int
    limb_w: int
    path_w: int
    head_r: float  # metres

    @classmethod
    def for_size(cls, width: int, height: int) -> _Style:
        s = min(width, height)
        fsize = max(9, round(s / 24))
        font = _font(fsize)
        small = _font(max(8, round(s / 28)))
        return cls(
            width,
            height,
            font,
            small,
            line_h=fsize + 3,
            limb_w=max(2, round(s / 100)),
            path_w=max(1, round(s / 200)),
            head_r=0.11,
        )


def _header_lines(
    captions: list[str], style: _Style, width: int | None = None, max_lines: int = 3
) -> list[list[str]]:
    w = (width or style.width) - 8
    return [_wrap(c, style.font, w, max_lines) if c.strip() else [] for c in captions]


_TEXT_LUT = {
    role: np.array(
        [COLOR["background"]] + [COLOR[f"{role}_{k}"] for k in range(1, _TEXT_LEVELS)] + [COLOR[role]],
        dtype=np.uint8,
    )
    for role in _TEXT_ROLES
}


@functools.lru_cache(maxsize=2048)
def _text_patch(text: str, font, role: str) -> tuple[Image.Image, Image.Image]:
    """Anti-aliased text as a palette image and its binary mask (drawn in "L", mapped to blends).

    Palette-mode drawing would render glyphs unhinted-but-aliased and wider than `getlength`.
    """
    ascent, descent = font.getmetrics()
    w, h = int(math.ceil(font.getlength(text))) + 2, ascent + descent + 1
    grey = Image.new("L", (max(w, 1), h), 0)
    ImageDraw.Draw(grey).text((0, 0), text, fill=255, font=font)
    level = (np.asarray(grey).astype(np.int32) * _TEXT_LEVELS + 127) // 255
    patch = Image.fromarray(_TEXT_LUT[role][level], "P")  # pasted as indices: no palette needed
    return patch, Image.fromarray(level > 0)


def _draw_text(image: Image.Image, xy: tuple[float, float], text: str, font, role: str) -> float:
    """Paste anti-aliased text at xy (top-left); returns its width in pixels."""
    patch, mask = _text_patch(text, font, role)
    image.paste(patch, (int(round(xy[0])), int(round(xy[1]))), mask)
    return font.getlength(text)


def _draw_header(
    image: Image.Image, lines: list[str], style: _Style, x0: int = 0, width: int | None = None
) -> None:
    width = width or style.width
    y = 3
    for line in lines:
        tw = style.font.getlength(line)
        _draw_text(image, (x0 + (width - tw) / 2, y), line, style.font, "text")
        y += style.line_h


def _header_height(lines: list[list[str]], style: _Style) -> int:
    n = max((len(lc) for lc in lines), default=0)
    return n * style.line_h + 6 if n else 0


def _polyline_segments(cam_pts: np.ndarray) -> list[np.ndarray]:
    """Split a camera-space polyline (N, 3) into runs in front of the near plane, clipped there."""
    if len(cam_pts) < 2:
        return []
    z = cam_pts[:, 2]
    front = z >= NEAR
    if front.all():
        return [cam_pts]
    runs: list[np.ndarray] = []
    current: list[np.ndarray] = []
    for i in range(len(cam_pts) - 1):
        a, b = cam_pts[i], cam_pts[i + 1]
        fa, fb = front[i], front[i + 1]
        if not fa and not fb:
            if len(current) >= 2:
                runs.append(np.array(current))
            current = []
            continue
        if fa and fb:
            if not current:
                current = [a]
            current.append(b)
            continue
        s = (NEAR - a[2]) / (b[2] - a[2])
        cut = a + s * (b - a)
        if fa:  # leaving the visible side
            if not current:
                current = [a]
            current.append(cut)
            runs.append(np.array(current))
            current = []
        else:  # entering
            current = [cut, b]
    if len(current) >= 2:
        runs.append(np.array(current))
    return runs


def _flat(pix: np.ndarray) -> list[float]:
    return pix.ravel().tolist()


def _clip_segments(a: np.ndarray, b: np.ndarray, lo: np.ndarray, hi: np.ndarray):
    """Liang-Barsky: the parts of segments a->b (N, 2) inside the box [lo, hi]; (a', b', kept)."""
    d = b - a
    t0 = np.zeros(len(a))
    t1 = np.ones(len(a))
    keep = np.ones(len(a), dtype=bool)
    for p, q in ((-d, a - lo), (d, hi - a)):
        for k in range(2):
            pk, qk = p[:, k], q[:, k]
            parallel = pk == 0
            keep &= ~(parallel & (qk < 0))
            with np.errstate(divide="ignore", invalid="ignore"):
                r = np.where(parallel, 0.0, qk / np.where(parallel, 1.0, pk))
            t0 = np.where(~parallel & (pk < 0), np.maximum(t0, r), t0)
            t1 = np.where(~parallel & (pk > 0), np.minimum(t1, r), t1)
    keep &= t0 <= t1
    return a + t0[:, None] * d, a + t1[:, None] * d, keep


def _polyline(
    draw: ImageDraw.ImageDraw, pix: np.ndarray, fill: int, width: int, joint: str | None = None
) -> None:
    """Draw a pixel polyline (N, 2); points far outside the image (wild motions) are clipped."""
    w, h = draw.im.size
    margin = 2.0 * max(w, h)
    lo, hi = np.array([-margin, -margin]), np.array([w + margin, h + margin])
    if ((pix >= lo) & (pix <= hi)).all():
        draw.line(_flat(pix), fill=fill, width=width, joint=joint)
        return
    a, b, keep = _clip_segments(pix[:-1], pix[1:], lo, hi)
    for p, q in zip(a[keep].tolist(), b[keep].tolist()):
        draw.line((*p, *q), fill=fill, width=width)


class _Panel:
    """Everything precomputed for drawing one motion: camera, projected joints, path, chains."""

    def __init__(
        self,
        joints: np.ndarray,
        skeleton: Skeleton,
        fps: float,
        style: _Style,
        top: int,
        spans: Sequence[tuple[int, int, str]] | None = None,
    ):
        self.spans = list(spans or [])  # (first frame, end frame, label) written beside the counter
        with np.errstate(all="ignore"):  # wild (e.g. untrained) motions overflow harmlessly
            self._setup(joints, skeleton, fps, style, top)

    def _setup(self, joints: np.ndarray, skeleton: Skeleton, fps: float, style: _Style, top: int) -> None:
        self.joints = joints
        self.skeleton = skeleton
        self.T = len(joints)
        self.fps = fps
        self.style = style
        self.camera = cam = _make_camera(joints, fps, style.width, style.height, top)
        self.cam_joints = cam.to_camera(joints)  # (T, J, 3)
        self.pix = cam.to_pixels(self.cam_joints)  # (T, J, 2)
        shadow = joints.copy()
        shadow[..., 1] = 0.0
        self.shadow_pix = cam.to_pixels(cam.to_camera(shadow))
        self.root_floor = np.stack((joints[:, 0, 0], np.zeros(self.T), joints[:, 0, 2]), axis=-1)  # (T, 3)

        names = skeleton.joint_names
        self.chains: list[tuple[list[int], str]] = []
        for chain in skeleton.kinematic_chains:
            end = names[chain[-1]]
            limb = "arm" if any(k in end for k in ("wrist", "hand", "elbow")) else "leg"
            if end.startswith("left"):
                role = f"left_{limb}"
            elif end.startswith("right"):
                role = f"right_{limb}"
            else:
                role = "spine"
            self.chains.append((list(chain), role))
        spine = next((c for c, r in self.chains if r == "spine"), self.chains[0][0])
        self.head = spine[-1]
        # Facing (for the face stroke): up × across, across = (R_hip - L_hip) + (R_sh - L_sh).
        r_hip, l_hip, r_sh, l_sh = skeleton.face_joints
        across = joints[:, r_hip] - joints[:, l_hip] + joints[:, r_sh] - joints[:, l_sh]
        across[:, 1] = 0.0
        forward = np.cross([0.0, 1.0, 0.0], across)
        forward /= np.maximum(np.linalg.norm(forward, axis=-1, keepdims=True), 1e-9)
        head = joints[:, self.head]
        self.head_center = head + np.array([0.0, 0.04, 0.0])
        nose = self.head_center + forward * (style.head_r + 0.06)
        self.head_cam = cam.to_camera(self.head_center)
        self.head_pix = cam.to_pixels(self.head_cam)
        self.nose_pix = cam.to_pixels(cam.to_camera(nose))
        nose_off = np.linalg.norm(self.nose_pix - self.head_pix, axis=-1) > style.width  # wild poses
        self.nose_pix[nose_off] = self.head_pix[nose_off]

    # -- layers ---------------------------------------------------------------------------------

    def draw_floor(self, draw: ImageDraw.ImageDraw, t: int) -> None:
        cam = self.camera
        center = cam.eye[t] + CAMERA_DISTANCE * cam.rot[2]  # the followed look-at point
        cx, cz = center[0], center[2]
        R = GRID_RADIUS
        angles = np.linspace(0.0, 2 * np.pi, 64, endpoint=False)
        disc = np.stack((cx + R * np.cos(angles), np.zeros_like(angles), cz + R * np.sin(angles)), axis=-1)
        disc_cam = cam.to_camera(disc, t)
        if (disc_cam[:, 2] >= NEAR).all():
            draw.polygon(_flat(cam.to_pixels(disc_cam)), fill=COLOR["floor"])
        # Grid lines x = k·s and z = k·s inside the disc.
        ends = []
        k0, k1 = math.ceil((cx - R) / GRID_SPACING), math.floor((cx + R) / GRID_SPACING)
        for k in range(k0, k1 + 1):
            x = k * GRID_SPACING
            h = math.sqrt(max(R * R - (x - cx) ** 2, 0.0))
            if h > 1e-6:
                ends.append(((x, 0.0, cz - h), (x, 0.0, cz + h)))
        k0, k1 = math.ceil((cz - R) / GRID_SPACING), math.floor((cz + R) / GRID_SPACING)
        for k in range(k0, k1 + 1):
            z = k * GRID_SPACING
            h = math.sqrt(max(R * R - (z - cz) ** 2, 0.0))
            if h > 1e-6:
                ends.append(((cx - h, 0.0, z), (cx + h, 0.0, z)))
        if not ends:
            return
        seg_cam = cam.to_camera(np.array(ends), t)  # (L, 2, 3)
        if (seg_cam[..., 2] >= NEAR).all():  # always, with the default camera and radius
            for seg in cam.to_pixels(seg_cam).reshape(-1, 4).tolist():
                draw.line(seg, fill=COLOR["grid"], width=1)
            return
        for seg in seg_cam:
            for run in _polyline_segments(seg):
                _polyline(draw, cam.to_pixels(run), COLOR["grid"], 1)

    def draw_path(self, draw: ImageDraw.ImageDraw, t: int) -> None:
        if self.T < 2:
            return
        cam = self.camera
        path_cam = cam.to_camera(self.root_floor, t)
        for run in _polyline_segments(path_cam):
            _polyline(draw, cam.to_pixels(run), COLOR["path_faint"], self.style.path_w)
        if t >= 1:
            for run in _polyline_segments(path_cam[: t + 1]):
                _polyline(draw, cam.to_pixels(run), COLOR["path"], self.style.path_w + 1)
        start = cam.to_pixels(path_cam[0])
        if path_cam[0, 2] >= NEAR and np.abs(start).max() < 4 * max(self.style.width, self.style.height):
            r = self.style.path_w + 1.5
            draw.ellipse((start[0] - r, start[1] - r, start[0] + r, start[1] + r), fill=COLOR["start"])

    def draw_figure(self, draw: ImageDraw.ImageDraw, t: int, done: bool) -> None:
        style = self.style
        shadow = self.shadow_pix[t]
        for chain, _ in self.chains:
            _polyline(draw, shadow[chain], COLOR["shadow"], style.limb_w, "curve")
        pix = self.pix[t]
        depth = self.cam_joints[t, :, 2]
        items = []  # (depth, kind, data)
        for chain, role in self.chains:
            items.append((float(depth[chain].mean()), 0, chain, role))
        head_depth = float(self.head_cam[t, 2])
        items.append((head_depth, 1, None, "head"))
        items.sort(key=lambda it: -it[0])  # farthest first
        for _, kind, chain, role in items:
            if kind == 0:
                if done:
                    fill = COLOR["done_spine"] if role == "spine" else COLOR["done_limb"]
                else:
                    fill = COLOR[role]
                _polyline(draw, pix[chain], fill, style.limb_w, "curve")
            else:
                hx, hy = self.head_pix[t]
                if not (-style.width <= hx <= 2 * style.width and -style.height <= hy <= 2 * style.height):
                    continue
                r = style.head_r * self.camera.focal / max(head_depth, NEAR)
                outline = COLOR["done_spine"] if done else COLOR["spine"]
                draw.ellipse(
                    (hx - r, hy - r, hx + r, hy + r),
                    fill=COLOR["done_head" if done else "head"],
                    outline=outline,
                    width=max(1, style.limb_w - 1),
                )
                nx, ny = self.nose_pix[t]
                draw.line((hx, hy, nx, ny), fill=outline, width=max(1, style.limb_w - 1))

    def draw_counter(self, image: Image.Image, t: int, done: bool) -> None:
        style = self.style
        y = style.height - style.line_h - 2
        text = f"{t + 1}/{self.T}  {t / self.fps:.2f}s"
        x = 4 + _draw_text(image, (4, y), text, style.small_font, "muted_text")
        if done:
            _draw_text(image, (x + 6, y), "done", style.small_font, "done_mark")
        elif self.spans:  # which part of a long motion this frame belongs to
            label = next((label for a, b, label in self.spans if a <= t < b), "transition")
            font, room = style.small_font, style.width - x - 10
            if _fitting_prefix(label, font, room) < len(label):
                label = label[: _fitting_prefix(label, font, room - font.getlength("…"))] + "…"
            _draw_text(image, (x + 6, y), label, font, "text")

    def render(self, t: int, header: Image.Image | None) -> Image.Image:
        """The panel at motion frame t (clamped to the last frame: 'done')."""
        done = t >= self.T
        t = min(t, self.T - 1)
        im = Image.new("P", (self.style.width, self.style.height), COLOR["background"])
        im.putpalette(_PALETTE_BYTES)
        draw = ImageDraw.Draw(im)
        self.draw_floor(draw, t)
        self.draw_path(draw, t)
        self.draw_figure(draw, t, done)
        if header is not None:
            im.paste(header, (0, 0))
        self.draw_counter(im, t, done)
        return im


def _new_image(width: int, height: int) -> Image.Image:
    im = Image.new("P", (width, height), COLOR["background"])
    im.putpalette(_PALETTE_BYTES)
    return im


def _prepare(motions, captions, size, names: list[str] | None = None):
    motions = _split_motions(motions)
    captions = _split_captions(captions, len(motions))
    width, height = int(size[0]), int(size[1])
    if width < 32 or height < 32:
        raise ValueError(f"panel size {tuple(size)} is too small: expected at least (32, 32) pixels")
    loaded = [as_joints(m, names[i] if names else f"motion {i}") for i, m in enumerate(motions)]
    return loaded, captions, width, height


# ----------------------------------------------------------------------------------------------
# Public API
# ----------------------------------------------------------------------------------------------


def frames(
    motions,
    captions=None,
    size=(320, 320),
    *,
    columns: int | None = None,
    spans: Sequence[Sequence[tuple[int, int, str]] | None] | None = None,
    _names: list[str] | None = None,
) -> list[Image.Image]:
    """One image per frame of the longest motion, the motions side by side (each `size` wide), or
    in rows of `columns` panels (e.g. references above their reconstructions). spans: per motion,
    (first frame, end frame, label) parts whose label is written beside the frame counter while
    they play ("transition" between them), e.g. the prompts of a long motion.

    Returns palette ("P") images sharing `PALETTE`; `.convert("RGB")` for RGB. A motion shorter
    than the longest holds its last frame, greyed and marked "done".
    """
    loaded, captions, width, height = _prepare(motions, captions, size, _names)
    style = _Style.for_size(width, height)
    lines = _header_lines(captions, style)
    top = _header_height(lines, style)
    panels = []
    headers = []
    for i, ((joints, skeleton), cap_lines) in enumerate(zip(loaded, lines)):
        panels.append(_Panel(joints, skeleton, skeleton.fps, style, top, spans[i] if spans else None))
        if top:
            header = _new_image(width, top)
            _draw_header(header, cap_lines, style)
            headers.append(header)
        else:
            headers.append(None)
    T = max(p.T for p in panels)
    n = len(panels)
    cols = max(1, min(columns or n, n))
    rows = (n + cols - 1) // cols
    out = []
    for t in range(T):
        frame = _new_image(width * cols, height * rows)
        for i, (panel, header) in enumerate(zip(panels, headers)):
            frame.paste(panel.render(t, header), ((i % cols) * width, (i // cols) * height))
        if n > 1:
            draw = ImageDraw.Draw(frame)
            for i in range(1, cols):
                draw.line((i * width, 0, i * width, height * rows), fill=COLOR["separator"], width=1)
            for r in range(1, rows):
                draw.line((0, r * height, width * cols, r * height), fill=COLOR["separator"], width=1)
        out.append(frame)
    return out


def _temp_path(out_path: Path) -> Path:
    fd, name = tempfile.mkstemp(prefix=f".{out_path.name}.", suffix=".tmp", dir=out_path.parent)
    os.close(fd)
    return Path(name)


def _write_atomic(out_path, write) -> Path:
    out_path = Path(out_path)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    tmp = _temp_path(out_path)
    try:
        write(tmp)
        os.chmod(tmp, 0o644)  # mkstemp creates 0600; the real file gets the usual permissions
        os.replace(tmp, out_path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return out_path


def _save_gif(images: list[Image.Image], out_path, fps: float) -> Path:
    if fps <= 0:
        raise ValueError(f"fps must be positive, got {fps}")
    duration = max(10, int(round(1000.0 / fps / 10.0)) * 10)  # GIF stores centiseconds

    def write(tmp: Path) -> None:
        images[0].save(
            tmp,
            format="GIF",
            save_all=True,
            append_images=images[1:],
            duration=duration,
            loop=0,
            optimize=False,
            disposal=1,
        )

    return _write_atomic(out_path, write)


def render_gif(
    motions,
    out_path,
    captions=None,
    fps: float = 20.0,
    size=(320, 320),
    columns: int | None = None,
    spans=None,
) -> Path:
    """Write an animated GIF (looping forever, one frame per motion frame) of the motions side by
    side, or in rows of `columns`; `spans` as in `frames`."""
    return _save_gif(frames(motions, captions, size, columns=columns, spans=spans), out_path, fps)


_ffmpeg_missing_logged = False


def _find_ffmpeg() -> str | None:
    """An ffmpeg executable: imageio_ffmpeg's (never downloads) or `ffmpeg` on PATH, else None."""
    try:
        import imageio_ffmpeg  # optional dependency (the mp4 extra)
    except ImportError:
        imageio_ffmpeg = None
    if imageio_ffmpeg is not None:
        try:
            exe = imageio_ffmpeg.get_ffmpeg_exe()
            if exe and Path(exe).exists():
                return str(exe)
        except Exception:  # no bundled binary and none configured
            pass
    return shutil.which("ffmpeg")


def _save_mp4(images: list[Image.Image], out_path, fps: float, exe: str) -> Path:
    if fps <= 0:
        raise ValueError(f"fps must be positive, got {fps}")
    width, height = images[0].size

    def write(tmp: Path) -> None:
        cmd = [
            exe,
            "-y",
            "-loglevel",
            "error",
            "-f",
            "rawvideo",
            "-pix_fmt",
            "rgb24",
            "-s",
            f"{width}x{height}",
            "-r",
            f"{fps:g}",
            "-i",
            "-",
            "-an",
            "-vf",
            "pad=ceil(iw/2)*2:ceil(ih/2)*2",
            "-c:v",
            "libx264",
            "-preset",
            "veryfast",
            "-crf",
            "23",
            "-pix_fmt",
            "yuv420p",
            "-movflags",
            "+faststart",
            "-f",
            "mp4",
            str(tmp),
        ]
        with tempfile.TemporaryFile() as err:
            proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.DEVNULL, stderr=err)
            try:
                for im in images:
                    proc.stdin.write(im.convert("RGB").tobytes())
                proc.stdin.close()
            except BrokenPipeError:
                pass
            rc = proc.wait()
            if rc != 0:
                err.seek(0)
                msg = err.read().decode(errors="replace").strip()
                raise RuntimeError(
                    f"ffmpeg ({exe}) failed with exit code {rc} writing {out_path}: {msg[-2000:]}"
                )

    return _write_atomic(out_path, write)


def render_mp4(motions, out_path, captions=None, fps: float = 20.0, size=(320, 320)) -> Path | None:
    """Write an H.264 (yuv420p) MP4 of the motions side by side, or return None without an encoder.

    The encoder is `imageio_ffmpeg.get_ffmpeg_exe()` when that package is installed (the `mp4`
    extra), else `ffmpeg` on PATH; nothing is ever downloaded.
    """
    global _ffmpeg_missing_logged
    exe = _find_ffmpeg()
    if exe is None:
        if not _ffmpeg_missing_logged:
            log.info(
                "no MP4 encoder (pip install imageio-ffmpeg, or put ffmpeg on PATH): skipping MP4 output"
            )
            _ffmpeg_missing_logged = True
        return None
    return _save_mp4(frames(motions, captions, size), out_path, fps, exe)


def _sheet(loaded, captions, num_frames: int, size) -> Image.Image:
    width, height = int(size[0]), int(size[1])
    style = _Style.for_size(width, height)
    row_w = width * num_frames
    lines = _header_lines(captions, style, width=row_w, max_lines=2)
    top = _header_height(lines, style)
    sheet = _new_image(row_w, height * len(loaded))
    draw = ImageDraw.Draw(sheet)
    for r, ((joints, skeleton), cap_lines) in enumerate(zip(loaded, lines)):
        panel = _Panel(joints, skeleton, skeleton.fps, style, top)
        idx = np.round(np.linspace(0, panel.T - 1, num_frames)).astype(int)
        for c, t in enumerate(idx):
            sheet.paste(panel.render(int(t), None), (c * width, r * height))
        if top:
            header = _new_image(row_w, top)
            _draw_header(header, cap_lines, style, width=row_w)
            sheet.paste(header, (0, r * height))
        for c in range(1, num_frames):
            draw.line(
                (c * width, r * height + top, c * width, (r + 1) * height), fill=COLOR["separator"], width=1
            )
        if r:
            draw.line((0, r * height, row_w, r * height), fill=COLOR["separator"], width=1)
    return sheet


def contact_sheet(motions, captions=None, num_frames: int = 6, size=(240, 240)) -> Image.Image:
    """The `render_frames` sheet as an RGB image (one row per motion, evenly spaced frames)."""
    if int(num_frames) < 1:
        raise ValueError(f"num_frames must be >= 1, got {num_frames}")
    loaded, captions, _, _ = _prepare(motions, captions, size)
    return _sheet(loaded, captions, int(num_frames), size).convert("RGB")


def render_frames(motions, out_png, captions=None, num_frames: int = 6, size=(240, 240)) -> Path:
    """Write a PNG contact sheet: one row per motion, `num_frames` evenly spaced frames per row.

    The sheet is (num_frames · size[0]) × (motions · size[1]) pixels; each row's caption is
    drawn across the top of the row.
    """
    sheet = contact_sheet(motions, captions, num_frames, size)
    return _write_atomic(out_png, lambda tmp: sheet.save(tmp, format="PNG"))


def load_motion_file(path) -> np.ndarray:
    """Load a motion `.npy` (joints or features), raising ValueError that names the file."""
    p = Path(path)
    if not p.exists():
        raise ValueError(f"{p}: file not found; expected a .npy file holding {_JOINT_SHAPES}")
    if p.is_dir():
        raise ValueError(f"{p}: is a directory; expected a .npy file holding {_JOINT_SHAPES}")
    try:
        arr = np.load(p, allow_pickle=False)
    except Exception as e:
        raise ValueError(
            f"{p}: cannot be loaded as .npy ({type(e).__name__}: {e}); "
            f"expected a .npy file holding {_JOINT_SHAPES}"
        ) from e
    if not isinstance(arr, np.ndarray):  # .npz archives
        raise ValueError(
            f"{p}: is an archive with arrays {list(arr.keys())}, not a single array; "
            f"expected a .npy file holding {_JOINT_SHAPES}"
        )
    if arr.dtype.kind not in "iuf":  # strings, bytes or true/false are no motion
        raise ValueError(
            f"{p}: holds {arr.dtype} values, not motion numbers; expected a .npy file holding {_JOINT_SHAPES}"
        )
    return arr


class EncoderNotFound(ValueError):
    """An MP4 was asked for but no ffmpeg executable is installed."""


def default_captions(paths: Sequence[Path]) -> list[str]:
    """A caption per motion file when none are given: the `caption` of a `meta.json` beside it
    (what `mmm generate`, `edit` and `generate-long` captioned the sample with), else the file
    name without `.npy`, with its folder when names repeat (`0/joints`, `1/joints`)."""
    stems = [p.stem for p in paths]
    captions = []
    for path, stem in zip(paths, stems):
        meta = path.parent / "meta.json"
        caption = None
        if meta.is_file():
            try:
                caption = json.loads(meta.read_text()).get("caption")
            except (ValueError, OSError, AttributeError) as e:  # someone else's meta.json: only a caption
                log.debug("%s: no caption read (%s)", meta, e)
        if not isinstance(caption, str) or not caption.strip():
            caption = f"{path.parent.name}/{stem}" if stems.count(stem) > 1 and path.parent.name else stem
        captions.append(caption)
    return captions


def render_files(
    paths: Sequence[str | Path], out_path, captions=None, fps: float | None = None
) -> list[Path]:
    """Render `.npy` motion files side by side to `out_path`; returns the written paths.

    The output type follows the suffix: `.gif`, `.mp4` (raises `EncoderNotFound`, a ValueError,
    when no encoder is installed) or `.png` (a `render_frames` contact sheet). Captions default to
    `default_captions`; fps to the first motion's skeleton fps. Bad input raises ValueError naming the
    file, the offending value and the expected shapes.
    """
    if isinstance(paths, (str, Path)):
        paths = [paths]
    paths = [Path(p) for p in paths]
    if not paths:
        raise ValueError("no motion files given: expected one or more .npy paths")
    out_path = Path(out_path)
    suffix = out_path.suffix.lower()
    if suffix not in (".gif", ".mp4", ".png"):
        raise ValueError(
            f"{out_path}: unknown output type {suffix or '(no suffix)'!r}; "
            "expected a path ending in .gif, .mp4 or .png"
        )
    if out_path.is_dir():
        raise ValueError(f"{out_path} is a folder: name the file to write, e.g. {out_path / 'motion.gif'}")
    blocking = next((p for p in out_path.parents if p.exists() and not p.is_dir()), None)
    if blocking is not None:
        raise ValueError(f"cannot write {out_path}: {blocking} is a file, not a folder; choose another path")
    if captions is None:
        captions = default_captions(paths)
    arrays = [load_motion_file(p) for p in paths]
    names = [str(p) for p in paths]
    loaded = [as_joints(a, n) for a, n in zip(arrays, names)]  # validate all before rendering
    longest = max(range(len(loaded)), key=lambda i: len(loaded[i][0]))
    if suffix != ".png" and len(loaded[longest][0]) * len(loaded) > MAX_PANEL_FRAMES:
        T = len(loaded[longest][0])
        raise ValueError(
            f"{names[longest]}: {T} frames x {len(loaded)} motion(s) side by side is more than a render "
            f"holds in memory ({MAX_PANEL_FRAMES} panel frames, about "
            f"{MAX_PANEL_FRAMES * 0.22 / 1000:.1f} GB); render a part (save np.load(path)"
            f"[:{MAX_PANEL_FRAMES // len(loaded)}] to a new .npy), fewer motions at once, or a .png "
            "contact sheet"
        )
    if fps is None:
        fps = loaded[0][1].fps
    if suffix == ".png":
        return [render_frames(arrays, out_path, captions)]
    if suffix == ".mp4":
        exe = _find_ffmpeg()
        if exe is None:
            raise EncoderNotFound(
                f"cannot write {out_path}: no MP4 encoder found; pip install imageio-ffmpeg "
                "(the 'mp4' extra) or put ffmpeg on PATH, or write a .gif instead"
            )
        return [_save_mp4(frames(arrays, captions, _names=names), out_path, fps, exe)]
    return [_save_gif(frames(arrays, captions, _names=names), out_path, fps)]
