"""Swapping a staged set of outputs into a folder so that a kill at any moment leaves the old
set or the new one (docs/RELIABILITY.md); shared by `mask` (masking.py) and `poses`
(data/poses.py).

A command writes its new outputs into a staging folder, marks it complete (a file listing the
staged names: the commit point), then calls `swap_in`: each old output moves to a retired
folder, its staged one moves in, the `last` file (transforms.json) is replaced last, and the
retired and staging folders are removed. `swap_in` is idempotent: run again after a kill it
finishes the swap, so the command's `recover` rolls a complete staging folder forward and
removes an incomplete one.

A staging folder holds OWNER (the host and process id that made it: `write_owner`), so that
another process's `recover` leaves the staging folder of a command still running alone
(`other_owner`) instead of discarding it under that command's feet.

A leaf: imports nothing of the package.
"""

from __future__ import annotations

import os
import shutil
import socket
from pathlib import Path

OWNER = "OWNER"


def write_owner(stage: Path) -> None:
    """Writes stage/OWNER: this process's host name and id ("HOST PID")."""
    (Path(stage) / OWNER).write_text(f"{socket.gethostname()} {os.getpid()}\n")


def read_owner(stage: Path) -> tuple[str, int] | None:
    """(host, pid) of stage/OWNER; None when it is missing or unreadable."""
    try:
        host, pid = (Path(stage) / OWNER).read_text().split()
        return host, int(pid)
    except (OSError, ValueError):
        return None


def _running(host: str, pid: int) -> bool:
    """Whether process `pid` of `host` still runs; another host's counts as running (not ours
    to judge)."""
    if host != socket.gethostname():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def owner_alive(stage: Path) -> bool:
    """Whether the process that made `stage` (its OWNER) still runs; a process of another host
    counts as running (not ours to judge), a missing OWNER as gone."""
    owner = read_owner(stage)
    return owner is not None and _running(*owner)


def other_owner(stage: Path) -> tuple[str, int] | None:
    """(host, pid) of `stage`'s OWNER when that is another process that still runs (not this
    one), else None (no OWNER, or no staging folder, included). OWNER is read once."""
    owner = read_owner(stage)
    if owner is None or owner == (socket.gethostname(), os.getpid()) or not _running(*owner):
        return None
    return owner


def remove(path: Path) -> None:
    """Removes a file, a link or a folder tree; nothing when absent."""
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)
    elif path.exists() or path.is_symlink():
        path.unlink()


def move(src: Path, dst: Path) -> None:
    """One rename of the swap (os.replace: atomic within a filesystem); tests slow it down."""
    os.replace(src, dst)


def present(path: Path) -> bool:
    """Whether `path` exists (a dangling symbolic link counts)."""
    return path.exists() or path.is_symlink()


def write_complete(stage: Path, complete: str, staged) -> None:
    """The commit point: `stage/complete` lists the staged names, one a line (written atomically)."""
    tmp = stage / f".{complete}.tmp"
    tmp.write_text("".join(f"{name}\n" for name in staged))
    os.replace(tmp, stage / complete)


def read_complete(stage: Path, complete: str) -> list[str] | None:
    """The staged names of a complete staging folder; None when it is not complete."""
    path = stage / complete
    return path.read_text().split("\n")[:-1] if path.is_file() else None


def swap_in(root: Path, stage: Path, retired: Path, names, staged, last: str | None = None) -> None:
    """Rolls a complete staging folder forward into `root` (idempotent, so it may run again
    after a kill). names: every output name the swap replaces or removes (the old set's, and
    outputs the new set no longer has); staged: those the new set holds (in `stage`); last:
    a staged file replaced after all the others (os.replace, atomic), or None."""
    root, stage, retired = Path(root), Path(stage), Path(retired)
    for name in names:
        if name in staged and not present(stage / name):
            continue  # moved in before a kill
        if present(root / name):  # the old set's (or one the new set no longer has)
            retired.mkdir(parents=True, exist_ok=True)
            remove(retired / name)
            move(root / name, retired / name)
        if name in staged:
            move(stage / name, root / name)
    if last is not None and present(stage / last):
        move(stage / last, root / last)
    shutil.rmtree(retired, ignore_errors=True)
    shutil.rmtree(stage, ignore_errors=True)
