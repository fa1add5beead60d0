"""The `renderfarm` command (parser.py: arguments and main; commands.py: what each does), its
token commands and the local farm.

`main` is re-exported: the console script's entry point is `renderfarm.cli:main`."""

from .parser import main

__all__ = ["main"]
