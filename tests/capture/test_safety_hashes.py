"""A store whose rows hold crafted object hashes: no path is built from them (issue 15 review)."""
from __future__ import annotations

import hashlib
import os
import sqlite3
from pathlib import Path

import pytest
from typer.testing import CliRunner

from capture.cli import app as gonio_app
from capture.cli.session import app as session_app
from capture.store import Store, StoreDamaged

cli = CliRunner()


def _store(root: Path) -> str:
    with Store(root) as st:
        sid = st.create_session("s1", plan={"name": "s1"}, plan_hash="h", steps=[{"frames": 1}]).id
        st.add_calibration(sid, "dark", result={}, artifacts={"a": os.urandom(30)})
        return st.add_frame(sid, 0, 0, 0, data=os.urandom(300), filename="f.dng", format="dng",
                            exposure_requested_s=0.01, exposure_s=0.01, completes_step=True)[1]


def _craft(root: Path, sha: str, table: str = "frames") -> None:
    db = sqlite3.connect(root / "gonio.sqlite")
    db.execute(f"UPDATE {table} SET sha256 = ?", (sha,))
    db.commit()
    db.close()


def _files(root: Path) -> dict[str, str]:
    return {str(p): hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(root.rglob("*"))
            if p.is_file() and not p.name.endswith(("-wal", "-shm"))}


def _hostile(tmp_path: Path, victim: Path) -> list[str]:
    """Hashes that lead to ``victim``: absolute (``'..' + '/abs'``), relative, upper-case hex,
    and one hex digit short of a hash."""
    return [".." + str(victim), "../../victim.txt", "AB" * 32, "a" * 63]


@pytest.mark.parametrize("which", range(4))
@pytest.mark.parametrize("table", ["frames", "result_objects"])
def test_crafted_hashes_are_refused_and_touch_no_file(tmp_path, which, table):
    victim = tmp_path / "victim.txt"
    victim.write_text("precious")
    root = tmp_path / "st"
    _store(root)
    _craft(root, _hostile(tmp_path, victim)[which], table)
    before = _files(tmp_path)
    for args in (["list"], ["show", "s1"], ["verify", "s1"], ["export", "s1", str(tmp_path / "o")],
                 ["export", "s1", str(tmp_path / "o.tar")]):
        r = cli.invoke(session_app, [*args, "--store", str(root)])
        assert r.exit_code == 2 and "not 64 lowercase hex" in r.output, (args, r.output)
        assert "Traceback" not in r.output
    r = cli.invoke(gonio_app, ["calibrate", "s1", "--store", str(root), "--out", str(tmp_path / "o")])
    assert r.exit_code == 2 and "not 64 lowercase hex" in r.output, r.output
    with pytest.raises(StoreDamaged, match="not 64 lowercase hex"):
        Store(root)  # the writing open too
    assert _files(tmp_path) == before and victim.read_text() == "precious"
    assert not (tmp_path / "o").exists() and not (tmp_path / "o.tar").exists()


def test_object_path_refuses_a_malformed_hash_even_after_the_open(tmp_path):
    """A row crafted while the store is open (another process) is refused where paths are built:
    reading, verifying, exporting and dropping an unreferenced object."""
    victim = tmp_path / "victim.txt"
    victim.write_text("precious")
    root = tmp_path / "st"
    _store(root)
    with Store(root) as st:
        _craft(root, ".." + str(victim))
        for call in (lambda: st.read_object(".." + str(victim)), lambda: st.verify("s1"),
                     lambda: st.export("s1", tmp_path / "out"),
                     lambda: st._drop_if_unreferenced("../../victim.txt")):
            with pytest.raises(StoreDamaged, match="not 64 lowercase hex"):
                call()
    assert victim.read_text() == "precious" and not (tmp_path / "out").exists()


def test_a_crafted_archive_is_refused_and_its_temporary_folder_removed(tmp_path, monkeypatch):
    import tarfile
    import tempfile
    private = tmp_path / "tmp"
    private.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(private))
    victim = tmp_path / "victim.txt"
    victim.write_text("precious")
    root = tmp_path / "st"
    _store(root)
    _craft(root, ".." + str(victim))
    archive = tmp_path / "crafted.tar"
    with tarfile.open(archive, "w") as t:
        t.add(root, arcname="st")
    for args in (["verify", "s1"], ["export", "s1", str(tmp_path / "out")]):
        r = cli.invoke(session_app, [*args, "--store", str(archive)])
        assert r.exit_code == 2 and "not 64 lowercase hex" in r.output, (args, r.output)
    assert victim.read_text() == "precious" and list(private.iterdir()) == []
