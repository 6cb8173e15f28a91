"""progress.bar: plain throttled lines on a non-terminal stream, silence when disabled."""

import io as pyio

from jaxnerf_grid.util import progress


class FakeClock:
    def __init__(self):
        self.now = 100.0

    def __call__(self):
        return self.now


def test_log_mode_throttles_lines_and_prints_the_final_one():
    stream, clock = pyio.StringIO(), FakeClock()
    bar = progress.bar(total=1000, desc="train ours", unit="step", stream=stream, clock=clock, interval=10.0)
    assert isinstance(bar, progress.LogBar)
    for step in range(1000):
        clock.now += 0.1              # 100 s in all: one line per 10 s (fake time, no sleeping)
        bar.set_postfix(loss=f"{1.0 / (step + 1):.4f}")
        bar.update(1)
    bar.close()
    bar.close()                       # idempotent
    text = stream.getvalue()
    assert "\r" not in text
    lines = text.splitlines()
    assert 9 <= len(lines) <= 11, lines    # ~every 10 s over 100 s, plus the final line
    assert lines[0].startswith("train ours: ") and "steps (" in lines[0]
    assert lines[-1] == "train ours: 1000/1000 steps (100%), 1 min 40 s, loss=0.0010"
    # no two consecutive lines closer than the interval: the counts of the throttled lines
    counts = [int(line.split(": ")[1].split("/")[0]) for line in lines[:-1]]
    assert all(b - a >= 100 for a, b in zip(counts, counts[1:]))


def test_log_mode_iteration_and_context_manager(capsys):
    clock = FakeClock()
    items = list(progress.bar(range(5), desc="eval", unit="view", clock=clock))   # sys.stderr (captured)
    assert items == [0, 1, 2, 3, 4]
    err = capsys.readouterr().err
    assert err == "eval: 5/5 views (100%), 0.0 s\n"
    with progress.bar(total=3, desc="synth", unit="view", initial=1, clock=clock) as pbar:
        pbar.update(2)
    assert capsys.readouterr().err == "synth: 3/3 views (100%), 0.0 s\n"


def test_short_inner_bar_without_leave_stays_silent():
    stream, clock = pyio.StringIO(), FakeClock()
    list(progress.bar(range(3), desc="render", leave=False, stream=stream, clock=clock))
    assert stream.getvalue() == ""
    long = progress.bar(range(3), desc="render", unit="chunk", leave=False, stream=stream, clock=clock)
    for _ in long:
        clock.now += 20.0
    lines = stream.getvalue().splitlines()
    assert lines[-1].startswith("render: 3/3 chunks (100%)") and len(lines) == 4


def test_disabled_prints_nothing(capsys):
    stream = pyio.StringIO()
    bar = progress.bar(range(4), desc="x", enabled=False, stream=stream)
    assert list(bar) == [0, 1, 2, 3]
    bar.update(3)
    bar.set_postfix(loss=1)
    bar.close()
    with progress.bar(total=2, enabled=False) as b:
        b.update(2)
    assert stream.getvalue() == ""
    assert capsys.readouterr() == ("", "")


def test_terminal_gets_a_tqdm_bar():
    from tqdm import tqdm

    class Tty(pyio.StringIO):
        def isatty(self):
            return True

    stream = Tty()
    bar = progress.bar(range(3), desc="t", stream=stream)
    assert isinstance(bar, tqdm)
    assert list(bar) == [0, 1, 2]
    assert "\r" in stream.getvalue()


def test_format_line_without_total():
    assert progress.format_line("load", 7, None, "frame", 3725.0, {}) == "load: 7 frames, 1 h 02 min"
    assert progress.format_line("", 1, None, "frame", 1.0, {"a": 1}) == "1 frame, 1.0 s, a=1"
