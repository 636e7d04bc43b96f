"""Session names are checked at every entry point, and no path built from one leaves its folder
(issue 15: ``--session ..`` let ``session export`` write outside its target and delete sessions)."""
from __future__ import annotations

import sqlite3
import tarfile
import zipfile

import pytest
from typer.testing import CliRunner

from capture.cli.capture import app as capture_app
from capture.cli.session import app as session_app
from capture.plan import Plan
from capture.runner import create_session
from capture.store import InvalidName, Store, check_session_name, safe_name_from

cli = CliRunner()
PLAN = {"name": "p", "turntable": {"angles_deg": [0]}, "exposure": {"base_s": 0.01, "stops": [0]}}
BAD = [".", "..", "../x", "a/b", "/abs", "a\\b", "-rf", "", " a", "a\nb", "a\x1bb", "a\x00",
       "[bold]n", "x" * 101, "é", "a b"]


def _files(root):
    """Paths under ``root``; SQLite's WAL index files (a reader's lock state, no content) aside."""
    return sorted(str(p.relative_to(root)) for p in root.rglob("*")
                  if not p.name.endswith(("-wal", "-shm")))


@pytest.mark.parametrize("name", BAD)
def test_unsafe_names_are_refused_by_the_store_and_the_runner(tmp_path, name):
    with Store(tmp_path / "st") as st:
        with pytest.raises(InvalidName, match="session name"):
            st.create_session(name, plan={}, plan_hash="h", steps=[])
        with pytest.raises(InvalidName):
            create_session(st, Plan.from_dict(PLAN), None, name=name, reserve_bytes=0)
        assert st.sessions() == []


def test_safe_names_pass_and_plan_names_are_made_safe():
    for name in ("a", "_x", "run-2026.11.24_1", "A" * 100):
        assert check_session_name(name) == name
    assert safe_name_from("../../etc [bold]x y") == "etc-bold-x-y"
    assert safe_name_from("..") == "session" and safe_name_from("") == "session"
    check_session_name(safe_name_from("ünïcode / plan") + "-20261124-070000")


def test_cli_run_refuses_dotdot_before_touching_anything(tmp_path):
    plan = tmp_path / "plan.toml"
    plan.write_text('name = "p"\n[turntable]\nangles_deg = [0]\n[exposure]\nbase_s = 0.01\n'
                    'stops = [0]\n')
    for name in ("..", "."):
        r = cli.invoke(capture_app, ["run", str(plan), "--rig", "sim", "--store",
                                     str(tmp_path / "st"), "--session", name, "--quiet"])
        assert r.exit_code == 2, r.output
        assert "is not allowed" in r.output and "Traceback" not in r.output
    assert not (tmp_path / "st").exists()


def _legacy_store(root):
    """A store written before names were checked: sessions '..' and 'keep', each with a frame."""
    with Store(root) as st:
        for name in ("keep", "dots"):
            sid = st.create_session(name, plan={}, plan_hash="h", steps=[{"frames": 1}]).id
            st.add_frame(sid, 0, 0, 0, data=name.encode() * 10, filename="a.dng", format="dng",
                         exposure_requested_s=0.01, exposure_s=0.01, completes_step=True)
    db = sqlite3.connect(root / "gonio.sqlite")
    db.execute("UPDATE sessions SET name = '..' WHERE name = 'dots'")
    db.commit()
    db.close()


@pytest.mark.parametrize("dest", ["OUT.tar", "OUT.zip", "OUT"])
def test_exporting_a_dotdot_session_writes_only_its_target_and_deletes_nothing(tmp_path, dest):
    root = tmp_path / "lab" / "st"
    _legacy_store(root)
    before_store, before_lab = _files(root), _files(tmp_path / "lab")
    out = tmp_path / "lab" / dest
    r = cli.invoke(session_app, ["export", "..", str(out), "--store", str(root)])
    assert r.exit_code == 0, r.output
    new = set(_files(tmp_path / "lab")) - set(before_lab)
    assert new and all(p == dest or p.startswith(dest + "/") for p in new), new
    assert _files(root) == before_store
    with Store(root) as st:
        assert [s.name for s in st.sessions()] == ["keep", ".."]
    if dest.endswith(".tar"):
        with tarfile.open(out) as t:
            assert all(".." not in m.name.split("/") for m in t.getmembers())
    if dest.endswith(".zip"):
        with zipfile.ZipFile(out) as z:
            assert all(".." not in n.split("/") for n in z.namelist())
    with Store.open(out) as ex:  # still a complete store of that one session
        assert [s.name for s in ex.sessions()] == [".."] and ex.verify("..").ok


@pytest.mark.parametrize("dest", ["OUT.tar", "sub"])
def test_exporting_into_the_store_itself_is_refused(tmp_path, dest):
    root = tmp_path / "st"
    _legacy_store(root)
    before = _files(root)
    r = cli.invoke(session_app, ["export", "keep", str(root / dest), "--store", str(root)])
    assert r.exit_code == 2 and "inside the store" in r.output, r.output
    assert _files(root) == before


def test_the_name_rule_says_ascii_letters():
    """'é' is a letter but not an ASCII one: the message must not say plain 'letters'."""
    with pytest.raises(InvalidName, match="ASCII letters"):
        check_session_name("café")
