"""Progress output that works in a terminal and in a log file.

`bar(...)` returns an object with the tqdm methods the package uses (iteration, `update(n)`,
`set_postfix(**kw)`, `set_description(desc)`, `close()`, context manager):
  * stderr is a terminal: a real tqdm bar (dynamic_ncols);
  * stderr is not a terminal (CI, `> log.txt 2>&1`): no carriage-return stream; one plain line
    at most every `interval` seconds (10 s) and a final one at the end, e.g.
    `train ours: 300/1000 steps (30%), 12.3 s, 28.7 s left, loss=0.0100` (the time left at the
    rate of the units done since the bar started; not on the final line). A bar made with `leave=False`
    (short inner loops) prints its final line only when it printed a line before, so short
    loops stay silent in logs;
  * `enabled=False`: nothing at all (the iterable is passed through).
"""

from __future__ import annotations

import sys
import time

DEFAULT_INTERVAL = 10.0


def _is_tty(stream) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):  # no isatty, or a closed stream
        return False


def format_seconds(seconds: float) -> str:
    """12.3 s, 5 min 03 s, 2 h 05 min."""
    if seconds < 59.95:
        return f"{seconds:.1f} s"
    whole = int(round(seconds))
    if whole < 3600:
        return f"{whole // 60} min {whole % 60:02d} s"
    return f"{whole // 3600} h {whole % 3600 // 60:02d} min"


def _plural(unit: str, n) -> str:
    return unit if n == 1 or not unit or unit.endswith("s") else unit + "s"


def seconds_left(n, total, initial, elapsed: float) -> float | None:
    """The time to reach `total` at the rate of the units done since `initial` (elapsed seconds
    for n - initial units); None without a total, before the first unit, or when done."""
    done = (n or 0) - (initial or 0)
    if not total or done <= 0 or n >= total or elapsed <= 0:
        return None
    return (total - n) * elapsed / done


def format_line(desc: str, n, total, unit: str, elapsed: float, postfix: dict, left: float | None = None) -> str:
    """One log line: `desc: n/total units (pct%), elapsed[, left s left], k=v, ...` (no total:
    `desc: n units, ...`)."""
    if total:
        count = f"{n}/{total} {_plural(unit, total)} ({100.0 * n / total:.0f}%)"
    else:
        count = f"{n} {_plural(unit, n)}"
    parts = [count, format_seconds(elapsed)] + ([f"{format_seconds(left)} left"] if left is not None else [])
    parts += [f"{k}={v}" for k, v in postfix.items()]
    return (f"{desc}: " if desc else "") + ", ".join(parts)


class NullBar:
    """A disabled bar: iterates the iterable, every method does nothing."""

    def __init__(self, iterable=None, total=None, initial=0):
        self.iterable, self.total, self.n = iterable, total, initial

    def __iter__(self):
        return iter(self.iterable if self.iterable is not None else ())

    def __len__(self):
        return len(self.iterable) if self.total is None else self.total

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False

    def update(self, n=1):
        self.n += n

    def set_postfix(self, ordered_dict=None, refresh=True, **kwargs):
        pass

    def set_description(self, desc=None, refresh=True):
        pass

    def close(self):
        pass


class LogBar(NullBar):
    """Throttled plain-line progress for streams that are not terminals (module docstring).

    stream: where lines go (default: sys.stderr at the time of each write); clock: a
    seconds counter (time.monotonic; tests pass a fake one); interval: seconds between lines.
    """

    def __init__(self, iterable=None, total=None, desc="", unit="it", initial=0, leave=True,
                 stream=None, clock=time.monotonic, interval=DEFAULT_INTERVAL):
        if total is None and iterable is not None and hasattr(iterable, "__len__"):
            total = len(iterable)
        super().__init__(iterable, total, initial)
        self.initial = initial
        self.desc, self.unit, self.leave = desc, unit, leave
        self.stream, self.clock, self.interval = stream, clock, float(interval)
        self.postfix: dict = {}
        self.start = self.last = clock()
        self.first: tuple | None = None  # (n, time) at the first update: the rate leaves out the start-up
        self.lines = 0
        self.closed = False

    def __iter__(self):
        for item in super().__iter__():
            yield item
            self.update(1)
        self.close()

    def _write(self, now: float) -> None:
        stream = self.stream if self.stream is not None else sys.stderr
        elapsed = now - self.start
        # the time left at the rate since the first unit: the first one carries the compile
        left = None if self.first is None else seconds_left(self.n, self.total, self.first[0], now - self.first[1])
        stream.write(format_line(self.desc, self.n, self.total, self.unit, elapsed, self.postfix, left) + "\n")
        stream.flush()
        self.last = now
        self.lines += 1

    def update(self, n=1):
        self.n += n
        now = self.clock()
        if self.first is None:
            self.first = (self.n, now)
        if not self.closed and now - self.last >= self.interval:
            self._write(now)

    def set_postfix(self, ordered_dict=None, refresh=True, **kwargs):
        self.postfix = {**dict(ordered_dict or {}), **kwargs}

    def set_description(self, desc=None, refresh=True):
        self.desc = desc or ""

    def close(self):
        if self.closed:
            return
        self.closed = True
        if self.leave or self.lines:
            self._write(self.clock())


def bar(iterable=None, total=None, desc: str = "", unit: str = "it", initial: int = 0, enabled: bool = True,
        leave: bool = True, *, stream=None, clock=time.monotonic, interval: float = DEFAULT_INTERVAL):
    """A progress bar over `iterable` (or a manual one with `total` and `update`).

    A tqdm bar when the stream (default sys.stderr) is a terminal, else a `LogBar`; a `NullBar`
    when not `enabled`. stream, clock and interval are for the log mode (and tests).
    """
    if not enabled:
        return NullBar(iterable, total, initial)
    target = stream if stream is not None else sys.stderr
    if _is_tty(target):
        from tqdm import tqdm

        return tqdm(iterable, total=total, desc=desc, unit=unit, initial=initial, leave=leave,
                    dynamic_ncols=True, file=target)
    return LogBar(iterable, total, desc, unit, initial, leave, stream=stream, clock=clock, interval=interval)
