"""`jaxnerf-grid recipes`: the named training recipes (`recipes.RECIPES`), one line each.

    jaxnerf-grid recipes [--show NAME]

--show NAME prints that recipe's settings over the defaults as JSON (a `train --config` file).
"""

from __future__ import annotations

import argparse
import json


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="jaxnerf-grid recipes", description="the named training recipes, one line each")
    p.add_argument("--show", default=None, metavar="NAME",
                   help="print this recipe's settings (over RunConfig's defaults) as JSON")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from jaxnerf_grid.config import recipes

    if args.show is not None:
        recipe = recipes.get(args.show)
        print(json.dumps(recipes.overrides(recipe.name), indent=2))
        return 0
    print("\n".join(recipes.listing()))
    print("\ntrain one: jaxnerf-grid train --data DIR --recipe NAME (docs/RECIPES.md)")
    return 0
