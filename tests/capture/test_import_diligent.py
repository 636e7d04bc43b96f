"""``gonio import diligent``: a DiLiGenT-layout set becomes a session; malformed sets write nothing.

The synthetic set is a Lambertian sphere rendered here under 8 known lights in DiLiGenT's frame
(x right, y up, z to the camera), so the normals read back must match the sphere's analytic
normals (flipped to OpenCV's frame) and photometric stereo on the imported images must recover
them. The real-data check reads pot1 of ``../shared/data/diligent`` and compares least squares
with the README's figure for these 8-bit crops.
"""
from __future__ import annotations

import re

import cv2
import numpy as np
import pytest
import scipy.io
from typer.testing import CliRunner

from capture.cli import app
from capture.importers import DiligentFormatError, import_diligent, read_diligent, read_imported_session
from capture.pipeline.imported import imported_facts, imported_inputs, process_imported_session
from capture.pipeline.progress import Progress
from capture.store import Store
from reconstruct.photometric_stereo import angular_error_deg, photometric_stereo

N_PX = 40
LIGHTS = np.array([[0.3, 0.2, 0.93], [-0.4, 0.1, 0.91], [0.1, -0.5, 0.86], [0.0, 0.0, 1.0],
                   [0.5, 0.5, 0.71], [-0.3, -0.3, 0.9], [0.6, -0.1, 0.79], [-0.2, 0.6, 0.77]])


def _sphere():
    """Unit normals of a sphere filling the frame, DiLiGenT frame (y up), and its mask."""
    c = (np.arange(N_PX) + 0.5) / N_PX * 2 - 1
    x, y = np.meshgrid(c, -c)
    r2 = x ** 2 + y ** 2
    mask = r2 < 0.9
    n = np.dstack([x, y, np.sqrt(np.clip(1 - r2, 0, None))])
    return np.where(mask[..., None], n, 0.0), mask


def write_set(folder, *, n_images=8):
    folder.mkdir(parents=True, exist_ok=True)
    L = LIGHTS / np.linalg.norm(LIGHTS, axis=1, keepdims=True)
    e = np.array([[1.0, 1.2, 1.5]] * len(L)) * np.linspace(0.8, 1.2, len(L))[:, None]
    n, mask = _sphere()
    albedo = np.array([0.7, 0.5, 0.3])
    names = []
    for k in range(n_images):
        shade = np.clip(n @ L[k], 0, None)[..., None] * albedo * e[k] / 2.0
        img = np.round(np.clip(shade, 0, 1) * 65535).astype(np.uint16)
        names.append(f"{k + 1:03d}.png")
        cv2.imwrite(str(folder / names[-1]), img[..., ::-1])
    (folder / "filenames.txt").write_text("\n".join(names) + "\n")
    np.savetxt(folder / "light_directions.txt", L)
    np.savetxt(folder / "light_intensities.txt", e)
    cv2.imwrite(str(folder / "mask.png"), (mask * 255).astype(np.uint8))
    scipy.io.savemat(folder / "Normal_gt.mat", {"Normal_gt": n})
    return n, mask


def test_import_round_trip_and_normals(tmp_path):
    n_true, mask = write_set(tmp_path / "ball")
    name = import_diligent(tmp_path / "ball", tmp_path / "store", hold_out_every=4)
    st = Store.open(tmp_path / "store")
    info = st.session(name)
    assert (name, info.state, info.object) == ("diligent-ball", "done", "ball")
    prov = info.plan["imported"]
    assert prov["source"] == str((tmp_path / "ball").resolve()) and len(prov["sha256"]) == 8 + 5
    assert {r.kind for r in st.results(info.id)} == {"lights_directional", "camera_orthographic"}
    data = read_imported_session(st, name)
    direct = read_diligent(tmp_path / "ball")
    assert np.array_equal(data.images, direct.images) and data.images.dtype == np.uint16
    assert data.held_out.tolist() == [False, False, False, True] * 2
    # OpenCV frame: y and z negated, the sphere faces the camera (n_z < 0)
    flip = np.array([1, -1, -1])
    assert np.allclose(data.normals_gt[mask], n_true[mask] * flip)
    assert np.allclose(data.light_directions, LIGHTS / np.linalg.norm(LIGHTS, axis=1)[:, None] * flip)
    ps = photometric_stereo(data.radiance(), data.light_directions, data.mask)
    err = angular_error_deg(ps.normals[ps.mask], data.normals_gt[ps.mask])
    assert np.median(err) < 0.1, np.median(err)  # 16-bit quantisation only


@pytest.mark.parametrize("fault, message", [
    ("missing_image", "images listed in filenames.txt are missing: 003.png"),
    ("light_count", "light_directions.txt: 7 rows of 3 numbers; expected 8 rows"),
    ("intensity_count", "light_intensities.txt: 9 rows"),
    ("mask_size", "mask.png: 30 x 40 px, the images are 40 x 40"),
    ("mask_empty", "mask.png: 0 object pixels"),
    ("mask_grey", "grey levels"),
    ("image_size", "002.png: (20, 40, 3) uint16, but 001.png is (40, 40, 3) uint16"),
    ("not_unit", "light_directions.txt: row 1 has length 2.000"),
    ("truth_shape", "Normal_gt.mat: needs a variable Normal_gt of shape (40, 40, 3)"),
])
def test_malformed_sets_write_nothing(tmp_path, fault, message):
    d = tmp_path / "ball"
    write_set(d)
    if fault == "missing_image":
        (d / "003.png").unlink()
    elif fault == "light_count":
        np.savetxt(d / "light_directions.txt", np.loadtxt(d / "light_directions.txt")[:7])
    elif fault == "intensity_count":
        e = np.loadtxt(d / "light_intensities.txt")
        np.savetxt(d / "light_intensities.txt", np.vstack([e, e[:1]]))
    elif fault == "mask_size":
        cv2.imwrite(str(d / "mask.png"), np.full((40, 30), 255, np.uint8))
    elif fault == "mask_empty":
        cv2.imwrite(str(d / "mask.png"), np.zeros((40, 40), np.uint8))
    elif fault == "mask_grey":
        cv2.imwrite(str(d / "mask.png"), np.arange(1600, dtype=np.uint8).reshape(40, 40))
    elif fault == "image_size":
        cv2.imwrite(str(d / "002.png"), np.zeros((20, 40, 3), np.uint16))
    elif fault == "not_unit":
        L = np.loadtxt(d / "light_directions.txt")
        L[0] *= 2
        np.savetxt(d / "light_directions.txt", L)
    elif fault == "truth_shape":
        scipy.io.savemat(d / "Normal_gt.mat", {"Normal_gt": np.zeros((40, 40))})
    with pytest.raises(DiligentFormatError) as exc:
        import_diligent(d, tmp_path / "store")
    assert message in str(exc.value)
    assert not (tmp_path / "store").exists()
    # the CLI: exit status 2, the same message, still nothing written
    r = CliRunner().invoke(app, ["import", "diligent", str(d), "--store", str(tmp_path / "store")])
    assert r.exit_code == 2 and message.split(":")[0] in r.output, r.output
    assert not (tmp_path / "store").exists()


def test_existing_session_is_refused_untouched(tmp_path):
    write_set(tmp_path / "ball")
    import_diligent(tmp_path / "ball", tmp_path / "store")
    st = Store.open(tmp_path / "store")
    before = st.progress(st.session("diligent-ball").id)
    r = CliRunner().invoke(app, ["import", "diligent", str(tmp_path / "ball"),
                                 "--store", str(tmp_path / "store")])
    assert r.exit_code == 2 and "already exists" in r.output
    assert st.progress(st.session("diligent-ball").id) == before and len(st.sessions()) == 1


def test_process_runs_on_an_imported_set_and_says_what_it_skips(tmp_path):
    """``gonio process`` on an imported set: no mesh asked for, every calibration stage listed as
    skipped with its reason, sharing and passive skipped (no polarization, no probe), the
    Lambertian reference relights the held-out lights of a Lambertian sphere to within the
    16-bit quantisation, and results are stored with the frames they came from; the HTML report
    says all of it and draws the normals' error against the truth."""
    _, mask = write_set(tmp_path / "ball")
    import_diligent(tmp_path / "ball", tmp_path / "store")
    r = CliRunner().invoke(app, ["process", "diligent-ball", "--store", str(tmp_path / "store"),
                                 "--methods", "lambertian,sharing,passive", "--json", "-q"])
    assert r.exit_code == 0, r.output
    import json
    out = json.loads(r.output[r.output.index("{"):])
    stages = {c["stage"]: c for c in out["calibration"]}
    assert stages["turntable"]["status"] == "skipped" and "no turntable" in stages["turntable"]["reason"]
    assert stages["lights_directional"]["status"] == "stored"
    methods = {m["method"]: m for m in out["methods"]}
    assert methods["sharing"]["status"] == "skipped" and "polariz" in methods["sharing"]["reason"]
    assert methods["passive"]["status"] == "skipped" and "probe" in methods["passive"]["reason"]
    assert methods["lambertian"]["status"] == "ok"
    assert methods["lambertian"]["figures"]["held_out_rel_rms"] < 2e-3
    # least squares is biased where a training light grazes the rim (attached shadow clipped to
    # 0); the robust variant drops those lights
    assert out["inputs"]["normal_error_robust_deg"] < 0.2
    assert out["inputs"]["normal_error_robust_deg"] < out["inputs"]["normal_error_least_squares_deg"] < 2
    st = Store.open(tmp_path / "store")
    info = st.session("diligent-ball")
    (res,) = st.results(info.id, "reconstruction")
    assert len(res.input_frames) == 10 and "model.npz" in res.artifacts
    # the HTML report (issue 25): what was imported, the skipped stages with their reasons, the
    # normals' error maps, held-out error per method, time per stage
    report = tmp_path / "diligent-ball-report.html"
    assert out["report"] == str(report)
    text = report.read_text()
    for words in ("What was imported", "<td>ball</td>", "<td>8</td>", "<td>40 × 40</td>", "<td>1124</td>",
                  "no turntable: one view of the object", "Normals against the ground truth",
                  "alt=\"normal error maps\"", "alt=\"light directions\"", "6. Timings"):
        assert words in text, words
    held = methods["lambertian"]["figures"]["held_out_rel_rms"]
    assert f"<td>lambertian</td><td>ok</td><td>{held:.4g}</td>" in text
    assert "passive: passive" not in text and "sharing</td><td>skipped" in text
    assert not re.search(r'(href|src)="(?!data:)', text)    # self-contained
    # the maps are the stated figures, drawn: their means are the inputs' mean errors
    facts = imported_facts(st, "diligent-ball", imported_inputs(st, "diligent-ball"), [])
    assert set(facts.normal_errors) == {"least squares", "robust least squares"}
    assert np.nanmean(facts.normal_errors["least squares"]) == pytest.approx(
        out["inputs"]["normal_error_least_squares_deg"], rel=1e-9)
    assert np.nanmean(facts.normal_errors["robust least squares"]) == pytest.approx(
        out["inputs"]["normal_error_robust_deg"], rel=1e-9)
    scored = np.isfinite(facts.normal_errors["least squares"])   # the texels' pixels, inside the mask
    assert np.all(mask[scored]) and scored.sum() == out["inputs"]["texels"]
    # held-out relighting pictures: the photographs under the most frontal and the most oblique
    # held-out light (every 4th of 8: lights 4, straight on, and 8, 39 deg off), the prediction
    # drawn at exactly the fitted pixels that light reaches (one per held-out sample), and within the 16-bit quantisation
    # of the photograph there (a Lambertian fit of a Lambertian ball)
    import io
    with np.load(io.BytesIO(st.read_object(res.artifacts["report.npz"]))) as z:
        pics = {k: z[k] for k in z.files}
    L = LIGHTS / np.linalg.norm(LIGHTS, axis=1, keepdims=True)
    np.testing.assert_allclose(pics["heldout_lights"], [[3, 0.0], [7, np.degrees(np.arccos(L[7, 2]))]], atol=1e-6)
    data = read_imported_session(st, "diligent-ball")
    for suffix, k in (("", 3), ("_2", 7)):
        photo, pred = pics["heldout_captured" + suffix], pics["heldout_predicted" + suffix]
        np.testing.assert_array_equal(photo, data.radiance([k])[0])
        drawn = np.isfinite(pred).all(axis=2)
        held = imported_inputs(st, "diligent-ball").held
        assert np.all(mask[drawn]) and drawn.sum() == np.sum(held.view == k) > 300
        assert np.abs(pred[drawn] - photo[drawn]).max() < 2e-3 * photo[drawn].max()
    assert text.count('alt="held-out capture, prediction and error"') == 2
    assert "held-out light 8 (39° from the view axis)" in text


def test_imported_report_draws_lenschs_fitted_normals(tmp_path):
    """Lensch's fitted normals (60 texels of the ball, for time) become the report's third error
    map, drawn at exactly the pixels it fitted, whose mean is its stated normal error."""
    n_true, mask = write_set(tmp_path / "ball")
    import_diligent(tmp_path / "ball", tmp_path / "store")
    st = Store.open(tmp_path / "store")
    events = []
    rep = process_imported_session(st, "diligent-ball", methods=["lensch"], max_texels=60,
                                   report_path=tmp_path / "r.html", progress=events.append)
    (lensch,) = rep.methods
    assert lensch.status == "ok", lensch.reason
    # the pipeline's one progress protocol (what `gonio process`'s bar takes), counted to the end
    assert events and all(isinstance(e, Progress) and e.stage == "lensch" for e in events)
    assert events[-1].done == events[-1].total
    facts = imported_facts(st, "diligent-ball", imported_inputs(st, "diligent-ball", max_texels=60), rep.methods)
    drawn = facts.normal_errors["lensch (fitted)"]
    assert np.isfinite(drawn).sum() == 60 and np.all(mask[np.isfinite(drawn)])
    assert np.nanmean(drawn) == pytest.approx(lensch.figures["normal_error_deg"], rel=1e-6)
    text = rep.report_path.read_text()
    assert "60 of the 1124 mask pixels" in text and "<h3>1. lensch</h3>" in text
    assert rep.report_path.with_suffix(".json").is_file() and "report" in rep.timings
