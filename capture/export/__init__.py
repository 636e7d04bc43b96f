"""gonio export: recovered appearance -> files other software reads."""
