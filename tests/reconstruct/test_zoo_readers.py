"""The test zoo's readers and lobes against values published with the data and formats."""
from __future__ import annotations

import numpy as np
import pytest

from reconstruct.brdf import TabulatedIsotropic, directional_albedo
from reconstruct.brdf.lobes import AshikhminShirley, RetroReflective, Sheen
from reconstruct.brdf.nbrdf import load_nbrdf
from reconstruct.brdf.rgl import read_rgl, read_tensor_file
from reconstruct.brdf.zoo import measured_files, measured_zoo
from reconstruct.coords import from_halfway_difference
from reconstruct.merl import MERL_SCALE, write_merl
from reconstruct.passive_prior import learn_prior

pytestmark = pytest.mark.realdata


def _dir(theta_deg, phi_deg):
    t, p = np.radians(theta_deg), np.radians(phi_deg)
    return np.array([[np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)]])


# the check values of ../shared/data/brdfs/README.md: material, wi, wo (theta, phi deg), f RGB
NBRDF_CHECKS = [
    ("white-paint", (30, 0), (30, 180), (0.284377, 0.278556, 0.278549)),
    ("white-paint", (60, 0), (10, 90), (0.105041, 0.101528, 0.0968929)),
    ("gold-metallic-paint", (30, 0), (30, 180), (0.549726, 0.390732, 0.115269)),
    ("gold-metallic-paint", (45, 0), (20, 180), (0.139461, 0.0972976, 0.0339058)),
    ("blue-metallic-paint", (10, 0), (70, 200), (0.00660362, 0.00535848, 0.0123882)),
]


@pytest.fixture(scope="module")
def brdfs(shared_data):
    return shared_data / "brdfs"


@pytest.mark.parametrize("name, wi, wo, expected", NBRDF_CHECKS)
def test_nbrdf_matches_the_published_check_values(brdfs, name, wi, wo, expected):
    model = load_nbrdf(brdfs / "nbrdf-merl" / f"{name}.npz", reciprocal=False)
    np.testing.assert_allclose(model.evaluate(_dir(*wi), _dir(*wo))[0], expected, rtol=2e-5)


def test_nbrdf_reciprocal_by_default_and_bad_files_named(brdfs, tmp_path):
    model = load_nbrdf(brdfs / "nbrdf-merl" / "white-paint.npz")
    wi, wo = _dir(60, 0), _dir(10, 90)
    np.testing.assert_array_equal(model.evaluate(wi, wo), model.evaluate(wo, wi))
    raw = load_nbrdf(brdfs / "nbrdf-merl" / "white-paint.npz", reciprocal=False)
    assert model.evaluate(wi, wo)[0, 0] == pytest.approx(
        0.5 * (raw.evaluate(wi, wo) + raw.evaluate(wo, wi))[0, 0], rel=1e-12)
    np.savez(tmp_path / "bad.npz", W1=np.zeros((6, 21)))
    with pytest.raises(ValueError, match="bad.npz: not an NBRDF file, missing arrays"):
        load_nbrdf(tmp_path / "bad.npz")


@pytest.mark.parametrize("name, expected", [
    ("colodur_napoli_4f_rgb", (0.241, 0.057, 0.061)),   # matte wall paint
    ("vch_golden_yellow_rgb", (0.523, 0.311, 0.032)),   # glossy vinyl film
])
def test_rgl_albedo_matches_the_independent_evaluator(brdfs, name, expected):
    """README: directional albedo at normal view of the two files, from an independent
    evaluator (we get 0.240 0.057 0.061 and 0.518 0.308 0.032 with 100,000 samples)."""
    model = read_rgl(brdfs / "rgl" / f"{name}.bsdf")
    albedo, err = directional_albedo(model, [0.0, 0.0, 1.0], 40_000, guide_alpha=0.05)
    assert np.all(err < 0.01 * np.asarray(expected) + 1e-3)
    np.testing.assert_allclose(albedo[0], expected, rtol=0.04)


def test_tensor_file_errors_name_the_file_and_field(brdfs, tmp_path):
    good = (brdfs / "rgl" / "colodur_napoli_4f_rgb.bsdf").read_bytes()
    fields = read_tensor_file(brdfs / "rgl" / "colodur_napoli_4f_rgb.bsdf")
    assert fields["vndf"].shape[2:] == (128, 128) and fields["rgb"].shape[2] == 3
    (tmp_path / "magic.bsdf").write_bytes(b"tensor_filX\x00" + good[12:])
    with pytest.raises(ValueError, match="magic.bsdf: not a tensor_file"):
        read_rgl(tmp_path / "magic.bsdf")
    (tmp_path / "cut.bsdf").write_bytes(good[:200_000])
    with pytest.raises(ValueError, match="cut.bsdf: field '.*' .* runs past the end"):
        read_rgl(tmp_path / "cut.bsdf")


def test_merl_binary_is_a_zoo_member_and_a_prior_entry(brdfs, tmp_path):
    """A MERL-layout table of an NBRDF (trained on MERL tables with the published channel
    scales) read back through the zoo gives the network's values at the nodes, and enters a
    prior library like the other materials."""
    source = load_nbrdf(brdfs / "nbrdf-merl" / "white-paint.npz")
    table = TabulatedIsotropic.from_brdf(source, (12, 12, 24))
    write_merl(tmp_path / "white.binary", table)
    stored = np.fromfile(tmp_path / "white.binary", "<f8", offset=12).reshape(3, -1)
    ok = np.isfinite(table.table.reshape(-1, 3)).all(axis=1)
    np.testing.assert_allclose(stored[:, ok].T * MERL_SCALE, table.table.reshape(-1, 3)[ok])
    assert "merl-binary/white" in measured_files(tmp_path)
    merl = measured_zoo(tmp_path)["merl-binary/white"]
    th, td, pd = (a.ravel() for a in np.meshgrid(*table.node_angles(), indexing="ij"))
    wi, wo = from_halfway_difference(th, 0.0, td, pd)
    up = (wi[:, 2] > 0.05) & (wo[:, 2] > 0.05)
    # the network runs in float32 (sgemm): its sums depend on the batch's size and the CPU's
    # kernels, and the table's nodes were evaluated in another batch (1.1e-6 apart measured on
    # an AMD EPYC, 2026-11-27; float32 resolution 6e-8)
    np.testing.assert_allclose(merl.evaluate(wi[up], wo[up]), source.evaluate(wi[up], wo[up]),
                               rtol=1e-5)
    prior = learn_prior([merl, source], (8, 8))
    assert prior.n_brdfs == 2 and np.all(prior.var_s > 0)


def test_zoo_lobes_are_reciprocal_and_conserve_energy():
    rng = np.random.default_rng(1)
    wi, wo = rng.normal(size=(2, 500, 3))
    wi[:, 2], wo[:, 2] = np.abs(wi[:, 2]), np.abs(wo[:, 2])
    wi /= np.linalg.norm(wi, axis=1, keepdims=True)
    wo /= np.linalg.norm(wo, axis=1, keepdims=True)
    for model in (AshikhminShirley(0.3, 0.05, 1000.0), RetroReflective(), Sheen()):
        np.testing.assert_allclose(model.evaluate(wi, wo), model.evaluate(wo, wi), rtol=1e-12)
    # Ashikhmin-Shirley: the specular lobe's albedo at normal incidence is ~Rs (their Eq. 4 is
    # normalised for it); the whole model stays below 1 at a 60 degree view
    spec = AshikhminShirley(0.0, 0.05, 1000.0)
    a0, e0 = directional_albedo(spec, [0.0, 0.0, 1.0], 40_000, guide_alpha=0.03)
    assert abs(a0[0, 0] - 0.05) < 0.005 + 3 * e0[0, 0]
    a60, _ = directional_albedo(AshikhminShirley(0.8, 0.05, 1000.0),
                                [np.sin(np.radians(60)), 0.0, np.cos(np.radians(60))], 40_000,
                                guide_alpha=0.03)
    assert np.all(a60 < 1.0)
    retro = RetroReflective(kd=0.5, b0=1.5, h=0.05)
    w = _dir(40, 30)  # the surge's peak at g = 0 and its value at g = 2 theta_d = 2 atan(h)
    assert retro.evaluate(w, w)[0, 0] == pytest.approx(0.5 / np.pi * 2.5)
    wo = _dir(40 - 2 * np.degrees(np.arctan(0.05)), 30)
    assert retro.evaluate(w, wo)[0, 0] == pytest.approx(0.5 / np.pi * 1.75)
