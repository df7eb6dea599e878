"""Stick-figure rendering of motions (GIF, MP4, PNG contact sheets) with Pillow only."""

from mmm.render.stick import (
    PALETTE,
    EncoderNotFound,
    as_joints,
    contact_sheet,
    frames,
    load_motion_file,
    render_files,
    render_frames,
    render_gif,
    render_mp4,
)

__all__ = [
    "PALETTE",
    "EncoderNotFound",
    "as_joints",
    "contact_sheet",
    "frames",
    "load_motion_file",
    "render_files",
    "render_frames",
    "render_gif",
    "render_mp4",
]
