"""Normals to depth (Frankot-Chellappa, masked Poisson) and depth to a triangle mesh.

Frame: OpenCV camera frame under an orthographic view — x along image columns, y along rows
(down), z forward (depth grows away from the camera). A surface facing the camera has normals with
``n_z < 0``; its depth gradients are ``dz/dx = -n_x / n_z`` and ``dz/dy = -n_y / n_z``.
Lengths are in pixels times ``pixel_size`` (e.g. mm per pixel).
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import trimesh


class IntegrationError(ValueError):
    """Normals that cannot be integrated (bad shape, empty mask, grazing everywhere)."""


def normals_to_gradients(normals: np.ndarray, mask: np.ndarray | None = None,
                         max_slope: float = 20.0) -> tuple[np.ndarray, np.ndarray]:
    """Depth gradients (p = dz/dx, q = dz/dy) from unit normals (H, W, 3).

    Slopes are clipped to ``max_slope`` (normals near grazing carry no reliable depth)."""
    n = np.asarray(normals, dtype=np.float64)
    if n.ndim != 3 or n.shape[2] != 3:
        raise IntegrationError(f"normals must have shape (H, W, 3), got {n.shape}")
    nz = np.where(np.abs(n[..., 2]) < 1e-6, -1e-6, n[..., 2])
    p = np.clip(-n[..., 0] / nz, -max_slope, max_slope)
    q = np.clip(-n[..., 1] / nz, -max_slope, max_slope)
    if mask is not None:
        p = np.where(mask, p, 0.0)
        q = np.where(mask, q, 0.0)
    return p, q


def frankot_chellappa(normals: np.ndarray, mask: np.ndarray | None = None, *,
                      pixel_size: float = 1.0) -> np.ndarray:
    """Integrable least-squares depth by projection onto Fourier basis (Frankot & Chellappa 1988).

    Periodic boundaries: best for surfaces filling the image or padded masks. Returns depth
    (H, W) in ``pixel_size`` units, zero mean over the mask (depth is defined up to a constant).
    """
    p, q = normals_to_gradients(normals, mask)
    H, W = p.shape
    wx = np.fft.fftfreq(W) * 2 * np.pi
    wy = np.fft.fftfreq(H) * 2 * np.pi
    WX, WY = np.meshgrid(wx, wy)
    denom = WX ** 2 + WY ** 2
    denom[0, 0] = 1.0
    Z = (-1j * WX * np.fft.fft2(p) - 1j * WY * np.fft.fft2(q)) / denom
    Z[0, 0] = 0
    z = np.real(np.fft.ifft2(Z)) * pixel_size
    if mask is not None:
        z = np.where(mask, z - z[mask].mean(), 0.0)
    return z


def poisson_integrate(normals: np.ndarray, mask: np.ndarray, *, pixel_size: float = 1.0) -> np.ndarray:
    """Depth whose forward differences best match the normals' gradients inside ``mask``.

    Solves min ||D_x z - p||^2 + ||D_y z - q||^2 over pixel pairs that are both in the mask
    (so the object's outline imposes no false boundary), a sparse least-squares problem. Each
    connected region is defined up to a constant: the result has zero mean over the mask.

    Returns
    -------
    ndarray of shape (H, W)
        Depth in ``pixel_size`` units (0 outside the mask).
    """
    mask = np.asarray(mask, bool)
    if mask.shape != np.asarray(normals).shape[:2]:
        raise IntegrationError(f"mask shape {mask.shape} does not match normals {np.shape(normals)}")
    if mask.sum() < 2:
        raise IntegrationError("mask has fewer than 2 pixels: nothing to integrate")
    p, q = normals_to_gradients(normals, mask)
    H, W = mask.shape
    index = -np.ones((H, W), np.int64)
    index[mask] = np.arange(mask.sum())
    rows, cols, vals, rhs = [], [], [], []
    eq = 0
    for dy, dx, g in ((0, 1, p), (1, 0, q)):
        a = mask[: H - dy, : W - dx] & mask[dy:, dx:]
        i0 = index[: H - dy, : W - dx][a]
        i1 = index[dy:, dx:][a]
        # central estimate of the slope between the two pixels
        gv = 0.5 * (g[: H - dy, : W - dx][a] + g[dy:, dx:][a])
        m = len(i0)
        e = np.arange(eq, eq + m)
        rows += [e, e]
        cols += [i1, i0]
        vals += [np.ones(m), -np.ones(m)]
        rhs.append(gv)
        eq += m
    A = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                      shape=(eq, int(mask.sum())))
    b = np.concatenate(rhs)
    # normal equations are a graph Laplacian (singular per connected component): a tiny ridge
    # pins the free constants at zero without biasing the shape
    N = (A.T @ A + 1e-8 * sp.identity(A.shape[1])).tocsc()
    z = spla.spsolve(N, A.T @ b)
    z -= z.mean()
    out = np.zeros((H, W))
    out[mask] = z * pixel_size
    return out


def depth_to_mesh(depth: np.ndarray, mask: np.ndarray, *, pixel_size: float = 1.0) -> trimesh.Trimesh:
    """Triangulate a masked depth map (orthographic, camera frame) into a mesh.

    Vertices are ``(x * pixel_size, y * pixel_size, depth)``; every 2x2 block of mask pixels gives
    two triangles wound so that face normals point towards the camera (-z).
    """
    mask = np.asarray(mask, bool)
    depth = np.asarray(depth, float)
    if depth.shape != mask.shape:
        raise IntegrationError(f"depth shape {depth.shape} does not match mask {mask.shape}")
    H, W = mask.shape
    index = -np.ones((H, W), np.int64)
    index[mask] = np.arange(mask.sum())
    ys, xs = np.nonzero(mask)
    vertices = np.stack([xs * pixel_size, ys * pixel_size, depth[mask]], axis=1)
    quad = mask[:-1, :-1] & mask[:-1, 1:] & mask[1:, :-1] & mask[1:, 1:]
    a = index[:-1, :-1][quad]
    b = index[:-1, 1:][quad]
    c = index[1:, :-1][quad]
    d = index[1:, 1:][quad]
    # (x right, y down): a->c->b is counter-clockwise seen from -z, i.e. normal towards the camera
    faces = np.concatenate([np.stack([a, c, b], 1), np.stack([b, c, d], 1)])
    if len(faces) == 0:
        raise IntegrationError("mask has no 2x2 block of pixels: no triangles")
    return trimesh.Trimesh(vertices=vertices, faces=faces, process=False)
