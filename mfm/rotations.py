"""Vectorised rotation helpers in torch: quaternions (w, x, y, z), continuous 6D, matrices, axis-angle.

Every function broadcasts over any other dims and works in the dtype/device of its inputs.
Conventions follow HumanML3D's ``common/quaternion.py`` (Hamilton product, ``qrot(q, v) = q v q*``,
6D = the first two *columns* of the rotation matrix), so features computed with these helpers match
the published dataset.

The quaternion/vector functions accept either a tensor holding the 4 (or 3) components along ``dim``
(default: the last axis) and then return a tensor laid out the same way, or a *tuple of component
tensors* ``(w, x, y, z)`` / ``(x, y, z)`` and then return a tuple. Hot loops use the tuple form on
components-first data: each component is a contiguous block, every step is a plain elementwise op on
contiguous memory and nothing is re-stacked between steps, several times faster on CPU than working
on interleaved ``(..., 4)`` data (strided reads and reductions over a size-3/4 axis are the slow part).
"""

from __future__ import annotations

from typing import Union

import torch

Tensor = torch.Tensor
Components = tuple  # tuple of component tensors, (w, x, y, z) or (x, y, z)
QuatLike = Union[Tensor, Components]


def _parts(x: QuatLike, size: int, dim: int, name: str) -> tuple[Tensor, ...]:
    if isinstance(x, tuple):
        if len(x) != size:
            raise ValueError(f"{name} must have {size} components, got a tuple of {len(x)}")
        return x
    if x.shape[dim] != size:
        raise ValueError(f"{name} must have {size} components along dim {dim}, got shape {tuple(x.shape)}")
    return x.unbind(dim)


def _pack(parts, as_tuple: bool, dim: int) -> QuatLike:
    if as_tuple:
        return tuple(parts)
    return torch.stack(torch.broadcast_tensors(*parts), dim=dim)


def _any_tuple(*xs) -> bool:
    return any(isinstance(x, tuple) for x in xs)


def _dot3(a, b) -> Tensor:
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _cross3(a, b) -> tuple[Tensor, Tensor, Tensor]:
    ax, ay, az = a
    bx, by, bz = b
    return ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx


def qmul(q: QuatLike, r: QuatLike, dim: int = -1) -> QuatLike:
    """Hamilton product ``q * r`` (apply ``r`` first, then ``q``)."""
    w1, x1, y1, z1 = _parts(q, 4, dim, "q")
    w2, x2, y2, z2 = _parts(r, 4, dim, "r")
    return _pack(
        (
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
        ),
        _any_tuple(q, r),
        dim,
    )


def qinv(q: QuatLike, dim: int = -1) -> QuatLike:
    """Conjugate, i.e. the inverse of a unit quaternion."""
    w, x, y, z = _parts(q, 4, dim, "q")
    return _pack((w, -x, -y, -z), _any_tuple(q), dim)


def qnormalize(q: QuatLike, dim: int = -1) -> QuatLike:
    c = _parts(q, 4, dim, "q")
    norm = torch.sqrt(c[0] * c[0] + c[1] * c[1] + c[2] * c[2] + c[3] * c[3])
    return _pack(tuple(v / norm for v in c), _any_tuple(q), dim)


def qrot(q: QuatLike, v: QuatLike, dim: int = -1) -> QuatLike:
    """Rotate vectors ``v`` (3 components) by unit quaternions ``q`` (4 components)."""
    w, *qvec = _parts(q, 4, dim, "q")
    vc = _parts(v, 3, dim, "v")
    uv = _cross3(qvec, vc)
    uuv = _cross3(qvec, uv)
    return _pack(tuple(vc[i] + 2 * (w * uv[i] + uuv[i]) for i in range(3)), _any_tuple(q, v), dim)


def rotate_about_y(q: QuatLike, v: QuatLike, dim: int = -1) -> QuatLike:
    """``qrot`` for quaternions ``(w, 0, s, 0)``, rotations about the vertical axis (HumanML3D's root and
    facing rotations): x and z turn by the angle whose cosine is ``1 - 2 s^2``, y is passed through.
    The x and z components of ``q`` are not read."""
    w, _, s, _ = _parts(q, 4, dim, "q")
    x, y, z = _parts(v, 3, dim, "v")
    cos, sin = 1 - 2 * s * s, 2 * w * s
    return _pack((x * cos + z * sin, y, z * cos - x * sin), _any_tuple(q, v), dim)


def qbetween(v0: QuatLike, v1: QuatLike, dim: int = -1) -> QuatLike:
    """Unit quaternion of the shortest-arc rotation taking direction ``v0`` to direction ``v1``.

    Same formula as the reference (``w = |v0||v1| + v0.v1``, ``xyz = v0 x v1``, normalised), which
    gives ``w >= 0``. For exactly opposite vectors that formula is 0/0; there we rotate by pi about an
    axis perpendicular to ``v0`` instead. Zero-length inputs give NaN (no direction).
    """
    a = _parts(v0, 3, dim, "v0")
    b = _parts(v1, 3, dim, "v1")
    xyz = _cross3(a, b)
    norms = torch.sqrt(_dot3(a, a) * _dot3(b, b))
    w = norms + _dot3(a, b)
    squared = w * w + _dot3(xyz, xyz)
    inv_norm = torch.rsqrt(squared)
    q = (w * inv_norm, xyz[0] * inv_norm, xyz[1] * inv_norm, xyz[2] * inv_norm)
    opposite = (squared <= 1e-24 * norms * norms) & (norms > 0)
    if bool(opposite.any()):
        # Half turn about v0 x e, e the basis vector least aligned with v0 (so the axis is well defined).
        ax, ay, az = (c.abs() for c in a)
        ex = ((ax <= ay) & (ax <= az)).to(w.dtype)
        ey = ((ay < ax) & (ay <= az)).to(w.dtype)
        axis = _cross3(a, (ex, ey, 1 - ex - ey))
        inv_axis = torch.rsqrt(_dot3(axis, axis))
        half_turn = (torch.zeros_like(w), axis[0] * inv_axis, axis[1] * inv_axis, axis[2] * inv_axis)
        q = tuple(torch.where(opposite, h, c) for h, c in zip(half_turn, q))
    return _pack(q, _any_tuple(v0, v1), dim)


def qfix(q: QuatLike, time_dim: int = 0, dim: int = -1) -> QuatLike:
    """Sign continuity over time: flip ``q`` to ``-q`` wherever that makes consecutive quaternions along
    ``time_dim`` have a non-negative dot product (the reference's ``qfix``). For a tensor, ``time_dim``
    and ``dim`` index its axes; for a tuple, ``time_dim`` indexes the axes of the component tensors."""
    as_tuple = isinstance(q, tuple)
    if not as_tuple:
        time_dim, dim = time_dim % q.ndim, dim % q.ndim
        if time_dim == dim:
            raise ValueError("qfix: the time dim cannot be the quaternion dim")
        # Index the component tensors, which lack the quaternion axis.
        time_dim = time_dim - 1 if time_dim > dim else time_dim
    c = _parts(q, 4, dim, "q")
    n = c[0].shape[time_dim]
    if n < 2:
        return _pack(tuple(v.clone() for v in c), as_tuple, dim)
    now = [v.narrow(time_dim, 1, n - 1) for v in c]
    before = [v.narrow(time_dim, 0, n - 1) for v in c]
    flips = (now[0] * before[0] + now[1] * before[1] + now[2] * before[2] + now[3] * before[3]) < 0
    odd = torch.cumsum(flips, dim=time_dim, dtype=torch.int32) % 2
    sign = torch.cat((torch.ones_like(odd.narrow(time_dim, 0, 1)), 1 - 2 * odd), dim=time_dim).to(c[0].dtype)
    return _pack(tuple(v * sign for v in c), as_tuple, dim)


def quat_to_matrix(q: Tensor) -> Tensor:
    """(..., 4) -> (..., 3, 3); ``q`` need not be normalised."""
    w, x, y, z = _parts(q, 4, -1, "q")
    two_s = 2.0 / (w * w + x * x + y * y + z * z)
    m = torch.stack(
        (
            1 - two_s * (y * y + z * z), two_s * (x * y - z * w), two_s * (x * z + y * w),
            two_s * (x * y + z * w), 1 - two_s * (x * x + z * z), two_s * (y * z - x * w),
            two_s * (x * z - y * w), two_s * (y * z + x * w), 1 - two_s * (x * x + y * y),
        ),
        dim=-1,
    )
    return m.reshape(q.shape[:-1] + (3, 3))


def quat_to_cont6d(q: QuatLike, dim: int = -1) -> QuatLike:
    """Unit quaternions (4 components) -> 6D (6 components): the first two columns of the rotation
    matrix, ``[R[:, 0], R[:, 1]]`` (HumanML3D's rot6d). Only those 6 entries are computed."""
    w, x, y, z = _parts(q, 4, dim, "q")
    two_s = 2.0 / (w * w + x * x + y * y + z * z)
    return _pack(
        (
            1 - two_s * (y * y + z * z), two_s * (x * y + z * w), two_s * (x * z - y * w),
            two_s * (x * y - z * w), 1 - two_s * (x * x + z * z), two_s * (y * z + x * w),
        ),
        _any_tuple(q),
        dim,
    )


def cont6d_to_matrix(d6: Tensor) -> Tensor:
    """(..., 6) -> (..., 3, 3) by Gram-Schmidt as in the reference: column 0 = normalised first half,
    column 2 = normalised (col0 x second half), column 1 = col2 x col0."""
    c = _parts(d6, 6, -1, "cont6d")
    norm_x = torch.sqrt(_dot3(c[:3], c[:3]))
    x = tuple(v / norm_x for v in c[:3])
    z = _cross3(x, c[3:])
    norm_z = torch.sqrt(_dot3(z, z))
    z = tuple(v / norm_z for v in z)
    y = _cross3(z, x)
    return torch.stack((torch.stack(x, -1), torch.stack(y, -1), torch.stack(z, -1)), dim=-1)


def matrix_to_quat(m: Tensor) -> Tensor:
    """(..., 3, 3) rotation matrices -> unit quaternions (..., 4) with ``w >= 0``.

    Shepperd's method: of the four algebraically equal formulas, use the one whose pivot
    (1+trace or 1+2*m_ii-trace) is largest, which keeps the division well conditioned.
    """
    if m.shape[-2:] != (3, 3):
        raise ValueError(f"matrix must be (..., 3, 3), got shape {tuple(m.shape)}")
    m00, m01, m02 = m[..., 0, 0], m[..., 0, 1], m[..., 0, 2]
    m10, m11, m12 = m[..., 1, 0], m[..., 1, 1], m[..., 1, 2]
    m20, m21, m22 = m[..., 2, 0], m[..., 2, 1], m[..., 2, 2]
    pivots = torch.stack(
        (1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22), dim=-1
    )
    # Row k is 2*sqrt(pivot_k) * q: pick the row with the largest pivot and normalise it.
    candidates = torch.stack(
        (
            torch.stack((pivots[..., 0], m21 - m12, m02 - m20, m10 - m01), dim=-1),
            torch.stack((m21 - m12, pivots[..., 1], m10 + m01, m02 + m20), dim=-1),
            torch.stack((m02 - m20, m10 + m01, pivots[..., 2], m12 + m21), dim=-1),
            torch.stack((m10 - m01, m20 + m02, m21 + m12, pivots[..., 3]), dim=-1),
        ),
        dim=-2,
    )
    best = pivots.argmax(dim=-1, keepdim=True)
    q = torch.gather(candidates, -2, best[..., None].expand(best.shape[:-1] + (1, 4))).squeeze(-2)
    q = qnormalize(q)
    return torch.where(q[..., :1] < 0, -q, q)


def axis_angle_to_matrix(axis_angle: Tensor) -> Tensor:
    """(..., 3) rotation vectors (axis * angle, radians) -> (..., 3, 3) by Rodrigues' formula,
    ``R = I + A [r]x + B [r]x^2`` with ``A = sin(t)/t``, ``B = (1-cos t)/t^2`` (Taylor series near 0)."""
    rx, ry, rz = _parts(axis_angle, 3, -1, "axis_angle")
    theta2 = rx * rx + ry * ry + rz * rz
    small = theta2 < 1e-8
    theta = torch.sqrt(torch.where(small, torch.ones_like(theta2), theta2))
    a = torch.where(small, 1 - theta2 / 6, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta2 / 24, (1 - torch.cos(theta)) / (theta * theta))
    zero = torch.zeros_like(rx)
    k = torch.stack((zero, -rz, ry, rz, zero, -rx, -ry, rx, zero), dim=-1).reshape(axis_angle.shape[:-1] + (3, 3))
    eye = torch.eye(3, dtype=axis_angle.dtype, device=axis_angle.device)
    return eye + a[..., None, None] * k + b[..., None, None] * (k @ k)


def quat_about_y(angle: Tensor, dim: int = -1, *, as_tuple: bool = False) -> QuatLike:
    """Quaternion ``(cos a, 0, sin a, 0)``: HumanML3D's root rotation from its integrated (half-)angle ``a``."""
    zero = torch.zeros_like(angle)
    return _pack((torch.cos(angle), zero, torch.sin(angle), zero), as_tuple, dim)
