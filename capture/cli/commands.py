"""The ``gonio`` Typer application: the root options and every command group's module registered
(``capture.cli.app`` is this module's ``app``; :func:`capture.cli.main` runs it)."""
from __future__ import annotations

import typer

app = typer.Typer(
    name="gonio",
    help="Image-based reflectometry: drive the rig, record sessions, calibrate, reconstruct.\n\n"
         "Every command that needs hardware takes --rig: 'sim' for the built-in simulated lab, "
         "or a rig TOML file naming each device's driver and port.",
    no_args_is_help=True,
    pretty_exceptions_show_locals=False,
)


@app.callback()
def _root(version: bool = typer.Option(False, "--version", help="Print gonio's version and exit.",
                                       is_eager=True)) -> None:
    if version:
        from importlib.metadata import version as _v
        typer.echo(f"gonio {_v('gonio')}")
        raise typer.Exit()


def _register() -> None:
    # one line per command or command group (a group's module defines `app`, a typer.Typer; a
    # command's help: its docstring with the paragraphs unwrapped, as the groups' own commands do)
    from .session import unwrap
    from .rig import app as rig_app; app.add_typer(rig_app, name="rig")  # noqa: E702
    from .session import app as session_app; app.add_typer(session_app, name="session")  # noqa: E702
    from .capture import app as capture_app; app.add_typer(capture_app, name="capture")  # noqa: E702
    from .sim import app as sim_app; app.add_typer(sim_app, name="sim")  # noqa: E702
    from .calibrate import calibrate; app.command("calibrate", help=unwrap(calibrate.__doc__))(calibrate)  # noqa: E702
    from .process import process; app.command("process", help=unwrap(process.__doc__))(process)  # noqa: E702
    from .demo import demo; app.command("demo", help=unwrap(demo.__doc__))(demo)  # noqa: E702
    from .export import export; app.command("export", help=unwrap(export.__doc__))(export)  # noqa: E702
    from .tui import tui; app.command("tui", help=unwrap(tui.__doc__))(tui)  # noqa: E702
    from .importers import app as import_app; app.add_typer(import_app, name="import")  # noqa: E702


_register()
