"""Landlock (Linux 5.13 and later): a process confines its own file-system access.

The USD conversion's child (infra/usd_import.py) calls `confine` before it opens the upload:
from then on it may read and execute only beneath the paths given as readable (Python, its
packages, the system's libraries, the upload) and write only beneath the writable ones (its
output directory), whatever a stage names and whatever the checks of domain/scenes/usd_assets.py
might miss. The kernel enforces it for the process and anything it starts, and it cannot be
undone. Where the kernel has no Landlock (older than 5.13, or disabled), or a call fails,
`confine` changes nothing and says why: the child then relies on its own checks alone, and the
server logs a notice; the conversion never fails because of it.

The system calls go through `landlockpy` (PyPI, dependency-free bindings that follow the
kernel's ABI versions); only file-system rights are handled, as before Landlock's network and
scope rights existed: the child opens no socket.
"""

from __future__ import annotations

import os
import stat
from collections.abc import Iterable

import landlockpy
from landlockpy import AccessFS, AccessNet, LandlockError, Ruleset

READ = AccessFS.EXECUTE | AccessFS.READ_FILE | AccessFS.READ_DIR
# The rights a rule on a file (not a directory) may hold; the others concern directories.
_FILE_ONLY = (
    AccessFS.EXECUTE | AccessFS.WRITE_FILE | AccessFS.READ_FILE | AccessFS.TRUNCATE
    | AccessFS.IOCTL_DEV
)  # fmt: skip


def abi_version() -> int:
    """The kernel's Landlock ABI version; 0 without Landlock."""
    return landlockpy.abi_version()


def confine(readable: Iterable[str | os.PathLike], writable: Iterable[str | os.PathLike]) -> str:
    """Allow this process from now on to read (and execute) only beneath `readable` and to read
    and write only beneath `writable` (paths that do not exist are left out). Returns
    "enforced (Landlock ABI n)", or "unavailable: why" when nothing was changed."""
    abi = abi_version()
    if abi <= 0:
        return "unavailable: the kernel has no Landlock (Linux 5.13 or later, enabled)"
    try:
        with Ruleset(handled_net=AccessNet.NONE) as ruleset:
            rules = [(p, READ) for p in readable] + [(p, ruleset.handled_fs) for p in writable]
            for path, rights in rules:
                try:
                    is_dir = stat.S_ISDIR(os.stat(path).st_mode)
                except OSError:
                    continue  # a path that is not there needs no rule
                ruleset.allow_path(path, rights if is_dir else rights & _FILE_ONLY)
            ruleset.restrict()
    except LandlockError as e:
        return f"unavailable: {e}"
    return f"enforced (Landlock ABI {abi})"


__all__ = ["abi_version", "confine"]
