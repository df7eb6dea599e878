"""Export of motions to interchange formats: BVH (Blender, MotionBuilder, ...) with a parser to check it."""

from mmm.export.bvh import *  # noqa: F401,F403  (the names of bvh.__all__)
