"""The methods over texel blocks (issue 21): every figure computed block by block from the stored
lumitexel arrays must equal the one computed on the gathered arrays to 1e-9 relative, whatever
the block size. A small synthetic lumitexel set (Lensch Sec. 11's Phong materials, not a
capture) is written in the pipeline's Zarr layout and read back block by block.
"""
from __future__ import annotations

import dataclasses
import pickle
from types import SimpleNamespace

import numpy as np
import pytest

from capture.pipeline.block_scoring import ErrorSums, score_blocks
from capture.pipeline.lumitexel_arrays import store_lumitexels
from capture.pipeline.methods import CAPTURED_LENSCH, BlockRoute, _surface_xy, fit_method
from capture.pipeline.stored_blocks import StoredBlocks
from reconstruct.lensch import ArrayBlocks, fit_svbrdf_blocks, fit_svbrdf_lumitexels
from reconstruct.lumitexels import Lumitexels, pixel_neighbours
from reconstruct.metrics import relative_rms, trimmed_relative_rms
from reconstruct.sharing import SharingError, fit_spatial, fit_spatial_blocks, reframe
from sims.reflectance_samples import paper_phong_materials, synthetic_samples

N_TRAIN = 11   # views 11.. (of up to 15 samples a texel) are held out
BLOCKS = (37, 1000)


def synthetic_lumitexels(n_texels: int = 240, rng: int = 3) -> Lumitexels:
    """Texels of three materials, each sample on its own view (its rank within its texel)."""
    s = synthetic_samples(paper_phong_materials(exponents=(10.0, 40.0, 80.0)), n_texels, rng=rng)
    counts = np.bincount(s.texel, minlength=n_texels)
    view = np.arange(len(s.texel)) - np.repeat(np.cumsum(counts) - counts, counts)
    g = np.random.default_rng(rng)
    f32 = lambda a: np.asarray(a, np.float32)   # noqa: E731  (the stored layout's precision)
    return Lumitexels(position=g.normal(size=(n_texels, 3)) * 50, normal=s.normal, best_view=np.zeros(n_texels, np.int32),
                      pixel=f32(g.uniform(0, 100, (n_texels, 2))), texel=s.texel, view=view.astype(np.int32),
                      wi=f32(s.wi), wo=f32(s.wo), reflectance=f32(s.reflectance), weight=np.ones(len(s.texel), np.float32))


@pytest.fixture(scope="module")
def stored(tmp_path_factory):
    lt = synthetic_lumitexels()
    root = tmp_path_factory.mktemp("blocks")
    return {b: store_lumitexels(lt, N_TRAIN, root / f"b{b}.zarr", block_texels=b) for b in BLOCKS}


def test_error_sums_over_any_split_equal_the_metrics():
    g = np.random.default_rng(0)
    p, m = g.normal(size=(1001, 3)), g.normal(size=(1001, 3))
    sums = ErrorSums()
    for part in np.array_split(np.arange(1001), [3, 400, 401, 950]):
        sums.add(p[part], m[part])
    assert sums.relative_rms == pytest.approx(relative_rms(p, m), rel=1e-12)
    assert sums.trimmed_relative_rms() == pytest.approx(trimmed_relative_rms(p, m), rel=1e-12)
    assert np.isnan(ErrorSums().relative_rms)
    with pytest.raises(ValueError, match="shape"):
        sums.add(p[:3], m[:2])


#: the pipeline's Lensch for captured sessions (its relabelling is a per-block task too), one normal round
LENSCH = {"fit_normals": True, "normal_rounds": 1, **CAPTURED_LENSCH}


@pytest.fixture(scope="module")
def whole_lensch(stored):
    """Lensch on the gathered training lumitexels (the pipeline's ``_lensch``, one normal round)."""
    return fit_svbrdf_lumitexels(stored[BLOCKS[0]].gather()[0], rng=0, **LENSCH)


@pytest.fixture(scope="module")
def fitted(stored, whole_lensch):
    """Per-sample predictors of the methods fitted on the gathered training lumitexels."""
    return {"lambertian": fit_method("lambertian", stored[BLOCKS[0]].gather()[0], None).predict_samples,
            "lensch": whole_lensch.predict}


@pytest.mark.parametrize("method", ["lambertian", "lensch"])
def test_held_out_scores_over_blocks_equal_the_gathered_ones(stored, fitted, method):
    train, held = stored[BLOCKS[0]].gather()
    assert held.n_samples > 50 and len(stored[BLOCKS[0]].blocks) == 7
    predict = fitted[method]
    p_train, p_held = (predict(lt.texel, lt.wi, lt.wo) for lt in (train, held))
    want = {"train": relative_rms(p_train, train.reflectance), "held": relative_rms(p_held, held.reflectance),
            "trimmed": trimmed_relative_rms(p_held, held.reflectance)}
    for b in BLOCKS:
        s = score_blocks(predict, stored[b], max_texels=None if b == BLOCKS[0] else 29)
        got = {"train": s.training.relative_rms, "held": s.held_out.relative_rms,
               "trimmed": s.held_out.trimmed_relative_rms()}
        assert s.held_out.count == held.n_samples and s.training.count == train.n_samples
        for k in want:
            assert got[k] == pytest.approx(want[k], rel=1e-9), (b, k)


def _as_on_a_cluster(fn, args):
    """An executor's map as a cluster runs it: every task and result pickled, the tasks run in
    reverse order, the results returned in order."""
    out = [pickle.loads(pickle.dumps(fn(*pickle.loads(pickle.dumps(a))))) for a in reversed(args)]
    return out[::-1]


def test_lambertian_over_blocks_equals_the_in_memory_fit(stored):
    train, held = stored[BLOCKS[0]].gather()
    whole = fit_method("lambertian", train, None)
    # the chunks, and a chunk of all texels cut into parts of 50 (blocks within a chunk)
    for blocks in (StoredBlocks(stored[BLOCKS[0]]), StoredBlocks(stored[BLOCKS[1]], max_texels=50)):
        assert blocks.n_texels == train.n_texels and blocks.ranges[-1][1] == train.n_texels
        fit = fit_method("lambertian", train, None, route=BlockRoute(blocks, _as_on_a_cluster))
        np.testing.assert_allclose(fit.predict(held), whole.predict(held), rtol=1e-12, atol=0)


def test_a_gathered_texel_subsample_equals_the_subset_of_the_gathered_arrays(stored):
    """The export's subsample (``gonio process`` beyond its memory limit): the picked texels with
    all their training and held-out samples, renumbered from 0, read in parts of any size."""
    train, held = stored[BLOCKS[0]].gather()
    pick = np.sort(np.random.default_rng(1).choice(train.n_texels, 50, replace=False))
    for arrays, part in ((stored[BLOCKS[0]], None), (stored[BLOCKS[1]], 29)):
        got = arrays.gather(pick, max_texels=part)
        for mine, whole in zip(got, (train, held)):
            want = whole.subset(pick)
            assert mine.n_texels == 50 and mine.n_samples == want.n_samples > 0
            for name in ("position", "normal", "texel", "view", "wi", "wo", "reflectance"):
                np.testing.assert_array_equal(getattr(mine, name), getattr(want, name), err_msg=name)


class _Counting(StoredBlocks):
    """Stored blocks that count the texels gathered for the global steps."""

    gathered = 0

    def gather(self, texels):
        self.gathered = max(self.gathered, len(texels))
        return super().gather(texels)


def test_lensch_over_blocks_of_any_size_equals_the_whole_array_fit(stored, whole_lensch):
    train, _ = stored[BLOCKS[0]].gather()
    whole = whole_lensch
    assert whole.n_materials >= 2 and whole.discovery_texels == train.n_texels
    for b in BLOCKS:
        blocks = StoredBlocks(stored[b])
        assert len(blocks.ranges) == len(stored[b].blocks) and blocks.n_texels == train.n_texels
        fit = fit_svbrdf_blocks(blocks, normals=train.normal, neighbours=pixel_neighbours(train), rng=0,
                                map_blocks=_as_on_a_cluster, **LENSCH)
        np.testing.assert_array_equal(fit.labels, whole.labels)
        for name in ("weights", "normals", "lobe_variance"):
            np.testing.assert_allclose(getattr(fit, name), getattr(whole, name), rtol=1e-9, atol=1e-12, err_msg=name)
        for k, v in whole.rms.items():
            assert (v is None and fit.rms[k] is None) or fit.rms[k] == pytest.approx(v, rel=1e-9), k
        np.testing.assert_array_equal(fit.no_highlight, whole.no_highlight)


def test_lensch_material_discovery_honours_and_states_its_subsample(stored):
    blocks = _Counting(stored[BLOCKS[0]])
    train, held = stored[BLOCKS[0]].gather()
    fit = fit_svbrdf_blocks(blocks, normals=train.normal, neighbours=pixel_neighbours(train), rng=0,
                            discovery_texels=160, **LENSCH)
    assert blocks.gathered == 160 == fit.discovery_texels < train.n_texels
    assert f"materials found on 160 of {train.n_texels} texels" in fit.report()
    # every texel still labelled, projected and scored: the materials of 160 texels serve all 240
    assert len(fit.labels) == len(fit.weights) == train.n_texels and fit.n_materials >= 2
    assert relative_rms(fit.predict(held.texel, held.wi, held.wo), held.reflectance) < 0.2


# -- reflectance sharing (Zickler et al.): per-texel steps per block, the RBFs on a subsample --------
SHARING = {"max_centers": 120, "fit_normals": True, "m_xy": 1.0}


@pytest.fixture(scope="module")
def separated(tmp_path_factory):
    """The synthetic texels with polarization-separated parts (diffuse = rho_d / pi cos theta_i,
    noisy; specular the rest), seen about mesh normals tilted 8 deg from the true ones (so the
    normal refit has work), stored in chunks of 37 and of all texels."""
    lt = synthetic_lumitexels()
    g = np.random.default_rng(7)
    tilt = np.radians(8.0)
    phi = g.uniform(0, 2 * np.pi, lt.n_texels)
    mesh = np.stack([np.sin(tilt) * np.cos(phi), np.sin(tilt) * np.sin(phi), np.full(lt.n_texels, np.cos(tilt))], 1)
    wi, wo = reframe(lt.texel, mesh, lt.wi, lt.wo)
    diffuse = np.asarray([0.15, 0.3, 0.1]) / np.pi * lt.wi[:, 2:3] * (1 + g.uniform(-0.05, 0.05, (lt.n_samples, 3)))
    f32 = lambda a: np.asarray(a, np.float32)   # noqa: E731
    lt = dataclasses.replace(lt, wi=f32(wi), wo=f32(wo), diffuse=f32(diffuse),
                             specular=f32(np.maximum(lt.reflectance - diffuse, 0.0)))
    root = tmp_path_factory.mktemp("separated")
    return {b: store_lumitexels(lt, N_TRAIN, root / f"b{b}.zarr", block_texels=b) for b in BLOCKS}


def _sharing_prediction(fit, lt):
    return fit.predict(lt.texel, np.asarray(lt.wi, float), np.asarray(lt.wo, float))


def test_sharing_over_blocks_of_any_size_equals_the_whole_array_fit(separated):
    """The per-texel steps (normal refit, albedo) over blocks of 37 and of all texels (parts of
    50), pickled and run in reverse order as on a cluster, and the RBFs on a 150-texel subsample:
    the whole-array fit's (one block, the same subsample) to 1e-9; with every texel, today's
    in-memory ``fit_spatial`` on the gathered samples."""
    train, held = separated[BLOCKS[0]].gather()
    xy = _surface_xy(train.position)
    whole_blocks = ArrayBlocks(train.texel, train.wi, train.wo, train.reflectance, train.weight,
                               n_texels=train.n_texels, block_texels=train.n_texels,
                               diffuse=train.diffuse, specular=train.specular)
    cos = np.maximum(train.wi[:, 2:3], 1e-6)
    today = fit_spatial(xy[train.texel], train.wi, train.wo, None, texel=train.texel, diffuse=train.diffuse / cos,
                        specular=train.specular / cos, rng=0, **SHARING)
    assert today.normals.fitted.sum() > train.n_texels // 2   # the tilted mesh normals are refitted
    wholes = {}
    for fit_texels in (150, train.n_texels):
        whole = wholes[fit_texels] = fit_spatial_blocks(whole_blocks, xy, fit_texels=fit_texels, rng=0, **SHARING)
        assert whole.fit_texels == fit_texels and f"RBFs fitted on {fit_texels} of 240 texels" in whole.report()
        want = _sharing_prediction(today if fit_texels == train.n_texels else whole, held)
        for blocks, n_blocks in ((StoredBlocks(separated[BLOCKS[0]]), 7), (StoredBlocks(separated[BLOCKS[1]], max_texels=50), 5)):
            assert len(blocks.ranges) == n_blocks
            fit = fit_spatial_blocks(blocks, xy, fit_texels=fit_texels, rng=0, map_blocks=_as_on_a_cluster, **SHARING)
            np.testing.assert_allclose(_sharing_prediction(fit, held), want, rtol=1e-9, atol=1e-12)
            # the per-texel steps do not depend on the subsample
            np.testing.assert_allclose(fit.albedo, today.albedo, rtol=1e-9, atol=1e-12)
            np.testing.assert_allclose(fit.normals.normals, today.normals.normals, rtol=1e-9, atol=1e-12)
            assert (fit.n_used, fit.n_dropped) == (today.n_used, today.n_dropped)
    # the subsample is honoured: the RBFs saw 150 texels' samples, and still predict the other 90
    sub, every = wholes[150].fits["specular"], today.fits["specular"]
    assert len(wholes[train.n_texels].fits["specular"].points) == len(every.points)
    assert len(sub.points) < 0.7 * len(every.points)
    assert relative_rms(_sharing_prediction(wholes[150], held), held.reflectance) < 1.5 * relative_rms(
        _sharing_prediction(today, held), held.reflectance)


def test_sharing_through_the_block_route_equals_the_in_memory_method(separated):
    train, held = separated[BLOCKS[0]].gather()
    inputs = SimpleNamespace()   # sharing reads only the lumitexels
    whole = fit_method("sharing", train, inputs, **SHARING)
    fit = fit_method("sharing", train, inputs, route=BlockRoute(StoredBlocks(separated[BLOCKS[0]]), _as_on_a_cluster),
                     **SHARING)
    np.testing.assert_allclose(fit.predict(held), whole.predict(held), rtol=1e-9, atol=1e-12)
    assert whole.figures["rbf_texels"] == "RBFs fitted on 240 of 240 texels" == fit.figures["rbf_texels"]
    with pytest.raises(SharingError, match="fit_texels must be a positive integer"):
        fit_method("sharing", train, inputs, fit_texels=0)
