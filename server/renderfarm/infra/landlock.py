"""Landlock (Linux 5.13 and later): a process confines its own file-system access.

The USD conversion's child (infra/usd_import.py) calls `confine` before it opens the upload:
from then on it may read and execute only beneath the paths given as readable (Python, its
packages, the system's libraries, the upload) and write only beneath the writable ones (its
output directory), whatever a stage names and whatever the checks of domain/scenes/usd_assets.py
might miss. The kernel enforces it for the process and anything it starts, and it cannot be
undone. Where the kernel has no Landlock (older than 5.13, or disabled), or a call fails,
`confine` changes nothing and says why: the child then relies on its own checks alone, and the
server logs a notice; the conversion never fails because of it.

Called through ctypes (the syscalls have no wrapper in Python's standard library); the numbers
and structures are those of include/uapi/linux/landlock.h, the same on every architecture.
"""

from __future__ import annotations

import ctypes
import os
import stat
from collections.abc import Iterable

_CREATE_RULESET, _ADD_RULE, _RESTRICT_SELF = 444, 445, 446
_CREATE_RULESET_VERSION = 1 << 0
_RULE_PATH_BENEATH = 1
_PR_SET_NO_NEW_PRIVS = 38

# LANDLOCK_ACCESS_FS_*: ABI 1 the first thirteen, REFER from ABI 2, TRUNCATE 3, IOCTL_DEV 5.
EXECUTE, WRITE_FILE, READ_FILE, READ_DIR = 1 << 0, 1 << 1, 1 << 2, 1 << 3
REFER, TRUNCATE, IOCTL_DEV = 1 << 13, 1 << 14, 1 << 15
_FILE_ONLY = EXECUTE | WRITE_FILE | READ_FILE | TRUNCATE | IOCTL_DEV  # rights a file rule may hold
READ = EXECUTE | READ_FILE | READ_DIR


class _RulesetAttr(ctypes.Structure):
    _fields_ = [("handled_access_fs", ctypes.c_uint64)]


class _PathBeneathAttr(ctypes.Structure):
    _pack_ = 1
    _fields_ = [("allowed_access", ctypes.c_uint64), ("parent_fd", ctypes.c_int32)]


def handled_access(abi: int) -> int:
    """Every file-system right the kernel's Landlock ABI version can restrict."""
    rights = (1 << 13) - 1
    if abi >= 2:
        rights |= REFER
    if abi >= 3:
        rights |= TRUNCATE
    if abi >= 5:
        rights |= IOCTL_DEV
    return rights


def abi_version() -> int:
    """The kernel's Landlock ABI version; 0 without Landlock."""
    libc = ctypes.CDLL(None, use_errno=True)
    libc.syscall.restype = ctypes.c_long
    version = libc.syscall(
        _CREATE_RULESET, None, ctypes.c_size_t(0), ctypes.c_uint32(_CREATE_RULESET_VERSION)
    )
    return max(0, int(version))


def confine(readable: Iterable[str | os.PathLike], writable: Iterable[str | os.PathLike]) -> str:
    """Allow this process from now on to read (and execute) only beneath `readable` and to read
    and write only beneath `writable` (paths that do not exist are left out). Returns
    "enforced (Landlock ABI n)", or "unavailable: why" when nothing was changed."""
    libc = ctypes.CDLL(None, use_errno=True)
    libc.syscall.restype = ctypes.c_long
    abi = abi_version()
    if abi <= 0:
        return "unavailable: the kernel has no Landlock (Linux 5.13 or later, enabled)"
    handled = handled_access(abi)
    attr = _RulesetAttr(handled)
    size = ctypes.c_size_t(ctypes.sizeof(attr))
    ruleset = int(libc.syscall(_CREATE_RULESET, ctypes.byref(attr), size, ctypes.c_uint32(0)))
    if ruleset < 0:
        return f"unavailable: landlock_create_ruleset: {os.strerror(ctypes.get_errno())}"
    try:
        rules = [(p, READ) for p in readable] + [(p, handled) for p in writable]
        for path, rights in rules:
            try:
                fd = os.open(path, os.O_PATH | os.O_CLOEXEC)
            except OSError:
                continue  # a path that is not there needs no rule
            try:
                if not stat.S_ISDIR(os.fstat(fd).st_mode):
                    rights &= _FILE_ONLY
                rule = _PathBeneathAttr(rights & handled, fd)
                done = libc.syscall(_ADD_RULE, ctypes.c_int(ruleset),
                                    ctypes.c_int(_RULE_PATH_BENEATH), ctypes.byref(rule),
                                    ctypes.c_uint32(0))  # fmt: skip
            finally:
                os.close(fd)
            if done < 0:
                return f"unavailable: landlock_add_rule({path}): {os.strerror(ctypes.get_errno())}"
        if libc.prctl(_PR_SET_NO_NEW_PRIVS, 1, 0, 0, 0) != 0:
            return f"unavailable: no_new_privs: {os.strerror(ctypes.get_errno())}"
        if libc.syscall(_RESTRICT_SELF, ctypes.c_int(ruleset), ctypes.c_uint32(0)) < 0:
            return f"unavailable: landlock_restrict_self: {os.strerror(ctypes.get_errno())}"
    finally:
        os.close(ruleset)
    return f"enforced (Landlock ABI {abi})"


__all__ = ["abi_version", "confine", "handled_access"]
