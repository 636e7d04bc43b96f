"""Every ``gonio`` command's options given hostile values: prints each invocation that ends in a
traceback (or an exit status other than 0-3) and the count.

Values: empty, NaN, inf, negative, 1e308, 20 digits; a folder where a file is wanted, ``/dev/full``,
``/dev/null``, an empty or random-bytes file, a missing folder; names with ``..``, ``/``, an
escape sequence, 5000 characters, a leading ``-``. Commands run in-process (Typer's runner) on a
small store in a temporary folder; ``gonio tui`` only with values it must refuse before starting,
``gonio demo`` only with ``--out`` values it must refuse. Issue 19: 15 tracebacks in 255 cases
before the fixes, none after.

Usage: ``python benchmarks/hostile_options.py [WORD]`` (WORD: only the cases whose arguments
contain it).
"""
from __future__ import annotations

import os
import signal
import sys
import tempfile
import traceback
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import trimesh  # noqa: E402
from typer.testing import CliRunner  # noqa: E402

from capture.cli import app  # noqa: E402
from capture.store import Store  # noqa: E402

NUMBERS = ["nan", "inf", "-1", "1e308", "-1e308", "0", "99999999999999999999"]
NAMES = ["", "../x", "/abs", "\x1b[31m", "a" * 5000, "-rf"]


def cases(t: Path) -> list[list[str]]:
    s, box, plan, folder, ok_out = str(t / "store"), str(t / "box.ply"), str(t / "plan.toml"), str(t / "folder"), str(t / "o")
    paths = ["", folder, "/dev/full", str(t / "empty"), str(t / "bin"), str(t / "missing" / "x"), "/dev/null"]
    out = []
    for p in paths:
        out += [["capture", "plan", p], ["capture", "run", p, "--rig", "sim", "--store", str(t / "st2")],
                ["capture", "resume", "s1", "--rig", "sim", "--store", s, "--plan", p],
                ["calibrate", "s1", "--store", s, "--out", p], ["calibrate", "s1", "--store", s, "--targets", p],
                ["process", "s1", "--store", s, "--mesh", p], ["process", "s1", "--store", s, "--targets", p, "--mesh", box],
                ["process", "s1", "--store", s, "--out", p, "--mesh", box],
                ["export", "s1", "--method", "lensch", "--out", p, "--store", s],
                ["export", "s1", "--method", "lensch", "--out", str(t / "new"), "--store", s, "--mesh", p],
                ["import", "diligent", p, "--store", str(t / "st3")], ["session", "export", "s1", p, "--store", s],
                ["session", "list", "--store", p], ["session", "verify", "s1", "--store", p],
                ["session", "rebuild-index", "--store", p], ["rig", "check", "--rig", p],
                ["rig", "sim", "--write", p, "--duration", "0.1", "--fast"]]
        if p not in (folder, str(t / "missing" / "x")):   # a folder demo may use would run a demo
            out.append(["demo", "--out", p])
    for n in NUMBERS:
        out += [["process", "s1", "--store", s, "--mesh", box, "--workers", n],
                ["process", "s1", "--store", s, "--mesh", box, "--memory-limit", n],
                ["import", "diligent", folder, "--store", str(t / "st3"), "--hold-out-every", n],
                ["rig", "home", "--rig", "sim", "--timeout", n], ["rig", "sim", "--duration", n, "--fast"],
                ["capture", "plan", plan, "--rig", "sim", "--sim-camera", n]]
    for nm in NAMES:
        out += [["process", nm, "--store", s], ["calibrate", nm, "--store", s], ["session", "show", nm, "--store", s],
                ["export", nm, "--method", "lensch", "--out", ok_out, "--store", s],
                ["capture", "resume", nm, "--rig", "sim", "--store", s],
                ["capture", "run", plan, "--rig", "sim", "--store", str(t / "st4"), "--session", nm],
                ["import", "diligent", folder, "--store", str(t / "st3"), "--session", nm],
                ["process", "s1", "--store", s, "--methods", nm, "--mesh", box],
                ["export", "s1", "--method", nm, "--out", ok_out, "--store", s],
                ["export", "s1", "--method", "lensch", "--format", nm, "--out", ok_out, "--store", s],
                ["process", "s1", "--store", s, "--scheduler", nm, "--mesh", box],
                ["rig", "check", "--rig", "sim", "--role", nm],
                ["rig", "sim", "--kinematics", nm, "--duration", "0.1", "--fast"],
                ["capture", "run", plan, "--rig", "sim", "--store", str(t / "st4"), "--operator", nm, "--session", "ok"]]
    out += [["tui", "--poll", "nan"], ["tui", "--poll", "inf"], ["tui", "--poll", "-1"], ["tui", "--store", ""],
            ["tui", "--store", " "]]
    return out


def make_inputs(t: Path) -> None:
    with Store(t / "store", durable=False) as st:
        sid = st.create_session("s1", plan={}, plan_hash="h", steps=[{"kind": "measure", "frames": 1}]).id
        st.add_frame(sid, 0, 0, 0, data=b"raw" * 50, filename="a.dng", format="dng", exposure_requested_s=0.01,
                     exposure_s=0.01, completes_step=True)
        st.set_state(sid, "done")
    trimesh.creation.box((50.0, 50.0, 50.0)).export(t / "box.ply")
    (t / "plan.toml").write_text('[turntable]\nangles_deg = [0]\n[exposure]\nbase_s = 0.01\n')
    (t / "folder").mkdir()
    (t / "empty").write_text("")
    (t / "bin").write_bytes(os.urandom(200))


def main() -> None:
    only = sys.argv[1] if len(sys.argv) > 1 else None
    with tempfile.TemporaryDirectory(prefix="gonio-hostile-") as tmp:
        t = Path(tmp)
        make_inputs(t)
        todo = [c for c in cases(t) if only is None or only in " ".join(c)]
        bad = 0
        for c in todo:
            signal.alarm(120)   # a case that started something long is a finding too
            r = CliRunner().invoke(app, c)
            signal.alarm(0)
            if r.exception is not None and not isinstance(r.exception, SystemExit):
                bad += 1
                last = traceback.format_exception(r.exception)[-1].strip()
                print(f"traceback: gonio {' '.join(repr(a) if not a or ' ' in a else a[:60] for a in c)} -> {last[:200]}")
            elif r.exit_code not in (0, 1, 2, 3):
                bad += 1
                print(f"exit {r.exit_code}: gonio {' '.join(a[:60] for a in c)}")
        print(f"{len(todo)} hostile invocations, {bad} ended in a traceback or an unknown exit status")
    sys.exit(1 if bad else 0)


if __name__ == "__main__":
    main()
