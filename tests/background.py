"""The suite's heavy simulated sessions, made in the background while other tests run.

Capturing and calibrating a simulated session takes tens of seconds to minutes on CI's two cores
(the quick demo, the example plan, the sessions of ``test_calibrate`` and ``test_process``), while
most of the suite runs on one core. Each such session is a *job*: a module-level function of its
test module that writes everything its tests read into an empty folder (the store, and any
in-memory result pickled with :func:`save`). When collection ends, ``conftest.py`` runs the jobs
the collected tests use, one at a time in a fresh, niced interpreter each, in the order the tests
need them; a test's fixture waits for its job's folder (:meth:`Background.folder`). The job runs
the code its fixture ran before, and the tests read the same store, so no assertion changes.

``python tests/background.py MODULE FUNCTION FOLDER`` runs one job (what the children run).
"""
from __future__ import annotations

import contextlib
import importlib.util
import os
import pickle
import shutil
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

TESTS = Path(__file__).resolve().parent
REPO = TESTS.parent
#: a job's stdout and stderr
LOG = "job.log"
#: the children's niceness: the lowest, so they take only what the foreground leaves (some of its tests are timed)
NICENESS = 19


@dataclass(frozen=True)
class Job:
    """A session made in the background: ``function(folder)`` of the test module ``module``
    (a path under ``tests/``), for the tests of that module that use the fixture ``fixture``."""

    name: str
    module: str
    function: str
    fixture: str

    def used_by(self, item) -> bool:
        """Whether the collected test ``item`` reads this job's folder."""
        return Path(item.path).resolve() == TESTS / self.module and self.fixture in item.fixturenames


JOBS = (
    Job("calibrate", "capture/test_calibrate.py", "capture_and_calibrate", "session"),
    Job("calibrate-default", "capture/test_calibrate.py", "capture_and_calibrate_default", "default_session"),
    Job("demo", "capture/test_demo.py", "run_demo", "demo"),
    Job("recapture", "capture/test_demo.py", "capture_then_process", "recaptured"),
    Job("example-plan.toml", "capture/test_example_plans.py", "calibrate_plan_toml", "calibrated_example"),
    Job("process", "capture/test_process.py", "capture_and_process", "captured"),
)


class JobFailed(RuntimeError):
    """A background job exited non-zero (the message holds the end of its log)."""


class Background:
    """Runs ``jobs`` in order, one child at a time, each into ``root / job.name``."""

    def __init__(self, root: Path, jobs: list[Job]) -> None:
        self.root = root
        self.jobs = {job.name: job for job in jobs}
        self._done = {job.name: threading.Event() for job in jobs}
        self._codes: dict[str, int | str] = {}   # exit status, or why it did not start
        #: per job: seconds it ran, and seconds the tests waited for it
        self.ran_s: dict[str, float] = {}
        self.waited_s: dict[str, float] = {}
        self._child: subprocess.Popen | None = None
        self._stopping = False
        self._thread = threading.Thread(target=self._run_all, args=(list(jobs),), name="background jobs",
                                        daemon=True)
        self._thread.start()

    def _run_all(self, jobs: list[Job]) -> None:
        for job in jobs:
            try:
                if not self._stopping:
                    started = time.monotonic()
                    self._codes[job.name] = self._run(job)
                    self.ran_s[job.name] = time.monotonic() - started
            except OSError as exc:   # the child could not be started: its fixture says so
                self._codes[job.name] = repr(exc)
            finally:
                self._done[job.name].set()

    def _run(self, job: Job) -> int:
        folder = self.root / job.name
        folder.mkdir(parents=True)
        path = os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")]))
        with open(folder / LOG, "w") as log:
            self._child = subprocess.Popen([sys.executable, __file__, job.module, job.function, str(folder)],
                                           cwd=REPO, env={**os.environ, "PYTHONPATH": path}, stdout=log,
                                           stderr=subprocess.STDOUT, start_new_session=True)
            # (before the child has started anything: it inherits the niceness)
            with contextlib.suppress(ProcessLookupError):
                os.setpriority(os.PRIO_PROCESS, self._child.pid, os.getpriority(os.PRIO_PROCESS, 0) + NICENESS)
            return self._child.wait()

    def folder(self, name: str) -> Path:
        """The folder job ``name`` wrote, once it has finished (waits; raises :class:`JobFailed`
        if it failed)."""
        if name not in self.jobs:
            raise KeyError(f"background job {name!r} was not started: no collected test uses its fixture "
                           f"(tests/background.py JOBS: {', '.join(job.name for job in JOBS)})")
        started = time.monotonic()
        self._done[name].wait()
        self.waited_s[name] = time.monotonic() - started
        code = self._codes.get(name)
        if code != 0:
            log = self.root / name / LOG
            tail = log.read_text()[-4000:] if log.is_file() else ""
            why = ("was stopped" if code is None else f"exited {code}" if isinstance(code, int)
                   else f"did not start: {code}")
            raise JobFailed(f"background job {name} ({self.jobs[name].module}::{self.jobs[name].function}) "
                            f"{why}; its log ends:\n{tail}")
        return self.root / name

    def summary(self) -> str:
        """One line: each job's seconds run and seconds waited for (wall)."""
        return "background jobs (s run / s the tests waited): " + ", ".join(
            f"{name} {self.ran_s.get(name, 0):.0f} / {self.waited_s.get(name, 0):.0f}" for name in self.jobs)

    def stop(self) -> None:
        """Kill a running child (and what it started), then remove every folder."""
        self._stopping = True
        child = self._child
        if child is not None and child.poll() is None:
            os.killpg(child.pid, signal.SIGKILL)
        self._thread.join(60)
        shutil.rmtree(self.root, ignore_errors=True)


def save(folder: Path, result: Any, name: str = "result") -> None:
    """Keep a job's in-memory result for its fixture (:func:`load`), as ``folder/NAME.pickle``."""
    (folder / f"{name}.pickle").write_bytes(pickle.dumps(result))


def load(folder: Path, name: str = "result") -> Any:
    """The result a job kept with :func:`save`."""
    return pickle.loads((folder / f"{name}.pickle").read_bytes())


def run_job(module: str, function: str, folder: Path) -> None:
    """Import the test module ``module`` (a path under ``tests/``; its folder on ``sys.path``, as
    pytest puts it) and call its ``function(folder)``."""
    path = TESTS / module
    sys.path.insert(0, str(path.parent))
    spec = importlib.util.spec_from_file_location(path.stem, path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[path.stem] = mod
    spec.loader.exec_module(mod)
    getattr(mod, function)(folder)


if __name__ == "__main__":
    run_job(sys.argv[1], sys.argv[2], Path(sys.argv[3]))
