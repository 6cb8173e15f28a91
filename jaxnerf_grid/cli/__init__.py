"""The single entry point `jaxnerf-grid` (also `python -m jaxnerf_grid`).

Each subcommand lives in its own module of this package (cli/synth.py, mask.py, train.py,
render.py, eval.py, demo.py) and exposes `main(argv: list[str]) -> int`; a subcommand only parses
its arguments and calls the library (runs, evaluate, demo, masking, data.synthetic). This file
only dispatches, so importing it is cheap and one subcommand's imports never slow another.
Nothing else in the package imports a cli module.
Errors of type `DataError` / `ConfigError` are printed as one line, never as a traceback, with
the library's keys turned into the subcommand's flags (`cli/flags.py`: `export.box` -> `--box`); so
are OS errors (a read-only folder, a full disk, a path that is a file): `error: PATH: reason`.
A warning is one line too (`jaxnerf-grid NAME: warning: ...`, no source line) and OpenCV's own log
shows errors only, both only while `main` runs (`one_line_warnings`, `io.quiet_opencv`: restored
after, also on an error). A flag's value that
begins with a minus sign (`--box -30,-30,0,30,30,40`) is taken as that value, not as a flag
(`flags.join_negative_values`).
"""

from __future__ import annotations

import contextlib
import importlib
import sys
import warnings

from jaxnerf_grid.cli.flags import join_negative_values, to_flags

SUBCOMMANDS = {
    "synth": ("jaxnerf_grid.cli.synth", "render the procedural tower benchmark scene"),
    "poses": ("jaxnerf_grid.cli.poses", "camera poses for a folder of photos (COLMAP via pycolmap)"),
    "mask": ("jaxnerf_grid.cli.mask", "DPT foreground masks and weights for a dataset"),
    "train": ("jaxnerf_grid.cli.train", "train a NeRF (a recipe: ours | ours-paper-mlp | nerf | nerfw) on a dataset"),
    "render": ("jaxnerf_grid.cli.render", "render views from a trained run"),
    "eval": ("jaxnerf_grid.cli.eval", "evaluate a trained run on its test views"),
    "export": ("jaxnerf_grid.cli.export", "metric mesh, point cloud and measurements of the tower"),
    "demo": ("jaxnerf_grid.cli.demo", "synthetic scene -> masks -> train -> render -> report"),
    "recipes": ("jaxnerf_grid.cli.recipes", "the named training recipes, one line each"),
}

USAGE = "usage: jaxnerf-grid {" + ",".join(SUBCOMMANDS) + "} [options]\n\n" + "\n".join(
    f"  {name:8s} {help_text}" for name, (_, help_text) in SUBCOMMANDS.items()
)


def os_error_line(err: OSError) -> str:
    """An OSError as one line naming the path: "PATH: No space left on device"."""
    reason = err.strerror or str(err)
    paths = [p for p in (err.filename, err.filename2) if p]
    return f"{' -> '.join(str(p) for p in paths)}: {reason}" if paths else reason


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help"):
        print(USAGE)
        return 0 if argv else 2
    name, rest = argv[0], argv[1:]
    if name not in SUBCOMMANDS:
        print(f"jaxnerf-grid: unknown command {name!r}\n\n{USAGE}", file=sys.stderr)
        return 2
    module = importlib.import_module(SUBCOMMANDS[name][0])
    entry = module.main
    rest = join_negative_values(rest)
    from jaxnerf_grid.config.schema import ConfigError
    from jaxnerf_grid.util.io import DataError, quiet_opencv  # after the subcommand: `--help` loads no NumPy

    with one_line_warnings(name), quiet_opencv():
        try:
            return int(entry(rest) or 0)
        except (DataError, ConfigError) as err:
            print(f"jaxnerf-grid {name}: error: {to_flags(name, str(err))}", file=sys.stderr)
            return 1
        except OSError as err:  # read-only folder, full disk (ENOSPC), a file where a folder should be
            print(f"jaxnerf-grid {name}: error: {os_error_line(err)}", file=sys.stderr)
            return 1
        except KeyboardInterrupt:
            print(f"jaxnerf-grid {name}: interrupted", file=sys.stderr)
            return 130


@contextlib.contextmanager
def one_line_warnings(name: str):
    """Inside the block, a Python warning prints as one line, `jaxnerf-grid NAME: warning: ...`,
    without its source line; after it (also on an error or SystemExit) `warnings.formatwarning`
    is what it was, so a program that calls `main` keeps its own format."""
    previous = warnings.formatwarning
    warnings.formatwarning = lambda message, *_: f"jaxnerf-grid {name}: warning: {message}\n"
    try:
        yield
    finally:
        warnings.formatwarning = previous
