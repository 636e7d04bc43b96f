"""Session store: schema migrations, durable content-addressed frames, verify, export, results."""
from __future__ import annotations

import errno
import hashlib
import os
import sqlite3
import stat

import pytest

from capture import store as store_mod
from capture.store import crash as store_crash
from capture.events import Event, EventKind
from capture.store import (SCHEMA_VERSION, SchemaError, SessionBusy, SessionExists, SessionNotFound,
                           Store, StoreError, StoreFull)


def _session(store: Store, name: str = "s1", n_steps: int = 2, frames: int = 2):
    steps = [{"index": i, "frames": frames} for i in range(n_steps)]
    return store.create_session(name, plan={"name": name}, plan_hash="h" * 64, steps=steps,
                                operator="ana", object="teapot")


def _frame(store, sid, step, b, data, r=0, **kw):
    return store.add_frame(sid, step, b, r, data=data, filename=f"IMG_{step}_{b}.DNG", format="dng",
                           exposure_requested_s=0.01, exposure_s=0.01, positions={"turntable_deg": 1.5},
                           **kw)


def test_fresh_store_has_current_schema_and_wal(tmp_path):
    with Store(tmp_path / "st") as st:
        assert st.schema_version == SCHEMA_VERSION == len(store_mod.MIGRATIONS)
        assert st._query("PRAGMA journal_mode")[0][0] == "wal"


def test_old_schema_is_migrated_forward(tmp_path):
    root = tmp_path / "st"
    root.mkdir()
    db = sqlite3.connect(root / store_mod.DB_NAME)
    db.execute("CREATE TABLE schema_version (version INTEGER NOT NULL)")
    store_mod.MIGRATIONS[0](db)
    db.execute("INSERT INTO schema_version VALUES (1)")
    db.commit()
    db.close()
    with Store(root) as st:
        assert st.schema_version == SCHEMA_VERSION
        names = {r[0] for r in st._query("SELECT name FROM sqlite_master WHERE type = 'index'")}
        assert "frames_sha" in names


def test_newer_schema_is_refused(tmp_path):
    with Store(tmp_path / "st") as st:
        st._db.execute("UPDATE schema_version SET version = 99")
    with pytest.raises(SchemaError, match="version 99"):
        Store(tmp_path / "st")


def test_missing_store_is_a_clear_error(tmp_path):
    with pytest.raises(StoreError, match="not a gonio store"):
        Store(tmp_path / "nope", create=False)


def test_sessions_create_find_and_duplicates(tmp_path):
    with Store(tmp_path) as st:
        info = _session(st)
        assert (info.state, info.operator, info.object) == ("planned", "ana", "teapot")
        with pytest.raises(SessionExists, match="already exists"):
            _session(st)
        with pytest.raises(SessionNotFound, match="sessions: s1"):
            st.session("s2")
        with pytest.raises(StoreError, match="not allowed"):
            _session(st, name="a/b")
        assert [s.name for s in st.sessions()] == ["s1"]


def test_frame_is_stored_durably_and_content_addressed(tmp_path):
    with Store(tmp_path) as st:
        sid = _session(st).id
        data = os.urandom(10_000)
        fid, sha = _frame(st, sid, 0, 0, data)
        assert sha == hashlib.sha256(data).hexdigest()
        path = st.object_path(sha)
        assert path == tmp_path / "objects" / sha[:2] / sha[2:]
        assert path.read_bytes() == data
        assert not stat.S_IMODE(path.stat().st_mode) & 0o222  # read-only
        rec = st.frame(fid)
        assert (rec.size, rec.positions, rec.format) == (10_000, {"turntable_deg": 1.5}, "dng")
        assert not [p for p in path.parent.iterdir() if p.name.startswith(".tmp-")]


def test_identical_bytes_are_stored_once(tmp_path):
    with Store(tmp_path) as st:
        sid = _session(st).id
        data = b"x" * 5000
        _, a = _frame(st, sid, 0, 0, data)
        _, b = _frame(st, sid, 0, 1, data)
        assert a == b
        assert len(list(st._files.files())) == 1
        assert len(st.frames(sid)) == 2


def test_restored_key_replaces_row_and_drops_unreferenced_file(tmp_path):
    with Store(tmp_path) as st:
        sid = _session(st).id
        _, old = _frame(st, sid, 0, 0, b"old" * 100)
        _, shared = _frame(st, sid, 0, 1, b"shared" * 100)
        _, new = _frame(st, sid, 0, 0, b"new" * 100)  # step re-done after a crash
        assert [f.sha256 for f in st.frames(sid, step=0)] == [new, shared]
        assert not st.object_path(old).exists()
        _frame(st, sid, 1, 0, b"shared" * 100)
        _frame(st, sid, 1, 0, b"other" * 100)  # replaced, but still referenced by (0, 1)
        assert st.object_path(shared).exists()
        assert st.verify("s1").orphans == []


class _Killed(BaseException):
    """Stands in for SIGKILL at a store hook point: nothing after it runs."""


def test_replacement_killed_before_commit_keeps_the_old_file(tmp_path, monkeypatch):
    # a re-done frame replaces the row; if the process dies before that commit, the old row is
    # still the truth and its file must still be there (only the new file may be left, orphaned)
    with Store(tmp_path) as st:
        sid = _session(st).id
        _, old = _frame(st, sid, 0, 0, b"old" * 100)

        def kill(name):
            if name == "before_commit":
                raise _Killed(name)
        monkeypatch.setattr(store_crash, "point", kill)
        with pytest.raises(_Killed):
            _frame(st, sid, 0, 0, b"new" * 100)
        monkeypatch.undo()
        [f] = st.frames(sid)
        assert f.sha256 == old and store_mod.sha256_file(st.object_path(old)) == old
        new = hashlib.sha256(b"new" * 100).hexdigest()
        assert st.verify("s1").orphans == [f"objects/{new[:2]}/{new[2:]}"]


def test_interrupt_right_after_begin_leaves_the_store_usable(tmp_path):
    # Ctrl-C in a script lands between bytecodes, e.g. just after BEGIN returned
    class Interrupting:
        def __init__(self, db):
            self.db, self.armed = db, True

        def execute(self, sql, *args):
            cur = self.db.execute(sql, *args)
            if sql.startswith("BEGIN") and self.armed:
                self.armed = False
                raise KeyboardInterrupt
            return cur

        def __getattr__(self, name):
            return getattr(self.db, name)
    with Store(tmp_path) as st:
        sid = _session(st).id
        real = st._db
        st._db = Interrupting(real)
        with pytest.raises(KeyboardInterrupt):
            _frame(st, sid, 0, 0, b"a" * 10)
        assert not real.in_transaction
        st._db.armed = True
        with pytest.raises(KeyboardInterrupt):
            st.progress(sid)  # a read transaction
        assert not real.in_transaction
        st._db = real
        _frame(st, sid, 0, 0, b"a" * 10)
        st.set_state(sid, "paused")
        assert st.session("s1").state == "paused" and len(st.frames(sid)) == 1


def test_database_full_at_commit_is_store_full_and_records_nothing(tmp_path):
    with Store(tmp_path) as st:
        sid = _session(st).id
        pages = st._query("PRAGMA page_count")[0][0]
        st._db.execute(f"PRAGMA max_page_count = {pages}")  # SQLite answers SQLITE_FULL beyond
        with pytest.raises(StoreFull, match="no space left .* to commit"):
            _frame(st, sid, 0, 0, b"a" * 10, metadata={"big": "x" * 200_000})
        assert st.frames(sid) == [] and not st._db.in_transaction
        st._db.execute("PRAGMA max_page_count = 1073741823")
        _frame(st, sid, 0, 0, b"a" * 10)
        assert len(st.frames(sid)) == 1


def test_writer_start_never_collects_an_object_whose_row_is_being_committed(tmp_path, monkeypatch):
    # a calibration (another process, no session lock) writes an artifact; a runner starting at
    # that moment must not take it for an orphan of a crashed writer
    import threading
    renamed, release = threading.Event(), threading.Event()

    def hold(name):
        if name == "object_renamed" and threading.current_thread().name == "calibrate":
            renamed.set()
            release.wait(10)
    monkeypatch.setattr(store_crash, "point", hold)
    with Store(tmp_path) as st, Store(tmp_path) as runner_side:
        sid = _session(st).id
        out = {}
        t = threading.Thread(name="calibrate", target=lambda: out.update(
            rid=st.add_calibration(sid, "intrinsics", result={}, artifacts={"k.npz": b"K" * 64})))
        t.start()
        assert renamed.wait(10)
        with runner_side.writer("s1") as removed:
            assert removed is None  # another writer is active: no cleaning now
        release.set()
        t.join(10)
        [res] = st.results(sid)
        sha = res.artifacts["k.npz"]
        assert st.read_object(sha) == b"K" * 64 and st.verify("s1").ok


def test_last_frame_completes_step_in_same_transaction(tmp_path):
    with Store(tmp_path) as st:
        sid = _session(st).id
        ev = Event(EventKind.NOTE, "s1", "hello", step=0)
        _frame(st, sid, 0, 0, b"a" * 10, events=[ev])
        assert st.progress(sid).steps_done == 0
        _frame(st, sid, 0, 1, b"b" * 10, completes_step=True)
        p = st.progress(sid)
        assert (p.steps_done, p.frames_stored, p.frames_total, p.bytes_stored) == (1, 2, 4, 20)
        assert [(s.index, s.done) for s in st.steps(sid)] == [(0, True), (1, False)]
        assert st.events(sid)[0]["message"] == "hello"


def test_disk_full_records_nothing_and_leaves_no_temp(tmp_path, monkeypatch):
    with Store(tmp_path) as st:
        sid = _session(st).id

        def full(fd):
            raise OSError(errno.ENOSPC, "No space left on device")
        monkeypatch.setattr(os, "fsync", full)
        with pytest.raises(StoreFull, match="no space left"):
            _frame(st, sid, 0, 0, b"z" * 1000)
        monkeypatch.undo()
        assert st.frames(sid) == []
        assert st.orphans() == []


def test_verify_reports_missing_corrupt_orphans_and_incomplete(tmp_path):
    with Store(tmp_path) as st:
        sid = _session(st).id
        _, a = _frame(st, sid, 0, 0, b"a" * 100)
        _, b = _frame(st, sid, 0, 1, b"b" * 100, completes_step=True)
        _, c = _frame(st, sid, 1, 0, b"c" * 100)
        assert st.verify("s1").ok
        pa = st.object_path(a)
        os.chmod(pa, 0o644)
        pa.write_bytes(b"A" * 100)
        st.object_path(b).unlink()
        orphan = st.put_object(b"nobody refers to me")
        (st.object_path(c).parent / ".tmp-123").write_bytes(b"half")
        st._db.execute("UPDATE steps SET done = 1 WHERE idx = 1")  # 1 of 2 frames: incomplete
        rep = st.verify("s1")
        assert rep.corrupt == [a] and rep.missing == [b] and rep.incomplete_steps == [1]
        assert sorted(rep.orphans) == sorted([f"objects/{orphan[:2]}/{orphan[2:]}",
                                              f"objects/{c[:2]}/.tmp-123"])
        assert rep.checked == 3 and not rep.ok


def test_writer_lock_collects_garbage_and_excludes_second_writer(tmp_path):
    with Store(tmp_path) as st, Store(tmp_path) as other:
        _session(st)
        orphan = st.put_object(b"left by a killed writer")
        with st.writer("s1") as removed:
            assert removed == [f"objects/{orphan[:2]}/{orphan[2:]}"]
            with pytest.raises(SessionBusy, match="another process"):
                with other.writer("s1"):
                    pass
        with other.writer("s1") as removed:
            assert removed == []
            assert st.session_active("s1")  # seen through another open file, as another process
            stray = st.put_object(b"stray")
            with pytest.raises(SessionBusy, match="being written"):
                st.remove_orphans()  # its files in flight would look like orphans
        assert not st.session_active("s1")
        assert st.remove_orphans() == [f"objects/{stray[:2]}/{stray[2:]}"]


def test_results_keep_provenance_and_artifacts(tmp_path):
    with Store(tmp_path) as st:
        sid = _session(st).id
        f1, _ = _frame(st, sid, 0, 0, b"a" * 10)
        rid = st.add_calibration(sid, "intrinsics", result={"rms_px": 0.21}, params={"board": "7x9"},
                                 input_frames=[f1], artifacts={"K.npy": b"\x93NUMPY..."})
        [res] = st.results(sid, "calibration")
        assert res.id == rid and res.input_frames == [f1] and res.params == {"board": "7x9"}
        assert res.code_version.startswith("gonio ")
        assert st.read_object(res.artifacts["K.npy"]) == b"\x93NUMPY..."
        with pytest.raises(StoreError, match="not frames of this session"):
            st.add_reconstruction(sid, "lensch2003", result={}, input_frames=[f1, 999])
        assert st.verify("s1").ok


@pytest.mark.parametrize("dest", ["out", "out.tar", "out.zip", "out.tar.gz"])
def test_export_is_self_contained_and_opens(tmp_path, dest):
    with Store(tmp_path / "st") as st:
        sid = _session(st).id
        _session(st, "other")
        _frame(st, sid, 0, 0, b"a" * 100)
        _frame(st, sid, 0, 1, b"b" * 100, completes_step=True)
        _frame(st, st.session("other").id, 0, 0, b"not exported" * 10)
        st.add_calibration(sid, "dark", result={"level": 512.0}, artifacts={"dark.npy": b"D" * 50})
        out = st.export("s1", tmp_path / dest)
    with Store.open(out) as ex:
        assert [s.name for s in ex.sessions()] == ["s1"]
        info = ex.session("s1")
        assert [f.size for f in ex.frames(info.id)] == [100, 100]
        assert ex.read_object(ex.frames(info.id)[1].sha256) == b"b" * 100
        assert ex.results(info.id)[0].result == {"level": 512.0}
        assert ex.verify("s1").ok  # the other session's object was not copied
    with pytest.raises(StoreError, match="already exists"):
        Store(tmp_path / "st").export("s1", out)


def test_verify_ignores_young_unreferenced_files_while_a_writer_runs(tmp_path):
    with Store(tmp_path) as st, Store(tmp_path) as reader:
        _session(st)
        with st.writer("s1"):
            in_flight = st.put_object(b"renamed, not yet committed")
            assert reader.writer_active()
            assert reader.verify("s1").orphans == []
        assert not reader.writer_active()
        assert reader.verify("s1").orphans == [f"objects/{in_flight[:2]}/{in_flight[2:]}"]


@pytest.mark.parametrize("dest", ["bad", "bad.zip"])
def test_export_refuses_corrupt_data_and_leaves_nothing(tmp_path, dest):
    with Store(tmp_path / "st") as st:
        sid = _session(st).id
        _, sha = _frame(st, sid, 0, 0, b"a" * 100)
        os.chmod(st.object_path(sha), 0o644)
        st.object_path(sha).write_bytes(b"b" * 100)
        with pytest.raises(StoreError, match=f"object {sha} is corrupt"):
            st.export("s1", tmp_path / dest)
    assert not (tmp_path / dest).exists()
    assert [p.name for p in tmp_path.iterdir()] == ["st"]  # no temporary folder left either
