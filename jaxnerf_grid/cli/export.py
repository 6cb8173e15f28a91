"""`jaxnerf-grid export`: the metric 3D model of a trained run's tower (`export.run.export_run`).

    jaxnerf-grid export --run RUN [--out DIR] [--resolution N] [--box auto|xmin,ymin,zmin,xmax,ymax,zmax]
                        [--threshold OPACITY] [--views N] [--geoid GRID [--vertical-crs EPSG:CODE]]
                        [--min-clearance M] [--span-length M] [--overwrite]

Writes tower_mesh.ply, tower_points.ply, box.json, measurements.json and export_views.png into
DIR (default RUN/export/), in the dataset's original units (metres for the synthetic scenes),
and the "Tower model" section of the run's report.md; docs/EXPORT.md.
"""

from __future__ import annotations

import argparse
import warnings


def build_parser() -> argparse.ArgumentParser:
    from jaxnerf_grid.export import fuse, mesh  # NumPy only: --help does not load JAX

    p = argparse.ArgumentParser(prog="jaxnerf-grid export",
                                description="metric mesh, point cloud and measurements of a trained run's tower")
    p.add_argument("--run", required=True, help="run directory")
    p.add_argument("--out", default=None, help="output folder (default RUN/export)")
    p.add_argument("--resolution", type=int, default=mesh.DEFAULT_RESOLUTION,
                   help="voxels along the box's longest side (default %(default)s)")
    p.add_argument("--box", default="auto",
                   help="'auto' (find the tower above the fitted ground) or xmin,ymin,zmin,xmax,ymax,zmax in the "
                        "dataset's original units (metres for the synthetic scenes)")
    p.add_argument("--threshold", type=float, default=mesh.DEFAULT_OPACITY,
                   help="surface level as the opacity a ray gets crossing one voxel, in (0, 1) "
                        "(density = -ln(1 - opacity) / voxel; default %(default)s)")
    p.add_argument("--views", type=int, default=fuse.DEFAULT_VIEWS,
                   help="training views rendered for the fused point cloud and the auto box (default %(default)s)")
    p.add_argument("--geoid", default=None, metavar="GRID",
                   help="a local geoid grid file PROJ reads (GTX or GeoTIFF, e.g. us_nga_egm96_15.tif): the CRS "
                        "outputs' heights become heights above that geoid (docs/GEOREFERENCE.md)")
    p.add_argument("--vertical-crs", default=None, metavar="EPSG:CODE",
                   help="with --geoid, the vertical datum the grid realises (EPSG:5773 for EGM96, EPSG:3855 for "
                        "EGM2008): tower_points.las's header carries the compound CRS")
    p.add_argument("--min-clearance", type=float, default=None, metavar="M",
                   help="flag the spans whose conductor clearance over the ground or the objects beneath is below M "
                        "(export units; no default: the clearance a line needs depends on its voltage and country)")
    p.add_argument("--span-length", type=float, default=None, metavar="M",
                   help="the distance between the towers (export units): each span's conductors fitted as a level "
                        "span of that length; without it each side's span is measured at the next tower where "
                        "photos look along the line and see it, else it comes from the wires' curvature, poorly "
                        "observed where few photos see the far part of a wire (docs/EXPORT.md)")
    p.add_argument("--overwrite", action="store_true", help="write into an output folder that holds files")
    p.add_argument("--allow-other-data", action="store_true",
                   help="export from a dataset other than the one the run was trained on (its fingerprint differs)")
    p.add_argument("--quiet", action="store_true")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from pathlib import Path

    from jaxnerf_grid.export import run
    from jaxnerf_grid.report import markdown as report

    m = run.export_run(args.run, args.out, resolution=args.resolution, box=args.box, opacity=args.threshold,
                       views=args.views, overwrite=args.overwrite, progress=not args.quiet,
                       allow_other_data=args.allow_other_data, geoid=args.geoid,
                       vertical_crs=args.vertical_crs, min_clearance=args.min_clearance,
                       span_length=args.span_length)
    out = Path(args.out) if args.out else Path(args.run) / "export"
    short_unit = "m" if m["units"] == "metres" else "units"
    unit = "m" if m["units"] == "metres" else "units (unknown scale)"
    height = "n/a" if m["height"] is None else f"{m['height']:.2f} {unit}"
    sigma = ((m.get("survey") or {}).get("height") or {}).get("sigma")
    if sigma is not None:
        height += f" +- {sigma:.2f} {unit}"
    if m.get("tilt"):
        height += f", axis tilted {m['tilt']['tilt_degrees']:.2f} deg from vertical"
    print(f"tower height {height}; mesh {m['mesh']['vertices']} vertices, {m['mesh']['faces']} faces; "
          f"{m['points']['count']} fused points; {m['seconds']:.0f} s; files in {out}")
    low = report.lower_part_missing(m)
    if low is not None:
        warnings.warn(f"the model's tower begins {low:.2f} {unit} above the ground (its legs were not "
                      "reconstructed there): the base centre and the tilt are extrapolated (docs/EXPORT.md)",
                      stacklevel=1)
    tilt = report.tilt_doubtful(m)
    if tilt is not None:
        warnings.warn(f"the tower's axis leans {tilt:.2f} deg from vertical: {report.TILT_WORDS}", stacklevel=1)
    for span, words in report.clearance_doubtful(m, short_unit):
        warnings.warn(f"the clearance over the ground of {span} is doubtful: {words}", stacklevel=1)
    lowest = report.lowest_point_doubtful(m, short_unit)
    if lowest is not None:
        warnings.warn(f"the clearance of {report.LOWEST_POINT} is doubtful: {lowest}", stacklevel=1)
    return 0
