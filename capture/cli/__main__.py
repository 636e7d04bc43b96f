"""``python -m capture.cli``: the same as the ``gonio`` command."""
from . import main

main()
