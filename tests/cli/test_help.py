"""Every subcommand's `--help` prints its usage and exits 0 (argparse formats each help string
with `%`, so a literal percent sign in one is a traceback at `--help`)."""

import pytest

from jaxnerf_grid import cli


@pytest.mark.parametrize("name", sorted(cli.SUBCOMMANDS))
def test_every_subcommand_prints_its_help_and_exits_zero(name, capsys):
    with pytest.raises(SystemExit) as stop:
        cli.main([name, "--help"])
    assert stop.value.code == 0
    out = capsys.readouterr().out
    assert out.startswith("usage: jaxnerf-grid") and "--" in out
