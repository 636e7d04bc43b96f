"""Options of every command that takes a path, a name or a number (issue 19 #9 #12): a message
naming the option, exit status 2, nothing written anywhere."""
from __future__ import annotations

import pytest
from typer.testing import CliRunner

from capture.cli import app
from capture.outputs import OutputError, check_out_file, session_file, write_atomically
from capture.plan import MotionModel

cli = CliRunner()


def _files(root):
    return sorted(str(p.relative_to(root)) for p in root.rglob("*"))


def test_an_empty_store_option_is_refused_not_the_current_folder(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    for args in (["session", "list", "--store", ""], ["process", "x", "--store", " "],
                 ["calibrate", "x", "--store", ""]):
        r = cli.invoke(app, args)
        assert r.exit_code == 2 and "--store is empty" in r.output, (args, r.output)
    assert _files(tmp_path) == []


def test_demo_refuses_an_out_that_already_holds_a_demo_or_is_a_file(tmp_path):
    (tmp_path / "done" / "store").mkdir(parents=True)
    (tmp_path / "done" / "report.html").write_text("kept")
    r = cli.invoke(app, ["demo", "--quick", "--out", str(tmp_path / "done"), "-q"])
    assert r.exit_code == 2 and "already holds a demo" in " ".join(r.output.split())
    (tmp_path / "file").write_text("kept")
    r = cli.invoke(app, ["demo", "--quick", "--out", str(tmp_path / "file"), "-q"])
    assert r.exit_code == 2 and "is a file, not a folder" in r.output
    assert _files(tmp_path) == ["done", "done/report.html", "done/store", "file"]
    assert (tmp_path / "done" / "report.html").read_text() == "kept"


@pytest.mark.parametrize("args, words", [
    (["--name", "../escape"], "--name '../escape'"),
    (["--name", "/tmp/abs"], "--name '/tmp/abs'"),
    (["--name", "-rf"], "--name '-rf'"),
    (["--turntable", "nan"], "--turntable must be a finite number"),
    (["--light-el", "inf"], "--light-el must be a finite number"),
    (["--exposure", "inf"], "--exposure must be in 1e-06..3600"),
    (["--exposure", "1e308"], "--exposure must be in 1e-06..3600"),   # was a traceback
    (["--iso", "1e300"], "--iso must be in 100..6400"),
    (["--fnumber", "1e-300"], "--fnumber must be in 2.8..22"),       # was ZeroDivisionError
    (["--seed", "-1"], "--seed must be >= 0"),                        # was numpy's ValueError
    (["--supersample", "100000"], "--supersample must be in 1..8"),
    (["--width", "100000", "--height", "64"], "in 16..8192"),
])
def test_sim_render_refuses_hostile_names_and_numbers(tmp_path, args, words):
    out = tmp_path / "out"
    r = cli.invoke(app, ["sim", "render", "--out", str(out), "--width", "32", "--height", "32", *args])
    assert r.exit_code == 2 and words in r.output, r.output
    assert _files(tmp_path) == []


def test_sim_render_refuses_an_out_that_is_a_file(tmp_path):
    (tmp_path / "f").write_text("kept")
    r = cli.invoke(app, ["sim", "render", "--out", str(tmp_path / "f"), "--width", "32", "--height", "32"])
    assert r.exit_code == 2 and "is a file, not a folder" in r.output and (tmp_path / "f").read_text() == "kept"


def test_report_names_from_stored_session_names_stay_in_their_folder(tmp_path):
    assert session_file(tmp_path, "proc", 3, "-report.html") == tmp_path / "proc-report.html"
    for hostile in ("../../escape", "/etc/x", "..", "a/b", "-rf", "\x1b[31mred", "", "a\nb"):
        assert session_file(tmp_path, hostile, 7, "-report.html") == tmp_path / "session-7-report.html"
    (tmp_path / "proc-report.html").symlink_to("/tmp/elsewhere.html")   # a link cannot lead it out
    with pytest.raises(OutputError, match="leads outside"):
        session_file(tmp_path, "proc", 3, "-report.html")


def test_out_files_are_checked_and_written_whole(tmp_path):
    for path, words in ((tmp_path, "is a folder"), ("/dev/full", "not a regular file"),
                        (tmp_path / "no" / "r.html", "does not exist")):
        with pytest.raises(OutputError, match=words):
            check_out_file(path)
    target = tmp_path / "r.html"
    write_atomically(target, "old report")
    # a full disk mid-write: the old report stays whole, no temporary file is left
    import os
    real = os.fsync

    def full(fd):
        raise OSError(28, "No space left on device")
    os.fsync = full
    try:
        with pytest.raises(OSError, match="No space"):
            write_atomically(target, "new report " * 1000)
    finally:
        os.fsync = real
    assert target.read_text() == "old report" and _files(tmp_path) == ["r.html"]


def test_the_space_estimate_uses_the_simulated_cameras_resolution():
    class SimRig:   # the built-in lab's camera reports no image size; its [rig] table does
        config = {"rig": {"camera_resolution": [320, 240]}}

        def describe(self):
            return {"camera": {"driver": "ptp"}}
    model = MotionModel.from_rig(SimRig())
    assert model.frame_bytes_source == "camera"
    assert 320 * 240 * 2 <= model.frame_bytes < 320 * 240 * 2 + 100_000   # a 16-bit mosaic + header


def test_a_full_disk_during_process_pauses_until_there_is_room_then_resumes(tmp_path, monkeypatch):
    """The store meets a full disk mid-way (StoreFull): what was stored is kept, the message says
    where and how much space it waits for, the free space is polled until there is that much,
    and the run goes on (issue 19 #7). The report's own full disk: test_process.py."""
    import trimesh
    from capture.cli import process as cli_process
    from capture.pipeline import run
    from capture.store import Store, StoreFull
    store = tmp_path / "store"
    with Store(store, durable=False) as st:
        sid = st.create_session("s1", plan={}, plan_hash="h", steps=[{"frames": 0}]).id
    trimesh.creation.box((50.0, 50.0, 50.0)).export(tmp_path / "box.ply")
    runs, polls = [], []

    def full_once(st, session, **kw):
        runs.append(kw["force"])
        if len(runs) == 1:
            st.add_calibration(sid, "dark", result={"stored before the disk filled": True})
            raise StoreFull("no space left on the disk holding the store while writing a 0.2 MB frame")
        return run.ProcessReport(session, report_path=kw["report_path"])
    free = [10_000_000, 10_000_000, 60_000_000, 70_000_000, 70_000_000]

    def free_bytes(folder):
        polls.append(folder)
        return free[min(len(polls), len(free)) - 1]
    monkeypatch.setattr(run, "process_session", full_once)
    monkeypatch.setattr(cli_process, "free_bytes", free_bytes)
    monkeypatch.setattr(cli_process, "SPACE_POLL_S", 0.0)
    r = cli.invoke(app, ["process", "s1", "--store", str(store), "--mesh", str(tmp_path / "box.ply"), "-q", "--force"])
    said = " ".join(r.output.split())
    assert r.exit_code == 0 and runs == [True, False], r.output   # resuming never redoes what --force redid
    assert f"paused: the disk holding {store} is full (10.0 MB free: no space left" in said
    assert "every calibration stage and method stored so far is kept. Waiting for 67.1 MB free there" in said
    assert "resuming: 70.0 MB free" in said
    assert polls[:4] == [store] * 4 and len(polls) == 5   # the message, 3 polls (10, 60, 70 MB), "resuming"
    with Store(store, readonly=True) as st:
        assert [r.result for r in st.results(sid)] == [{"stored before the disk filled": True}]


def test_a_full_disk_while_the_report_is_written_pauses_and_never_leaves_a_partial_report(tmp_path, monkeypatch):
    """A real ``gonio process`` (an imported 40 x 40 set) meets ENOSPC writing its report (an
    imported session's is JSON), after the method was stored: it pauses naming the report's
    folder, resumes once there is room, reuses the stored fit, and the report is whole; no
    temporary file is left (the report was written in place, 0 bytes on a full disk).
    The report is HTML with a JSON summary; the HTML is written first."""
    import errno
    import json
    import os
    from capture.cli import process as cli_process
    from capture.importers import import_diligent
    from capture.store import Store
    from test_import_diligent import write_set
    write_set(tmp_path / "ball")
    import_diligent(tmp_path / "ball", tmp_path / "store")
    out = tmp_path / "out"
    out.mkdir()
    monkeypatch.setenv("GONIO_STORE_DURABLE", "0")   # the store's writes skip fsync: the first is the report's
    real_fsync, fsyncs = os.fsync, []

    def fsync(fd):
        fsyncs.append(fd)
        if len(fsyncs) == 1:
            raise OSError(errno.ENOSPC, "No space left on device")
        real_fsync(fd)
    monkeypatch.setattr(os, "fsync", fsync)
    free = iter([1_000_000, 1_000_000, 10**12, 10**12])
    monkeypatch.setattr(cli_process, "free_bytes", lambda folder: next(free))
    monkeypatch.setattr(cli_process, "SPACE_POLL_S", 0.0)
    r = cli.invoke(app, ["process", "diligent-ball", "--store", str(tmp_path / "store"), "--methods", "lambertian",
                         "--out", str(out / "r.html"), "--json", "-q"])
    said = " ".join(r.output.split())
    assert r.exit_code == 0, r.output
    # the report's first file written (its HTML, since imported sessions have one) met the full disk
    assert f"paused: the disk holding {out} is full (1.0 MB free: [Errno 28] No space left on device: '{out / 'r.html'}')" in said
    assert "Waiting for 67.1 MB free there" in said and "resuming: 1.0 TB free" in said
    report = json.loads(r.output[r.output.index("{"):])
    assert report["methods"][0]["status"] == "done"   # the fit stored before the disk filled
    assert sorted(p.name for p in out.iterdir()) == ["r.html", "r.json"]   # whole, no temporary left
    assert (out / "r.html").read_text().rstrip().endswith("</html>")
    assert json.loads((out / "r.json").read_text()) == report
    with Store(tmp_path / "store", readonly=True) as st:
        assert len(st.results(st.session("diligent-ball").id, "reconstruction")) == 1


def test_process_without_calibration_captures_says_what_the_session_lacks(tmp_path):
    import trimesh
    from capture.plan import Step
    from capture.store import Store
    with Store(tmp_path / "store", durable=False) as st:
        step = Step(0, "measure", "object", None, None, None, (0.01,))
        sid = st.create_session("s1", plan={}, plan_hash="h", steps=[step.to_dict()]).id
        st.add_frame(sid, 0, 0, 0, data=b"raw" * 50, filename="a.dng", format="dng",
                     exposure_requested_s=0.01, exposure_s=0.01, completes_step=True)
        before = st.results(sid)
    trimesh.creation.box((50.0, 50.0, 50.0)).export(tmp_path / "box.ply")
    r = cli.invoke(app, ["process", "s1", "--store", str(tmp_path / "store"), "--mesh", str(tmp_path / "box.ply"),
                         "--targets", str(tmp_path / "none.toml"), "-q"])
    assert r.exit_code == 2 and "none.toml" in r.output       # --targets checked first
    r = cli.invoke(app, ["process", "s1", "--store", str(tmp_path / "store"), "--mesh", str(tmp_path / "box.ply"), "-q"])
    said = " ".join(r.output.split())
    assert r.exit_code == 3 and "has no calibration captures" in said and "gonio calibrate" not in said, said
    with Store(tmp_path / "store", readonly=True) as st:
        assert st.results(st.session("s1").id) == before


@pytest.mark.parametrize("error, code, words", [
    ("MemoryLimitError", 2, "--memory-limit 64 MiB cannot hold one view's images"),
    ("ClusterError", 2, "cannot reach the Dask scheduler"),
    ("ProcessError", 3, "cannot process: the session has no measurement steps"),
    ("ValueError", 1, None),      # a programming error: its traceback, never a user message
    ("ZeroDivisionError", 1, None),
])
def test_process_turns_only_its_typed_errors_into_messages(tmp_path, monkeypatch, error, code, words):
    import trimesh
    from capture.pipeline import cluster, lumitexel_arrays, process, run
    from capture.store import Store
    with Store(tmp_path / "store", durable=False) as st:
        st.create_session("s1", plan={}, plan_hash="h", steps=[{"frames": 0}])
    trimesh.creation.box((50.0, 50.0, 50.0)).export(tmp_path / "box.ply")
    raised = {"MemoryLimitError": lumitexel_arrays.MemoryLimitError, "ClusterError": cluster.ClusterError,
              "ProcessError": process.ProcessError, "ValueError": ValueError,
              "ZeroDivisionError": ZeroDivisionError}[error](words or "a bug")

    def fails(*args, **kw):
        raise raised
    monkeypatch.setattr(run, "process_session", fails)
    r = cli.invoke(app, ["process", "s1", "--store", str(tmp_path / "store"), "--mesh", str(tmp_path / "box.ply"), "-q"])
    assert r.exit_code == code, r.output
    if words is None:
        assert r.exception is raised and "error:" not in r.output
    else:
        assert words in " ".join(r.output.split())


@pytest.mark.parametrize("size", ["15x16", "16x15", "0x0", "9000x480", "640x"])
def test_a_simulated_camera_size_the_lab_cannot_render_is_refused(tmp_path, size):
    plan = tmp_path / "plan.toml"
    plan.write_text('[turntable]\nangles_deg = [0]\n[exposure]\nbase_s = 0.01\n')
    r = cli.invoke(app, ["capture", "plan", str(plan), "--rig", "sim", "--sim-camera", size])
    assert r.exit_code == 2 and f"got {size!r}" in r.output and "even and in 16..8192" in " ".join(r.output.split())


HOSTILE = [   # (arguments, what the message must say): each was a traceback before (issue 19 "go beyond")
    (["rig", "sim", "--fast", "--duration", "nan"], "--duration must be more than 0 and at most 86400 s"),
    (["rig", "sim", "--fast", "--duration", "-1"], "--duration must be more than 0"),
    (["rig", "sim", "--fast", "--duration", "1e308"], "--duration must be more than 0 and at most 86400 s"),
    (["rig", "sim", "--fast", "--write", "{tmp}"], "--write {tmp} is a folder"),
    (["rig", "sim", "--fast", "--write", ""], "--write . is a folder"),
    (["rig", "sim", "--fast", "--write", "/dev/full"], "--write /dev/full"),
    (["rig", "home", "--rig", "sim", "--timeout", "inf"], "--timeout must be more than 0 and at most 86400 s"),
    (["rig", "home", "--rig", "sim", "--timeout", "99999999999999999999"], "--timeout must be more than 0"),
    (["process", "s1", "--store", "{tmp}/store", "--memory-limit", "inf"], "--memory-limit must be at most"),
    (["process", "s1", "--store", "{tmp}/store", "--memory-limit", "1e308"], "--memory-limit must be at most"),
    (["process", "s1", "--store", "{tmp}/store", "--memory-limit", "nan"], "--memory-limit"),   # typer's range check
    (["tui", "--poll", "nan"], "--poll"),          # was accepted: the console started refreshing every NaN s
    (["tui", "--poll", "inf"], "--poll"),
    (["tui", "--store", ""], "--store is empty"),  # was the current folder
    (["demo", "--out", ""], "--out is empty"),       # ran a demo in the current folder
    (["sim", "render", "--out", ""], "--out is empty"),
    (["calibrate", "s1", "--store", "{tmp}/store", "--out", ""], "--out is empty"),
]


@pytest.mark.parametrize("args, words", HOSTILE)
def test_hostile_numbers_and_paths_get_a_message_naming_the_option(tmp_path, monkeypatch, args, words):
    monkeypatch.chdir(tmp_path)
    before = _files(tmp_path)
    r = cli.invoke(app, [a.format(tmp=tmp_path) for a in args])
    assert r.exit_code == 2 and (r.exception is None or isinstance(r.exception, SystemExit)), r.output
    assert words.format(tmp=tmp_path) in " ".join(r.output.split()), r.output
    assert _files(tmp_path) == before   # nothing written, no simulator started


def test_a_full_disk_while_the_calibration_report_is_drawn_leaves_no_partial_png(tmp_path, monkeypatch):
    """The calibration PNG met ENOSPC: it was written in place (a partial file) and the command
    ended in a traceback; now no file is left, the message names the folder, exit 2, the stored
    calibration is kept."""
    import errno
    import os
    import capture.pipeline.calibrate as pipeline_calibrate
    from capture.pipeline.calibrate import STAGES, CalibrationReport, StageResult
    from capture.store import Store
    store = tmp_path / "store"
    with Store(store, durable=False) as st:
        sid = st.create_session("s1", plan={}, plan_hash="h", steps=[{"frames": 0}]).id

    def calibrated(st, session, **kw):
        st.add_calibration(sid, "dark", result={"kept": True})
        return CalibrationReport(session, [StageResult(s, "skipped", "no captures for it") for s in STAGES])
    monkeypatch.setattr(pipeline_calibrate, "calibrate_session", calibrated)
    monkeypatch.setenv("GONIO_STORE_DURABLE", "0")   # the first fsync is the PNG's
    from matplotlib.figure import Figure   # rendering is test_calibrate's: here only the bytes' way out
    monkeypatch.setattr(Figure, "savefig", lambda self, f, **kw: f.write(b"\x89PNG\r\n\x1a\n"))

    def fsync(fd):
        raise OSError(errno.ENOSPC, "No space left on device")
    monkeypatch.setattr(os, "fsync", fsync)
    out = tmp_path / "out"
    r = cli.invoke(app, ["calibrate", "s1", "--store", str(store), "--out", str(out), "-q"])
    said = " ".join(r.output.split())
    assert r.exit_code == 2 and (r.exception is None or isinstance(r.exception, SystemExit)), r.output
    assert f"the disk holding {out} is full: the calibration is stored" in said and "no partial file" in said
    assert list(out.iterdir()) == []
    with Store(store, readonly=True) as st:
        assert [x.result for x in st.results(sid)] == [{"kept": True}]


def test_sim_render_and_export_on_a_full_disk_say_so_and_leave_no_partial_file(tmp_path, monkeypatch):
    """Both wrote in place or ended in a traceback on ENOSPC."""
    import errno
    import os
    import capture.export.session
    from capture.store import Store

    def full(*args, **kw):
        raise OSError(errno.ENOSPC, "No space left on device")
    monkeypatch.setattr(os, "fsync", full)
    out = tmp_path / "render"
    r = cli.invoke(app, ["sim", "render", "--out", str(out), "--width", "32", "--height", "32", "--name", "f"])
    assert r.exit_code == 2 and f"cannot write {out / 'f.dng'}: No space left on device" in " ".join(r.output.split())
    assert list(out.iterdir()) == []
    with Store(tmp_path / "store", durable=False) as st:
        st.create_session("s1", plan={}, plan_hash="h", steps=[])
    monkeypatch.setattr(capture.export.session, "export_session", full)
    r = cli.invoke(app, ["export", "s1", "--method", "lensch", "--out", str(tmp_path / "x"), "--store", str(tmp_path / "store")])
    said = " ".join(r.output.split())
    assert r.exit_code == 2 and f"the disk holding {tmp_path} is full (No space left on device); nothing was written" in said
