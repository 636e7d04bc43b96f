"""The methods' per-block results in Zarr (issue 21): a block-route run interrupted after some
block tasks resumes from the stored results, computing only the missing blocks, and ends with the
same fit and the same stored arrays as an uninterrupted run (bit for bit). The quick-demo-sized
synthetic lumitexels of :mod:`test_block_methods` (Lensch Sec. 11's Phong materials), stored in
the pipeline's Zarr layout.
"""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import zarr

from capture.pipeline.block_results import BlockResults, read_result, write_result
from capture.pipeline.lumitexel_arrays import store_lumitexels
from capture.pipeline.methods import BlockRoute, fit_method
from capture.pipeline.stored_blocks import StoredBlocks
from reconstruct.lensch.svbrdf import _block_stats
from test_block_methods import N_TRAIN, synthetic_lumitexels

LENSCH = {"normal_rounds": 1}
BLOCK = 80   # 3 blocks of the 240 texels


class Interrupted(Exception):
    """Stands for the SIGKILL of ``gonio process`` between two block tasks."""


def _serial(limit: int | None = None):
    """An executor's ``map`` that runs ``limit`` tasks (all: None), then stops the run."""
    left = [limit]

    def run(fn, args):
        out = []
        for a in args:
            if left[0] == 0:
                raise Interrupted
            out.append(fn(*a))
            left[0] = None if left[0] is None else left[0] - 1
        return out
    return run


def _lensch(arrays, run):
    train, _ = arrays.gather()
    blocks = StoredBlocks(arrays, BLOCK)
    results = BlockResults(blocks, {"method": "lensch", "options": LENSCH, "rng": 0})
    fit = fit_method("lensch", train, None, rng=0, route=BlockRoute(blocks, results.map(run)), **LENSCH)
    return fit, results


def _stored(results: BlockResults) -> dict[str, dict[str, np.ndarray]]:
    """Every stored task's arrays, by task key."""
    group = zarr.open_group(str(results.group.path), mode="r")
    keys = [p.name for p in (results.group.path / "done").iterdir()]
    return {key: {name: a[...] for name, a in group[key].arrays()} for key in keys}


@pytest.fixture(scope="module")
def lumitexels():
    return synthetic_lumitexels()


def test_an_interrupted_lensch_run_resumes_from_the_stored_blocks(tmp_path, lumitexels):
    whole, first = _lensch(store_lumitexels(lumitexels, N_TRAIN, tmp_path / "a" / "lumitexels.zarr", block_texels=BLOCK),
                           _serial())
    n_tasks = first.computed
    assert first.reused == 0 and n_tasks > 5 * 3   # 3 blocks, a pass over them per step

    arrays = store_lumitexels(lumitexels, N_TRAIN, tmp_path / "b" / "lumitexels.zarr", block_texels=BLOCK)
    stopped = n_tasks // 2 + 3   # in the middle of a pass
    with pytest.raises(Interrupted):
        _lensch(arrays, _serial(stopped))
    resumed, again = _lensch(arrays, _serial())
    assert (again.reused, again.computed) == (stopped, n_tasks - stopped)   # only the missing blocks

    np.testing.assert_array_equal(resumed.arrays["labels"], whole.arrays["labels"])
    for name in ("weights", "normals"):
        np.testing.assert_array_equal(resumed.arrays[name], whole.arrays[name], err_msg=name)
    assert resumed.figures == whole.figures
    held = arrays.gather()[1]
    np.testing.assert_array_equal(resumed.predict(held), whole.predict(held))
    a, b = _stored(first), _stored(again)
    assert a.keys() == b.keys() and len(a) == n_tasks
    for key in a:
        assert a[key].keys() == b[key].keys()
        for name in a[key]:
            np.testing.assert_array_equal(a[key][name], b[key][name], err_msg=f"{key}/{name}")

    # a re-run computes nothing; other options are other tasks, never the stored results
    _, third = _lensch(arrays, _serial(0))
    assert (third.reused, third.computed) == (n_tasks, 0)
    blocks = StoredBlocks(arrays, BLOCK)
    same = BlockResults(blocks, {"method": "lensch", "options": LENSCH, "rng": 0})
    other = BlockResults(blocks, {"method": "lensch", "options": {"normal_rounds": 2}, "rng": 0})
    assert same.group.done(same.key(_block_stats, (blocks, 0)))
    assert not other.group.done(other.key(_block_stats, (blocks, 0)))

    # a finished run keeps what it read; a run with other options makes the first run's stale
    assert third.prune() == 0 and len(_stored(third)) == n_tasks
    other.map(_serial())(_block_stats, [(blocks, 0)])
    assert other.prune() == n_tasks
    assert set(_stored(other)) == other.used and len(other.used) == 1
    assert sorted(p.name for p in other.group.path.iterdir() if p.name.startswith("lensch-")) == sorted(other.used)


@dataclasses.dataclass
class _Sums:
    counts: np.ndarray
    sse: float


def test_a_stored_result_reads_back_as_returned(tmp_path):
    result = (np.arange(6, dtype=np.int32).reshape(2, 3), np.float64(0.1), 3, 2.5, True, None,
              np.zeros((0, 3)), [np.float32(1.5)], {"sums": _Sums(np.array([1, 2]), 1e-300)})
    write_result(tmp_path, "k", result)
    back = read_result(tmp_path, "k")
    assert type(back) is tuple and len(back) == len(result)
    np.testing.assert_array_equal(back[0], result[0])
    assert back[0].dtype == np.int32 and type(back[1]) is np.float64 and back[1] == 0.1
    assert [type(v) for v in back[2:5]] == [int, float, bool] and back[2:6] == (3, 2.5, True, None)
    assert back[6].shape == (0, 3) and type(back[7]) is list and type(back[7][0]) is np.float32
    assert isinstance(back[8]["sums"], _Sums) and back[8]["sums"].sse == 1e-300
    with pytest.raises(TypeError, match="set at r.0"):
        write_result(tmp_path, "bad", ({1, 2},))
