"""Crash safety: a subprocess running a session is SIGKILLed at write/rename/commit hook points
and at random moments; after each kill, ``resume`` finishes the session with exactly the planned
frames, no duplicates, no orphans, every hash verified.

Hook-point and random-time kills run in forked children (milliseconds each, so many points can
be covered); chained kills run the session in fresh interpreters, as the CLI would.
"""
from __future__ import annotations

import io
import multiprocessing
import os
import random
import shutil
import signal
import subprocess
import sys
import time
from contextlib import redirect_stdout
from pathlib import Path

import pytest

from capture import store as store_mod
from capture.store import crash as store_crash
from capture.store import Store, sha256_file
from crash_child import run_session

CHILD = Path(__file__).with_name("crash_child.py")
N_ANGLES = 4                     # steps; 2 exposures each
HOOK_NAMES = {"object_half_written", "object_fsynced", "object_renamed", "before_commit",
              "after_commit"}
FORK = multiprocessing.get_context("fork")


@pytest.fixture(autouse=True)
def _scratch_store(monkeypatch):
    # a SIGKILL cannot tell fsynced pages from cached ones (the kernel keeps both); skipping fsync
    # keeps the write -> rename -> commit order under test and makes each child much faster
    monkeypatch.setenv("GONIO_STORE_DURABLE", "0")
    monkeypatch.delenv("GONIO_CRASH_AFTER", raising=False)


def _forked(store_dir: Path, after: int | None, n_angles: int, err_path: Path,
            reached=None, frames: int = 0) -> None:
    """Child body: arm the kill hook, run the session, exit with its status. ``reached`` (an
    Event) is set once ``frames`` frames of the session are stored."""
    if after is not None:
        os.environ["GONIO_CRASH_AFTER"] = str(after)
    store_crash.count = 0
    fd = os.open(err_path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC)
    os.dup2(fd, 2)

    def progress(e):
        if e.data.get("frames_done", 0) >= frames:
            reached.set()
    with redirect_stdout(io.StringIO()):
        code = run_session(store_dir, n_angles, progress if reached is not None else None)
    os._exit(code)


def _fork_run(store_dir: Path, after: int | None = None, n_angles: int = N_ANGLES) -> tuple[int, str]:
    err = store_dir.with_suffix(".err")
    store_dir.parent.mkdir(parents=True, exist_ok=True)
    p = FORK.Process(target=_forked, args=(store_dir, after, n_angles, err))
    p.start()
    p.join(60)
    return p.exitcode, err.read_text() if err.exists() else ""


def _exec_run(store_dir: Path, after: int | None = None, n_angles: int = N_ANGLES):
    env = dict(os.environ)
    if after is not None:
        env["GONIO_CRASH_AFTER"] = str(after)
    return subprocess.Popen([sys.executable, str(CHILD), str(store_dir), str(n_angles)], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _count_hooks(store_dir: Path, n_angles: int) -> int:
    p = _exec_run(store_dir, after=10**9, n_angles=n_angles)
    out, err = p.communicate(timeout=60)
    assert p.returncode == 0, err
    return int(out.split("hooks=")[1])


def _check_consistent(store_dir: Path) -> None:
    """Invariants that hold at every instant, crash or not: every row's file is there and
    intact, no key twice, a done step has exactly its planned frames."""
    if not (store_dir / store_mod.DB_NAME).exists():
        return
    with Store(store_dir) as st:
        if not st.sessions():
            return  # killed before the session was committed
        info = st.session("crash")
        frames = st.frames(info.id)
        keys = [(f.step, f.bracket_index, f.repeat) for f in frames]
        assert len(keys) == len(set(keys))
        for f in frames:
            assert sha256_file(st.object_path(f.sha256)) == f.sha256
        assert st.verify("crash").incomplete_steps == []


def _check_complete(store_dir: Path, n_angles: int) -> None:
    with Store(store_dir) as st:
        info = st.session("crash")
        assert info.state == "done"
        keys = sorted((f.step, f.bracket_index, f.repeat) for f in st.frames(info.id))
        assert keys == [(s, b, 0) for s in range(n_angles) for b in range(2)]
        report = st.verify("crash")
        assert report.ok, report  # no missing, corrupt or orphaned files
        assert report.checked == 2 * n_angles  # unique bytes per shot: one file per frame


def _hook_kills(tmp: Path, hooks: list[int], n_angles: int) -> list[str]:
    where = []
    for h in hooks:
        store_dir = tmp / f"hook{h}"
        code, err = _fork_run(store_dir, after=h, n_angles=n_angles)
        assert code == -signal.SIGKILL, f"expected a kill at hook {h}: {err}"
        where.append(err.split("GONIO_CRASH at ")[1].split()[0])
        _check_consistent(store_dir)
        code, err = _fork_run(store_dir, n_angles=n_angles)
        assert code == 0, f"resume after a kill at hook {h} ({where[-1]}) failed: {err}"
        _check_complete(store_dir, n_angles)
    return where


def test_sigkill_at_hook_points_then_resume(tmp_path):
    total = _count_hooks(tmp_path / "reference", N_ANGLES)
    assert total >= 40
    # every other point (hook names repeat with an odd period, so all kinds are hit), last included
    hooks = sorted({*range(1, total + 1, 2), total})
    where = _hook_kills(tmp_path, hooks, N_ANGLES)
    assert len(hooks) >= 20
    assert HOOK_NAMES == set(where)  # mid-file-write, after rename, mid-commit, after commit


def _frames_stored(store_dir: Path) -> int:
    if not (store_dir / store_mod.DB_NAME).exists():
        return 0
    with Store(store_dir) as st:
        return len(st.frames(st.session("crash").id)) if st.sessions() else 0


def test_sigkill_while_resume_redoes_a_half_done_step(tmp_path):
    # kill the first run right after one frame of a step committed, then kill the resume at each
    # hook point while it re-does that step (replacing the stored frame, then deleting its old
    # file): every row keeps its file at every instant
    half = None
    for h in range(1, 60):
        store_dir = tmp_path / f"first{h}"
        assert _fork_run(store_dir, after=h)[0] == -signal.SIGKILL
        if _frames_stored(store_dir) % 2 == 1:
            half = store_dir
            break
    assert half is not None, "no kill point left a step half done"
    names = set()
    for k in range(1, 13):
        store_dir = tmp_path / f"resume{k}"
        shutil.copytree(half, store_dir)
        code, err = _fork_run(store_dir, after=k)
        assert code == -signal.SIGKILL, f"expected a kill at resume hook {k}: {err}"
        names.add(err.split("GONIO_CRASH at ")[1].split()[0])
        _check_consistent(store_dir)
        assert _fork_run(store_dir)[0] == 0
        _check_complete(store_dir, N_ANGLES)
    assert {"object_half_written", "before_commit", "after_commit"} <= names


def test_sigkill_at_random_times_then_resume(tmp_path):
    # a random frame count, then a random 0-3 ms: the kill lands somewhere in the next capture,
    # file write or commit, anywhere in the session, however fast or loaded the machine is
    rng = random.Random(20261121)
    kills, at_frames = 0, []
    for i in range(10):
        if kills == 5:
            break
        store_dir = tmp_path / f"random{i}"
        reached, frames = FORK.Event(), rng.randrange(0, 2 * N_ANGLES - 1)
        p = FORK.Process(target=_forked, args=(store_dir, None, N_ANGLES, tmp_path / f"r{i}.err",
                                               reached, frames))
        p.start()
        assert reached.wait(60)
        time.sleep(rng.uniform(0, 0.003))
        os.kill(p.pid, signal.SIGKILL)
        p.join(60)
        if p.exitcode == -signal.SIGKILL:  # (a child may finish before its kill: not counted)
            kills += 1
            at_frames.append(_frames_stored(store_dir))
        _check_consistent(store_dir)
        code, err = _fork_run(store_dir)
        assert code == 0, err
        _check_complete(store_dir, N_ANGLES)
    assert kills == 5
    assert any(0 < n < 2 * N_ANGLES for n in at_frames), at_frames  # some landed mid-session


def test_repeated_kills_during_resume(tmp_path):
    store_dir = tmp_path / "chain"
    for after in (9, 4, 17, 2):  # the resumes themselves are killed
        p = _exec_run(store_dir, after=after)
        p.communicate(timeout=60)
        assert p.returncode == -signal.SIGKILL
        _check_consistent(store_dir)
    r = _exec_run(store_dir)
    out, err = r.communicate(timeout=60)
    assert r.returncode == 0, err
    _check_complete(store_dir, N_ANGLES)


# ~30 s of process launches on an idle 2-core machine (24 angles and 20 random kills took
# ~95 s, 12 and 10 took 56 s: more than the suite, ~14 minutes, can afford under CI's 15)
def test_sigkill_at_every_hook_point_big_session(tmp_path):
    n_angles = 8
    total = _count_hooks(tmp_path / "reference", n_angles)
    _hook_kills(tmp_path, list(range(1, total + 1)), n_angles)
    rng = random.Random(7)
    for i in range(6):
        store_dir = tmp_path / f"random{i}"
        p = _exec_run(store_dir, n_angles=n_angles)
        time.sleep(rng.uniform(0.3, 2.0))
        p.send_signal(signal.SIGKILL)
        p.communicate(timeout=60)
        _check_consistent(store_dir)
        assert _exec_run(store_dir, n_angles=n_angles).wait(60) == 0
        _check_complete(store_dir, n_angles)
