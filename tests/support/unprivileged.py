"""Running the command line as an unprivileged user: read-only folders,
permission-denied files and a full disk as they really happen, where the tests run as root
(which ignores permissions). Shared by tests/cli/test_unprivileged.py and scripts/hostile_corpus.py.

`as_nobody(argv)` is the command line that runs `python argv...` as user and group 65534
(`nobody`), with no supplementary groups (`setpriv`, util-linux); with `disk` and `disk_kib` it
first mounts a tmpfs of that size at `disk` in a private mount namespace (`unshare -m`: the
mount exists only for that command and vanishes with it), so a write there fails with ENOSPC, a
real full disk. `unavailable()` says why none of this can run here (None when it can).

A full disk without root: an unprivileged user may do the same in a user namespace
(`unshare -Urm`, where the kernel allows unprivileged user namespaces), but the Python it then
runs must be reachable by that user; RLIMIT_FSIZE (`prlimit --fsize`) gives EFBIG ("File too
large"), not ENOSPC. Here root mounts the tmpfs and `setpriv` drops to nobody for the command.
"""

from __future__ import annotations

import functools
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
NOBODY = 65534


def _probe(argv: list[str]) -> str | None:
    """None when `argv` runs and exits 0 (from ROOT, with ROOT on PYTHONPATH), else its stderr's last line."""
    try:
        done = subprocess.run(argv, cwd=ROOT, capture_output=True, text=True, timeout=600,
                              env={**os.environ, "PYTHONPATH": str(ROOT), "JAX_PLATFORMS": "cpu"})
    except (OSError, subprocess.TimeoutExpired) as err:
        return str(err)
    return None if done.returncode == 0 else (done.stderr.strip().splitlines() or [f"exit {done.returncode}"])[-1]


@functools.cache
def unavailable() -> str | None:
    """Why commands cannot run as an unprivileged user here: not root (cannot drop to another
    user), no `setpriv`, or that user cannot run this Python and import the package. None when they can."""
    if os.geteuid() != 0:
        return "not root: cannot switch to the unprivileged user (the permission cases need root to start them)"
    if shutil.which("setpriv") is None:
        return "setpriv (util-linux) is missing"
    why = _probe(as_nobody(["-c", "import jaxnerf_grid, numpy"]))
    return None if why is None else f"user {NOBODY} cannot run {sys.executable} here: {why}"


@functools.cache
def disk_unavailable() -> str | None:
    """Why a tiny tmpfs cannot be mounted for one command here (None when it can)."""
    why = unavailable()
    if why is not None:
        return why
    if shutil.which("unshare") is None:
        return "unshare (util-linux) is missing"
    with tempfile.TemporaryDirectory() as folder:
        why = _probe(as_nobody(["-c", "pass"], disk=Path(folder), disk_kib=64))
    return None if why is None else f"cannot mount a tmpfs in a private mount namespace: {why}"


def cannot_read(folder: Path) -> str | None:
    """Why the unprivileged user cannot list `folder` (a folder above it private to root), or None."""
    why = _probe(as_nobody(["-c", f"import os; os.listdir({str(folder)!r})"]))
    return None if why is None else f"user {NOBODY} cannot read {folder}: {why}"


def as_nobody(argv: list[str], disk: Path | None = None, disk_kib: int = 0) -> list[str]:
    """The command line running `python argv...` as user 65534 (module docstring); with `disk`,
    on a tmpfs of `disk_kib` KiB mounted there for that command only."""
    drop = ["setpriv", f"--reuid={NOBODY}", f"--regid={NOBODY}", "--clear-groups", sys.executable, *argv]
    if disk is None:
        return drop
    script = 'mount -t tmpfs -o size="$1"k,mode=1777 jaxnerf-full-disk "$0" || exit 97; shift; exec "$@"'
    return ["unshare", "-m", "--propagation", "private", "sh", "-c", script, str(disk), str(disk_kib), *drop]


def shared_folder(prefix: str = "jaxnerf-nobody-") -> Path:
    """A new folder under the system's temporary folder that the unprivileged user may read
    (0755, owned by root): the tests' own temporary folders are private to root."""
    folder = Path(tempfile.mkdtemp(prefix=prefix))
    folder.chmod(0o755)
    return folder


def give_to_nobody(path: Path) -> Path:
    """Makes the folder `path` (created if missing) the unprivileged user's, so it may write there."""
    path.mkdir(parents=True, exist_ok=True)
    os.chown(path, NOBODY, NOBODY)
    return path


def environment(home: Path) -> dict:
    """The child's environment: this checkout first on the path, CPU JAX, and a home (and
    matplotlib's folder) the unprivileged user may write, so no library warns about its cache."""
    return {**os.environ, "PYTHONPATH": str(ROOT), "JAX_PLATFORMS": os.environ.get("JAX_PLATFORMS", "cpu"),
            "HOME": str(home), "MPLCONFIGDIR": str(home / "mpl"), "XDG_CACHE_HOME": str(home / "cache")}
