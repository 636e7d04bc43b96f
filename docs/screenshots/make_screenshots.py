"""Regenerate the operator-console screenshots (SVG) in this folder.

    python docs/screenshots/make_screenshots.py [--size 100x30]

Drives ``gonio tui`` headless against the fast simulated lab: homes the rig, takes a test shot,
runs a small session with a three-exposure bracket, pauses a second one on an injected
turntable disconnect, and saves each tab with ``App.save_screenshot``.
"""
from __future__ import annotations

import argparse
import asyncio
import tempfile
from pathlib import Path

from capture.events import EventBus, EventKind
from capture.tui import GonioApp
from capture.tui.imageview import HalfBlockImage

HERE = Path(__file__).resolve().parent
PLAN = """
name = "teapot"
[turntable]
angles_deg = { start = 0, stop = 90, step = 45 }
[light]
azimuth_deg = [0, 90]
elevation_deg = [30]
[polarizer]
angles_deg = [0, 90]
[exposure]
base_s = 0.01
stops = [-2, 0, 2]
"""


async def wait(pilot, cond, timeout: float = 60.0) -> None:
    for _ in range(int(timeout / 0.05)):
        if cond():
            return
        await pilot.pause(0.05)
    raise TimeoutError("the console did not get there in time")


async def main(size: tuple[int, int]) -> None:
    work = Path(tempfile.mkdtemp(prefix="gonio-shots-"))
    plan = work / "teapot.toml"
    plan.write_text(PLAN)
    bus = EventBus()
    app = GonioApp("sim", work / "store", fast=True, plan=plan, bus=bus)

    def save(name: str) -> None:
        app.save_screenshot(f"{name}.svg", str(HERE))
        print(f"wrote {HERE / name}.svg")

    async with app.run_test(size=size) as pilot:
        await wait(pilot, lambda: app.rig is not None and app.plan is not None)
        await pilot.press("H")
        await wait(pilot, lambda: app.devices_pane.states.get("turntable") is not None
                   and app.devices_pane.states["turntable"].homed)
        await pilot.press("t")
        await wait(pilot, lambda: bool(app.last_frames))
        await pilot.pause(0.5)
        save("devices")
        await pilot.press("2", "n")
        await wait(pilot, lambda: app.session_pane.state == "done")
        await pilot.pause(0.3)
        await pilot.press("3")
        await wait(pilot, lambda: app.query_one(HalfBlockImage).rendered)
        await pilot.pause(0.3)
        save("preview")
        # a second session, paused by a pulled cable half-way
        bus.subscribe(lambda ev: ev.kind == EventKind.STEP_DONE and ev.step == 2
                      and app.lab.sims["turntable"].inject("disconnect"))
        await pilot.press("2", "n")
        await wait(pilot, lambda: app.session_pane.state == "paused" and not app.runner_active)
        await pilot.pause(0.3)
        save("session")
        await pilot.press("4")
        await pilot.pause(0.3)
        save("log")
        await pilot.press("f1")
        await pilot.pause(0.3)
        save("help")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", default="100x30", help="terminal size, COLSxROWS")
    cols, rows = (int(v) for v in parser.parse_args().size.split("x"))
    asyncio.run(main((cols, rows)))
