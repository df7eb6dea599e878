"""Export of motions to interchange formats: BVH (Blender, MotionBuilder, ...) with a parser to check it."""

from mmm.export.bvh import (
    END_SITE_LENGTH,
    BVHInfo,
    BVHMotion,
    bvh_joint_names,
    euler_to_matrix,
    features_to_bvh,
    matrix_to_euler_zxy,
    read_bvh,
    write_bvh,
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
