"""A refused `poses` run's reconstruction, kept beside DATA_DIR so that the same run with
`--accept-few-cameras` finishes without running COLMAP again.

`poses` refuses a camera set too thin to train on (`camera_set`) after COLMAP's features,
matching and mapping are done: minutes on a few photos, a quarter of an hour on a few hundred.
The refusal is a judgement the user may overrule, and the user needs to see what it rests on.
So the refused run leaves DATA_DIR.refused/ (`keep`): the model COLMAP returned (before the
vetting), its matching database (why photos stayed out), `poses_report.md` (the summary and
the vetting table: which photos were left out and why), `poses_topview.png`, and a record
holding the run's key. The next `poses` writing DATA_DIR reads the model back (`load`) when its
key (`run_key`: each photo's name, size and modification time, and every option that changes
COLMAP's work) is the same, and removes the folder once a dataset is written (`discard`). The
folder holds MARKER: only a folder this module wrote is read or removed.
"""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

from jaxnerf_grid.util import io

SUFFIX = ".refused"
MARKER = ".jaxnerf-grid-poses-refused"
RECORD = "run.json"
MODEL = "model"
DATABASE = "database.db"


def folder_of(out) -> Path:
    """DATA_DIR.refused, beside DATA_DIR."""
    out = Path(out)
    return out.with_name(out.name + SUFFIX)


def run_key(photos: list[Path], options: dict) -> str:
    """A hex digest of the photos (each one's name, size in bytes and modification time in ns,
    in the given order) and `options` (JSON-serialisable: every setting that changes COLMAP's
    features, matching or mapping). Equal keys: COLMAP would be given the same work."""
    files = [[p.name, p.stat().st_size, p.stat().st_mtime_ns] for p in photos]
    text = json.dumps({"photos": files, "options": options}, sort_keys=True, default=str)
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def keep(out, key: str, model_dir: Path, database: Path, record: dict, report: str, topview=None) -> Path:
    """Moves a refused run's model folder (`model_dir`, pycolmap's binary model) and matching
    database into DATA_DIR.refused, with `report` as poses_report.md, `topview(path)` drawing
    poses_topview.png, and {"key", **record} as RECORD; an older folder of ours is replaced.
    Built beside it and renamed, so a kill leaves the old one or the new one. Returns the folder."""
    folder = folder_of(out)
    building = folder.with_name(folder.name + ".building")
    shutil.rmtree(building, ignore_errors=True)
    building.mkdir(parents=True)
    shutil.move(str(model_dir), str(building / MODEL))
    if Path(database).is_file():
        shutil.move(str(database), str(building / DATABASE))
    io.atomic_write_bytes(building / "poses_report.md", report.encode("utf-8"))
    if topview is not None:
        topview(building / "poses_topview.png")
    io.write_json(building / RECORD, {"key": key, **record})
    (building / MARKER).write_text("a refused jaxnerf-grid poses run; the next poses on its DATA_DIR reuses it\n")
    discard(out)
    building.rename(folder)
    return folder


def load(pycolmap, out, key: str):
    """(the kept pycolmap.Reconstruction, its record, the database path) of DATA_DIR.refused when
    it is ours and its key is `key`; else None."""
    folder = folder_of(out)
    if not (folder / MARKER).is_file() or not (folder / RECORD).is_file():
        return None
    try:
        record = json.loads((folder / RECORD).read_text())
    except (OSError, ValueError):
        return None
    if record.get("key") != key:
        return None
    return pycolmap.Reconstruction(str(folder / MODEL)), record, folder / DATABASE


def discard(out) -> None:
    """Removes DATA_DIR.refused when this module wrote it (it holds MARKER)."""
    folder = folder_of(out)
    if (folder / MARKER).is_file():
        shutil.rmtree(folder)
