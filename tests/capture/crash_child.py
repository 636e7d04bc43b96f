"""Child process for the crash test: run (or resume) one small session on fake devices.

``python crash_child.py STORE [STEPS]``. With ``GONIO_CRASH_AFTER=N`` in the environment the
store SIGKILLs this process at its N-th write/rename/commit hook point. Prints the number of
hook points passed (``hooks=K``) when the session finishes.
"""
from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))

from capture.store import crash as store_crash  # noqa: E402
from capture.plan import Plan  # noqa: E402
from capture.runner import RetryPolicy, Runner, create_session  # noqa: E402
from capture.store import SessionNotFound, Store  # noqa: E402
from capture_fakes import make_rig  # noqa: E402


def run_session(root: Path, n_angles: int, on_event=None) -> int:
    """Create (first time) and run the session ``crash``; 0 when it finished.
    ``on_event(event)`` is subscribed to the runner's events."""
    rig = make_rig(frame_bytes=20_000, capture_s=0.002)
    angles = [k * 350 / n_angles for k in range(n_angles)]  # inside the fake turntable's limits
    plan = Plan.from_dict({"name": "crash", "turntable": {"angles_deg": angles},
                           "exposure": {"base_s": 0.01, "stops": [-1, 1]}})
    with Store(root) as store:
        try:
            store.session("crash")
        except SessionNotFound:
            create_session(store, plan, None, name="crash", reserve_bytes=0)
        runner = Runner(rig, store, "crash", reserve_bytes=0,
                        retry=RetryPolicy(attempts=2, base_delay_s=0.001))
        if on_event is not None:
            runner.bus.subscribe(on_event)
        state = runner.run()
    print(f"state={state} hooks={store_crash.count}", flush=True)
    return 0 if state == "done" else 1


if __name__ == "__main__":
    sys.exit(run_session(Path(sys.argv[1]), int(sys.argv[2]) if len(sys.argv) > 2 else 4))
