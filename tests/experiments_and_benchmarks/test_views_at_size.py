"""benchmarks/views_at_size.py: a report_views grid is cut into its views, and each view's PSNR at
a common size is the closed form of a render that differs from its photo on every other column."""

import json
import math

import cv2
import numpy as np
import pytest

from benchmarks import views_at_size as bench
from jaxnerf_grid.report.markdown import side_by_side

W, H = 8, 6


def _view(offset: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(photo, render, depth) [H, W, 3] in [0, 1] on the 8-bit grid: the photo is 100 everywhere, the
    render 100 + offset on the even columns and 100 on the odd ones."""
    photo = np.full((H, W, 3), 100, np.uint8)
    render = photo.copy()
    render[:, ::2] += offset
    depth = np.zeros((H, W, 3), np.uint8)
    return tuple(x.astype(np.float32) / 255.0 for x in (photo, render, depth))


def _write_grid(path, offsets) -> None:
    grid = side_by_side([_view(o) for o in offsets])
    cv2.imwrite(str(path), np.round(grid[..., ::-1] * 255).astype(np.uint8))


def _psnr_of_mse(mse: float) -> float:
    return -10 * math.log10(mse)


def test_each_view_scores_the_closed_form_at_its_own_size_and_at_half_size(tmp_path):
    _write_grid(tmp_path / "grid.png", [20, 40])
    out = tmp_path / "out.json"
    bench.main(["--run", f"a={tmp_path / 'grid.png'}:{W}x{H}", "--size", f"{W}x{H}", "--out", str(out)])
    full = json.loads(out.read_text())["runs"]["a"]["per_view_psnr"]
    # half of the pixels off by d: MSE = d^2 / 2
    assert full == pytest.approx([_psnr_of_mse((20 / 255) ** 2 / 2), _psnr_of_mse((40 / 255) ** 2 / 2)], abs=1e-4)
    bench.main(["--run", f"a={tmp_path / 'grid.png'}:{W}x{H}", "--size", f"{W // 2}x{H // 2}", "--out", str(out)])
    half = json.loads(out.read_text())
    # area averaging of 2x2 blocks: every pixel off by d / 2
    assert half["runs"]["a"]["per_view_psnr"] == pytest.approx(
        [_psnr_of_mse((10 / 255) ** 2), _psnr_of_mse((20 / 255) ** 2)], abs=1e-4)
    assert half["runs"]["a"]["psnr"] == pytest.approx(np.mean(half["runs"]["a"]["per_view_psnr"]))


def test_the_views_are_cut_at_the_gaps():
    rows = [_view(20), _view(40), _view(60)]
    grid = side_by_side(rows)
    views = bench.split_views(grid, W, H)
    assert len(views) == 3
    for (photo, render), (p, r, _d) in zip(views, rows):
        np.testing.assert_array_equal(photo, p)
        np.testing.assert_array_equal(render, r)


def test_a_grid_smaller_than_its_views_is_one_line(tmp_path):
    _write_grid(tmp_path / "grid.png", [20])
    with pytest.raises(SystemExit, match="holds no 64x48 views"):
        bench.main(["--run", f"a={tmp_path / 'grid.png'}:64x48", "--size", "8x6"])
    with pytest.raises(SystemExit, match="not an image"):
        bench.main(["--run", f"a={tmp_path / 'missing.png'}:8x6", "--size", "8x6"])
