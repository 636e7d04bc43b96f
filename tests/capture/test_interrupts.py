"""Ctrl-C in gonio's long commands (issue 19 #12): exit status 3, one line ``interrupted; ...``
naming the command that continues, nothing stored lost, and the same command then finishing.

A real subprocess sent SIGINT twice is in ``test_process.py`` (``gonio process``) and
``test_safety_rig.py`` (``gonio capture run``); here each command's interrupt is a
KeyboardInterrupt raised inside its work (what the first SIGINT does), in-process.
"""
from __future__ import annotations

import shlex

import pytest
from typer.testing import CliRunner

from capture.cli import app
from capture.store import Store
from test_import_diligent import write_set

cli = CliRunner()


def _said(r) -> str:
    return " ".join(r.output.split())


def _interrupt(*args, **kwargs):
    raise KeyboardInterrupt


def test_an_import_interrupted_mid_way_keeps_its_files_and_the_same_command_finishes_it(tmp_path, monkeypatch):
    write_set(tmp_path / "ball")
    store = tmp_path / "store"
    real, calls = Store.add_frame, []

    def add_frame(self, *args, **kwargs):
        calls.append(1)
        if len(calls) == 4:
            raise KeyboardInterrupt
        return real(self, *args, **kwargs)
    monkeypatch.setattr(Store, "add_frame", add_frame)
    args = ["import", "diligent", str(tmp_path / "ball"), "--store", str(store)]
    r = cli.invoke(app, args)
    said = _said(r)
    assert r.exit_code == 3, r.output
    assert f"interrupted; the files stored so far are kept; continue with: gonio {shlex.join(args)}" in said
    with Store(store, readonly=True) as st:
        info = st.session("diligent-ball")
        assert info.state == "paused" and len(st.frames(info.id)) == 3
        kept = {f.step: f.sha256 for f in st.frames(info.id)}
    monkeypatch.setattr(Store, "add_frame", real)
    r = cli.invoke(app, args)
    assert r.exit_code == 0, r.output
    with Store(store, readonly=True) as st:
        info = st.session("diligent-ball")
        frames = {f.step: f.sha256 for f in st.frames(info.id)}
        assert info.state == "done" and len(frames) == 10 and st.verify("diligent-ball").ok  # 8 + mask + truth
        assert {k: frames[k] for k in kept} == kept
        assert sorted(r.kind for r in st.results(info.id, "calibration")) == ["camera_orthographic",
                                                                             "lights_directional"]


def _store_with_session(root, state="done"):
    with Store(root, durable=False) as st:
        sid = st.create_session("s1", plan={}, plan_hash="h", steps=[{"frames": 1}]).id
        st.add_frame(sid, 0, 0, 0, data=b"raw" * 50, filename="a.dng", format="dng",
                     exposure_requested_s=0.01, exposure_s=0.01, completes_step=True)
        st.set_state(sid, state)


def test_calibrate_and_export_interrupted_say_the_command_that_runs_them_again(tmp_path, monkeypatch):
    import capture.export.session
    import capture.pipeline.calibrate
    store = tmp_path / "store"
    _store_with_session(store)
    monkeypatch.setattr(capture.pipeline.calibrate, "calibrate_session", _interrupt)
    r = cli.invoke(app, ["calibrate", "s1", "--store", str(store), "-q"])
    assert r.exit_code == 3 and "Traceback" not in r.output
    assert ("interrupted; the session's frames are kept and a calibration cut short is never reused; "
            f"calibrate again with: gonio calibrate s1 --store {store}") in _said(r)
    monkeypatch.setattr(capture.export.session, "export_session", _interrupt)
    r = cli.invoke(app, ["export", "s1", "--method", "lensch", "--out", str(tmp_path / "x"), "--store", str(store)])
    assert r.exit_code == 3 and not (tmp_path / "x").exists()
    assert (f"interrupted; nothing was written to {tmp_path / 'x'}; export again with: gonio export s1 --method "
            f"lensch --format maps,gltf,mitsuba --out {tmp_path / 'x'} --store {store}") in _said(r)
    with Store(store, readonly=True) as st:
        assert st.verify("s1").ok and len(st.frames(st.session("s1").id)) == 1


@pytest.mark.parametrize("state, then", [
    (None, "nothing was captured"),
    ("paused", "every frame stored is kept; resume with: gonio capture resume s1 --rig sim --store {store}, "
               "then gonio process s1 --store {store} --out {out}/report.html"),
    ("done", "the capture and whatever was processed are kept; resume with: gonio process s1 --store {store} "
             "--out {out}/report.html")])
def test_an_interrupted_demo_names_the_commands_that_finish_it(tmp_path, monkeypatch, state, then):
    import capture.pipeline.demo
    out = tmp_path / "demo"

    def interrupted_demo(out_dir, **kw):
        if state is not None:
            _store_with_session(out_dir / "store", state)
        raise KeyboardInterrupt
    monkeypatch.setattr(capture.pipeline.demo, "run_demo", interrupted_demo)
    r = cli.invoke(app, ["demo", "--out", str(out), "-q"])
    assert r.exit_code == 3, r.output
    assert "interrupted; " + then.format(store=out / "store", out=out) in _said(r)


def test_gonio_installs_its_ctrl_c_handling_before_loading_the_commands():
    """``capture.cli`` (what the ``gonio`` script and ``python -m capture.cli`` import first) loads
    only the interrupt handling: the commands (and a running command's layers) load after
    :func:`capture.cli.interrupts.install`, so a Ctrl-C while gonio starts exits 3 too."""
    import subprocess
    import sys
    code = ("import sys, capture.cli; print(sorted(m for m in sys.modules if m.startswith("
            "('capture.cli.', 'capture.pipeline', 'capture.store', 'typer', 'numpy'))))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "['capture.cli.interrupts']"
