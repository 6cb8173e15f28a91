"""Hand-made mutants at the joins of the tower model (docs/TESTING.md; records in
benchmarks/results/mutation/): each is a one-line mistake of a kind a reviewer would try
(units, axes, argument order, the sign of a normal, which pass's setting), applied to a copy of
the working tree, one at a time, and run against the fast tests named for it with a per-mutant
timeout. Not part of CI.

    python scripts/mutants.py                  every mutant, each against its own tests
    python scripts/mutants.py M3 M4            some of them
    python scripts/mutants.py --list           the table
    python scripts/mutants.py --tests tests/export/test_export.py M1a
                                               other tests (e.g. to show the old suite missed it)

A mutant is "killed" when the tests fail, "survived" when they pass, "timeout" past --timeout
seconds. The unmutated copy runs first against each set of tests (it must pass). The copy lives in
a temporary folder; the working tree is never changed. Exit status: the number of survivors.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
J = "tests/joins/test_join_truth.py"
E = "tests/joins/test_join_export.py"
P = "tests/joins/test_join_poses.py"
L = "tests/nerf/test_losses.py"
X = "tests/export/test_export.py"
N = "tests/data/test_normalize.py"
ES = "test_export_section_reads_the_files_record_the_users_reference_and_a_record_without_scale"
TW = "test_loss_weights_without_masks_ignore_the_floor_and_prior_weights_check_the_data_not_the_batch"

# name: (file, the exact text, its mutation, tests that must kill it, what the mistake is)
MUTANTS = {
    "M1a": ("jaxnerf_grid/eval/geometry.py", "result = score_points(pred, ref, thresholds, ground_strip)",
            "result = score_points(ref, pred, thresholds, ground_strip)", [J],
            "eval's geometry score with the predicted and reference clouds crossed"),
    "M1b": ("jaxnerf_grid/eval/export_score.py",
            "geometry.score_points(io.read_ply_points(path), reference, thresholds, strip)",
            "geometry.score_points(reference, io.read_ply_points(path), thresholds, strip)", [J],
            "export's score with the mesh / points and the reference crossed"),
    "M2": ("jaxnerf_grid/eval/evaluate.py",
           'score.score_export(folder, points, float(ds.normalization.get("scale", 1.0)))',
           'score.score_export(folder, points, float(ds.normalization.get("metric_scale", 1.0)))', [J],
           "export's ground strip in normalised units on metric clouds (the scale read from a missing key)"),
    "M2b": ("jaxnerf_grid/eval/export_score.py", "strip = geometry.DEFAULT_GROUND_STRIP / float(scale)",
            "strip = geometry.DEFAULT_GROUND_STRIP * float(scale)", [J],
            "export's ground strip multiplied by the scale instead of divided"),
    "M3": ("jaxnerf_grid/export/field.py",
           "x = models.field_inputs(mcfg, points, jnp.zeros_like(points), zeros)[..., 0, :]",
           "x = points", [J, E], "export's field queried without models.field_inputs"),
    "M4": ("jaxnerf_grid/export/run.py",
           'n_m, d_m = plane_to_metric(plane["normal"], plane["offset"], norm)',
           'n_m, d_m = plane_to_metric(-plane["normal"], -plane["offset"], norm)', [E],
           "the ground plane handed on with its normal flipped (heights measured downward)"),
    "M4b": ("jaxnerf_grid/export/__init__.py", "n = rotation.T @ n", "n = rotation @ n", [E],
            "the ground normal turned by R instead of R^T into metres"),
    "M4c": ("jaxnerf_grid/export/__init__.py", "return n, float(n @ translation + float(offset) / scale)",
            "return n, float(n @ translation + float(offset) * scale)", [E],
            "the ground offset multiplied by the scale instead of divided"),
    "M5": ("jaxnerf_grid/train/loop.py", "np.minimum(w, 1.0 - cfg.mask_weight_floor)",
           "np.minimum(w, cfg.mask_weight_floor)", [J],
           "the loss weights capping masked pixels at the floor instead of 1 - floor"),
    "M6": ("jaxnerf_grid/capture/poses.py", "scene.near * scale, scene.far * scale",
           "scene.near / scale, scene.far / scale", [P], "poses writing near / far divided by the scale"),
    "M6b": ("jaxnerf_grid/capture/poses.py",
            'top["scene_bounds"] = scene_bounds(c2w, points_norm if len(points) else None, scene.near * scale)',
            'top["scene_bounds"] = scene_bounds(c2w, points if len(points) else None, scene.near * scale)', [P],
            "poses' scene bounds from the points before the normalisation"),
    "M7": ("jaxnerf_grid/nerf/samplers/proposal.py",
           "cfg.main_samples + 1, passes.single_jitter,\n                                   cfg.padding)",
           "cfg.main_samples + 1,\n                                   cfg.padding)", [J],
           "proposal_rounds' main resampling without single_jitter (the padding in its slot)"),
    "M7b": ("jaxnerf_grid/nerf/samplers/proposal.py",
            "cfg.main_samples + 1, passes.single_jitter,\n                                   cfg.padding)",
            "cfg.main_samples + 1, passes.single_jitter)", [J],
            "proposal_rounds' main resampling without the padding"),
    "M8": ("jaxnerf_grid/export/run.py", "heights = verts_m @ n_m + d_m", "heights = verts_m @ n_m - d_m", [E],
           "the height measured with the plane's offset of the wrong sign"),
    "M9": ("jaxnerf_grid/export/run.py", '"voxel_size": h / scale', '"voxel_size": h * scale', [E],
           "the voxel size in normalised units times the scale"),
    "M10": ("jaxnerf_grid/export/__init__.py",
            "return apply_normalization_to_points(points, invert_normalization(_record_or_identity(normalization)))",
            "return apply_normalization_to_points(points, _record_or_identity(normalization))", [E],
            "to_metric64 applying the normalisation instead of undoing it"),
    # the survivors of mutmut's runs on losses, the loss weights, Eq. 7 and the ground, each
    # against the test written for it
    "M11": ("jaxnerf_grid/train/loop.py", "if cfg.mask_weight_floor > 0 and dataset.masks is not None:",
            "if cfg.mask_weight_floor > 0 or dataset.masks is not None:", [f"{J}::{TW}"],
            "loss_weights capping under masks a dataset does not have (weights without masks, floor > 0)"),
    "M12": ("jaxnerf_grid/train/loop.py",
            "check_robust(dataclasses.replace(cfg, batch_rays=cfg.robust.patch ** 2), 1, dataset)",
            "check_robust(dataclasses.replace(cfg, batch_rays=cfg.robust.patch ** 2), 1, None)", [f"{J}::{TW}"],
            "prior_weights checking the robust settings without the dataset (dpt+robust without weights let through)"),
    "M13": ("jaxnerf_grid/nerf/losses.py", "jnp.maximum(total, 1e-12)", "jnp.maximum(total, 1.0)",
            [f"{L}::test_weighted_mean_with_weights_summing_below_one"],
            "weighted_mean's guard against a zero total as 1 (totals below 1 not divided by)"),
    "M14": ("jaxnerf_grid/nerf/losses.py", "/ (w + eps), axis=-1)", "/ (w - eps), axis=-1)",
            [f"{L}::test_interlevel_loss_of_a_main_weight_as_small_as_eps_is_finite"],
            "the proposal loss dividing by w - eps (inf at w = eps)"),
    "M15": ("jaxnerf_grid/nerf/losses.py", "w_before = jnp.cumsum(weights, axis=-1) - weights",
            "w_before = jnp.cumsum(weights, axis=None) - weights",
            [f"{L}::test_squared_error_and_distortion_per_ray_of_a_batch"],
            "the distortion loss's running sum over the whole batch instead of each ray"),
    "M16": ("jaxnerf_grid/masks/foreground.py", "jnp.maximum(dmax, 1e-12)", "jnp.maximum(dmax, 1.0)",
            ["tests/masks/test_foreground.py::test_eq7_with_depths_below_one_and_a_dmax_per_image"],
            "Eq. 7 dividing by at least 1 (DPT's depths, far below 1, give M_w near 0)"),
    "M17": ("jaxnerf_grid/export/ground.py", "n = n / norm\n    if n[UP] < 0:", "n = n / norm\n    if n[UP] > 1:",
            [f"{X}::test_plane_through_and_refine_plane_against_a_known_tilted_plane"],
            "plane_through's normal not turned up (half of RANSAC's samples thrown away as too steep)"),
    "M18": ("jaxnerf_grid/export/ground.py", "labels, _ = ndimage.label(grown, structure=np.ones((3, 3, 3), bool))",
            "labels, _ = ndimage.label(grown)",
            [f"{X}::test_largest_cluster_joins_cells_three_apart_diagonally_and_not_four_apart"],
            "the tower's cells joined through faces only (a lattice's diagonal members split off)"),
    "M19": ("jaxnerf_grid/export/ground.py",
            "np.array([lo[0], lo[0], hi[0], hi[0]]), np.array([lo[1], hi[1], lo[1], hi[1]])",
            "np.array([lo[1], hi[1], lo[1], hi[1]]), np.array([lo[0], lo[0], hi[0], hi[0]])",
            [f"{X}::test_tower_box_on_sloping_ground_clears_its_highest_corner_and_refuses_by_name"],
            "the box's bottom corners with x and y crossed (the ground's height at the wrong corners)"),
    "M20": ("jaxnerf_grid/export/ground.py",
            "if n[UP] < min_nz:   # the refinement may not tilt it past the limit",
            "if False:   # the refinement may not tilt it past the limit",
            [f"{X}::test_ransac_keeps_its_sample_plane_when_the_refit_tilts_past_the_limit"],
            "RANSAC keeping a refit tilted past the limit (a slope taken for the ground)"),
    "M21": ("jaxnerf_grid/eval/evaluate.py", "ref = reference_cloud(ds, reference_ply)\n    if ref is not None:",
            "ref = reference_cloud(ds, None)\n    if ref is not None:", [f"{J}::{ES}"],
            "eval's export score ignoring the user's reference (eval.reference_ply)"),
    "M22": ("jaxnerf_grid/eval/evaluate.py",
            "score.reference_in_export_units(io.read_ply_points(path), file_norm, ds.normalization)",
            "score.reference_in_export_units(io.read_ply_points(path), None, ds.normalization)", [f"{J}::{ES}"],
            "eval's export score reading the dataset's tower in the dataset's record, not the file's"),
    # normalize, export's field, poses' report and top view
    "M23": ("jaxnerf_grid/data/normalize.py",
            "cap = camera_fraction * float(np.median(np.linalg.norm(c2w[:, :3, 3] - centre, axis=-1)))",
            "cap = camera_fraction * float(np.median(np.linalg.norm(c2w[:, :3, 3] + centre, axis=-1)))",
            [f"{N}::test_orbit_roi_far_from_the_origin_with_its_cap_deciding_below_one_unit"],
            "the orbit's cap measured from the origin, not the centre (the radius where the cap decides)"),
    "M24": ("jaxnerf_grid/data/normalize.py",
            "if eig[2] > 1e-12 and eig[0] <= flatness * eig[1] and eig[1] >= flatness * eig[2]:",
            "if eig[2] > 1e-12:", [f"{N}::test_up_from_cameras_one_heading_small_plane_blob_and_wall"],
            "up_from_cameras taking any cloud of centres for a plane (the scene turned by a blob's short axis)"),
    "M25": ("jaxnerf_grid/data/normalize.py", "turned, pts = rotate_scene(c2w, rot, points)",
            "turned, pts = rotate_scene(c2w, rot, None)",
            [f"{N}::test_z_up_normalization_of_a_tilted_scene_keeps_the_points_radius"],
            "z_up_normalization dropping the points of a tilted scene (its scale from the cameras alone)"),
    "M26": ("jaxnerf_grid/export/field.py", "yz = np.stack(np.meshgrid(ys, zs, indexing=\"ij\"), axis=-1)",
            "yz = np.stack(np.meshgrid(ys, zs, indexing=\"xy\"), axis=-1)",
            [f"{J}::test_export_density_grid_nodes_are_origin_plus_h_times_ijk"],
            "density_grid's nodes with the y and z axes crossed"),
    "M27": ("jaxnerf_grid/export/field.py", "d = points - centres[idx[:, j]]", "d = centres[idx[:, j]] - points",
            [f"{J}::test_export_colours_are_the_mean_seen_from_the_k_nearest_cameras"],
            "the exported colours seen along the reversed direction (from the point to the camera)"),
    "M28": ("jaxnerf_grid/capture/poses.py", "(1 - xy[:, 1] / extent) * size / 2", "(1 + xy[:, 1] / extent) * size / 2",
            [f"{P}::test_poses_topview_puts_each_camera_and_point_where_it_stands_seen_from_above"],
            "poses' top view mirrored (y down the picture)"),
    "M29": ("jaxnerf_grid/capture/poses.py", 'lines += vetting.format_table(vet.get("photos", []))',
            "lines += vetting.format_table([])",
            [f"{P}::test_poses_report_names_each_left_out_photo_with_its_reasons_in_the_summary_and_the_table"],
            "poses_report.md's vetting table without its rows"),
    # the robust weights' joins in the training step, the export's box floor and the axis' errors
    "M30": ("jaxnerf_grid/masks/photo_consistency.py",
            "neighbours, frame, pixel // width, pixel % width, points)",
            "neighbours, frame, pixel % width, pixel // width, points)",
            ["tests/masks/test_photo_consistency.py::test_confirmed_at_ids_splits_flat_ids_as_numpy_unravels_them"],
            "the confirmation's flat pixel ids split with rows and columns crossed"),
    "M31": ("jaxnerf_grid/masks/photo_consistency.py", "return (error <= threshold).astype(jnp.float32)",
            "return (error >= threshold).astype(jnp.float32)",
            ["tests/masks/test_photo_consistency.py::test_confirmed_at_ids_splits_flat_ids_as_numpy_unravels_them"],
            "a pixel confirmed when its difference is at least the threshold"),
    "M32": ("jaxnerf_grid/train/loop.py", 'points = batch["origins"] + batch["directions"] * depth[:, None]',
            'points = batch["origins"] - batch["directions"] * depth[:, None]',
            ["tests/train/test_robust_training.py::test_multiview_confirmation_keeps_pixels_the_other_photos_confirm"],
            "the confirmation's 3-D points behind the camera"),
    "M33": ("jaxnerf_grid/train/loop.py",
            'weight = jnp.where(state["opt_state"].count < warmup_steps, batch["weight"], evidence)',
            'weight = jnp.where(state["opt_state"].count < warmup_steps, evidence, batch["weight"])',
            ["tests/train/test_robust_training.py"], "the robust warm-up's weights and the evidence's swapped"),
    "M34": ("jaxnerf_grid/train/loop.py", 'evidence = robust_lib.batch_weights(residual, batch["weight"], everyone,',
            'evidence = robust_lib.batch_weights(residual, 1.0 - batch["weight"], everyone,',
            ["tests/train/test_robust_training.py"],
            "the evidence given the DPT's mask M_w as the prior instead of 1 - M_w"),
    "M35": ("jaxnerf_grid/export/ground.py",
            "lo[UP] = float(corners_z.max()) + clearance   # a tower stands on the ground, seen or not",
            "lo[UP] = max(float(corners_z.max()) + clearance, float(tower[:, UP].min()) - cell)",
            [f"{X}::test_tower_box_reaches_down_to_the_ground_where_the_cloud_missed_the_legs"],
            "the auto box's floor where the fused cloud's tower begins (the legs it missed cut off)"),
    "M36": ("jaxnerf_grid/export/run.py", "reach = extrapolated * math.tan(math.radians(angle))", "reach = 0.0",
            ["tests/export/test_export_run.py::test_survey_record_of_a_full_measurement_by_hand"],
            "the base centre's sigma without the tilt's error over the height it is extrapolated"),
    "M37": ("jaxnerf_grid/export/run.py", 'spread = float(tilt.get("thickness_spread_degrees", 0.0))',
            "spread = 0.0", ["tests/export/test_export_run.py::test_survey_record_of_a_full_measurement_by_hand"],
            "the tilt's sigma without its spread over slice thicknesses"),
    "M38": ("jaxnerf_grid/export/measure.py", '"lowest_height": float(h.min()),', '"lowest_height": float(h.max()),',
            ["tests/export/test_survey.py::test_axis_tilt_thickness_spread_and_lowest_height_against_a_brute_force_refit"],
            "the height the base is extrapolated from taken at the top"),
}


def copy_tree(dest: Path) -> None:
    """The tracked and untracked (not ignored) files of the working tree -> dest."""
    files = subprocess.run(["git", "ls-files", "-co", "--exclude-standard", "-z"], cwd=ROOT, check=True,
                           capture_output=True).stdout
    tar = subprocess.Popen(["tar", "--null", "-T", "-", "-cf", "-"], cwd=ROOT, stdin=subprocess.PIPE,
                           stdout=subprocess.PIPE)
    out, _ = tar.communicate(files)
    subprocess.run(["tar", "-xf", "-"], cwd=dest, input=out, check=True)


def run_tests(tree: Path, tests: list[str], timeout: float) -> tuple[str, str]:
    """('passed' | 'failed' | 'timeout', the first failing test's id or "") of pytest on tests in
    tree (stopping at the first failure)."""
    env = dict(os.environ, JAX_PLATFORMS=os.environ.get("JAX_PLATFORMS", "cpu"), PYTHONDONTWRITEBYTECODE="1")
    env.setdefault("XLA_FLAGS", "--xla_force_host_platform_device_count=2")
    try:
        done = subprocess.run([sys.executable, "-m", "pytest", "-x", "-q", "-rfE", "-p", "no:cacheprovider", *tests],
                              cwd=tree, env=env, capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return "timeout", ""
    failed = [line.split()[1] for line in done.stdout.splitlines() if line.startswith(("FAILED ", "ERROR "))]
    return ("passed" if done.returncode == 0 else "failed"), (failed[0] if failed else "")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawTextHelpFormatter)
    parser.add_argument("names", nargs="*", help="mutants to run (default: all)")
    parser.add_argument("--tests", nargs="+", help="run these tests instead of each mutant's own")
    parser.add_argument("--timeout", type=float, default=300.0, help="seconds per mutant (default 300)")
    parser.add_argument("--list", action="store_true", help="print the mutants and exit")
    args = parser.parse_args(argv)
    unknown = [n for n in args.names if n not in MUTANTS]
    if unknown:
        parser.error(f"unknown mutant(s) {', '.join(unknown)}; --list shows them")
    names = args.names or list(MUTANTS)
    if args.list:
        for name in names:
            path, _, _, tests, what = MUTANTS[name]
            print(f"{name:5s} {path}: {what} [{', '.join(tests)}]")
        return 0
    survivors, baselines = 0, {}
    with tempfile.TemporaryDirectory(prefix="jaxnerf-grid-mutants-") as tmp:
        tree = Path(tmp)
        copy_tree(tree)
        for name in names:
            path, old, new, tests, what = MUTANTS[name]
            tests = args.tests or tests
            source = (tree / path).read_text()
            if source.count(old) != 1:
                print(f"{name}: {path}: the text to mutate is not found exactly once (stale table)", flush=True)
                survivors += 1
                continue
            start = time.monotonic()
            if tuple(tests) not in baselines:
                baselines[tuple(tests)] = run_tests(tree, tests, args.timeout)
            baseline = baselines[tuple(tests)][0]
            if baseline != "passed":
                print(f"{name}: the unmutated tree {baseline} {' '.join(tests)}: no verdict", flush=True)
                survivors += 1
                continue
            (tree / path).write_text(source.replace(old, new))
            try:
                status, by = run_tests(tree, tests, args.timeout)
            finally:
                (tree / path).write_text(source)
            verdict = {"failed": "killed", "passed": "SURVIVED", "timeout": "timeout"}[status]
            survivors += verdict != "killed"
            print(f"{name:5s} {verdict:8s} {time.monotonic() - start:6.1f} s  {path}: {what} "
                  f"[{by or ' '.join(tests)}]", flush=True)
    return survivors


if __name__ == "__main__":
    sys.exit(main())
