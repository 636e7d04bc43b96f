"""The operator console (``gonio tui``): a Textual app over the capture runner and store."""
from .app import GonioApp

__all__ = ["GonioApp"]
