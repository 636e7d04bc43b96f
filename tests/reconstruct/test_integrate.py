import numpy as np
import pytest

from reconstruct.integrate import (IntegrationError, depth_to_mesh, frankot_chellappa,
                                   poisson_integrate)


def sphere(H=160, W=200, r=60.0):
    Y, X = np.mgrid[:H, :W]
    cx, cy = W / 2, H / 2
    nx, ny = (X - cx) / r, (Y - cy) / r
    inside = nx ** 2 + ny ** 2 < 0.95 ** 2
    nz = -np.sqrt(np.clip(1 - nx ** 2 - ny ** 2, 1e-12, None))
    depth = -np.sqrt(np.clip(r ** 2 - (X - cx) ** 2 - (Y - cy) ** 2, 0, None))
    return np.stack([nx, ny, nz], -1), inside, depth


def test_poisson_recovers_sphere_depth():
    n, inside, depth = sphere()
    z = poisson_integrate(n, inside, pixel_size=0.5)
    truth = (depth - depth[inside].mean()) * 0.5
    rms = np.sqrt(np.mean((z[inside] - truth[inside]) ** 2))
    assert rms < 0.01 * np.ptp(truth[inside])


def test_frankot_chellappa_recovers_full_frame_surface():
    H, W = 128, 128
    Y, X = np.mgrid[:H, :W]
    z_true = 5 * np.sin(2 * np.pi * X / W) * np.cos(2 * np.pi * Y / H)   # periodic surface
    zy, zx = np.gradient(z_true)
    n = np.stack([zx, zy, -np.ones_like(zx)], -1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    z = frankot_chellappa(n)
    z -= z.mean()
    assert np.sqrt(np.mean((z - z_true) ** 2)) < 0.02 * np.ptp(z_true)


def test_mesh_faces_point_at_camera_and_match_depth():
    n, inside, depth = sphere(60, 80, 25)
    z = poisson_integrate(n, inside)
    mesh = depth_to_mesh(z, inside)
    assert mesh.face_normals[:, 2].mean() < -0.5
    assert len(mesh.vertices) == inside.sum()
    assert np.allclose(mesh.vertices[:, 2], z[inside])


def test_bad_inputs():
    with pytest.raises(IntegrationError, match="fewer than 2"):
        poisson_integrate(np.zeros((4, 4, 3)), np.zeros((4, 4), bool))
    with pytest.raises(IntegrationError, match=r"\(H, W, 3\)"):
        frankot_chellappa(np.zeros((4, 4)))
