"""BRDF coordinates: Rusinkiewicz halfway/difference angles, Zickler (u, v, w), Romeiro (s, t).

All functions are vectorised over samples; angles are radians. Directions are unit vectors in
the local shading frame (z = surface normal, see ``frames.py``), ``wi`` towards the light and
``wo`` towards the viewer. ``local_directions`` takes world directions into that frame.

Halfway/difference angles (Rusinkiewicz 1998): h = (wi + wo)/|wi + wo| has spherical angles
(theta_h, phi_h); d, the light direction ``wi`` expressed in the frame where h is the pole
(rotate by -phi_h about the normal, then by -theta_h about the binormal y), has angles
(theta_d, phi_d). ``wo`` in that frame is d reflected about the pole, i.e. phi_d + pi: swapping
wi and wo (reciprocity) maps phi_d -> phi_d + pi. The MERL database uses the same construction.

References
----------
S. Rusinkiewicz, "A new change of variables for efficient BRDF representation", EGWR 1998;
T. Zickler et al., "Reflectance sharing", EGSR 2005, Eq. 1;
F. Romeiro, Y. Vasilyev, T. Zickler, "Passive reflectometry", ECCV 2008, Sect. 2.
"""
from __future__ import annotations

import numpy as np

from .frames import tangent_frames, to_local

HALF_PI = 0.5 * np.pi


def _directions(name: str, v) -> np.ndarray:
    a = np.asarray(v, dtype=np.float64)
    if a.ndim == 0 or a.shape[-1] != 3:
        raise ValueError(f"{name} must be an array of 3-vectors with shape (N, 3), got {a.shape}")
    return a.reshape(-1, 3)


def _angles(name: str, v) -> np.ndarray:
    a = np.asarray(v, dtype=np.float64)
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} must be finite")
    return a


def local_directions(wi_world, wo_world, normals, tangents=None):
    """World-frame unit directions (N, 3) into the local shading frames of ``normals`` (N, 3).

    Uses ``frames.tangent_frames`` (branch-free tangent unless ``tangents`` are given; for
    isotropic models the tangent choice does not matter). Returns (wi_local, wo_local), (N, 3).
    """
    frames = tangent_frames(_directions("normals", normals), tangents)
    wi = _directions("wi_world", wi_world)
    wo = _directions("wo_world", wo_world)
    if not (len(wi) == len(wo) == len(frames)):
        raise ValueError(f"wi_world, wo_world and normals need the same length, got "
                         f"{len(wi)}, {len(wo)}, {len(frames)}")
    return to_local(wi, frames), to_local(wo, frames)


def halfway_difference(wi, wo):
    """Rusinkiewicz angles of local direction pairs.

    Parameters
    ----------
    wi, wo : array_like, (N, 3)
        Local unit directions to the light and to the viewer.

    Returns
    -------
    theta_h, phi_h, theta_d, phi_d : ndarray, (N,)
        Radians: theta_h in [0, pi], phi_h in (-pi, pi], theta_d in [0, pi/2],
        phi_d in (-pi, pi]. Where wi = -wo the halfway vector is undefined; the normal is used.
    """
    wi = _directions("wi", wi)
    wo = _directions("wo", wo)
    if wi.shape != wo.shape:
        raise ValueError(f"wi and wo must have the same shape, got {wi.shape} and {wo.shape}")
    xi, yi, zi = wi.T
    hx, hy, hz = (wi + wo).T  # unnormalised halfway vector: angles need no normalisation
    rho_h = np.hypot(hx, hy)
    norm_h = np.hypot(rho_h, hz)
    degenerate = norm_h < 1e-12  # wi = -wo: use the normal as halfway vector
    hz = np.where(degenerate, 1.0, hz)
    norm_h = np.where(degenerate, 1.0, norm_h)
    theta_h = np.arctan2(rho_h, hz)
    phi_h = np.arctan2(hy, hx)
    # d = R_y(-theta_h) R_z(-phi_h) wi, with cos/sin of the angles taken from h directly
    has_azimuth = rho_h > 0
    safe = np.where(has_azimuth, rho_h, 1.0)
    cp = np.where(has_azimuth, hx / safe, 1.0)
    sp = hy / safe
    ct, st = hz / norm_h, rho_h / norm_h
    x1 = cp * xi + sp * yi
    y1 = cp * yi - sp * xi
    dx = ct * x1 - st * zi
    dz = st * x1 + ct * zi
    theta_d = np.arctan2(np.hypot(dx, y1), dz)
    phi_d = np.arctan2(y1, dx)
    return theta_h, phi_h, theta_d, phi_d


def _spherical(theta, phi):
    st = np.sin(theta)
    return np.stack([st * np.cos(phi), st * np.sin(phi), np.cos(theta)], axis=-1)


def from_halfway_difference(theta_h, phi_h, theta_d, phi_d):
    """Local directions (wi, wo), each (N, 3), from Rusinkiewicz angles (radians, broadcast).

    Inverse of ``halfway_difference``: wi = R_z(phi_h) R_y(theta_h) d(theta_d, phi_d) and
    wo the same rotation of d(theta_d, phi_d + pi). Directions may lie below the surface
    (theta_h + theta_d > pi/2); callers that need valid pairs check ``wi[:, 2] > 0``.
    """
    theta_h, phi_h, theta_d, phi_d = np.broadcast_arrays(
        *(_angles(n, a) for n, a in (("theta_h", theta_h), ("phi_h", phi_h),
                                     ("theta_d", theta_d), ("phi_d", phi_d))))
    d = _spherical(theta_d, phi_d).reshape(-1, 3)
    ct, st = np.cos(theta_h).reshape(-1), np.sin(theta_h).reshape(-1)
    cp, sp = np.cos(phi_h).reshape(-1), np.sin(phi_h).reshape(-1)

    def rotate(v):  # R_z(phi_h) R_y(theta_h) v
        x = ct * v[:, 0] + st * v[:, 2]
        z = -st * v[:, 0] + ct * v[:, 2]
        return np.stack([cp * x - sp * v[:, 1], sp * x + cp * v[:, 1], z], axis=1)

    return rotate(d), rotate(d * [-1.0, -1.0, 1.0])


def zickler_uvw(theta_h, theta_d, phi_d) -> np.ndarray:
    """Zickler et al.'s (u, v, w) = (sin th_h cos 2 phi_d, sin th_h sin 2 phi_d, 2 th_d / pi).

    The doubled phi_d makes f(u, v, w) reciprocal (phi_d -> phi_d + pi leaves it unchanged) and
    removes the theta_h = 0 singularity of the halfway/difference angles (Eq. 1). Inputs in
    radians (broadcast); returns (N, 3) with u, v in [-1, 1] and w in [0, 1].
    """
    theta_h, theta_d, phi_d = np.broadcast_arrays(
        _angles("theta_h", theta_h), _angles("theta_d", theta_d), _angles("phi_d", phi_d))
    s = np.sin(theta_h)
    return np.stack([s * np.cos(2 * phi_d), s * np.sin(2 * phi_d), theta_d / HALF_PI],
                    axis=-1).reshape(-1, 3)


def zickler_uvw_inverse(uvw):
    """(theta_h, theta_d, phi_d) from (u, v, w) (N, 3); radians.

    theta_h in [0, pi/2], theta_d = w pi/2, phi_d in [0, pi): the mapping is 2-to-1 in phi_d
    (phi_d and phi_d + pi, the reciprocal pair), and phi_d is undefined (0) at theta_h = 0.
    """
    uvw = _directions("uvw", uvw)
    r = np.hypot(uvw[:, 0], uvw[:, 1])
    if np.any(r > 1 + 1e-9):
        raise ValueError(f"uvw: u^2 + v^2 must be <= 1 (it is sin^2 theta_h), got {r.max() ** 2:g}")
    theta_h = np.arcsin(np.minimum(r, 1.0))
    phi_d = np.mod(0.5 * np.arctan2(uvw[:, 1], uvw[:, 0]), np.pi)
    return theta_h, uvw[:, 2] * HALF_PI, phi_d


def uvw_from_directions(wi, wo) -> np.ndarray:
    """Zickler (u, v, w) (N, 3) of local direction pairs (N, 3): angles, then Eq. 1."""
    theta_h, _, theta_d, phi_d = halfway_difference(wi, wo)
    return zickler_uvw(theta_h, theta_d, phi_d)


def romeiro_st(theta_h, theta_d):
    """Romeiro et al.'s bivariate coordinates s = 2 theta_d / pi, t = sqrt(2 theta_h / pi).

    The square root concentrates samples near the specular peak (theta_h = 0). Inputs in
    radians within [0, pi/2] (broadcast); returns (s, t), each in [0, 1].
    """
    theta_h = _angles("theta_h", theta_h)
    theta_d = _angles("theta_d", theta_d)
    if np.any(theta_h < 0) or np.any(theta_d < 0):
        raise ValueError("theta_h and theta_d must be >= 0 radians")
    return theta_d / HALF_PI, np.sqrt(theta_h / HALF_PI)


def romeiro_st_inverse(s, t):
    """(theta_h, theta_d) in radians from Romeiro (s, t): theta_h = t^2 pi/2, theta_d = s pi/2."""
    s = _angles("s", s)
    t = _angles("t", t)
    if np.any(t < 0):
        raise ValueError("t must be >= 0 (t = sqrt(2 theta_h / pi))")
    return t ** 2 * HALF_PI, s * HALF_PI


def st_from_directions(wi, wo):
    """Romeiro (s, t), each (N,), of local direction pairs (N, 3)."""
    theta_h, _, theta_d, _ = halfway_difference(wi, wo)
    return romeiro_st(theta_h, theta_d)
