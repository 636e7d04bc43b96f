"""Nothing stored is lost and nothing outside the store changes (issue 19 #1 #2 #11 #12): archive
stores refuse writes, archive bombs are capped, a restored database backup never lets a capture
delete newer frames (they are quarantined and ``gonio session rebuild-index`` takes them back,
reproducing the sessions it lost), a foreign database is left alone, stored control characters
are shown escaped."""
from __future__ import annotations

import hashlib
import io
import shutil
import sqlite3
import tarfile
import tempfile
import zipfile
from pathlib import Path

import pytest
from typer.testing import CliRunner

from capture.cli import app
from capture.plan import Plan
from capture.runner import Runner, create_session
from capture.store import ForeignDatabase, ObjectDamaged, Store, StoreError
from capture.store import archive
from capture.store.archive import MAX_EXPANSION
from capture_fakes import SMALL_PLAN, make_rig

cli = CliRunner()
TINY = {**SMALL_PLAN, "turntable": {"angles_deg": [0, 90]}, "polarizer": {"angles_deg": [0]}}


def _snapshot(root: Path) -> dict[str, str]:
    """Every file's SHA-256 under ``root`` (SQLite's -wal/-shm lock files aside)."""
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file() and not p.name.endswith(("-wal", "-shm"))}


def _capture(root: Path, name: str) -> None:
    with Store(root, durable=False) as st:
        rig = make_rig()
        create_session(st, Plan.from_dict(TINY), rig, name=name, reserve_bytes=0)
        assert Runner(rig, st, name, reserve_bytes=0).run() == "done"


def _sessions(root: Path) -> dict[str, tuple]:
    """Each session's state, steps (spec, done) and frames (key, hash, exposure), as stored."""
    with Store(root, readonly=True) as st:
        return {s.name: (s.state, s.plan_hash, st.steps(s.id),
                         [(f.step, f.bracket_index, f.repeat, f.sha256, f.exposure_s, f.filename)
                          for f in st.frames(s.id)], len(st.rig_snapshots(s.id)))
                for s in st.sessions()}


# -- #2: a restored backup, quarantine, rebuild-index -------------------------------------------
def test_a_restored_backup_loses_no_frames_and_rebuild_index_reproduces_the_lost_session(tmp_path):
    root = tmp_path / "store"
    _capture(root, "first")
    shutil.copy(root / "gonio.sqlite", tmp_path / "backup.sqlite")   # the backup, before "second"
    _capture(root, "second")
    before = _sessions(root)
    frames_of_second = {f[3] for f in before["second"][3]}
    (root / "gonio.sqlite").unlink()
    shutil.copy(tmp_path / "backup.sqlite", root / "gonio.sqlite")   # as the damaged-db message advises
    _capture(root, "third")        # its writer's garbage collection meets second's unlisted frames
    kept = {p.name for p in (root / "quarantine").iterdir()}
    assert frames_of_second <= kept                       # quarantined, not deleted
    r = cli.invoke(app, ["session", "list", "--store", str(root)])
    assert f"{len(kept)} frame file(s) in" in " ".join(r.output.split()) and "rebuild-index" in r.output
    r = cli.invoke(app, ["session", "rebuild-index", "--store", str(root)])
    assert r.exit_code == 0 and "sessions restored: second" in r.output, r.output
    after = _sessions(root)
    assert after["second"] == before["second"] and after["first"] == before["first"]
    assert list((root / "quarantine").iterdir()) == []
    v = cli.invoke(app, ["session", "verify", "second", "--store", str(root)])
    assert v.exit_code == 0, v.output
    again = cli.invoke(app, ["session", "rebuild-index", "--store", str(root)])   # idempotent
    assert "sessions restored: none; frame rows restored: 0" in again.output and _sessions(root) == after


def test_a_lost_database_is_rebuilt_from_the_journals_and_frame_files(tmp_path):
    root = tmp_path / "store"
    _capture(root, "only")
    before = _sessions(root)
    with Store(root, readonly=True) as st:   # an export carries the session's journal with it
        st.export("only", tmp_path / "export")
    (tmp_path / "export" / "gonio.sqlite").unlink()
    assert cli.invoke(app, ["session", "rebuild-index", "--store", str(tmp_path / "export")]).exit_code == 0
    assert _sessions(tmp_path / "export") == before
    (root / "gonio.sqlite").unlink()
    r = cli.invoke(app, ["session", "list", "--store", str(root)])
    assert r.exit_code == 2 and "gonio session rebuild-index" in " ".join(r.output.split())
    r = cli.invoke(app, ["session", "rebuild-index", "--store", str(root)])
    assert r.exit_code == 0 and "sessions restored: only" in r.output
    assert _sessions(root) == before


def test_a_store_from_before_journals_is_verified_journaled_and_rebuilt_or_says_what_it_cannot(tmp_path):
    """A store written before journals existed (the same store with journal/ gone): verify works
    and warns; a lost database is rebuilt as far as it can be and the command names what it cannot
    put back, keeping the files; rebuild-index (and any writer) journals the old sessions from
    their rows, after which a lost database is rebuilt exactly (issue 19 #2)."""
    root = tmp_path / "store"
    _capture(root, "old")
    shutil.rmtree(root / "journal")
    before = _sessions(root)
    files = {f[3] for f in before["old"][3]}
    v = cli.invoke(app, ["session", "verify", "old", "--store", str(root)])
    said = " ".join(v.output.split())
    assert v.exit_code == 0 and "note: session old has no journal (recorded before journals)" in said, v.output
    assert "rebuild-index" in said and "ok: every file is present" in said
    lost = tmp_path / "lost"   # the database lost before any journal was written
    shutil.copytree(root, lost)
    (lost / "gonio.sqlite").unlink()
    objects = _snapshot(lost / "objects")
    r = cli.invoke(app, ["session", "rebuild-index", "--store", str(lost)])
    said = " ".join(r.output.split())
    assert r.exit_code == 0 and "sessions restored: none" in said, r.output
    assert f"{len(files)} file(s) (" in said and "are listed by no database row and no journal" in said
    assert "no session can be rebuilt from them" in said
    assert _snapshot(lost / "objects") == objects   # kept as they were
    writable = tmp_path / "writer"   # any writer of an old session journals it
    shutil.copytree(root, writable)
    with Store(writable, durable=False) as st, st.writer("old"):
        pass
    assert len(list((writable / "journal").glob("*-old.jsonl"))) == 1
    r = cli.invoke(app, ["session", "rebuild-index", "--store", str(root)])
    assert r.exit_code == 0 and "journals written for the session(s) recorded before journals: old" in r.output
    assert "note:" not in cli.invoke(app, ["session", "verify", "old", "--store", str(root)]).output
    for store in (root, writable):
        (store / "gonio.sqlite").unlink()
        r = cli.invoke(app, ["session", "rebuild-index", "--store", str(store)])
        assert r.exit_code == 0 and "sessions restored: old" in r.output, r.output
        assert _sessions(store) == before


def test_remove_orphans_quarantines_and_purge_keeps_young_files(tmp_path):
    with Store(tmp_path, durable=False) as st:
        stray = st.put_object(b"a frame no row lists")
        assert st.remove_orphans() == [f"objects/{stray[:2]}/{stray[2:]}"]
        assert [p.name for p in st.quarantined()] == [stray]
        assert st.purge_quarantine() == [] and st.quarantined()          # a week's grace
        assert st.purge_quarantine(min_age_s=0) == [f"quarantine/{stray}"]


def test_a_truncated_frame_is_named_by_its_step_when_read(tmp_path):
    _capture(tmp_path, "s1")
    with Store(tmp_path, durable=False) as st:
        f = st.frames(st.session("s1").id)[3]
        path = st.object_path(f.sha256)
        path.chmod(0o644)
        path.write_bytes(path.read_bytes()[:100])
        with pytest.raises(ObjectDamaged, match=rf"is truncated \(100 of {f.size} bytes\); used by session "
                                                rf"'s1' step {f.step} frame {f.bracket_index} of the bracket"):
            st.read_object(f.sha256)


# -- #1: archives are read-only ------------------------------------------------------------------
@pytest.fixture(scope="module")
def archive_store(tmp_path_factory) -> Path:
    tmp = tmp_path_factory.mktemp("archive")
    _capture(tmp / "lab", "s1")
    with Store(tmp / "lab", readonly=True) as st:
        return st.export("s1", tmp / "q1.tar")


@pytest.mark.parametrize("args", [
    ["capture", "run", "PLAN", "--rig", "sim", "--session", "newone", "-q"],
    ["capture", "resume", "s1", "--rig", "sim"],
    ["calibrate", "s1"],
    ["process", "s1"],
    ["session", "rebuild-index"],
])
def test_a_command_that_writes_refuses_an_archive_store(archive_store, tmp_path, args):
    archive = archive_store
    (tmp_path / "plan.toml").write_text('[turntable]\nangles_deg = [0]\n')
    before = archive.read_bytes()
    files = sorted(p.name for p in tmp_path.iterdir()), sorted(p.name for p in archive.parent.iterdir())
    r = cli.invoke(app, [a.replace("PLAN", str(tmp_path / "plan.toml")) for a in args] + ["--store", str(archive)])
    said = " ".join(r.output.split())
    assert r.exit_code == 2 and "is an exported archive: gonio reads it but never writes to it" in said
    assert "tar -xf" in said and "Traceback" not in said
    assert archive.read_bytes() == before
    assert (sorted(p.name for p in tmp_path.iterdir()), sorted(p.name for p in archive.parent.iterdir())) == files
    with Store.open(archive) as st:   # opened in Python: read-only, the same message on a write
        with pytest.raises(StoreError, match="never writes to it"):
            st.create_session("x", plan={}, plan_hash="h", steps=[])


# -- #11: archive bombs ----------------------------------------------------------------------------
@pytest.mark.parametrize("kind", ["zip", "tar.gz"])
def test_an_archive_bomb_is_refused_before_it_fills_the_disk(tmp_path, kind, monkeypatch):
    # the caps scaled down (no 64 MB slack) so that an 8 MB bomb stands for the 1.6 GB one
    monkeypatch.setattr(archive, "EXPANSION_SLACK_BYTES", 0)
    big = 8 << 20                            # zeros: deflate packs them ~1000 x
    bomb = tmp_path / f"bomb.{kind}"
    if kind == "zip":
        with zipfile.ZipFile(bomb, "w", zipfile.ZIP_DEFLATED) as z:
            z.writestr("st/gonio.sqlite", b"x")
            z.writestr("st/objects/zz", bytes(big))
    else:
        with tarfile.open(bomb, "w:gz") as t:
            info = tarfile.TarInfo("st/objects/zz")
            info.size = big
            t.addfile(info, io.BytesIO(bytes(big)))
    assert bomb.stat().st_size * MAX_EXPANSION < big
    before = {p.name for p in Path(tempfile.gettempdir()).glob("gonio-store-*")}
    r = cli.invoke(app, ["session", "list", "--store", str(bomb)])
    said = " ".join(r.output.split())
    assert r.exit_code == 2 and "refusing to extract it" in said and f"{MAX_EXPANSION} x the archive" in said
    assert {p.name for p in Path(tempfile.gettempdir()).glob("gonio-store-*")} == before   # nothing left


# -- #12: a foreign database, control characters ----------------------------------------------------
def test_a_foreign_database_with_gonio_like_tables_is_left_untouched(tmp_path):
    db = sqlite3.connect(tmp_path / "gonio.sqlite")
    db.executescript("CREATE TABLE sessions (id INTEGER PRIMARY KEY, title TEXT); "
                     "CREATE TABLE schema_version (version INTEGER); INSERT INTO schema_version VALUES (1);"
                     "INSERT INTO sessions (title) VALUES ('their data');")
    db.commit()
    db.close()
    before = _snapshot(tmp_path)
    with pytest.raises(ForeignDatabase, match="not a gonio store .* it lacks"):
        Store(tmp_path)
    r = cli.invoke(app, ["capture", "run", "nothing.toml", "--rig", "sim", "--store", str(tmp_path)])
    assert r.exit_code == 2
    r = cli.invoke(app, ["session", "list", "--store", str(tmp_path)])
    assert r.exit_code == 2 and "leaves it untouched" in " ".join(r.output.split())
    assert _snapshot(tmp_path) == before


def test_terminal_escape_sequences_in_stored_text_are_shown_escaped(tmp_path):
    with Store(tmp_path, durable=False) as st:
        rig = make_rig()
        plan = Plan.from_dict({**TINY, "object": "\x1b]0;pwned\x07\x1b[31mred\u202e"})
        create_session(st, plan, rig, name="s1", reserve_bytes=0)
    for args in (["session", "list"], ["session", "show", "s1"]):
        r = cli.invoke(app, [*args, "--store", str(tmp_path)])
        assert r.exit_code == 0 and "\x1b" not in r.output and "\u202e" not in r.output
        assert "\\x1b[31mred\\u202e" in r.output
