"""The `renderfarm` command (commands.py), its token commands and the local farm.

`main` is re-exported: the console script's entry point is `renderfarm.cli:main`."""

from .commands import main

__all__ = ["main"]
