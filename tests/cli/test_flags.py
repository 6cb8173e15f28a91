"""cli/flags.py: the library's keys become the subcommand's flags in the one-line error.

Checked against the parsers themselves (every flag in the table is one its subcommand accepts),
against the library source (every key in the table is one a library string names) and on
messages written out here.
"""

import ast
import importlib
import os
import subprocess
import sys
from pathlib import Path

import pytest

from jaxnerf_grid import cli
from jaxnerf_grid.cli.flags import FLAGS, to_flags

PACKAGE = Path(__file__).resolve().parents[2] / "jaxnerf_grid"


def option_strings(subcommand: str) -> set[str]:
    parser = importlib.import_module(cli.SUBCOMMANDS[subcommand][0]).build_parser()
    return {s for action in parser._actions for s in action.option_strings}


@pytest.mark.parametrize("subcommand", sorted(FLAGS))
def test_every_flag_is_one_the_subcommand_accepts(subcommand):
    assert subcommand in cli.SUBCOMMANDS
    missing = set(FLAGS[subcommand].values()) - option_strings(subcommand)
    assert not missing, f"jaxnerf-grid {subcommand} has no {sorted(missing)}"


def library_strings() -> str:
    """Every string literal of the library (cli/ left out), joined."""
    out = []
    for path in sorted(PACKAGE.rglob("*.py")):
        if "cli" in path.relative_to(PACKAGE).parts:
            continue
        out += [n.value for n in ast.walk(ast.parse(path.read_text()))
                if isinstance(n, ast.Constant) and isinstance(n.value, str)]
    return "\n".join(out)


def test_every_key_is_one_the_library_names():
    text = library_strings()
    unused = sorted({key for table in FLAGS.values() for key in table if key not in text})
    assert not unused, f"keys no library string names: {unused}"


def test_to_flags_rewrites_whole_keys_of_its_subcommand_only():
    msg = ("x: export.box auto found no ground; give export.box; lower export.opacity; pass overwrite=True; "
           "mask.max_side = 3; my.export.box")
    assert to_flags("export", msg) == ("x: --box auto found no ground; give --box; lower --threshold; "
                                       "pass --overwrite; mask.max_side = 3; my.export.box")
    assert to_flags("mask", "mask.tile_overlap = 2, mask.tiles = 0, mask.tilesx") == \
        "--tile-overlap = 2, --tiles = 0, mask.tilesx"
    assert to_flags("demo", "mask.max_side = -1: must be >= 1") == "mask.max_side = -1: must be >= 1"
    assert to_flags("nosuch", "export.box") == "export.box"


def test_the_dispatcher_prints_flags(tmp_path, capsys):
    """A library error met through `jaxnerf-grid mask` names --threshold, not mask.threshold."""
    assert cli.main(["mask", "--data", str(tmp_path), "--source", "gt", "--threshold", "2"]) == 1
    err = capsys.readouterr().err
    assert err == "jaxnerf-grid mask: error: --threshold = 2.0: must be in [0, 1]\n", err


def test_parsers_load_no_jax():
    """Why cli/ imports the library inside `main` (docs/ARCHITECTURE.md): every subcommand's
    parser, so `jaxnerf-grid X --help` and argument errors, runs without loading JAX."""
    code = ("import importlib, sys\nfrom jaxnerf_grid import cli\n"
            "for module, _ in cli.SUBCOMMANDS.values():\n    importlib.import_module(module).build_parser()\n"
            "print(sorted(m for m in ('jax', 'torch') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         cwd=PACKAGE.parent, env={**os.environ, "JAX_PLATFORMS": "cpu"})
    assert out.stdout.strip() == "[]", out.stdout + out.stderr
