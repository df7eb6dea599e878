"""What the adherence checker measures on joint positions (T, 22, 3): facing and heading, root
path and speed, flight frames, excursions past a threshold. Conventions and measurement choices
are described in adherence.py.
"""

from __future__ import annotations

import math

import numpy as np

from mmm.data.synthetic.constants import FPS

# Joint indices of the 22-joint skeleton.
PELVIS, L_HIP, R_HIP = 0, 1, 2
L_ANKLE, R_ANKLE, L_TOE, R_TOE = 7, 8, 10, 11
HEAD, L_SHOULDER, R_SHOULDER, L_WRIST, R_WRIST = 15, 16, 17, 20, 21
SIDE_JOINTS = {  # side -> (ankle, toe, shoulder, wrist)
    "left": (L_ANKLE, L_TOE, L_SHOULDER, L_WRIST),
    "right": (R_ANKLE, R_TOE, R_SHOULDER, R_WRIST),
}
OTHER_SIDE = {"left": "right", "right": "left"}

# Measurement constants (not thresholds of the spec's table).
HYSTERESIS = 0.02
FLIGHT_CLEARANCE = 0.03
HEADING_FRAMES = 3


def facing_vectors(joints: np.ndarray) -> np.ndarray:
    """Horizontal unit facing directions (T, 2) as (x, z) from hips and shoulders of (T, 22, 3)."""
    across = (joints[:, R_HIP] - joints[:, L_HIP]) + (joints[:, R_SHOULDER] - joints[:, L_SHOULDER])
    fwd = np.stack((across[:, 2], -across[:, 0]), axis=-1)  # up × across, (x, z)
    return fwd / np.maximum(np.linalg.norm(fwd, axis=-1, keepdims=True), 1e-9)


def heading_angles(joints: np.ndarray) -> np.ndarray:
    """Unwrapped heading (T,) in radians, increasing when turning left (+Z towards +X)."""
    fwd = facing_vectors(joints)
    return np.unwrap(np.arctan2(fwd[:, 0], fwd[:, 1]))


def heading_change(joints: np.ndarray) -> float:
    """Heading change (deg) from the part's first to its last frames (HEADING_FRAMES averaged)."""
    heading = heading_angles(joints)
    k = min(HEADING_FRAMES, len(heading))
    return math.degrees(heading[-k:].mean() - heading[:k].mean())


def initial_frame(joints: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Forward and left unit vectors (x, z) of the part's initial heading."""
    fwd = facing_vectors(joints[:HEADING_FRAMES]).mean(axis=0)
    fwd = fwd / max(np.linalg.norm(fwd), 1e-9)
    left = np.array([fwd[1], -fwd[0]])  # forward turned by +90 degrees (+Z -> +X)
    return fwd, left


def excursions(signal: np.ndarray, threshold: float, above: bool) -> int:
    """Number of excursions past `threshold` (above or below), with HYSTERESIS to leave one."""
    count, inside = 0, False
    for v in signal:
        if not inside and ((v >= threshold) if above else (v <= threshold)):
            count, inside = count + 1, True
        elif inside and ((v < threshold - HYSTERESIS) if above else (v > threshold + HYSTERESIS)):
            inside = False
    return count


def runs(mask: np.ndarray) -> int:
    """Number of maximal runs of True."""
    m = np.asarray(mask, dtype=bool)
    if m.size == 0:
        return 0
    return int(m[0]) + int(np.count_nonzero(m[1:] & ~m[:-1]))


def displacement(joints: np.ndarray) -> np.ndarray:
    """Horizontal (x, z) displacement of the pelvis from the first to the last frame."""
    xz = joints[:, PELVIS][:, [0, 2]]
    return xz[-1] - xz[0]


def root_path_length(joints: np.ndarray) -> float:
    xz = joints[:, PELVIS][:, [0, 2]]
    return float(np.linalg.norm(np.diff(xz, axis=0), axis=-1).sum())


def mean_speed(joints: np.ndarray, fps: float = FPS) -> float:
    n = joints.shape[0]
    return root_path_length(joints) * fps / max(n - 1, 1)


def flight_frames(joints: np.ndarray) -> np.ndarray:
    """(T,) bool: both feet off the ground (every foot joint above FLIGHT_CLEARANCE)."""
    feet = joints[:, [L_ANKLE, L_TOE, R_ANKLE, R_TOE], 1]
    return feet.min(axis=-1) > FLIGHT_CLEARANCE
