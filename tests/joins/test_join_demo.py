"""The demo (the README's first command) end to end as `demo.run_demo(None, out)`: synth (a
small tower scene instead of tower-small's 48 views at 160x120) -> mask (the built-in DPT, or
ground-truth stand-ins when no model is shipped) -> train "ours" with the demo recipe for a
few steps -> evaluate -> a fly-around video of a few frames; then its report's figures and tables
are read back and checked against the renders, depth maps and metrics.json it wrote, and the
videos with OpenCV (docs: `demo.py`, `report.py`, docs/VIDEOS.md)."""

from pathlib import Path

import cv2
import pytest

from jaxnerf_grid import cli, demo
from jaxnerf_grid.config.schema import ConfigError
from jaxnerf_grid.data.synthetic import generate as synth_generate
from jaxnerf_grid.masks import write as masking
from jaxnerf_grid.train import runs
from jaxnerf_grid.util import io
from tests.joins.test_join_eval import _table, check_report_figures

SMALL_SCENE = dict(width=40, height=30, num_train=4, num_test=1, supersample=1, buildings=4, trees=0.3)


def test_tiny_demo_end_to_end_and_its_report(tmp_path, monkeypatch, capsys):
    real = synth_generate.generate_scene
    asked = []

    def small_scene(preset, out_dir, **kw):
        asked.append(preset)
        return real(preset, out_dir, **{**kw, **SMALL_SCENE})

    monkeypatch.setattr(synth_generate, "generate_scene", small_scene)
    result = demo.run_demo(None, tmp_path / "demo", steps=2, progress=False, video_frames=3)
    assert asked == ["tower-small"] and set(result["timings"]) == {"synth", "mask", "train", "eval", "video"}
    run = Path(result["run_dir"])
    meta = io.read_json(tmp_path / "demo/data/transforms.json")
    assert result["mask_source"] == meta["mask_source"] == ("dpt" if masking.BUILTIN.exists() else "ground-truth")
    assert all("weight_path" in f for f in meta["frames"])
    cfg = io.read_json(run / "config.json")
    assert cfg["model"]["sampler"]["kind"] == "proposal" and cfg["train"]["max_steps"] == 2
    m = io.read_json(run / "metrics.json")
    assert m["step"] == 2 and m["num_views"] == 1
    assert m["target"] == "clean images" and abs(m["mean"]["psnr"] - result["metrics"]["mean"]["psnr"]) < 1e-12
    # the report's figures are the clean target, the render and the depth it wrote
    ds = runs.load_dataset(tmp_path / "demo/data", progress=False)
    i = int(ds.split["test"][0])
    check_report_figures(run, runs.frame_name(ds, i), ds.clean_images[i], ds.semantics[i])
    # its table is metrics.json's
    report = (run / "report.md").read_text()
    rows = _table(report)
    assert rows["PSNR"] == f"{m['mean']['psnr']:.2f}" and rows["SSIM"] == f"{m['mean']['ssim']:.4f}"
    for name, value in m["regions_mean"].items():
        assert rows[f"PSNR, {name.replace('_', ' ')}"] == (f"{value:.2f}" if value is not None else "unavailable")
    assert demo._mask_note(result["mask_source"]) in report
    # the time of each stage: timings.json and the report's table, in the order of the stages
    recorded = io.read_json(run / "timings.json")
    assert recorded == {k: round(v, 2) for k, v in result["timings"].items()}
    table = report[report.index("## Time per stage"):]
    rows = [line.split("|")[1].strip() for line in table.splitlines()
            if line.startswith("| ") and "seconds" not in line]
    assert rows == ([demo.STAGES[k] for k in ("synth", "mask", "train", "eval", "video")]
                    + ["total of the demo (poses excluded)"])
    assert f"| {demo.STAGES['train']} | {result['timings']['train']:.1f} |" in table
    # the one-line summary quotes the same numbers
    line = demo.demo_summary(result)
    assert f"test PSNR {m['mean']['psnr']:.2f} dB" in line
    if m["regions_mean"].get("tower") is not None:
        assert f"tower {m['regions_mean']['tower']:.2f} dB" in line
    # the synthetic scene has a reference tower cloud, so the line quotes its F-score at 0.02
    assert f"tower F-score@0.02 {m['geometry']['thresholds']['0.02']['fscore']:.3f}" in line
    # the fly-around: 3 frames, DEMO_VIDEO_WIDTH wide with the photos' aspect, colour and depth,
    # linked from report.md and report.html
    height = round(demo.DEMO_VIDEO_WIDTH * SMALL_SCENE["height"] / SMALL_SCENE["width"])
    for name in ("orbit.mp4", "orbit_depth.mp4"):
        assert mp4_frames(run / "videos" / name) == (3, height, demo.DEMO_VIDEO_WIDTH, demo.DEMO_VIDEO_FPS)
        assert f"[videos/{name}](videos/{name})" in report
        assert f'<a href="videos/{name}">' in (run / "report.html").read_text()
    assert result["video"]["video"] == run / "videos" / "orbit.mp4"


def mp4_frames(path: Path) -> tuple[int, int, int, float]:
    """(frames decoded, height, width, fps) of a video read back with OpenCV frame by frame; every
    frame the same size, three channels."""
    cap = cv2.VideoCapture(str(path))
    assert cap.isOpened(), f"{path}: OpenCV cannot open it"
    fps, shapes = cap.get(cv2.CAP_PROP_FPS), []
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        shapes.append(frame.shape)
    cap.release()
    assert len(set(shapes)) == 1 and shapes[0][2] == 3
    return len(shapes), shapes[0][0], shapes[0][1], fps


def test_a_bad_video_frame_count_is_a_one_line_error_before_anything_is_written(tmp_path, capsys):
    assert cli.main(["demo", "--out", str(tmp_path / "demo"), "--video-frames=-1", "--quiet"]) == 1
    err = capsys.readouterr().err.strip()
    assert "--video-frames = -1" in err and len(err.splitlines()) == 1 and "Traceback" not in err
    for bad in (2.5, True, "3"):
        with pytest.raises(ConfigError, match="demo.video_frames"):
            demo.run_demo(None, tmp_path / "demo", video_frames=bad)
    assert not (tmp_path / "demo").exists()


def test_the_video_flags_help_quotes_the_demos_constants():
    from jaxnerf_grid.cli import demo as demo_cli

    text = " ".join(demo_cli.build_parser().format_help().split())
    assert (f"{demo.DEMO_VIDEO_WIDTH} px wide, {demo.DEMO_VIDEO_FPS:g} fps; default {demo.DEMO_VIDEO_FRAMES}"
            in text)


def test_a_video_that_cannot_be_written_leaves_the_demo_its_report(tmp_path, capsys):
    """demo_video_step on a run folder the video cannot be made from (no trained run: a real
    DataError from loading it): a one-line warning, a report.md note, and the time table still
    written by record_timings."""
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    (run_dir / "report.md").write_text("# Report\n", encoding="utf-8")
    timings = {"train": 1.0, "eval": 2.0}
    video, lines = demo.demo_video_step(run_dir, 3, False, timings)
    assert video is None and "video" in timings
    warning = [line for line in capsys.readouterr().out.splitlines() if "video" in line]
    assert len(warning) == 1 and warning[0].startswith("warning: the fly-around video was not written: ")
    assert "Traceback" not in warning[0]
    demo.record_timings(run_dir, timings, lines)
    report = (run_dir / "report.md").read_text(encoding="utf-8")
    assert report.startswith("# Report\n") and "Not written: " in report and "Time per stage" in report
    assert not (run_dir / "videos").exists()
    assert demo.demo_video_step(run_dir, 0, False, {}) == (None, [])
