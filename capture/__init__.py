"""The application: session store, plans, runner, CLI (``gonio``), TUI, pipeline glue."""
