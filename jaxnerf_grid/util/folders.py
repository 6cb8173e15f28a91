"""May a command write into, or clear, this output folder? The marker rule (docs/RELIABILITY.md).

Every command that makes a folder writes a marker file naming itself into it first (MARKERS:
`.jaxnerf-grid-run`, `-poses`, `-export`, `-synth`, `-preprocess`, `-dataset`). `overwrite`
clears only a folder that holds the command's own marker, and in it only the command's own
outputs (names it passes); a user's other files stay, a folder without the marker is never
cleared, and an output that is a symbolic link is refused rather than skipped (clearing
through a link would delete files elsewhere; skipping it would keep old outputs silently). An
output folder equal to or inside a dataset folder is refused for every command (links
resolved). Every check here runs before anything is written or removed; `prepare_output` is
the whole rule in one call (check, clear, marker) for a writer of a whole folder.

A leaf: imports only `io`, so `data/` (poses) may use it.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

from jaxnerf_grid.util.io import DataError, naming_path

MARKERS = {"train": ".jaxnerf-grid-run", "poses": ".jaxnerf-grid-poses", "export": ".jaxnerf-grid-export",
           "synth": ".jaxnerf-grid-synth", "preprocess": ".jaxnerf-grid-preprocess",
           "dataset": ".jaxnerf-grid-dataset"}  # dataset: `data.formats.save_transforms_json`
MARKER_TEXT = "written by jaxnerf-grid {command}; its overwrite=True may clear this command's outputs here\n"


def marker(command: str) -> str:
    """The marker file name of `command` (a key of MARKERS)."""
    return MARKERS[command]


def is_marked(folder, command: str) -> bool:
    """True when `folder` holds `command`'s marker file."""
    return (Path(folder) / MARKERS[command]).is_file()


def is_empty(folder) -> bool:
    """True when `folder` does not exist or is an empty folder (a file is not empty)."""
    folder = Path(folder)
    if not folder.exists():
        return True
    return folder.is_dir() and not any(folder.iterdir())


def inside(path, folder) -> bool:
    """Whether `path` is `folder` or lies inside it, after resolving symbolic links."""
    path, folder = Path(path).resolve(), Path(folder).resolve()
    return path == folder or folder in path.parents


def check_folder(out, key: str) -> None:
    """DataError when `out` exists and is not a folder (a file, or a link to one), or when this
    user may not write it: `out` itself, or the nearest folder above it that exists (where it
    would be made), is read-only to this user or on a read-only file system. Checked before
    any work, so a command does not render or train for minutes to find it cannot save."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise DataError(f"{out}: {key} exists and is not a folder")
    here = next((p for p in (out, *out.absolute().parents) if p.exists()), None)
    if here is not None and not here.is_dir():
        raise DataError(f"{out}: {key} cannot be made there: {here} is a file, not a folder")
    if here is not None and not os.access(here, os.W_OK | os.X_OK):
        raise DataError(f"{out}: {key} is not writable by this user ({here}: permission denied, or a read-only "
                        f"file system); nothing was changed: make it writable or choose another {key}")


def check_outside(out, dataset, key: str) -> None:
    """DataError when the output folder `out` is the dataset folder `dataset` or lies inside it
    (links resolved): a command never adds files to a dataset it reads."""
    if dataset is not None and inside(out, dataset):
        raise DataError(f"{out}: {key} is the dataset folder {dataset} or inside it; choose a folder outside "
                        "the dataset")


def linked_outputs(folder, outputs) -> list[Path]:
    """The entries of `folder` named in `outputs` that are symbolic links."""
    folder = Path(folder)
    return [folder / name for name in outputs if (folder / name).is_symlink()]


def check_clearable(folder, command: str, outputs, key: str, legacy: bool = False) -> None:
    """DataError unless `overwrite` may clear `outputs` in `folder`: the folder is absent or
    empty, or it holds `command`'s marker (or `legacy`: the caller recognised an older output
    of the command, made before the marker), and none of those outputs is a symbolic link."""
    folder = Path(folder)
    check_folder(folder, key)
    if is_empty(folder):
        return
    if not (is_marked(folder, command) or legacy):
        raise DataError(f"{folder}: exists, is not empty and was not written by jaxnerf-grid {command} (no "
                        f"{MARKERS[command]}); nothing was changed: choose another {key}")
    links = linked_outputs(folder, outputs)
    if links:
        raise DataError(f"{links[0]}: is a symbolic link; overwrite=True does not clear through links (it would "
                        f"delete files elsewhere, or keep old outputs): empty or remove {links[0].name} yourself, "
                        f"or choose another {key}")


def clear_outputs(folder, command: str, outputs, key: str, legacy: bool = False) -> None:
    """Removes `outputs` (file or folder names) from `folder` after `check_clearable`."""
    folder = Path(folder)
    check_clearable(folder, command, outputs, key, legacy)
    if not folder.is_dir():
        return
    for name in outputs:
        path = folder / name
        if path.is_dir():
            shutil.rmtree(path)
        elif path.exists():
            path.unlink()


def write_marker(folder, command: str) -> Path:
    """Creates `folder` (and parents) and writes `command`'s marker into it; returns its path."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / MARKERS[command]
    with naming_path(path):  # a full disk names the marker, not only "No space left on device"
        path.write_text(MARKER_TEXT.format(command=command))
    return path


def check_output(folder, command: str, outputs, key: str, overwrite: bool, legacy: bool = False) -> None:
    """DataError unless `command` may write its outputs into `folder`: the folder is absent or
    empty, or `overwrite` and `check_clearable` allows it. Writes nothing."""
    folder = Path(folder)
    check_folder(folder, key)
    if not overwrite and not is_empty(folder):
        raise DataError(f"{folder}: {key} exists and is not empty; nothing was changed: pass overwrite=True to "
                        f"replace what jaxnerf-grid {command} wrote there, or choose another {key}")
    check_clearable(folder, command, outputs, key, legacy)


def prepare_output(folder, command: str, outputs, key: str, overwrite: bool, legacy: bool = False) -> Path:
    """The marker rule in one call, for a command that writes a whole folder: `check_output`,
    then its old `outputs` removed (`clear_outputs`; a user's other files stay) and its marker
    written before any output. Returns the folder as a Path."""
    check_output(folder, command, outputs, key, overwrite, legacy)
    clear_outputs(folder, command, outputs, key, legacy)
    return write_marker(folder, command).parent
