"""Fuzz-style: random and hostile session names, plan texts and rig values through the CLI
(issue 15). Every outcome must be a message and an exit status, never a traceback."""
from __future__ import annotations

import random
import sqlite3
import string
from pathlib import Path

import pytest
from typer.testing import CliRunner

from capture.cli import app
from capture.store import Store

cli = CliRunner()
SEEDS = [1, 2]
HOSTILE_NAMES = [".", "..", "../..", "/", "a/../../b", "~", "-", "-rf", "[bold]x", "[/]",
                 "%s%n", "$(id)", "`id`", "a\tb", "a\rb", "\x1b[31mred", "\u202eevil", "名前",
                 "CON", "a" * 300, " ", "'", '"', "\\", "*", "?", "x\x7f"]
ANY = string.ascii_letters + string.digits + string.punctuation + " \t\x1b\x7féü名\u202e"


def _random_text(rng: random.Random, n: int = 12) -> str:
    return "".join(rng.choice(ANY) for _ in range(rng.randint(1, n)))


def _check(args: list[str]):
    r = cli.invoke(app, args)
    assert r.exception is None or isinstance(r.exception, SystemExit), (args, repr(r.exception))
    assert r.exit_code in (0, 1, 2, 3, 4), (args, r.exit_code, r.output)
    assert "Traceback" not in r.output, (args, r.output)
    return r


@pytest.fixture(scope="module")
def store(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("fuzz") / "st"
    with Store(root) as st:
        st.create_session("real", plan={"name": "x"}, plan_hash="h", steps=[])
    return root


@pytest.fixture(scope="module")
def dead_rig(tmp_path_factory) -> Path:
    """A rig whose only device is on a port that does not exist: fails fast, starts nothing."""
    p = tmp_path_factory.mktemp("rig") / "dead.toml"
    p.write_text('[turntable]\ndriver = "zaber"\nport = "/nonexistent/ttyUSB9"\n')
    return p


@pytest.mark.parametrize("seed", SEEDS)
def test_random_and_hostile_session_names(tmp_path, store, dead_rig, seed):
    rng = random.Random(seed)
    plan = tmp_path / "plan.toml"
    plan.write_text('[turntable]\nangles_deg = [0]\n[exposure]\nbase_s = 0.01\n')
    names = HOSTILE_NAMES if seed == SEEDS[0] else [_random_text(rng, 40) for _ in range(15)]
    for name in names:
        for args in (["session", "show", name], ["session", "verify", name],
                     ["session", "export", name, str(tmp_path / "out.tar")],
                     ["capture", "resume", name, "--rig", str(dead_rig)]):
            r = _check([*args, "--store", str(store)])
            assert r.exit_code == 2, (args, r.output)
        r = _check(["capture", "run", str(plan), "--rig", str(dead_rig), "--store", str(store),
                    "--session", name, "--quiet"])
        assert r.exit_code == 2
    with Store(store, readonly=True) as st:  # nothing was created, renamed or removed
        assert [s.name for s in st.sessions()] == ["real"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["plan.toml"]


def _random_value(rng: random.Random, depth: int = 0) -> str:
    pick = rng.randrange(12 if depth < 2 else 9)
    return [lambda: str(rng.choice([0, -1, 1, 10**9, 10**19, -10**19])),
            lambda: rng.choice(["nan", "inf", "-inf", "1e308", "-0.0", "5e-324", "1e-320"]),
            lambda: repr(rng.uniform(-1e6, 1e6)),
            lambda: rng.choice(["true", "false"]),
            lambda: '"' + _random_text(rng).replace("\\", "\\\\").replace('"', '\\"') + '"',
            lambda: "'[/bold] [red]x'",
            lambda: "1979-05-27T07:32:00Z",
            lambda: "[]",
            lambda: "{ start = 0, stop = 1e9, step = 1e-9 }",
            lambda: "[" + ", ".join(_random_value(rng, depth + 1) for _ in range(rng.randint(1, 4))) + "]",
            lambda: "{ " + ", ".join(f"{k} = {_random_value(rng, depth + 1)}" for k in
                                     rng.sample(["start", "stop", "step", "x"], rng.randint(1, 3))) + " }",
            lambda: "[[1, 2, 3], [4, 5, 6]]"][pick]()


PLAN_KEYS = {"": ["name", "object", "operator", "notes", "repeats", "x"],
             "turntable": ["angles_deg", "x"], "polarizer": ["angles_deg", "count"],
             "light": ["azimuth_deg", "elevation_deg", "distance_mm", "xyz_mm"],
             "exposure": ["base_s", "stops", "iso", "auto", "highlight"]}


@pytest.mark.parametrize("seed", SEEDS)
def test_random_plan_texts(tmp_path, seed):
    rng = random.Random(seed)
    plan = tmp_path / "plan.toml"
    for _ in range(60):
        lines = []
        for table, keys in PLAN_KEYS.items():
            if table and rng.random() < 0.8:
                lines.append(f"[{table}]")
            for key in rng.sample(keys, rng.randint(0, len(keys))):
                lines.append(f"{key} = {_random_value(rng)}")
        if rng.random() < 0.4:
            kind = rng.choice(['"dark"', '"spheres"', "1", '"[x]"'])
            lines += ["[[calibration]]", f"kind = {kind}", f"frames = {_random_value(rng)}"]
        text = "\n".join(lines)
        if rng.random() < 0.1:  # broken bytes or syntax
            plan.write_bytes(rng.randbytes(40) + text.encode())
        else:
            plan.write_text(text)
        _check(["capture", "plan", str(plan)])


RIG_KEYS = ["driver", "port", "baudrate", "timeout_s", "device", "axis", "address", "kinematics",
            "use_checksum", "poll_retries", "poll_interval_s", "speed_deg_s", "microstep_deg", "x"]


@pytest.mark.parametrize("seed", SEEDS)
def test_random_rig_values(tmp_path, seed):
    rng = random.Random(seed)
    rig = tmp_path / "rig.toml"
    for _ in range(40):
        lines = []
        for role in rng.sample(["turntable", "positioner", "polarizer", "camera", "rig", "arm"],
                               rng.randint(1, 3)):
            lines.append(f"[{role}]")
            lines.append("driver = " + rng.choice(['"zaber"', '"grbl"', '"elliptec"', '"ptp"',
                                                   '"gphoto2"', '"[bold]"', "3", '["zaber"]',
                                                   '{ name = "grbl" }']))
            lines.append("port = " + rng.choice(['"/nonexistent/tty0"', '"/dev/null"', '"/"',
                                                 '"usb:zz:1"', '"usb:1:2"', '""', "5", "[1]",
                                                 '"[/bold]"', f'"{tmp_path}"', '"/dev/./null"',
                                                 '"/dev//null"', '"/dev/../dev/null"']))
            for key in rng.sample(RIG_KEYS[2:], rng.randint(0, 3)):
                lines.append(f"{key} = {_random_value(rng)}")
        rig.write_text("\n".join(lines))
        _check(["rig", "check", "--rig", str(rig)])


@pytest.mark.parametrize("seed", SEEDS)
def test_random_and_hostile_object_hashes(tmp_path, seed):
    """Rows whose sha256 text is random or a path: every command answers with a message and no
    file outside the store is read, written or deleted."""
    rng = random.Random(seed)
    victim = tmp_path / "victim.txt"
    victim.write_text("precious")
    root = tmp_path / "st"
    with Store(root) as st:
        sid = st.create_session("s", plan={}, plan_hash="h", steps=[{"frames": 1}]).id
        st.add_frame(sid, 0, 0, 0, data=b"x" * 100, filename="f.dng", format="dng",
                     exposure_requested_s=0.01, exposure_s=0.01, completes_step=True)
    shas = [".." + str(victim), "../../victim.txt", "..", "/", "", "0" * 64 + "/..", "F" * 64,
            " " + "0" * 63] if seed == SEEDS[0] else [_random_text(rng, 70) for _ in range(6)]
    for sha in shas:
        db = sqlite3.connect(root / "gonio.sqlite")
        db.execute("UPDATE frames SET sha256 = ?", (sha,))
        db.commit()
        db.close()
        for args in (["session", "list"], ["session", "show", "s"], ["session", "verify", "s"],
                     ["session", "export", "s", str(tmp_path / "out")], ["calibrate", "s"]):
            r = _check([*args, "--store", str(root)])
            assert r.exit_code == 2 and "hash" in r.output, (sha, args, r.output)
        assert victim.read_text() == "precious" and not (tmp_path / "out").exists()
