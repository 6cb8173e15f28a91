"""The marker rule (`folders`), the staged swap (`staging`) and the recovery of a `poses` run
killed while swapping its dataset in (`data.poses.recover`).

The expected trees are written out by hand (the old set, the new set, the user's own file),
never read back from the code under test. The kill tests stop the swap after each of its
renames (an exception from a patched `staging.move`) and, once, with SIGKILL in a child
process; `recover` must then leave the new dataset and the user's files, nothing else.
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

import pytest

from jaxnerf_grid.capture import poses
from jaxnerf_grid.util import folders, staging
from jaxnerf_grid.util.io import DataError
from tests.support.killing import kill_when

ROOT = Path(__file__).resolve().parents[2]


def tree(root: Path) -> dict:
    """{relative path: file text, or "dir" / "link"} of everything under root."""
    out = {}
    for p in sorted(root.rglob("*")):
        rel = p.relative_to(root).as_posix()
        out[rel] = "link" if p.is_symlink() else "dir" if p.is_dir() else p.read_text()
    return out


def write(root: Path, files: dict) -> None:
    for rel, text in files.items():
        path = root / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)


# ------------------------------------------------------------------------------- the marker rule


def test_clear_outputs_refuses_an_unmarked_folder(tmp_path):
    write(tmp_path / "out", {"box.json": "mine", "report.md": "my notes"})
    before = tree(tmp_path)
    with pytest.raises(DataError, match="no .jaxnerf-grid-export"):
        folders.clear_outputs(tmp_path / "out", "export", ("box.json", "report.md"), "export.out")
    assert tree(tmp_path) == before


def test_clear_outputs_removes_only_the_commands_outputs(tmp_path):
    out = tmp_path / "out"
    write(out, {"box.json": "old", "sub/a.png": "old", "keep.txt": "mine"})
    folders.write_marker(out, "export")
    folders.clear_outputs(out, "export", ("box.json", "sub", "absent.ply"), "export.out")
    assert set(tree(out)) == {"keep.txt", ".jaxnerf-grid-export"}


def test_clear_outputs_refuses_a_linked_output_and_removes_nothing(tmp_path):
    """A symlinked checkpoints/ (weights on a bigger disk): refused, neither cleared through
    nor skipped; nothing on either side of the link changes."""
    elsewhere, run = tmp_path / "big_disk", tmp_path / "run"
    write(elsewhere, {"ckpt_10.npz": "weights"})
    write(run, {"config.json": "{}", "metrics.jsonl": "line"})
    folders.write_marker(run, "train")
    (run / "checkpoints").symlink_to(elsewhere, target_is_directory=True)
    before = tree(tmp_path)
    with pytest.raises(DataError, match="checkpoints: is a symbolic link"):
        folders.clear_outputs(run, "train", ("config.json", "checkpoints", "metrics.jsonl"), "run.out")
    assert tree(tmp_path) == before


def test_check_outside_resolves_links(tmp_path):
    data = tmp_path / "data"
    data.mkdir()
    (tmp_path / "alias").symlink_to(data, target_is_directory=True)
    for out in (data, data / "export", tmp_path / "alias" / "export", tmp_path / "alias"):
        with pytest.raises(DataError, match="inside it"):
            folders.check_outside(out, data, "export.out")
    folders.check_outside(tmp_path / "elsewhere", data, "export.out")
    folders.check_outside(tmp_path / "data2", data, "export.out")  # a prefix of the name is not inside


# ------------------------------------------------------------------ the poses swap and its recovery

OLD = {"images/a.png": "old a", "images/b.png": "old b", "sparse/0/cameras.bin": "old cams",
       "transforms.json": "old transforms", poses.REPORT: "old report", poses.MARKER: "",
       "masks/a.png": "old mask", "weights/a.exr": "old weight"}
NEW = {"images/a.png": "new a", "images/c.png": "new c", "sparse/0/cameras.bin": "new cams",
       "transforms.json": "new transforms", poses.TOPVIEW: "new top", poses.REPORT: "new report",
       poses.MARKER: ""}
USER = {"notes.txt": "the surveyor's notes"}


def dataset_with_stage(tmp_path: Path) -> tuple[Path, Path]:
    """An old poses dataset with a user's file, and a finished staging folder beside it."""
    out = tmp_path / "Mast Nord ü"
    write(out, {**OLD, **USER})
    stage = poses.make_stage(out)
    write(stage, NEW)
    return out, stage


def expected_new() -> dict:
    want = {**NEW, **USER}
    dirs = {"images", "sparse", "sparse/0"}
    return {**{d: "dir" for d in dirs}, **want}


def hidden_siblings(out: Path) -> list[str]:
    return sorted(p.name for p in out.parent.iterdir() if p.name.startswith("."))


def test_move_into_place_swaps_and_keeps_the_users_file(tmp_path):
    out, stage = dataset_with_stage(tmp_path)
    poses.move_into_place(stage, out)
    assert tree(out) == expected_new()
    assert hidden_siblings(out) == []


def count_moves(tmp_path: Path) -> int:
    out, stage = dataset_with_stage(tmp_path / "count")
    n = 0
    real = staging.move

    def counting(src, dst):
        nonlocal n
        n += 1
        real(src, dst)

    staging.move = counting
    try:
        poses.move_into_place(stage, out)
    finally:
        staging.move = real
    return n


class Killed(BaseException):
    pass


def test_a_swap_stopped_after_any_rename_is_finished_by_recover(tmp_path, monkeypatch):
    """Every rename of the swap, one at a time, is the last one before a 'kill'; then `recover`
    (what the next `poses`, `train` or `mask` runs first) must give exactly the new dataset."""
    total = count_moves(tmp_path)
    assert total >= 10  # old images, sparse, report, marker, masks, weights out; the new ones in
    real = staging.move
    for k in range(total):
        case = tmp_path / f"k{k}"
        out, stage = dataset_with_stage(case)
        done = 0

        def dying(src, dst, k=k):
            nonlocal done
            if done == k:
                raise Killed()
            real(src, dst)
            done += 1

        monkeypatch.setattr(staging, "move", dying)
        with pytest.raises(Killed):
            poses.move_into_place(stage, out)
        monkeypatch.setattr(staging, "move", real)
        assert poses.recover(out) == "rolled forward", k
        assert tree(out) == expected_new(), k
        assert hidden_siblings(out) == [], k


def test_recover_finishes_the_older_versions_interrupted_swap(tmp_path):
    """The state an older version left when killed: old images/ and sparse/ moved to `.NAME.old-*`, the new set still
    in `.NAME.poses-*` (no OWNER or COMPLETE: written by the version before them)."""
    out = tmp_path / "d"
    write(out, {"transforms.json": "old transforms", **USER})
    write(tmp_path / ".d.old-abc", {"images/a.png": "old a", "sparse/0/cameras.bin": "old cams"})
    write(tmp_path / ".d.poses-xyz", NEW)
    assert poses.recover(out) == "rolled forward"
    assert tree(out) == expected_new()
    assert hidden_siblings(out) == []


def test_recover_cleans_a_killed_runs_staging_copy_but_not_a_running_one(tmp_path):
    out = tmp_path / "d"
    write(out, {**OLD, **USER})
    dead = tmp_path / ".d.poses-dead"
    write(dead, {"_work/photos/a.png": "copy", "OWNER": f"{os.uname().nodename} 999999999\n"})
    running = poses.make_stage(out)  # this process: still running
    write(running, {"_work/photos/a.png": "copy"})
    before = tree(out)
    assert poses.recover(out) == "cleaned"
    assert tree(out) == before
    assert hidden_siblings(out) == [running.name]


def _slow_swap_child(base: str, pause: str) -> None:
    """Builds dataset_with_stage under `base` and swaps it in with a pause after each rename."""
    out, stage = dataset_with_stage(Path(base))
    real = staging.move
    marks = Path(base) / "moves"

    def slow(src, dst):
        real(src, dst)
        marks.write_text(str(int(marks.read_text() or 0) + 1) if marks.exists() else "1")
        time.sleep(float(pause))

    staging.move = slow
    poses.move_into_place(stage, out)


@pytest.mark.parametrize("after_moves", [1, 6])
def test_poses_swap_killed_with_sigkill_is_finished_by_recover(tmp_path, after_moves):
    """kill -9 of a process in the middle of the swap (the COLMAP stages before it run in the
    staging folder only: a kill there is the staging copy `recover` cleans, tested above)."""
    base = tmp_path / "base"
    base.mkdir()
    marks = base / "moves"
    kill_when([__file__, str(base), "0.3"], timeout=600, poll=0.01,
              ready=lambda: marks.exists() and int(marks.read_text() or 0) >= after_moves)
    out = base / "Mast Nord ü"
    assert tree(out) != expected_new()  # it really stopped half-way
    assert poses.recover(out) == "rolled forward"
    assert tree(out) == expected_new()
    assert hidden_siblings(out) == []


if __name__ == "__main__":
    _slow_swap_child(sys.argv[1], sys.argv[2])
