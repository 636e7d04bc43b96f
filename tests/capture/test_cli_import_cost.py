"""``gonio --help`` and every ``gonio <command> --help`` load none of the heavy layers.

The CLI modules import the simulated lab, the calibration and processing pipeline, the rig
drivers and the runner inside the command functions, and the plan loads numpy's kinematics and
hand-held views only when it checks reach or words a board view (docs/architecture.md), so an
operator's ``--help`` loads typer, rich, the store and the plan, and no numpy (what each import
costs: ``python -X importtime -m capture.cli --help``; every page's wall time:
``benchmarks/cli_help.py``).
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]

#: what ``--help`` must not load: module names and packages (with their submodules)
HEAVY = ("numpy", "sims", "trimesh", "cv2", "scipy", "dask", "zarr", "matplotlib", "textual", "rawpy",
         "calibration", "reconstruct", "capture.pipeline", "capture.rigs", "capture.runner",
         "capture.metering", "capture.lab",
         "rig.zaber", "rig.grbl", "rig.elliptec", "rig.ptp", "rig.ptp_camera", "rig.gphoto2_camera",
         "rig.transport", "serial", "usb")

#: every command group and command, in the order ``--help`` lists them
COMMANDS = {
    (): ["calibrate", "process", "demo", "export", "tui", "rig", "session", "capture", "sim", "import"],
    ("rig",): ["check", "home", "sim"],
    ("session",): ["list", "show", "verify", "export", "rebuild-index"],
    ("capture",): ["plan", "run", "resume"],
    ("sim",): ["render"],
    ("import",): ["diligent"],
}

# in a fresh interpreter: every --help the CLI has, then the modules loaded
_PROBE = """
import json, sys
from typer.testing import CliRunner
from capture.cli import app
groups = json.loads(sys.argv[1])
runner = CliRunner()
helps = {}
for group, names in groups:
    for args in [group] + [group + [n] for n in names]:
        r = runner.invoke(app, args + ["--help"], env={"COLUMNS": "200", "NO_COLOR": "1"})
        helps[" ".join(args)] = [r.exit_code, r.output]
print(json.dumps({"helps": helps, "modules": sorted(sys.modules)}))
"""


def _listed(output: str) -> list[str]:
    """The command names of a help page's Commands panel, in order."""
    lines = output.splitlines()
    start = next(i for i, line in enumerate(lines) if "Commands" in line)
    names = []
    for line in lines[start + 1:]:
        if line.startswith("╰"):
            break
        first = line.strip("│ ").split("  ")[0]
        if first and line[2] != " ":   # a name starts the row; its help's wrapped lines are indented
            names.append(first)
    return names


def test_every_help_loads_no_heavy_layer_and_lists_every_command():
    groups = [[list(g), names] for g, names in COMMANDS.items()]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))}
    proc = subprocess.run([sys.executable, "-c", _PROBE, json.dumps(groups)], capture_output=True, text=True,
                          env=env, cwd=ROOT, timeout=120)
    assert proc.returncode == 0, proc.stderr
    probe = json.loads(proc.stdout)
    loaded = [m for m in probe["modules"] if any(m == h or m.startswith(h + ".") for h in HEAVY)]
    assert loaded == [], f"--help loaded {loaded}"
    for group, names in COMMANDS.items():
        code, output = probe["helps"][" ".join(group)]
        assert code == 0, output
        assert _listed(output) == names, output
    for args, (code, output) in probe["helps"].items():   # each command's own page: usage and options
        assert code == 0 and f"Usage: gonio {args}".rstrip() in output and "--help" in output, (args, output)
