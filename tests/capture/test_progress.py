"""The pipeline's one progress protocol: typed events from the stage clock and the adapters."""
from __future__ import annotations

from capture.pipeline.progress import Progress, counter
from capture.pipeline.run import ProcessReport, _Clock


def test_counter_adapts_done_total_callbacks_and_is_none_without_a_sink():
    got = []
    tick = counter(got.append, "lensch")
    tick(3, 7)
    assert got == [Progress("lensch", 3, 7)]
    assert counter(None, "lensch") is None


def test_each_stage_is_announced_and_timed_even_when_it_raises():
    got, rep = [], ProcessReport("s")
    clock = _Clock(rep, got.append)
    with clock.stage("inputs"):
        pass
    try:
        with clock.stage("lensch"):
            raise ValueError("boom")
    except ValueError:
        pass
    assert got == [Progress("inputs", 0, 1), Progress("lensch", 0, 1)]
    assert set(rep.timings) == {"inputs", "lensch"} and all(t >= 0 for t in rep.timings.values())
