"""A cut-short DPT training run's loss curve rebuilt from its log lines
(experiments/dpt_train_curve.py): the numbers read back are the ones printed, other lines skipped."""

import json

import pytest

from experiments import dpt_train_curve

LOG = """[19:44:47] compiling the training step
[19:45:27] step 25: loss 1.0793 (ce 1.472, static 0.126, l1 0.138, acc 0.760), lr 2.77e-04, 8.04 steps/s
[19:46:03] step 360: val IoU 0.413 precision 0.501 recall 0.700 bird recall 0.586 static share 0.0117
[19:46:07] step 400: loss 0.5666 (ce 0.851, static 0.047, l1 0.058, acc 0.819), lr 7.27e-04, 12.16 steps/s
[19:46:34] step 721: val IoU 0.457 precision 0.555 recall 0.721 bird recall 0.602 static share None
"""


def test_training_and_validation_lines_read_back_as_printed():
    log, vals = dpt_train_curve.parse_log(LOG)
    assert [r["step"] for r in log] == [25, 400]
    assert log[0] == pytest.approx({"step": 25, "loss": 1.0793, "ce": 1.472, "static": 0.126, "l1": 0.138,
                                    "acc": 0.760, "lr": 2.77e-4, "steps_per_s": 8.04})
    assert log[1]["lr"] == pytest.approx(7.27e-4) and log[1]["loss"] == pytest.approx(0.5666)
    assert vals[0] == pytest.approx({"step": 360, "iou": 0.413, "precision": 0.501, "recall": 0.700,
                                     "bird_recall": 0.586, "static_share": 0.0117})
    assert vals[1]["step"] == 721 and vals[1]["static_share"] is None


def test_the_command_writes_the_curve_json_and_png(tmp_path):
    (tmp_path / "train.log").write_text(LOG)
    assert dpt_train_curve.main([str(tmp_path / "train.log"), "--out", str(tmp_path / "out")]) == 0
    rec = json.loads((tmp_path / "out" / "train_log.json").read_text())
    assert rec["source"] == "train.log" and len(rec["log"]) == 2 and len(rec["val"]) == 2
    assert (tmp_path / "out" / "loss_curve.png").read_bytes()[:4] == b"\x89PNG"


def test_a_log_without_training_lines_is_a_one_line_error(tmp_path):
    (tmp_path / "empty.log").write_text("compiling\n")
    with pytest.raises(SystemExit, match="empty.log: no training lines"):
        dpt_train_curve.main([str(tmp_path / "empty.log"), "--out", str(tmp_path / "out")])
