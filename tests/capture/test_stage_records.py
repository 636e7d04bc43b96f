"""The calibration stages' typed records (capture/pipeline/stage_records.py): results stored by the
gonio before them (format 1: ``data/calibration_format1.json``, every stage's result as the quick
demo stored it, long lists cut to their first rows) still read, to the same values; what is
written reads back to the same record; a result that does not fit says which key."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from capture.pipeline.stage_records import (FORMAT, RECORDS, RESULT_KIND, GrayCardRecord, IntrinsicsRecord,
                                            PositionerRecord, RecordFormatError, TurntableRecord, read_record)
from capture.pipeline.process import ProcessError, read_calibration
from capture.plan import Step
from capture.store import ResultRecord, Store
from rig import LightTarget

OLD = json.loads((Path(__file__).parent / "data" / "calibration_format1.json").read_text())


def _stored(kind: str, result: dict) -> ResultRecord:
    return ResultRecord(id=7, category="calibration", kind=kind, created=0.0, params={}, result=result,
                        input_frames=[], code_version="", artifacts={})


def _same(a, b) -> bool:
    """Equal JSON trees, a null value the same as an absent key (format 2 writes every field,
    format 1 left some out), NaN equal to NaN (the polarization check stores NaN where it has no
    ratio)."""
    if isinstance(a, dict):
        a, b = ({k: v for k, v in x.items() if v is not None} for x in (a, b))
        return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, list):
        return isinstance(b, list) and len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    if isinstance(a, float) and isinstance(b, float):
        return a == b or (np.isnan(a) and np.isnan(b))
    return a == b


def test_every_stage_kind_of_an_old_session_has_a_record_and_reads():
    assert set(OLD) == set(RECORDS)   # the fixture holds every kind a calibration stores
    assert set(RESULT_KIND.values()) == set(RECORDS) - {"calibration_run"}
    for kind, result in OLD.items():
        record = read_record(_stored(kind, result))
        assert type(record) is RECORDS[kind]
        # format 1 to format 2 loses nothing but the prose keys: every data value is the same
        again = record.to_json()
        assert again["format"] == FORMAT
        kept = {k: v for k, v in result.items() if k not in type(record).PROSE}
        assert _same({k: v for k, v in again.items() if k != "format"}, kept), kind
        # and format 2 reads back to the same record
        assert _same(RECORDS[kind].from_json(again).to_json(), again), kind


def test_old_results_give_the_values_the_pipeline_reads():
    intr = IntrinsicsRecord.from_json(OLD["intrinsics"])
    assert intr.K.shape == (3, 3) and np.array_equal(intr.K, np.array(OLD["intrinsics"]["K"]))
    assert intr.image_size == tuple(OLD["intrinsics"]["image_size"]) == (320, 240)
    tt = TurntableRecord.from_json(OLD["turntable"])
    assert np.array_equal(tt.lab_to_camera.R, np.array(OLD["turntable"]["lab_to_camera"]["R"]))
    assert np.array_equal(tt.lab_to_camera.t_mm, np.array(OLD["turntable"]["lab_to_camera"]["t_mm"]))
    assert tt.angle_scale == OLD["turntable"]["angle_scale"]
    pos = PositionerRecord.from_json(OLD["positioner_model"])
    first = OLD["positioner_model"]["step_lights"][0]
    assert pos.step_lights[0].step == first["step"]
    assert np.array_equal(pos.step_lights[0].position_lab_mm, first["position_lab_mm"])
    card = GrayCardRecord.from_json(OLD["gray_card"])
    assert card.albedo == 0.18 and np.array_equal(card.cards[0].value_rgb, OLD["gray_card"]["cards"][0]["value_rgb"])


def test_a_result_that_does_not_fit_names_the_key():
    no_k = {k: v for k, v in OLD["intrinsics"].items() if k != "K"}
    with pytest.raises(RecordFormatError, match=r"#7 \(intrinsics\) lacks 'K'"):
        read_record(_stored("intrinsics", no_k))
    with pytest.raises(RecordFormatError, match="format 3"):
        read_record(_stored("dark", {**OLD["dark"], "format": 3}))
    # format 2 has no prose keys: an unknown one is an error, not silently dropped
    with pytest.raises(RecordFormatError, match="unknown key.*meaning"):
        GrayCardRecord.from_json({**OLD["gray_card"], "format": FORMAT})
    with pytest.raises(RecordFormatError, match=r"cards\[0\]\.value_rgb is null"):
        bad = json.loads(json.dumps(OLD["gray_card"]))
        bad["cards"][0]["value_rgb"] = None
        GrayCardRecord.from_json(bad)
    with pytest.raises(KeyError, match="metering"):
        read_record(_stored("metering", {"exposure_s": 0.1}))


def test_processing_a_session_whose_stored_result_does_not_read_says_which(tmp_path):
    store = Store(tmp_path / "st", durable=False)
    step = Step(0, "measure", "object", 0.0, LightTarget(0.0, 30.0), None, (0.01,))
    sid = store.create_session("s", plan={}, plan_hash="h", steps=[step.to_dict()]).id
    store.add_calibration(sid, "intrinsics", result={k: v for k, v in OLD["intrinsics"].items() if k != "K"})
    with pytest.raises(ProcessError, match=r"\(intrinsics\) lacks 'K'.*calibrate the session again"):
        read_calibration(store, "s")
    store.close()
