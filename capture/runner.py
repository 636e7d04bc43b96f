"""The capture runner: executes a session's steps on a rig, durably, resumably.

For each step not yet done, in order: move every axis the step names at once (``move_to`` on
each, then ``wait_all``), read back where they ended up (degrees / millimetres; stored with
every frame of the step: nothing moves during a bracket), capture the bracket (``set_exposure`` +
``capture`` per exposure, ``repeats`` times) and store each frame durably; the step's last frame
marks it done in the same transaction. Events go to an :class:`~capture.events.EventBus` and into
the store. Plans with ``exposure.auto`` are metered once per session first
(:mod:`capture.metering`); the metering is stored and reused on resume.

Faults: a retryable device error (busy, timeout, garbled reply) is retried with bounded
exponential back-off; when retries run out, or the error needs an operator (``Disconnected``,
limits, homing), the rig is stopped and the session *paused* with the fault recorded, never a
traceback. ``run()`` again (``gonio capture resume``) reconnects what dropped and continues from
the first step not done; a half-done step is re-done and its frames replaced.

Control from another thread (the CLI's Ctrl-C handler, a TUI button): :meth:`Runner.request_pause`
(after the current step, or at once), :meth:`Runner.request_abort` (stops motion now).
"""
from __future__ import annotations

import contextlib
import threading
import time
from dataclasses import dataclass
from typing import Any, Callable

from rig import RigError, wait_all
from rig.errors import Disconnected

from .events import Event, EventBus, EventKind
from .metering import MeteringError, meter
from .plan import Estimate, MotionModel, Plan, Step, limit_from_describe, plan_diff, step_prompt
from .store import SessionInfo, Store, StoreFull, check_session_name, safe_name_from

#: free space kept in reserve on the store's disk, bytes
DEFAULT_RESERVE_BYTES = 1 << 30


class RunnerError(Exception):
    """The session cannot be run as asked (aborted, not enough space ...); the message says why."""


@dataclass(frozen=True)
class RetryPolicy:
    """Bounded exponential back-off: ``attempts`` tries in all, waiting ``base_delay_s *
    factor**k`` (at most ``max_delay_s``) before try ``k + 2``."""

    attempts: int = 4
    base_delay_s: float = 0.05
    factor: float = 2.0
    max_delay_s: float = 2.0

    def delay_s(self, failed_attempts: int) -> float:
        return min(self.max_delay_s, self.base_delay_s * self.factor ** (failed_attempts - 1))


class _Stop(Exception):
    """Internal: leave the step loop (pause or abort requested, or a fault)."""

    def __init__(self, state: str, message: str) -> None:
        super().__init__(message)
        self.state = state
        self.message = message


def create_session(store: Store, plan: Plan, rig: Any = None, *, name: str | None = None,
                   plan_path: str | None = None, operator: str | None = None,
                   reserve_bytes: int = DEFAULT_RESERVE_BYTES) -> SessionInfo:
    """Validate ``plan`` against ``rig``, expand it and record a new ``planned`` session.

    Parameters
    ----------
    name : str, optional
        Session name (see :func:`~capture.store.check_session_name`); default
        ``<plan name made safe, or 'session'>-YYYYmmdd-HHMMSS``.
    plan_path : str, optional
        The plan file, remembered so ``resume`` can check it is unchanged.
    operator : str, optional
        Who runs it, if not the plan's ``operator`` (the plan and its hash stay as given).
    reserve_bytes : int
        Space to keep free beyond the plan's estimated bytes.

    Raises
    ------
    PlanError
        The plan does not fit the rig (the message names the field).
    RunnerError
        The store's disk lacks room for the plan's estimated frames.
    """
    if name is not None:
        check_session_name(name)  # before any work: a bad name is the cheapest error
    if rig is not None:
        plan.check_rig(rig)
    steps = plan.steps(rig)
    estimate = MotionModel.from_rig(rig).estimate(steps)
    free = store.free_bytes()
    if free < estimate.bytes + reserve_bytes:
        assumed = (f", assuming {estimate.frame_bytes / 1e6:.0f} MB per frame (the camera does not "
                   "report its image size)" if estimate.frame_bytes_assumed else "")
        raise RunnerError(f"not enough disk space in {store.root}: the plan needs about "
                          f"{estimate.bytes / 1e9:.2f} GB{assumed} (+{reserve_bytes / 1e9:.2f} GB "
                          f"reserve), {free / 1e9:.2f} GB are free")
    name = name or f"{safe_name_from(plan.name or 'session')}-{time.strftime('%Y%m%d-%H%M%S')}"
    return store.create_session(name, plan=plan.to_dict(), plan_hash=plan.hash,
                                steps=[s.to_dict() for s in steps], plan_path=plan_path,
                                operator=plan.operator if operator is None else operator,
                                object=plan.object, notes=plan.notes)


def estimate_remaining(store: Store, session: str | SessionInfo, rig: Any = None) -> Estimate:
    """Steps, frames, bytes and time (s) a session still has to do (its steps not done), with
    ``rig``'s speeds; the frame size is the mean of the frames the session already stored, else
    what the camera reports (see :class:`~capture.plan.Estimate` ``frame_bytes_source``)."""
    info = store.session(session) if isinstance(session, str) else session
    model = MotionModel.from_rig(rig)
    progress = store.progress(info.id)
    if progress.frames_stored:
        model = model.with_frame_bytes(progress.bytes_stored / progress.frames_stored)
    return model.estimate([s.step for s in store.steps(info.id) if not s.done])


def check_plan_unchanged(session: SessionInfo, plan: Plan, source: str = "the plan") -> None:
    """Refuse to resume ``session`` with a plan that differs from the one it was planned with.

    Raises
    ------
    RunnerError
        Listing each differing field as ``path: old -> new``.
    """
    if plan.hash != session.plan_hash:
        diff = plan_diff(session.plan, plan.to_dict())
        raise RunnerError(f"refusing to resume {session.name}: {source} changed since the session "
                          "was planned:\n  " + "\n  ".join(diff) + "\nrestore it, or start a new "
                          "session with 'gonio capture run'")


class Runner:
    """Runs one session of a store on a rig.

    Parameters
    ----------
    rig : rig.Rig
        Connected (or connectable) devices; roles the plan does not use may be absent.
    store : Store
    session : str or SessionInfo
        The session to run (created with :func:`create_session`).
    bus : EventBus, optional
        Where events go (a new bus by default; see :attr:`bus`).
    retry : RetryPolicy
    move_timeout_s : float
        Longest a step's concurrent moves may take, seconds.
    reserve_bytes : int
        Free space to keep on the store's disk; below it the session pauses (``low_disk``).
    prepare_target : callable(target, step), optional
        Called when the scene must change (``checkerboard``, ``dark``, ``object`` ...) before
        the first step needing it, e.g. to prompt the operator or tell a simulator. Without it a
        ``target`` event is emitted and the runner carries on.
    home : bool
        Home (all at once) the axes that report ``homed == False`` when a run starts, e.g. a
        positioner that lost its reference after a power cycle. False: such an axis faults.
    """

    def __init__(self, rig: Any, store: Store, session: str | SessionInfo, *,
                 bus: EventBus | None = None, retry: RetryPolicy = RetryPolicy(),
                 move_timeout_s: float = 300.0, reserve_bytes: int = DEFAULT_RESERVE_BYTES,
                 prepare_target: Callable[[str, Step], None] | None = None,
                 home: bool = True) -> None:
        self.rig = rig
        self.store = store
        self.name = session if isinstance(session, str) else session.name
        self.bus = bus or EventBus()
        self.retry = retry
        self.move_timeout_s = move_timeout_s
        self.reserve_bytes = reserve_bytes
        self.prepare_target = prepare_target
        self.home = home
        self._pause = threading.Event()
        self._pause_now = threading.Event()
        self._abort = threading.Event()
        self._wake = threading.Event()  # interrupts back-off sleeps
        self._pending: list[Event] = []
        self._drop: set[str] = set()  # roles whose link dropped: reconnect on the next run
        self._session: SessionInfo | None = None
        self._counters: dict[str, Any] = {}
        self._exposure_scale = 1.0  # metered / plan base exposure, for auto-exposure steps
        self._model = MotionModel()  # frame size for disk-space checks; set per run
        self._remeasured = False

    # -- control (any thread) -----------------------------------------------------------------
    def request_pause(self, *, now: bool = False) -> None:
        """Pause after the current step; ``now=True`` also stops motion at once (the
        interrupted step is re-done on resume)."""
        self._pause.set()
        if now:
            self._pause_now.set()
            self._wake.set()
            self._stop_rig()

    def request_abort(self) -> None:
        """Abort: stop all motion now and end the session as ``aborted`` (final)."""
        self._abort.set()
        self._wake.set()
        self._stop_rig()

    def _stop_rig(self) -> None:
        try:
            self.rig.stop_all()
        except RigError:
            pass  # best effort: a device that cannot answer is not moving under our control

    # -- events -------------------------------------------------------------------------------
    def _emit(self, kind: EventKind, message: str = "", /, *, step: int | None = None,
              device: str | None = None, **data: Any) -> Event:
        event = Event(kind, self.name, message, step=step, device=device, data=data)
        self._pending.append(event)  # persisted with the next store write
        self.bus.emit(event)
        return event

    def _take_events(self) -> list[Event]:
        events, self._pending = self._pending, []
        return events

    def _set_state(self, state: str) -> None:
        events = self._take_events()
        try:
            self.store.set_state(self._session.id, state, events)
        except BaseException:
            self._pending[:0] = events  # not recorded: keep them for the next write
            raise

    def _finish(self, state: str) -> None:
        """Record the final state; on a full disk give up the store's space reserve to record
        it, and failing even that leave it for ``resume`` (it shows as interrupted)."""
        try:
            self._set_state(state)
        except StoreFull:
            self.store.release_reserve()
            with contextlib.suppress(StoreFull):
                self._set_state(state)

    def on_frame_stored(self, callback: Callable[[int, int], None] | None) -> None:
        """Call ``callback(frames_done, frames_total)`` of the whole session after every stored
        frame (the counts the ``frame_stored`` events carry); None: nothing to call."""
        if callback is not None:
            self.bus.subscribe(lambda e: callback(e.data["frames_done"], e.data["frames_total"])
                               if e.kind == EventKind.FRAME_STORED else None)

    # -- the run ------------------------------------------------------------------------------
    def run(self) -> str:
        """Run (or resume) the session until done, paused or aborted; return that state.

        Raises
        ------
        RunnerError
            The session was aborted earlier (aborted sessions are final).
        SessionBusy
            Another process is writing this session.
        """
        info = self.store.session(self.name)
        if info.state == "done":
            return "done"
        if info.state == "aborted":
            raise RunnerError(f"session {self.name!r} was aborted; aborted sessions are final "
                              "(start a new session from the plan)")
        self._session = info
        self._pause.clear()
        self._pause_now.clear()
        self._wake.clear()
        with self.store.writer(self.name) as removed:
            if removed:
                self._emit(EventKind.NOTE, f"removed {len(removed)} file(s) left by an "
                           "interrupted write", files=removed[:20])
            try:
                self._run_steps(resumed=info.state != "planned")
            except _Stop as stop:
                self._finish(stop.state)
                return stop.state
            except StoreFull as exc:  # any other write (state, events, rig snapshot) met a full disk
                self._stop_rig()
                self._emit(EventKind.LOW_DISK, str(exc))
                self._emit(EventKind.PAUSED, "paused: the disk is full; free space, then: gonio "
                           f"capture resume {self.name}", **self._counters)
                self._finish("paused")
                return "paused"
            except BaseException as exc:
                # a bug or KeyboardInterrupt: never leave the session marked running
                self._stop_rig()
                self._emit(EventKind.FAULT, f"unexpected error: {exc!r}", error=type(exc).__name__)
                self._emit(EventKind.PAUSED, "paused after an unexpected error")
                self._finish("paused")
                raise
        return "done"

    def _run_steps(self, *, resumed: bool) -> None:
        sid = self._session.id
        self._prepare_rig()
        all_steps = self.store.steps(sid)
        pending = [s.step for s in all_steps if not s.done]
        done_steps = [s.step for s in all_steps if s.done]
        progress = self.store.progress(sid)
        self._model, self._remeasured = MotionModel.from_rig(self.rig), False
        if progress.frames_stored:  # frames of this session tell the size best
            self._model = self._model.with_frame_bytes(
                progress.bytes_stored / progress.frames_stored)
        self._counters = {"steps_total": len(all_steps), "steps_done": len(done_steps),
                          "frames_total": progress.frames_total,
                          "frames_done": sum(s.frames for s in done_steps), "eta_s": None}
        self._check_space(sum(s.frames for s in pending) * self._model.frame_bytes,
                          "to finish the session")
        self._emit(EventKind.RESUMED if resumed else EventKind.SESSION_STARTED,
                   f"{'resuming' if resumed else 'starting'} at step "
                   f"{pending[0].index if pending else len(all_steps)} of {len(all_steps)}",
                   **self._counters)
        self._set_state("running")
        target = None if resumed or not done_steps else done_steps[-1].target
        if any(s.auto_exposure for s in pending):
            target = self._meter([s.step for s in all_steps], target)
        started = time.monotonic()
        for n, step in enumerate(pending):
            self._check_requests()
            if self._remeasured:
                # the first frame gave the real size: does the rest of the session still fit?
                self._remeasured = False
                self._check_space(sum(s.frames for s in pending[n:]) * self._model.frame_bytes,
                                  "to finish the session (re-estimated from the first frame)")
            self._check_space(step.frames * self._model.frame_bytes, f"for step {step.index}")
            if step.target != target or step.view is not None:  # each hand-held view is a new pose
                self._change_target(step)
                target = step.target
                self._check_requests()  # a pause asked for while the operator set the scene up
            self._run_step(step)
            elapsed = time.monotonic() - started
            self._counters["eta_s"] = elapsed / (n + 1) * (len(pending) - n - 1)
        self._check_requests()
        self._emit(EventKind.DONE, f"all {len(all_steps)} steps done", **self._counters)
        self._set_state("done")

    def _prepare_rig(self) -> None:
        """Connect devices that are not (or whose link dropped in an earlier run), then record
        the rig config and every device's describe() with the session."""
        for role, device in self.rig.devices.items():
            try:
                if role in self._drop:
                    device.close()
                if role in self._drop or not device.connected:
                    device.connect()
                self._drop.discard(role)
            except RigError as exc:
                self._fault(exc, f"connecting the {role}", role, step=None)
        if self.home:
            try:
                unhomed = [(role, d) for role, d in self.rig.devices.items()
                           if getattr(d, "homed", True) is False]
                if unhomed:
                    self._emit(EventKind.NOTE, f"homing {', '.join(r for r, _ in unhomed)}")
                    wait_all([d.home() for _, d in unhomed], timeout=self.move_timeout_s)
            except RigError as exc:
                self._fault(exc, "homing", exc.device, step=None)
        try:
            describe = self.rig.describe()
        except RigError as exc:
            self._fault(exc, "reading the devices' describe()", exc.device, step=None)
        self.store.add_rig_snapshot(self._session.id, getattr(self.rig, "config", {}), describe)

    def _check_requests(self, *, hard_only: bool = False) -> None:
        """Leave the step loop if an abort (or a pause; with ``hard_only`` only an immediate
        pause) was requested."""
        if self._abort.is_set():
            self._emit(EventKind.ABORTED, "aborted by operator", **self._counters)
            raise _Stop("aborted", "aborted")
        if self._pause_now.is_set() if hard_only else self._pause.is_set():
            self._emit(EventKind.PAUSED, f"paused by operator; continue with: gonio capture "
                       f"resume {self.name}", **self._counters)
            raise _Stop("paused", "paused")

    def _check_space(self, need_bytes: float, what: str) -> None:
        free = self.store.free_bytes()
        if free < need_bytes + self.reserve_bytes:
            msg = (f"low disk space: {free / 1e9:.2f} GB free in {self.store.root}, about "
                   f"{need_bytes / 1e9:.2f} GB needed {what} (+{self.reserve_bytes / 1e9:.2f} GB "
                   f"reserve); free space, then: gonio capture resume {self.name}")
            self._emit(EventKind.LOW_DISK, msg, free_bytes=free, need_bytes=need_bytes)
            self._emit(EventKind.PAUSED, "paused: low disk space", **self._counters)
            raise _Stop("paused", msg)

    def _change_target(self, step: Step) -> None:
        msg = step_prompt(step)
        self._emit(EventKind.TARGET, msg, step=step.index, target=step.target, kind=step.kind,
                   **({"view": step.view, "views": step.views} if step.view is not None else {}))
        if self.prepare_target is not None:
            self.prepare_target(step.target, step)

    def _meter(self, steps: list[Step], target: str | None) -> str | None:
        """Set the auto-exposure scale: from the session's stored metering, or by metering now
        at the first measurement pose (the metering shots are kept as a calibration result)."""
        sid, plan_exposure = self._session.id, self._session.plan["exposure"]
        base = plan_exposure["base_s"]
        stored = [r for r in self.store.results(sid, "calibration") if r.kind == "metering"]
        if stored:
            metered = stored[-1].result["exposure_s"]
        else:
            step = next((s for s in steps if s.kind == "measure"),
                        next(s for s in steps if s.auto_exposure))
            if step.target != target:
                self._change_target(step)
                target = step.target
            self._attempt(lambda: self._move(step), "moving to the metering pose", step)
            shots: list[Any] = []

            def shoot(t: float) -> bytes:
                _, frame = self._attempt(lambda: self._capture(t), "metering", step, device="camera")
                shots.append(frame)
                return frame.data

            limits = limit_from_describe(self.rig.camera.describe(), "exposure") or (1e-5, 3600.0)
            try:
                m = meter(shoot, base, limits_s=limits, highlight=plan_exposure.get("highlight", 0.8))
            except MeteringError as exc:
                self._emit(EventKind.FAULT, f"metering failed: {exc}", step=step.index, device="camera",
                           error="MeteringError")
                self._emit(EventKind.PAUSED, f"paused: {exc}", step=step.index, **self._counters)
                raise _Stop("paused", str(exc)) from None
            metered = m.exposure_s
            self.store.add_calibration(
                sid, "metering", result={"exposure_s": metered, "base_s": base, "shots": m.shots},
                params={"highlight": plan_exposure.get("highlight", 0.8), "start_s": base},
                artifacts={f"metering_{i}.{f.format}": f.data for i, f in enumerate(shots)})
        self._exposure_scale = metered / base
        self._emit(EventKind.METERED, f"auto-exposure: {metered:g} s (bracket x{metered / base:.3g} of "
                   f"the plan's {base:g} s){' from the stored metering' if stored else ''}",
                   exposure_s=metered, scale=self._exposure_scale)
        return target

    # -- one step -----------------------------------------------------------------------------
    def _run_step(self, step: Step) -> None:
        sid = self._session.id
        self._emit(EventKind.STEP_STARTED, f"step {step.index} ({step.kind})", step=step.index,
                   **step.to_dict())
        self._attempt(lambda: self._move(step), "moving", step)
        positions = self._attempt(self._read_back, "reading positions", step)
        self._emit(EventKind.MOVED, _where(positions), step=step.index, positions=positions)
        camera = self.rig.camera
        if step.iso is not None and camera.iso != step.iso:
            self._attempt(lambda: camera.set_iso(step.iso), "setting ISO", step, device="camera")
        total = step.frames
        exposures = ([t * self._exposure_scale for t in step.exposures_s] if step.auto_exposure
                     else step.exposures_s)
        k = 0
        for repeat in range(step.repeats):
            for b, exposure in enumerate(exposures):
                self._check_requests(hard_only=True)
                taken, frame = self._attempt(lambda: self._capture(exposure), "capturing", step,
                                             device="camera")
                k += 1
                try:
                    _, sha = self.store.add_frame(
                        sid, step.index, b, repeat, data=frame.data, filename=frame.filename,
                        format=frame.format, exposure_requested_s=exposure,
                        exposure_s=frame.exposure_s, iso=frame.iso, fnumber=frame.fnumber,
                        positions=positions, captured_at=frame.timestamp,
                        metadata={**frame.metadata, "exposure_set_s": taken},
                        events=self._take_events(), completes_step=k == total)
                except StoreFull as exc:
                    self._emit(EventKind.LOW_DISK, str(exc), step=step.index)
                    self._emit(EventKind.PAUSED, "paused: the disk is full", step=step.index,
                               **self._counters)
                    raise _Stop("paused", str(exc)) from None
                self._counters["frames_done"] += 1
                self._counters["steps_done"] += k == total
                if self._model.frame_bytes_source == "default":
                    self._measure_frame_bytes(len(frame.data), step)
                self._emit(EventKind.FRAME_STORED, f"{frame.filename} {frame.exposure_s:g} s",
                           step=step.index, bracket_index=b, repeat=repeat, size=len(frame.data),
                           sha256=sha, **self._counters)
        self._emit(EventKind.STEP_DONE, f"step {step.index} done", step=step.index,
                   **self._counters)

    def _measure_frame_bytes(self, size: int, step: Step) -> None:
        """The camera could not tell its frame size: take it from the first frame stored, and
        re-estimate the bytes still to store (checked against free space before the next step)."""
        assumed = self._model.frame_bytes
        self._model = self._model.with_frame_bytes(size)
        self._remeasured = True
        left = (self._counters["frames_total"] - self._counters["frames_done"]) * size
        left_text = f"{left / 1e9:.2f} GB" if left >= 1e9 else f"{left / 1e6:.1f} MB"
        self._emit(EventKind.NOTE, f"frame size measured from the first frame: {size / 1e6:.2f} MB "
                   f"(the camera does not report it; {assumed / 1e6:.0f} MB was assumed); about "
                   f"{left_text} still to store", step=step.index, frame_bytes=size,
                   assumed_frame_bytes=assumed, bytes_left=left)

    def _move(self, step: Step) -> None:
        rig, statuses = self.rig, []
        try:
            if step.turntable_deg is not None:
                statuses.append(rig.turntable.move_to(step.turntable_deg))
            if step.light is not None:
                statuses.append(rig.positioner.move_to(step.light))
            if step.polarizer_deg is not None:
                statuses.append(rig.polarizer.move_to(step.polarizer_deg))
        except RigError:
            # one device refused at once: let the moves already started end before reporting
            try:
                wait_all(statuses, timeout=self.move_timeout_s)
            except RigError:
                pass
            raise
        wait_all(statuses, timeout=self.move_timeout_s)

    def _read_back(self) -> dict[str, Any]:
        rig, pos = self.rig, {}
        if rig.turntable is not None:
            pos["turntable_deg"] = rig.turntable.position
        if rig.positioner is not None:
            pos["light_mm"] = list(rig.positioner.light_position_mm)
        if rig.polarizer is not None:
            pos["polarizer_deg"] = rig.polarizer.position
        return pos

    def _capture(self, exposure_s: float):
        camera = self.rig.camera
        taken = camera.set_exposure(exposure_s)
        return taken, camera.capture()

    def _attempt(self, fn: Callable[[], Any], what: str, step: Step, *, device: str | None = None):
        """Call ``fn``; retry retryable device errors with back-off; otherwise fault-pause."""
        for attempt in range(1, self.retry.attempts + 1):
            try:
                return fn()
            except RigError as exc:
                self._check_requests(hard_only=True)  # the error may be our own stop_all()
                dev = exc.device or device
                if not exc.retryable or attempt == self.retry.attempts:
                    self._fault(exc, what, dev, step=step.index, attempts=attempt)
                delay = self.retry.delay_s(attempt)
                self._emit(EventKind.RETRY, f"{what}: {exc}; retry {attempt + 1} of "
                           f"{self.retry.attempts} in {delay:g} s", step=step.index, device=dev,
                           attempt=attempt, delay_s=delay, error=type(exc).__name__)
                self._wake.wait(delay)
                self._check_requests(hard_only=True)

    def _fault(self, exc: RigError, what: str, device: str | None, *, step: int | None,
               attempts: int = 1) -> None:
        """Record a device fault, stop the rig and pause the session (raises _Stop)."""
        if isinstance(exc, Disconnected) and device:
            self._drop.add(device)
        self._stop_rig()
        tried = f" after {attempts} attempts" if attempts > 1 else ""
        self._emit(EventKind.FAULT, f"{what} failed{tried}: {exc}", step=step, device=device,
                   error=type(exc).__name__, retryable=exc.retryable, attempts=attempts)
        msg = f"{exc}. Fix the cause, then continue with: gonio capture resume {self.name}"
        self._emit(EventKind.PAUSED, msg, step=step, device=device, **self._counters)
        raise _Stop("paused", msg)


def _where(pos: dict[str, Any]) -> str:
    parts = []
    if "turntable_deg" in pos:
        parts.append(f"turntable {pos['turntable_deg']:.2f}°")
    if "light_mm" in pos:
        parts.append("light ({:.1f}, {:.1f}, {:.1f}) mm".format(*pos["light_mm"]))
    if "polarizer_deg" in pos:
        parts.append(f"polarizer {pos['polarizer_deg']:.2f}°")
    return ", ".join(parts) or "no axes"


__all__ = ["DEFAULT_RESERVE_BYTES", "RetryPolicy", "Runner", "RunnerError", "check_plan_unchanged",
           "create_session", "estimate_remaining"]
