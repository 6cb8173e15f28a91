"""Library keys -> command-line flags in the one-line errors of `jaxnerf-grid`.

The library names what it refuses by key, as a Python caller spells it: a config key
(`train.batch_rays`, the user's own words for `--set` and `--config`), a setting of one command
as `<command>.<argument>` (`export.box`, `mask.threshold`) and a switch as `<argument>=True`
(`overwrite=True`). The dispatcher (`cli/__init__.py`) rewrites the keys of the subcommand that
ran into its flags with `to_flags`; a key another command owns stays a key (e.g. `mask.max_side`
inside `demo`, which has no such flag). `tests/test_layers.py` checks that every flag here is
one its subcommand's parser accepts.
"""

from __future__ import annotations

import re

_SWITCHES = {"overwrite=True": "--overwrite"}
_OTHER_DATA = {"allow_other_data=True": "--allow-other-data"}
_DISTRIBUTED = {"distributed.num_processes": "--num-processes", "distributed.process_id": "--process-id",
                "distributed.coordinator": "--coordinator"}

FLAGS = {  # subcommand -> {key: flag}
    "synth": {"synth.gps_origin": "--gps-origin", "synth.gcp_layout": "--gcp-layout", **_SWITCHES},
    "poses": {"poses.matcher": "--matcher", "poses.overlap": "--overlap", "poses.neighbours": "--neighbours",
              "poses.vocab_tree": "--vocab-tree",
              "poses.max_side": "--max-side",
              "poses.single_camera": "--single-camera",
              "poses.out": "--out", "poses.crs": "--crs", "poses.gcp": "--gcp", "poses.scale_bar": "--scale-bar",
              "ignore_gps=True": "--ignore-gps", "accept_few_cameras=True": "--accept-few-cameras", **_SWITCHES},
    "mask": {"mask.data": "--data", "mask.source": "--source", "mask.weights": "--weights",
             "mask.classes": "--classes", "mask.threshold": "--threshold",
             "mask.floor": "--floor", "mask.dilate": "--dilate", "mask.max_side": "--max-side",
             "mask.tiles": "--tiles", "mask.tile_overlap": "--tile-overlap", "mask.batch_size": "--batch-size",
             **_SWITCHES},
    "train": {"run.out": "--out", "run.data": "--data", "run.steps": "--steps", "run.method": "--method",
              "run.progress_page": "--progress-page", "train.max_side": "--max-side",
              "run.minutes": "--minutes",
              **_SWITCHES, **_OTHER_DATA, **_DISTRIBUTED},
    "render": {"render.frames": "--frames", "render.out": "--out",
               "render.fps": "--fps", "render.width": "--width", "render.path": "--path",
               **_OTHER_DATA},
    "eval": {"eval.lpips_weights": "--lpips-weights", "eval.reference_ply": "--reference-ply",
             "eval.distractor_views": "--distractor-views", "eval.appearance_steps": "--appearance-steps",
             **_OTHER_DATA},
    "export": {"export.box": "--box", "export.resolution": "--resolution", "export.opacity": "--threshold",
               "export.views": "--views", "export.out": "--out", "export.geoid": "--geoid",
               "export.vertical_crs": "--vertical-crs", "export.min_clearance": "--min-clearance",
               "export.span_length": "--span-length",
               **_SWITCHES, **_OTHER_DATA},
    "demo": {"demo.data": "--data", "train.max_side": "--max-side",
             "demo.out": "--out", "demo.steps": "--steps", "demo.masks": "--masks", "demo.minutes": "--minutes",
             "demo.video_frames": "--video-frames", "accept_few_cameras=True": "--accept-few-cameras",
             **_SWITCHES, **_DISTRIBUTED},
}


def to_flags(subcommand: str, message: str) -> str:
    """`message` with each key of `subcommand`'s table (a whole word: not part of a longer
    dotted name) replaced by its flag. Returns the message unchanged for other keys."""
    table = FLAGS.get(subcommand, {})
    for key in sorted(table, key=len, reverse=True):
        message = re.sub(rf"(?<![\w.]){re.escape(key)}(?![\w])", table[key], message)
    return message


_NEGATIVE_VALUE = re.compile(r"^-\.?\d")


def join_negative_values(argv: list[str]) -> list[str]:
    """argv with each `--flag VALUE` whose VALUE begins with a minus sign and a digit
    (`--box -30,-30,0,30,30,40`, `--gps-origin -33.9,18.4,10`) joined into `--flag=VALUE`:
    argparse reads such a value as an unknown flag unless it is a plain negative number.
    Only argv is read (no parser internals): every option of the subcommands takes one value
    or none (`tests/cli/test_hostile_corpus.py` checks it), so the joined form means what the user
    typed, and a switch given such a value stays an error ("ignored explicit argument").
    Arguments after `--`, and `--flag=VALUE` already joined, are left as they are."""
    out: list[str] = []
    k = 0
    while k < len(argv):
        arg = argv[k]
        if arg == "--":
            return out + argv[k:]
        if (arg.startswith("--") and "=" not in arg and k + 1 < len(argv)
                and _NEGATIVE_VALUE.match(argv[k + 1])):
            out.append(f"{arg}={argv[k + 1]}")
            k += 2
            continue
        out.append(arg)
        k += 1
    return out
