"""Constants shared by the animation (body, locomotion, animations) and the adherence checker.

They live here, below both, so that the generator never imports from the checker: the frame rate,
the neutral standing pose the animation builds and the checker measures against, and the walking
speeds the generator draws from and the checker accepts.
"""

from __future__ import annotations

import math

import numpy as np

from mmm.motion.skeleton import T2M_SKELETON, Skeleton

FPS = 20.0  # frames per second of the synthetic motions (tracks, labels, captions)

# Neutral standing pose: the foot bone (ankle -> toe joint) points forward and down by this angle
# with the toe joint on the floor, and the knees are nearly straight (hip-to-ankle distance =
# STAND_REACH × leg length).
NEUTRAL_FOOT_PITCH = math.radians(22.0)
STAND_REACH = 0.997
# The pelvis->hip bones point out and down by this angle, as in HumanML3D (54 degrees on the
# reference sample): the hips sit ~0.085 m below the pelvis joint, which lifts the pelvis.
HIP_DROP = math.radians(54.0)

# Mean speed (m/s) of each walking speed label: the generator draws inside, the checker accepts inside.
WALK_SPEEDS = {"slow": (0.5, 0.8), "normal": (1.0, 1.4), "fast": (1.6, 2.0)}


def standing_height(skeleton: Skeleton = T2M_SKELETON) -> float:
    """Pelvis height (m) of the neutral standing pose, from the skeleton's bone lengths.

    Hips HIP_DROP below the pelvis, legs nearly straight (STAND_REACH of hip->knee + knee->ankle)
    above ankles that sit foot_length · sin(NEUTRAL_FOOT_PITCH) above the toe joints on the
    floor; mean of both sides. About 0.96 m for the HumanML3D target skeleton.
    """
    lengths = skeleton.bone_lengths
    if lengths is None or skeleton.num_joints != 22:
        raise ValueError(
            f"standing_height needs the 22-joint skeleton with target bone lengths, got {skeleton.name!r}"
        )
    heights = []
    for pelvis_hip, hip_knee, knee_ankle, ankle_toe in ((1, 4, 7, 10), (2, 5, 8, 11)):
        leg = lengths[hip_knee] + lengths[knee_ankle]
        drop = lengths[pelvis_hip] * math.sin(HIP_DROP)
        heights.append(drop + STAND_REACH * leg + lengths[ankle_toe] * math.sin(NEUTRAL_FOOT_PITCH))
    return float(np.mean(heights))


STANDING_HEIGHT = standing_height()
