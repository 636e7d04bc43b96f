"""What ``gonio --help`` costs: the wall and CPU time of every help page, each in a fresh interpreter.

Run: ``python benchmarks/cli_help.py [--repeats 5] [--save DIR]``. Walks the Typer application's
command tree, runs ``python -m capture.cli ARGS --help`` for the root, every group and every
command, and prints the best of ``--repeats`` wall and CPU (user + sys) times per page (seconds:
interpreter start, imports and rendering; CPU time leaves out the waits for a core, so it moves
less on a loaded machine) and their medians. ``--save DIR`` also writes each page (stdout, stderr
and exit status, at COLUMNS=100) to DIR, one file per page, so that two trees' pages can be
compared with ``diff -r``. What each import costs: ``python -X importtime -m capture.cli --help``.
"""
from __future__ import annotations

import argparse
import os
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

import typer

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # benchmarks/capture.py shadows the package
from capture.cli import app  # noqa: E402


def pages(command, args: tuple[str, ...] = ()) -> list[tuple[str, ...]]:
    """The argument lists of every help page under ``command`` (a Typer click command; a group
    has ``commands``): itself, then its subcommands."""
    found = [args]
    for name, sub in getattr(command, "commands", {}).items():
        found += pages(sub, args + (name,))
    return found


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5, help="runs per page; the best counts")
    ap.add_argument("--save", type=Path, help="folder to write each page to")
    opts = ap.parse_args()
    env = {**os.environ, "COLUMNS": "100", "NO_COLOR": "1",
           "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))}
    wall, cpu = {}, {}
    for args in pages(typer.main.get_command(app)):
        walls, cpus = [], []
        for _ in range(opts.repeats):
            r0, t0 = resource.getrusage(resource.RUSAGE_CHILDREN), time.perf_counter()
            proc = subprocess.run([sys.executable, "-m", "capture.cli", *args, "--help"], capture_output=True,
                                  text=True, env=env, cwd=ROOT)
            r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
            walls.append(time.perf_counter() - t0)
            cpus.append(r1.ru_utime - r0.ru_utime + r1.ru_stime - r0.ru_stime)
        name = " ".join(("gonio",) + args)
        wall[name], cpu[name] = min(walls), min(cpus)
        print(f"wall {wall[name]:6.3f} s  CPU {cpu[name]:6.3f} s  {name} --help", flush=True)
        if opts.save:
            opts.save.mkdir(parents=True, exist_ok=True)
            page = f"exit {proc.returncode}\n--- stdout\n{proc.stdout}--- stderr\n{proc.stderr}"
            (opts.save / ("_".join(("gonio",) + args) + ".txt")).write_text(page)
    print(f"median of {len(wall)} pages (best of {opts.repeats} each): wall {statistics.median(wall.values()):.3f} s, "
          f"CPU {statistics.median(cpu.values()):.3f} s")


if __name__ == "__main__":
    main()
