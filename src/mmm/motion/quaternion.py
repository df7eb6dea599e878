"""Rotation utilities on torch tensors.

Quaternions are (..., 4) in (w, x, y, z) order and act on column vectors: qrot(q, v) = q v q*.
Every function broadcasts over leading dimensions and keeps the input dtype; the numpy-facing
entry points in `mmm.motion.features` convert to float64 tensors and back.
"""

from __future__ import annotations

import torch


def qnormalize(q: torch.Tensor) -> torch.Tensor:
    """Unit quaternion (..., 4)."""
    return q / q.norm(dim=-1, keepdim=True)


def qinv(q: torch.Tensor) -> torch.Tensor:
    """Conjugate (the inverse of a unit quaternion) (..., 4)."""
    return q * q.new_tensor([1.0, -1.0, -1.0, -1.0])


def qmul(q: torch.Tensor, r: torch.Tensor) -> torch.Tensor:
    """Hamilton product q r (..., 4); the result applies r first, then q."""
    q, r = torch.broadcast_tensors(q, r)
    w1, x1, y1, z1 = q.unbind(-1)
    w2, x2, y2, z2 = r.unbind(-1)
    return torch.stack(
        (
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
        ),
        dim=-1,
    )


def qrot(q: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Rotate vectors v (..., 3) by quaternions q (..., 4); leading dimensions broadcast."""
    if q.shape[:-1] != v.shape[:-1]:
        # broadcast_tensors is a C++ op; torch.broadcast_shapes is Python and slow per call.
        lead = torch.broadcast_tensors(q[..., 0], v[..., 0])[0].shape
        q = q.expand(lead + (4,))
        v = v.expand(lead + (3,))
    qvec = q[..., 1:]
    uv = torch.linalg.cross(qvec, v, dim=-1)
    uuv = torch.linalg.cross(qvec, uv, dim=-1)
    return v + 2.0 * (q[..., :1] * uv + uuv)


def qbetween(v0: torch.Tensor, v1: torch.Tensor) -> torch.Tensor:
    """Shortest-arc quaternion rotating v0 onto v1, both (..., 3) (need not be unit).

    For opposite vectors the arc is not unique (and the plain formula is 0/0): those get a half
    turn about an axis perpendicular to v0, the vertical one for horizontal vectors.
    """
    v = torch.linalg.cross(v0, v1, dim=-1)
    w = torch.sqrt((v0**2).sum(-1, keepdim=True) * (v1**2).sum(-1, keepdim=True)) + (v0 * v1).sum(
        -1, keepdim=True
    )
    q = torch.cat((w, v), dim=-1)
    scale = (v0.norm(dim=-1) * v1.norm(dim=-1)).clamp_min(torch.finfo(q.dtype).tiny)
    opposite = q.norm(dim=-1) <= 1e-7 * scale
    if opposite.any():
        axis = torch.linalg.cross(v0, v0.new_tensor([1.0, 0.0, 0.0]).expand_as(v0), dim=-1)
        along_x = axis.norm(dim=-1, keepdim=True) <= 1e-6 * v0.norm(dim=-1, keepdim=True)
        axis = torch.where(
            along_x, torch.linalg.cross(v0, v0.new_tensor([0.0, 1.0, 0.0]).expand_as(v0), dim=-1), axis
        )
        half_turn = torch.cat((torch.zeros_like(w), axis / axis.norm(dim=-1, keepdim=True)), dim=-1)
        q = torch.where(opposite.unsqueeze(-1), half_turn, q)
    return qnormalize(q)


def quat_from_axis_angle(axis: torch.Tensor, angle: torch.Tensor) -> torch.Tensor:
    """Quaternion (..., 4) for a rotation of `angle` radians (...) about unit `axis` (..., 3)."""
    half = 0.5 * angle.unsqueeze(-1)
    return torch.cat((torch.cos(half), torch.sin(half) * axis), dim=-1)


def quat_about_y(angle: torch.Tensor) -> torch.Tensor:
    """Rotation (..., 4) about the vertical axis by `angle` (...) radians (+Z turns towards +X)."""
    half = 0.5 * angle
    zero = torch.zeros_like(half)
    return torch.stack((torch.cos(half), zero, torch.sin(half), zero), dim=-1)


def quat_to_matrix(q: torch.Tensor) -> torch.Tensor:
    """Rotation matrices (..., 3, 3) from unit quaternions (..., 4)."""
    w, x, y, z = q.unbind(-1)
    two = 2.0
    m = torch.stack(
        (
            1 - two * (y * y + z * z),
            two * (x * y - w * z),
            two * (x * z + w * y),
            two * (x * y + w * z),
            1 - two * (x * x + z * z),
            two * (y * z - w * x),
            two * (x * z - w * y),
            two * (y * z + w * x),
            1 - two * (x * x + y * y),
        ),
        dim=-1,
    )
    return m.reshape(q.shape[:-1] + (3, 3))


def quat_to_cont6d(q: torch.Tensor) -> torch.Tensor:
    """Continuous 6-D form (..., 6): the first two columns of the rotation matrix, column-major."""
    m = quat_to_matrix(q)
    return torch.cat((m[..., :, 0], m[..., :, 1]), dim=-1)


def cont6d_to_matrix(d6: torch.Tensor) -> torch.Tensor:
    """Rotation matrices (..., 3, 3) from the 6-D form (..., 6) by Gram-Schmidt."""
    a1, a2 = d6[..., :3], d6[..., 3:]
    b1 = a1 / a1.norm(dim=-1, keepdim=True)
    b2 = a2 - (b1 * a2).sum(-1, keepdim=True) * b1
    b2 = b2 / b2.norm(dim=-1, keepdim=True)
    b3 = torch.linalg.cross(b1, b2, dim=-1)
    return torch.stack((b1, b2, b3), dim=-1)


def yaw_of(q: torch.Tensor) -> torch.Tensor:
    """Heading angle (...) in radians of the direction +Z rotated by q, measured from +Z towards +X."""
    fwd = qrot(q, q.new_tensor([0.0, 0.0, 1.0]).expand(q.shape[:-1] + (3,)))
    return torch.atan2(fwd[..., 0], fwd[..., 2])


def gaussian_smooth_time(x: torch.Tensor, sigma: float, truncate: float = 4.0) -> torch.Tensor:
    """Gaussian filter along dim 0 of x (T, C) with edge replication.

    Matches scipy.ndimage.gaussian_filter1d(x, sigma, axis=0, mode='nearest'), which the
    reference pipeline uses to smooth the facing direction.
    """
    radius = int(truncate * float(sigma) + 0.5)
    offsets = torch.arange(-radius, radius + 1, dtype=x.dtype, device=x.device)
    kernel = torch.exp(-0.5 * (offsets / sigma) ** 2)
    kernel = kernel / kernel.sum()
    T = x.shape[0]
    # Edge replication for any T (the kernel can be longer than the sequence).
    idx = (torch.arange(T + 2 * radius, device=x.device) - radius).clamp(0, T - 1)
    padded = x[idx]  # (T + 2r, C)
    windows = padded.unfold(0, 2 * radius + 1, 1)  # (T, C, 2r + 1)
    return (windows * kernel).sum(-1)


__all__ = [
    "qnormalize",
    "qinv",
    "qmul",
    "qrot",
    "qbetween",
    "quat_from_axis_angle",
    "quat_about_y",
    "quat_to_matrix",
    "quat_to_cont6d",
    "cont6d_to_matrix",
    "yaw_of",
    "gaussian_smooth_time",
]
