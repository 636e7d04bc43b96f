"""``gonio session``: list, show, verify and export recorded sessions.

- ``gonio session list [--store DIR]`` one line per session: state, steps, frames, size. A
  session marked running that no process writes is shown ``interrupted`` (resume it).
- ``gonio session show NAME`` plan summary, progress, rig snapshot, recent faults and events,
  results with provenance.
- ``gonio session verify NAME [--remove-orphans]`` re-hashes every file; lists missing, corrupt
  and orphaned files and done steps with the wrong frame count; exit status 1 if anything is
  wrong. ``--remove-orphans`` takes what interrupted writes left out of ``objects/``: temporary
  files deleted, frame files moved to ``quarantine/`` (no session may be writing).
- ``gonio session rebuild-index`` puts back the sessions and frames the database lacks (restored
  from an older backup, or lost) from the session journals and the frame files.
- ``gonio session export NAME DEST`` writes a self-contained store (folder, ``.tar``, ``.tar.gz``
  or ``.zip``) holding only that session, which ``--store`` can open directly.

``--store`` defaults to ``$GONIO_STORE`` or ``./gonio-store`` and also accepts an exported
archive (read in a temporary folder).
"""
from __future__ import annotations

import contextlib
import datetime as _dt
import inspect
import json
import re
from collections import Counter
from dataclasses import asdict
from pathlib import Path
from typing import Iterator

import typer
from rich.console import Console
from rich.markup import escape
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn
from rich.table import Table

from ..store import Store, StoreError
from ..store.archive import archive_read_only, is_archive

HELP = """List, inspect, verify and export recorded sessions.

A store is a folder that 'gonio capture run --store DIR' writes: DIR/gonio.sqlite (sessions,
their plans and steps, frames with what the devices reported, events and faults, calibration
and reconstruction results) and DIR/objects/ (the frame files, named by their SHA-256).
--store defaults to $GONIO_STORE or ./gonio-store and also opens an exported .tar, .tar.gz or
.zip. Reading is safe while a session is being recorded, and list, show, verify and export
never write the database (they work on a full disk).

Exit status: 0 ok; 1 'verify' found missing, corrupt or orphaned files; 2 error (no such store
or session).
"""


def unwrap(text: str) -> str:
    """Help text with the source's line breaks inside paragraphs removed (rich prints them)."""
    return re.sub(r"(?<!\n)\n(?!\n)", " ", inspect.cleandoc(text))


app = typer.Typer(name="session", help=unwrap(HELP), no_args_is_help=True)

STORE_OPTION = typer.Option("gonio-store", "--store", envvar="GONIO_STORE",
                            help="Store folder (or an exported .tar/.zip). Env: GONIO_STORE.")


def fail(message: str, code: int = 2) -> typer.Exit:
    typer.secho(f"error: {message}", err=True, fg=typer.colors.RED)
    return typer.Exit(code)


def check_store_option(path: str, *, readonly: bool) -> None:
    """Refuse an empty ``--store`` ("" would be the current folder) and, for a command that
    writes, an exported archive (its writes would vanish): call it before any work."""
    if not str(path).strip():
        raise fail("--store is empty; give the store's folder (or set GONIO_STORE)")
    if not readonly and is_archive(Path(path)):
        raise fail(archive_read_only(Path(path)))


def open_store(path: str, *, create: bool = False, readonly: bool = False) -> Store:
    """Open ``--store`` or exit with a clear message (``readonly``: commands that only read
    never write the database, so they work on a full disk and leave a foreign file alone)."""
    check_store_option(path, readonly=readonly)
    try:
        return Store.open(path, create=create, readonly=readonly)
    except StoreError as exc:
        raise fail(str(exc)) from None
    except OSError as exc:  # e.g. --store names a file that is neither a store nor an archive
        raise fail(f"cannot open store {path}: {exc}") from None


@contextlib.contextmanager
def store_errors() -> Iterator[None]:
    """Turn a store error met after opening (a database damaged past its first page, a disk
    that filled up) into the message and exit status 2, never a traceback."""
    try:
        yield
    except StoreError as exc:
        raise fail(str(exc)) from None
    except OSError as exc:
        raise fail(f"store: {exc}") from None


def visible(text: object) -> str:
    """``text`` with control characters (terminal escape sequences, bidirectional overrides)
    written as ``\\x1b``-style escapes, so stored text can neither restyle nor rewrite the
    terminal."""
    return "".join(c if c.isprintable() or c == " " else c.encode("unicode_escape").decode("ascii")
                   for c in str(text))


def shown(text: object) -> str:
    """Stored text as rich prints it literally: :func:`visible`, with markup escaped."""
    return escape(visible(text))


def human_bytes(n: float) -> str:
    for unit in ("B", "kB", "MB", "GB", "TB"):
        if abs(n) < 1000 or unit == "TB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1000
    raise AssertionError("unreachable")


def human_time(seconds: float | None) -> str:
    if seconds is None:
        return "-"
    s = int(round(seconds))
    if s < 60:
        return f"{seconds:.1f} s" if seconds < 10 else f"{s} s"
    if s < 3600:
        return f"{s // 60} min {s % 60:02d} s"
    return f"{s // 3600} h {s % 3600 // 60:02d} min"


def display_state(st: Store, info) -> str:
    """The stored state, but ``interrupted`` for a session marked running that no process is
    writing (its runner was killed or the machine lost power)."""
    if info.state == "running" and not st.session_active(info.name):
        return "interrupted"
    return info.state


def _when(t: float) -> str:
    return _dt.datetime.fromtimestamp(t).strftime("%Y-%m-%d %H:%M:%S")


@app.command("list")
def list_(store: str = STORE_OPTION,
          as_json: bool = typer.Option(False, "--json", help="Print JSON instead of a table.")) -> None:
    """One line per session of the store."""
    with open_store(store, readonly=True) as st, store_errors():
        unknown = st.orphans(min_age_s=60.0 if st.writer_active() else 0.0)
        held = st.quarantined()
        rows = []
        for s in st.sessions():
            p = st.progress(s.id)
            rows.append({"name": s.name, "state": display_state(st, s), "steps_done": p.steps_done,
                         "steps_total": p.steps_total, "frames_stored": p.frames_stored,
                         "frames_total": p.frames_total, "bytes": p.bytes_stored,
                         "object": s.object, "operator": s.operator, "created": s.created})
    if unknown:  # never hide captured data: files no row knows (an interrupted write, a lost db)
        typer.secho(f"warning: {len(unknown)} file(s) in {Path(store) / 'objects'} belong to no "
                    "session (e.g. objects/" + "/".join(Path(unknown[0]).parts[-2:]) + "); "
                    "'gonio session verify NAME' lists them", err=True, fg=typer.colors.YELLOW)
    if held:   # frame files no row listed when a writer started: maybe a restored backup's newer frames
        typer.secho(f"warning: {len(held)} frame file(s) in {Path(store) / 'quarantine'} belong to no "
                    f"session; 'gonio session rebuild-index --store {store}' restores the sessions they "
                    "came from", err=True, fg=typer.colors.YELLOW)
    if as_json:
        typer.echo(json.dumps(rows, indent=2))
        return
    if not rows:
        typer.echo(f"no sessions in {store}")
        return
    table = Table(title=f"sessions in {shown(store)}")
    for col in ("name", "state", "steps", "frames", "size", "object", "created"):
        table.add_column(col)
    colour = {"done": "green", "paused": "yellow", "running": "cyan", "aborted": "red",
              "planned": "white", "interrupted": "yellow"}
    for r in rows:
        table.add_row(shown(r["name"]), f"[{colour[r['state']]}]{r['state']}[/]",
                      f"{r['steps_done']}/{r['steps_total']}", f"{r['frames_stored']}/{r['frames_total']}",
                      human_bytes(r["bytes"]), shown(r["object"]), _when(r["created"]))
    Console(width=140).print(table)


@app.command()
def show(name: str = typer.Argument(..., help="Session name."), store: str = STORE_OPTION,
         events: int = typer.Option(10, help="How many recent events to print."),
         as_json: bool = typer.Option(False, "--json", help="Print JSON.")) -> None:
    """Details of one session: plan, progress, rig, faults, recent events, results."""
    with open_store(store, readonly=True) as st, store_errors():
        try:
            info = st.session(name)
        except StoreError as exc:
            raise fail(str(exc)) from None
        p = st.progress(info.id)
        state = display_state(st, info)
        kinds = Counter(str(s.spec.get("kind", "?")) for s in st.steps(info.id))
        snaps = st.rig_snapshots(info.id)
        faults = st.events(info.id, kinds=["fault", "low_disk"])
        recent = st.events(info.id)[-events:] if events > 0 else []
        results = st.results(info.id)
    if as_json:
        typer.echo(json.dumps({"name": info.name, "state": state, "operator": info.operator,
                               "object": info.object, "notes": info.notes, "plan": info.plan,
                               "plan_hash": info.plan_hash, "plan_path": info.plan_path,
                               "created": info.created, "updated": info.updated,
                               "progress": p.__dict__, "steps_by_kind": kinds,
                               "rig": snaps[-1] if snaps else None, "faults": faults,
                               "events": recent, "results": [asdict(r) for r in results]},
                               indent=2, default=str))
        return
    c = Console(width=140, highlight=False)
    e = shown  # every stored text is the user's (names, plan, device messages): never markup
    c.print(f"[bold]{e(info.name)}[/]  state [bold]{state}[/]  object {e(info.object) or '-'}  "
            f"operator {e(info.operator) or '-'}")
    if state in ("paused", "interrupted", "planned"):
        c.print(f"continue with: gonio capture resume {e(info.name)} --rig <sim|rig file> "
                f"--store {e(store)}")
    c.print(f"created {_when(info.created)}, updated {_when(info.updated)}; plan "
            f"{e(info.plan_path or '(built in Python)')} hash {info.plan_hash[:12]}")
    if info.notes:
        c.print(f"notes: {e(info.notes)}")
    c.print(f"steps {p.steps_done}/{p.steps_total}, frames {p.frames_stored}/{p.frames_total}, "
            f"{human_bytes(p.bytes_stored)} stored; steps by kind: "
            + ", ".join(f"{e(str(k))} {n}" for k, n in kinds.items()))
    if snaps:
        last = snaps[-1]["describe"]
        c.print("rig: " + "; ".join(e(f"{role} {d.get('model', d.get('driver', '?'))}"
                                      + (f" fw {d['firmware']}" if d.get("firmware") else ""))
                                    for role, d in last.items())
                + f" ({len(snaps)} snapshot{'s' if len(snaps) > 1 else ''})")
    for f in faults:
        c.print(f"[red]{f['kind']}[/] {_when(f['time'])} step {f['step']} "
                f"{e(f['device'] or '')}: {e(f['message'])}")
    if recent:
        table = Table(title="recent events")
        for col in ("time", "kind", "step", "device", "message"):
            table.add_column(col, overflow="fold")
        for ev in recent:
            table.add_row(_when(ev["time"]), ev["kind"], "" if ev["step"] is None else str(ev["step"]),
                          e(ev["device"] or ""), e(ev["message"]))
        c.print(table)
    for r in results:
        c.print(e(f"{r.category} {r.kind} #{r.id} ({_when(r.created)}, {r.code_version}, "
                  f"{len(r.input_frames)} input frames, artifacts: "
                  f"{', '.join(r.artifacts) or '-'})"))


@app.command()
def verify(name: str = typer.Argument(..., help="Session name."), store: str = STORE_OPTION,
           remove_orphans: bool = typer.Option(
               False, "--remove-orphans", help="Take the orphaned files found out of objects/: "
               "interrupted writes' temporary files are deleted, unreferenced frame files moved to "
               "quarantine/ (rebuild-index takes them back); refused while a session is being written.")) -> None:
    """Re-hash every file of the session; exit 1 on missing, corrupt or orphaned files."""
    with open_store(store, readonly=True) as st, store_errors():
        try:
            st.session(name)
        except StoreError as exc:
            raise fail(str(exc)) from None
        with Progress(TextColumn("verifying"), BarColumn(), MofNCompleteColumn(),
                      transient=True) as bar:
            task = bar.add_task("verify", total=None)
            report = st.verify(name, progress=lambda i, n: bar.update(task, completed=i, total=n))
        if remove_orphans and report.orphans:
            try:
                removed = st.remove_orphans()
            except StoreError as exc:
                raise fail(str(exc)) from None
            typer.echo(f"took {len(removed)} orphaned file(s) out of objects/ (frame files kept in "
                       f"{st.quarantine}; gonio session rebuild-index takes back the ones a journal lists)")
            report.orphans = [o for o in report.orphans if o not in removed]
    typer.echo(f"{report.checked} file(s) checked")
    for label, items in (("missing", report.missing), ("corrupt", report.corrupt),
                         ("orphaned", report.orphans)):
        for item in items:
            uses = "; ".join(report.where.get(item, []))
            typer.secho(visible(f"{label}: {item}" + (f" ({uses})" if uses else "")), fg=typer.colors.RED)
    for step in report.incomplete_steps:
        typer.secho(f"incomplete: step {step} is marked done but has the wrong number of frames",
                    fg=typer.colors.RED)
    if not report.journaled:
        typer.secho(visible(f"note: session {name} has no journal (recorded before journals): were "
                            "gonio.sqlite lost, its frames could not be put back into it; 'gonio session "
                            f"rebuild-index --store {store}' writes one from the database now"),
                    fg=typer.colors.YELLOW)
    if not report.ok:
        raise fail(f"{len(report.missing)} missing, {len(report.corrupt)} corrupt, "
                   f"{len(report.orphans)} orphaned file(s), {len(report.incomplete_steps)} "
                   f"incomplete step(s)", 1)
    typer.secho("ok: every file is present and matches its SHA-256", fg=typer.colors.GREEN)


@app.command()
def export(name: str = typer.Argument(..., help="Session name."),
           dest: Path = typer.Argument(..., help="New folder, or a .tar / .tar.gz / .zip file."),
           store: str = STORE_OPTION) -> None:
    """Write a self-contained store holding only this session (open it with --store DEST)."""
    with open_store(store, readonly=True) as st, store_errors():
        try:
            out = st.export(name, dest)
        except StoreError as exc:
            raise fail(str(exc)) from None
    size = out.stat().st_size if out.is_file() else sum(p.stat().st_size for p in out.rglob("*") if p.is_file())
    typer.echo(f"exported {name} to {out} ({human_bytes(size)}); open with --store {out}")


@app.command("rebuild-index")
def rebuild_index(store: str = STORE_OPTION) -> None:
    """Put back the sessions and frames gonio.sqlite lacks (a database restored from an older
    backup, or lost) from the session journals and the frame files themselves; frames moved to
    quarantine/ come back. Results (calibration, reconstruction) are recomputed by gonio process."""
    check_store_option(store, readonly=False)
    try:
        st = Store(store, create=False, rebuilding=True) if not Path(store, "objects").is_dir() else \
            Store(store, create=True, rebuilding=True)
    except StoreError as exc:
        raise fail(str(exc)) from None
    with st, store_errors():
        try:
            rep = st.rebuild_index()
        except StoreError as exc:
            raise fail(str(exc)) from None
    if rep.journals_written:
        typer.echo(visible(f"journals written for the session(s) recorded before journals: "
                           f"{', '.join(rep.journals_written)} (a lost index can be rebuilt for them from now on)"))
    for note in rep.notes:
        typer.secho(visible(note), fg=typer.colors.YELLOW)
    if rep.unlisted_files:
        typer.secho(f"{rep.unlisted_files} file(s) ({human_bytes(rep.unlisted_bytes)}) are listed by no database row "
                    "and no journal: frames of sessions recorded before journals whose rows are lost, or "
                    "calibration and reconstruction files (gonio process computes those again). They are kept "
                    f"in {st.root / 'objects'} and {st.quarantine}, but no session can be rebuilt from them: "
                    "a frame file names neither its session nor its step", fg=typer.colors.YELLOW)
    added = ", ".join(visible(n) for n in rep.sessions_added) or "none"
    typer.echo(f"sessions restored: {added}; frame rows restored: {rep.frames_added}; files taken back "
               f"from quarantine: {rep.unquarantined}")
