"""``gonio capture plan|run|resume`` and ``gonio session list|show|verify|export``."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

from typer.testing import CliRunner

from capture.cli.capture import app as capture_app
from capture.cli.session import app as session_app
from capture.plan import Plan
from capture.rigs import to_toml
from capture.runner import create_session
from capture.store import Store
from capture_fakes import tolerant_sim_config

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "plan.toml"
TINY = """
name = "tiny"
object = "sphere"
[turntable]
angles_deg = [0, 90]
[light]
azimuth_deg = [0]
elevation_deg = [40]
[exposure]
base_s = 0.01
stops = [0]
"""
cli = CliRunner()


def _rig(tmp_path: Path) -> str:
    """The simulated lab from a rig file with generous reply timeouts (see capture_fakes)."""
    p = tmp_path / "rig.toml"
    p.write_text(to_toml(tolerant_sim_config()))
    return str(p)


def _plan(tmp_path: Path, text: str = TINY) -> Path:
    p = tmp_path / "plan.toml"
    p.write_text(text)
    return p


def test_plan_prints_steps_frames_bytes_time():
    r = cli.invoke(capture_app, ["plan", str(EXAMPLE)])
    assert r.exit_code == 0, r.output
    est = Plan.from_toml(EXAMPLE).estimate()
    assert f"steps {est.steps}, frames {est.frames}" in r.output
    assert "limits not checked" in r.output and "measure 240 steps / 720 frames" in r.output


def test_plan_with_sim_rig_lists_steps(tmp_path):
    r = cli.invoke(capture_app, ["plan", str(_plan(tmp_path)), "--rig", "sim", "--steps"])
    assert r.exit_code == 0, r.output
    assert "limits checked" in r.output and "steps 2, frames 2" in r.output
    assert "az 0° el 40°" in r.output
    # the simulated PTP camera's describe() has no image size; the built-in lab's [rig] table
    # states its resolution (320 x 240: a 16-bit mosaic and a header, not the 25 MB default)
    assert "frame size 219.1 kB (from the camera)" in r.output


def test_help_explains_plans_store_resume_and_exit_codes():
    text = " ".join(cli.invoke(capture_app, ["--help"]).output.split())
    for words in ("A plan is a TOML file", "examples/plan.toml", "DIR/objects/", "SHA-256",
                  "gonio capture resume NAME", "Exit status: 0 done, 3 paused", "4 aborted"):
        assert words in text, words
    text = " ".join(cli.invoke(capture_app, ["run", "--help"]).output.split())
    assert "Ctrl-C pauses after the current step" in text and "Exit status" in text
    text = " ".join(cli.invoke(capture_app, ["resume", "--help"]).output.split())
    assert "first step not done" in text and "refuses and lists the changed fields" in text
    text = " ".join(cli.invoke(session_app, ["--help"]).output.split())
    assert "gonio.sqlite" in text and "1 'verify' found" in text


def test_plan_errors_name_the_field(tmp_path):
    r = cli.invoke(capture_app, ["plan", str(_plan(tmp_path, TINY.replace("[40]", "[40, 88]"))),
                                 "--rig", _rig(tmp_path)])
    assert r.exit_code == 2
    assert "light.elevation_deg[1] = 88 is outside the positioner's limit 0..85" in r.output
    r = cli.invoke(capture_app, ["plan", str(_plan(tmp_path, TINY + "\n[extra]\nx = 1\n"))])
    assert r.exit_code == 2 and "plan: unknown key 'extra'" in r.output


def test_run_then_list_show_verify_export(tmp_path):
    store = tmp_path / "store"
    r = cli.invoke(capture_app, ["run", str(_plan(tmp_path)), "--rig", _rig(tmp_path), "--store", str(store),
                                 "--session", "one", "--quiet"])
    assert r.exit_code == 0, r.output
    assert "session one done" in r.output
    assert "frame size 25.0 MB assumed" in r.output and "frame size measured from the first frame" in r.output
    r = cli.invoke(session_app, ["list", "--store", str(store)])
    assert r.exit_code == 0 and "one" in r.output and "done" in r.output and "2/2" in r.output
    r = cli.invoke(session_app, ["show", "one", "--store", str(store)])
    assert r.exit_code == 0 and "steps 2/2, frames 2/2" in r.output and "SimCam PTP" in r.output
    r = cli.invoke(session_app, ["verify", "one", "--store", str(store)])
    assert r.exit_code == 0 and "2 file(s) checked" in r.output
    r = cli.invoke(session_app, ["export", "one", str(tmp_path / "one.zip"), "--store", str(store)])
    assert r.exit_code == 0, r.output
    r = cli.invoke(session_app, ["verify", "one", "--store", str(tmp_path / "one.zip")])
    assert r.exit_code == 0, r.output
    # damage one file and orphan another: verify says so and fails
    with Store(store) as st:
        f = st.frames(st.session("one").id)[0]
        path = st.object_path(f.sha256)
        orphan = st.put_object(b"stray")
    os.chmod(path, 0o644)
    path.write_bytes(b"damaged")
    r = cli.invoke(session_app, ["verify", "one", "--store", str(store)])
    assert r.exit_code == 1
    assert f"corrupt: {f.sha256}" in r.output and f"orphaned: objects/{orphan[:2]}/{orphan[2:]}" in r.output
    r = cli.invoke(session_app, ["verify", "one", "--store", str(store), "--remove-orphans"])
    assert r.exit_code == 1 and "took 1 orphaned file(s) out of objects/" in r.output  # still corrupt
    assert "0 missing, 1 corrupt, 0 orphaned" in r.output
    with Store(store) as st:
        assert not st.object_path(orphan).exists() and st.object_path(f.sha256).exists()
        assert [p.name for p in st.quarantined()] == [orphan]   # moved aside, never deleted
    r = cli.invoke(session_app, ["show", "nope", "--store", str(store)])
    assert r.exit_code == 2 and "no session 'nope'" in r.output


def test_resume_refuses_a_changed_plan(tmp_path):
    plan_file = _plan(tmp_path)
    store = tmp_path / "store"
    with Store(store) as st:
        create_session(st, Plan.from_toml(plan_file), None, name="s", plan_path=str(plan_file),
                       reserve_bytes=0)
    plan_file.write_text(TINY.replace("[0, 90]", "[0, 45, 90]"))
    r = cli.invoke(capture_app, ["resume", "s", "--rig", _rig(tmp_path), "--store", str(store)])
    assert r.exit_code == 2
    assert "the plan" in r.output and "changed since the session was planned" in r.output
    assert "turntable.angles_deg: [0.0, 90.0] -> [0.0, 45.0, 90.0]" in r.output
    plan_file.write_text(TINY)
    r = cli.invoke(capture_app, ["resume", "s", "--rig", _rig(tmp_path), "--store", str(store), "--quiet"])
    assert r.exit_code == 0, r.output
    assert "session s (planned): 0 of 2 steps done; 2 steps, 2 frames left" in r.output
    with Store(store) as st:
        assert st.session("s").state == "done" and st.verify("s").ok


def test_ctrl_c_pauses_cleanly_and_resume_finishes(tmp_path):
    """A real SIGINT to ``gonio capture run`` while it records (8 rendered frames)."""
    plan_file = _plan(tmp_path, TINY.replace("[0, 90]", "{ start = 0, stop = 315, step = 45 }"))
    store = tmp_path / "store"
    gonio = [sys.executable, "-m", "capture.cli"]
    p = subprocess.Popen([*gonio, "capture", "run", str(plan_file), "--rig", _rig(tmp_path),
                          "--store", str(store), "--session", "slow", "--quiet"],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    # the runner announces the object target just before step 0 (event-driven: no polling)
    seen = []
    for line in p.stderr:
        seen.append(line)
        if line.startswith("target: put the object"):
            break
    assert seen and seen[-1].startswith("target:"), "".join(seen)
    p.send_signal(signal.SIGINT)
    out, err = p.communicate(timeout=120)
    err = "".join(seen) + err
    assert p.returncode == 3, out + err
    assert "pausing after the current step" in err
    assert "gonio capture resume slow" in out
    with Store(store) as st:
        info = st.session("slow")
        assert info.state == "paused"
        assert st.progress(info.id).steps_done < 8
        assert st.events(info.id)[-1]["kind"] == "paused"
    r = cli.invoke(capture_app, ["resume", "slow", "--rig", _rig(tmp_path), "--store", str(store), "--quiet"])
    assert r.exit_code == 0, r.output
    with Store(store) as st:
        assert st.session("slow").state == "done" and st.verify("slow").ok
        assert len(st.frames(st.session("slow").id)) == 8


def test_session_left_running_without_a_writer_shows_as_interrupted(tmp_path):
    store = tmp_path / "store"
    with Store(store) as st:
        info = create_session(st, Plan.from_toml(_plan(tmp_path)), None, name="s", reserve_bytes=0)
        st.set_state(info.id, "running")  # what a killed runner leaves behind
        with Store(store) as runner_side, runner_side.writer("s"):
            r = cli.invoke(session_app, ["list", "--store", str(store)])
            assert "running" in r.output and "interrupted" not in r.output
    r = cli.invoke(session_app, ["list", "--store", str(store)])
    assert r.exit_code == 0 and "interrupted" in r.output
    r = cli.invoke(session_app, ["show", "s", "--store", str(store)])
    assert "state interrupted" in r.output and "gonio capture resume s" in r.output
