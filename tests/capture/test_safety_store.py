"""Hostile archives, damaged / empty / foreign databases, full disks (issue 15): a clear message,
nothing changed, no temporary folder left, and a full disk pauses a session resumably."""
from __future__ import annotations

import contextlib
import hashlib
import io
import os
import sqlite3
import subprocess
import tarfile
import tempfile
import zipfile
from pathlib import Path

import pytest
from typer.testing import CliRunner

from capture import store as store_mod
from capture.store import version as store_version
from capture.cli.capture import app as capture_app
from capture.cli.session import app as session_app
from capture.events import EventKind
from capture.plan import Plan
from capture.runner import Runner, create_session
from capture.store import ForeignDatabase, Store, StoreDamaged, StoreError
from capture_fakes import SMALL_PLAN, make_rig

cli = CliRunner()


def _store_with_frames(root: Path, name: str = "s1", n: int = 2) -> list[str]:
    with Store(root) as st:
        sid = st.create_session(name, plan={"name": name}, plan_hash="h", steps=[{"frames": n}]).id
        return [st.add_frame(sid, 0, i, 0, data=os.urandom(500), filename=f"f{i}.dng", format="dng",
                             exposure_requested_s=0.01, exposure_s=0.01, completes_step=i == n - 1)[1]
                for i in range(n)]


def _snapshot(root: Path) -> dict[str, str]:
    """Every file's SHA-256 under ``root`` (SQLite's -wal/-shm lock files aside)."""
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file() and not p.name.endswith(("-wal", "-shm"))}


def _gonio_temp_dirs() -> set[str]:
    return {p.name for p in Path(tempfile.gettempdir()).glob("gonio-store-*")}


def _run(*args: str):
    r = cli.invoke(session_app, list(args))
    assert r.exception is None or isinstance(r.exception, SystemExit), r.exception
    return r


# -- archives ----------------------------------------------------------------------------------
def _tar_with(path: Path, member: tarfile.TarInfo, data: bytes = b"") -> None:
    with tarfile.open(path, "w") as t:
        info = tarfile.TarInfo("st/gonio.sqlite")
        info.size = 4
        t.addfile(info, io.BytesIO(b"SQLi"))
        t.addfile(member, io.BytesIO(data) if member.isfile() else None)


def _member(name: str, kind: bytes = tarfile.REGTYPE, target: str = "") -> tarfile.TarInfo:
    m = tarfile.TarInfo(name)
    m.type, m.linkname = kind, target
    m.size = 5 if kind == tarfile.REGTYPE else 0
    return m


@pytest.mark.parametrize("member", [
    _member("../evil.txt"), _member("/tmp/evil-abs.txt"), _member("st/../../evil.txt"),
    _member("st/link", tarfile.SYMTYPE, "/etc/passwd"), _member("st/hard", tarfile.LNKTYPE, "/etc/passwd"),
    _member("st/fifo", tarfile.FIFOTYPE)], ids=lambda m: m.name)
def test_tar_with_hostile_members_is_refused_by_name_and_leaves_nothing(tmp_path, member):
    archive = tmp_path / "bad.tar"
    _tar_with(archive, member, b"pwned")
    before = _gonio_temp_dirs()
    with pytest.raises(StoreError, match=f"refusing unsafe member '{member.name}'"):
        Store.open(archive)
    r = _run("list", "--store", str(archive))
    assert r.exit_code == 2 and member.name in r.output and "Traceback" not in r.output
    assert _gonio_temp_dirs() == before
    assert not (tmp_path / "evil.txt").exists() and not Path("/tmp/evil-abs.txt").exists()


@pytest.mark.parametrize("name", ["../evil.txt", "/abs.txt", "st/../../evil.txt"])
def test_zip_with_hostile_members_is_refused_by_name(tmp_path, name):
    archive = tmp_path / "bad.zip"
    with zipfile.ZipFile(archive, "w") as z:
        z.writestr("st/gonio.sqlite", b"SQLi")
        z.writestr(name, b"pwned")
    before = _gonio_temp_dirs()
    with pytest.raises(StoreError, match="refusing unsafe member"):
        Store.open(archive)
    assert _gonio_temp_dirs() == before


@pytest.mark.parametrize("content", [b"", b"SQLite format 3\x00" + b"\x07" * 200])
def test_an_archive_holding_a_damaged_store_leaves_no_temporary_folder(tmp_path, content):
    archive = tmp_path / "x.tar"
    with tarfile.open(archive, "w") as t:
        info = tarfile.TarInfo("st/gonio.sqlite")
        info.size = len(content)
        t.addfile(info, io.BytesIO(content))
    before = _gonio_temp_dirs()
    r = _run("list", "--store", str(archive))
    assert r.exit_code == 2 and "gonio.sqlite" in r.output
    assert _gonio_temp_dirs() == before


# -- damaged, empty, foreign databases ---------------------------------------------------------
def _damage_header(db: Path) -> None:
    data = bytearray(db.read_bytes())
    data[:16] = b"garbage garbage!"
    db.write_bytes(bytes(data))


def _damage_pages(db: Path) -> None:
    data = bytearray(db.read_bytes())
    page = int.from_bytes(data[16:18], "big")
    for i in range(1, len(data) // page):  # every page but the first: schema readable, rows not
        data[i * page: i * page + 16] = b"\xff" * 16
    db.write_bytes(bytes(data))


def _damage_sessions_root(db: Path) -> None:
    """Zero the first 8 bytes of the sessions table's root page, header intact: the schema reads,
    the first query of a row fails, and so did the COMMIT after it (a second error)."""
    con = sqlite3.connect(db)
    root_page = con.execute("SELECT rootpage FROM sqlite_master WHERE name = 'sessions'").fetchone()[0]
    con.close()
    data = bytearray(db.read_bytes())
    page = int.from_bytes(data[16:18], "big")
    data[(root_page - 1) * page:(root_page - 1) * page + 8] = bytes(8)
    db.write_bytes(bytes(data))


@pytest.mark.parametrize("damage, words", [(_damage_header, "file is not a database"),
                                           (_damage_pages, "malformed"),
                                           (_damage_sessions_root, "malformed")])
def test_a_damaged_database_gives_a_clear_message_and_changes_nothing(tmp_path, damage, words):
    root = tmp_path / "st"
    _store_with_frames(root)
    damage(root / "gonio.sqlite")
    before = _snapshot(root)
    for args in (["list"], ["show", "s1"], ["verify", "s1"], ["export", "s1", str(tmp_path / "o.tar")]):
        r = _run(*args, "--store", str(root))
        assert r.exit_code == 2, (args, r.output)
        assert "is damaged" in r.output and words in r.output, (args, r.output)
        assert "2 frame file(s)" in r.output and "restore" in r.output.lower()
    with pytest.raises(StoreDamaged, match=words):
        with Store(root) as st:  # a writing open says the same and writes nothing either
            st.sessions()
    assert _snapshot(root) == before


def test_an_empty_database_beside_frames_is_reported_not_rebuilt(tmp_path):
    root = tmp_path / "st"
    _store_with_frames(root, n=3)
    (root / "gonio.sqlite").write_bytes(b"")
    before = _snapshot(root)
    r = _run("list", "--store", str(root))
    assert r.exit_code == 2 and "is empty but" in r.output and "3 file(s)" in r.output
    with pytest.raises(StoreDamaged, match="3 file"):
        Store(root, create=True)  # the writing path (capture run) refuses too
    assert _snapshot(root) == before and (root / "gonio.sqlite").stat().st_size == 0


def test_frames_no_row_knows_are_reported_by_list(tmp_path):
    root = tmp_path / "st"
    _store_with_frames(root)
    with Store(root) as st:
        stray = st.put_object(b"a frame whose row was lost")
    r = _run("list", "--store", str(root))
    assert r.exit_code == 0 and "1 file(s)" in r.output and "belong to no session" in r.output
    assert f"objects/{stray[:2]}/{stray[2:]}" in r.output


def test_a_foreign_database_is_refused_and_left_untouched(tmp_path):
    root = tmp_path / "st"
    root.mkdir()
    db = sqlite3.connect(root / "gonio.sqlite")
    db.execute("CREATE TABLE recipes (name TEXT)")
    db.execute("INSERT INTO recipes VALUES ('bread')")
    db.commit()
    db.close()
    before = _snapshot(root)
    for args in (["list"], ["show", "x"], ["verify", "x"]):
        r = _run(*args, "--store", str(root))
        assert r.exit_code == 2 and "not a gonio store" in r.output and "recipes" in r.output
    with pytest.raises(ForeignDatabase):
        Store(root, create=True)
    assert _snapshot(root) == before
    assert sorted(p.name for p in root.iterdir()) == ["gonio.sqlite"]


def test_read_only_commands_do_not_write_the_database(tmp_path):
    root = tmp_path / "st"
    _store_with_frames(root)
    before = _snapshot(root)
    for args in (["list"], ["show", "s1"], ["verify", "s1"]):
        assert _run(*args, "--store", str(root)).exit_code == 0
    assert _snapshot(root) == before
    with Store(root, readonly=True) as st, pytest.raises(StoreError, match="read-only"):
        st.set_state(st.session("s1").id, "done")


# -- full disk ---------------------------------------------------------------------------------
@contextlib.contextmanager
def _small_tmpfs(path: Path, size: str):
    path.mkdir()
    if os.geteuid() != 0 or subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs",
                                            str(path)], capture_output=True).returncode != 0:
        pytest.skip("mounting a small tmpfs needs root")
    try:
        yield path
    finally:
        subprocess.run(["umount", "-l", str(path)], check=False)


def _fill(path: Path) -> None:
    with open(path, "wb") as f:
        with contextlib.suppress(OSError):
            while True:
                f.write(b"\0" * 65536)
                f.flush()


def test_a_disk_filling_mid_session_pauses_it_and_resume_completes(tmp_path):
    with _small_tmpfs(tmp_path / "disk", "8m") as disk:
        store, rig = Store(disk / "st"), make_rig(frame_bytes=100_000)
        info = create_session(store, Plan.from_dict(SMALL_PLAN), rig, name="s", reserve_bytes=0)
        runner = Runner(rig, store, "s", reserve_bytes=0)
        events = []

        def fill_after_five(e):
            events.append(e)
            if e.kind == EventKind.FRAME_STORED and e.data["frames_done"] == 5:
                _fill(disk / "filler")  # another program takes the rest of the disk
        runner.bus.subscribe(fill_after_five)
        assert runner.run() == "paused"
        assert store.session("s").state == "paused"  # recorded, not left 'running'
        assert any(e.kind == EventKind.LOW_DISK and "no space left" in e.message for e in events)
        assert store.progress(info.id).frames_stored >= 5
        store.close()  # no connection left: SQLite's WAL index must be made anew to read
        assert not (disk / "st" / "gonio.sqlite-shm").exists()
        for args in (["list"], ["show", "s"], ["verify", "s"]):  # read-only: they work
            r = _run(*args, "--store", str(disk / "st"))
            assert r.exit_code == 0 and "s" in r.output, (args, r.output)
        r = cli.invoke(capture_app, ["resume", "s", "--rig", "sim", "--store", str(disk / "st")])
        # refused at open (2) or paused at its space check (3), depending on the last free bytes
        assert (r.exit_code, r.exit_code == 2 and "no space left" in r.output or r.exit_code == 3
                and "low disk space" in r.output) in ((2, True), (3, True)), r.output
        with Store(disk / "st", readonly=True) as ro:
            assert ro.session("s").state == "paused"
        (disk / "filler").unlink()
        store = Store(disk / "st")
        assert Runner(rig, store, "s", reserve_bytes=0).run() == "done"
        frames = store.frames(info.id)
        assert len(frames) == 24 and len({(f.step, f.bracket_index) for f in frames}) == 24
        assert store.verify("s").ok
        store.close()


def test_every_commit_failing_for_space_still_pauses_through_the_reserve(tmp_path, monkeypatch):
    """A patched write (no tmpfs needed): after frame 3 every SQLite commit reports a full disk
    until the store gives up its space reserve, as a real full disk would behave."""
    store, rig = Store(tmp_path / "st"), make_rig()
    info = create_session(store, Plan.from_dict(SMALL_PLAN), rig, name="s", reserve_bytes=0)
    reserve = tmp_path / "st" / "locks" / store_mod.RESERVE_NAME
    real_db, full = store._db, {"on": False}

    class FullDisk:  # the connection, but COMMIT fails with SQLITE_FULL while the disk is full
        def __getattr__(self, name):
            return getattr(real_db, name)

        def execute(self, sql, *args):
            if sql == "COMMIT" and full["on"] and reserve.exists():
                exc = sqlite3.OperationalError("database or disk is full")
                exc.sqlite_errorcode = sqlite3.SQLITE_FULL
                raise exc
            return real_db.execute(sql, *args)

    store._db = FullDisk()
    runner = Runner(rig, store, "s", reserve_bytes=0)
    runner.bus.subscribe(lambda e: full.update(on=full["on"] or (
        e.kind == EventKind.FRAME_STORED and e.data["frames_done"] == 3)))
    assert runner.run() == "paused"
    assert store.session("s").state == "paused" and not reserve.exists()
    kinds = [e["kind"] for e in store.events(info.id)]
    assert "low_disk" in kinds and kinds[-1] == "paused"
    full["on"] = False
    assert Runner(rig, store, "s", reserve_bytes=0).run() == "done"
    assert store.progress(info.id).frames_stored == 24 and reserve.exists()
    store._db = real_db
    store.close()


def test_code_version_is_computed_outside_the_write_lock(tmp_path, monkeypatch):
    """The git subprocess ran inside the write transaction (holding the database lock)."""
    store_version.code_version.cache_clear()
    seen = []

    def probe():
        seen.append(store._db.in_transaction)
        return "gonio test"
    monkeypatch.setattr(store_version, "code_version", probe)
    with Store(tmp_path / "st") as store:
        sid = store.create_session("s", plan={}, plan_hash="h", steps=[]).id
        store.add_calibration(sid, "dark", result={"level": 1})
        assert seen == [False] and store.results(sid)[0].code_version == "gonio test"


@pytest.mark.parametrize("size, frame_bytes", [("16k", 500), ("400k", 300_000)])
@pytest.mark.parametrize("target", ["out", "out.tar", "out.zip", "."])
def test_export_to_a_full_disk_says_so_and_leaves_no_partial_files(tmp_path, size, frame_bytes,
                                                                   target):
    """16k: the database copy itself fails (SQLite backup); 400k: a frame file does."""
    root = tmp_path / "st"
    with Store(root) as st:
        sid = st.create_session("s1", plan={}, plan_hash="h", steps=[{"frames": 2}]).id
        for i in range(2):
            st.add_frame(sid, 0, i, 0, data=os.urandom(frame_bytes), filename=f"f{i}.dng",
                         format="dng", exposure_requested_s=0.01, exposure_s=0.01,
                         completes_step=i == 1)
    with _small_tmpfs(tmp_path / "disk", size) as disk:
        r = _run("export", "s1", str(disk / target), "--store", str(root))
        assert r.exit_code == 2 and "no space left" in r.output and str(disk) in r.output, r.output
        assert list(disk.iterdir()) == []  # "." : the disk's own empty folder is emptied again
