#!/usr/bin/env bash
# Mutation testing (mutmut 3) of the modules where the blocks are joined, each against the fast
# tests that cover it (docs/TESTING.md). Not part of CI: it runs for tens of minutes to hours.
#
#   scripts/mutation.sh                         every group below, all of each module
#   scripts/mutation.sh foreground models       some groups
#   scripts/mutation.sh evaluate -- 'jaxnerf_grid.eval.evaluate.x_region_masks*'
#                                               one group, only the mutants of some functions
#                                               (mutmut's names: module.x_function__mutmut_N)
#
# Each group runs in its own copy of the working tree (tracked and untracked, not ignored files)
# under $MUTATION_DIR (default /tmp/jaxnerf-grid-mutation/<group>), so the tree itself is never
# mutated; a copy keeps mutmut's cache, so a second run only retries what changed. Summary per
# group: $MUTATION_DIR/<group>/summary.txt (counts by status) and survivors.txt (mutmut show of
# each survivor). Environment: PYTHON (default python), MAX_CHILDREN (default 2), TESTS (test
# files or test ids replacing the group's own, e.g. only the join tests for a quicker run),
# TIMEOUT_MULTIPLIER (mutmut's timeout_multiplier, default 15; raise it for tests whose
# module-scoped fixture trains a run, or mutants there end as timeouts instead of verdicts).
set -euo pipefail

ROOT=$(cd "$(dirname "$0")/.." && pwd)
PYTHON=${PYTHON:-python}
MUTATION_DIR=${MUTATION_DIR:-/tmp/jaxnerf-grid-mutation}
MAX_CHILDREN=${MAX_CHILDREN:-2}

# the block tests of data/normalize.py in test_poses.py and test_export.py (not their pycolmap or training runs)
NORMALIZE_BLOCKS="tests/capture/test_poses.py::test_up_from_cameras_level_cameras \
tests/capture/test_poses.py::test_up_from_cameras_rolled_cameras_within_a_degree \
tests/capture/test_poses.py::test_up_from_cameras_one_heading_uses_the_plane_of_centres \
tests/capture/test_poses.py::test_up_from_cameras_on_a_line_is_the_mean_up tests/capture/test_poses.py::test_rotation_between \
tests/capture/test_poses.py::test_rotate_scene_keeps_projections tests/capture/test_poses.py::test_normalize_orbit_closed_forms \
tests/export/test_export.py::test_metric_round_trip tests/export/test_export.py::test_metric_round_trip_with_rotation \
tests/export/test_export.py::test_metric_map_of_a_missing_or_partial_record_is_the_identity_in_what_is_missing"

# the block tests of data/poses.py's cameras, metric frame, model choice and options in test_poses.py
# (not its pycolmap runs), test_poses_cameras_and_frame.py, test_poses_run_colmap.py, test_poses_from_images.py and test_georef.py's report test
POSES_BLOCKS="$(for t in working_size_and_crop_offsets similarity_fit_and_poses_agree choose_model_counts_only_vetted_photos \
choose_matcher_auto_rule names_look_ordered poses_vocab_needs_a_tree_file poses_bad_matcher_or_overlap_says_which_flag \
prepare_photo_honours_exif_orientation; \
do printf 'tests/capture/test_poses.py::test_%s ' $t; done) tests/capture/test_poses_cameras_and_frame.py tests/capture/test_poses_run_colmap.py tests/capture/test_poses_from_images.py \
tests/capture/test_georef.py::test_report_flags_residuals_beyond_the_sources_accuracy"

# the block tests of export/measure.py in test_export.py and test_survey.py (not test_export's
# training fixture; test_join_export.py's module-scoped export is credited by mutmut to its first test only)
MEASURE_BLOCKS="$(for t in min_area_rectangle_against_brute_force footprint_and_cross_arms_of_a_synthetic_tower \
cross_arm_ends_of_a_one_sided_arm_on_a_tilted_ground orthographic_views_draw_the_nearest_point \
plane_basis_is_the_x_axis_projected_on_the_plane_and_orthonormal min_area_rectangle_of_one_two_three_and_collinear_points \
footprint_of_a_turned_rectangle_on_tilted_offset_ground footprint_band_includes_its_upper_edge \
cross_arms_of_a_counted_tower_on_tilted_offset_ground cross_arms_needs_ten_points \
cross_arms_counts_the_highest_point_in_the_top_slice_and_looks_past_a_sparse_slice; do printf 'tests/export/test_export.py::test_%s ' $t; done) \
$(for t in tilt_of_a_generated_tower_within_0_3_degrees tilt_from_the_ground_normal_on_sloping_ground \
conductor_clearance_is_the_lowest_point_of_the_wire_leaving_the_tower axis_tilt_of_slices_on_a_known_line_against_linregress \
axis_tilt_of_three_slices_of_three_points_and_the_line_fit_of_two \
conductor_clearance_counts_the_box_edge_the_height_limit_and_the_gap_by_hand \
axis_tilt_thickness_spread_and_lowest_height_against_a_brute_force_refit \
axis_tilt_thicker_fit_keeps_a_centre_within_half_its_own_slice_height; do printf 'tests/export/test_survey.py::test_%s ' $t; done)"

# the fast tests of export/run.py's blocks (not test_export's training fixture): the analytic
# exports of test_join_export and test_export_geoid, and the box and units tests. mutmut orders a
# mutant's tests by their recorded time, which leaves out a module fixture's setup, so the
# analytic export (5-9 s) tends to run first: for the small functions give TESTS= the block
# tests alone (docs/TESTING.md)
EXPORT_RUN_BLOCKS="tests/joins/test_join_export.py tests/export/test_geoid.py tests/export/test_export_run.py \
tests/export/test_export.py::test_parse_box tests/export/test_export.py::test_units_are_metres_only_when_the_dataset_states_its_normalisation \
tests/export/test_survey.py::test_units_follow_the_georeference_record_else_the_synthetic_scale"

# the box tests of export/__init__.py in test_survey.py (box_to_scene, box_to_metric)
BOX_BLOCKS="$(for t in a_metric_box_maps_to_the_scene_box_around_its_8_corners_by_hand \
a_scene_box_maps_to_the_metric_box_around_its_8_corners_by_hand a_box_with_a_turn_of_more_than_90_degrees_is_not_inverted; \
do printf 'tests/export/test_survey.py::test_%s ' $t; done)"

# the block tests of export/fuse.py and export/mesh.py in test_export.py (not its training fixture)
FUSE_BLOCKS="tests/export/test_export.py::test_project_inverts_lift_view tests/export/test_export.py::test_fusion_keeps_the_surface_and_drops_floaters"
MESH_BLOCKS="$(for t in grid_spec_covers_the_box_with_resolution_voxels_on_the_longest_side \
density_threshold_gives_the_opacity_of_one_voxel marching_cubes_on_a_sphere_lies_on_the_surface_and_is_closed \
marching_cubes_on_a_box_closes_at_the_grid_border no_surface_gives_an_empty_mesh small_components_are_removed \
mesh_ply_read_back_by_plyfile; do printf 'tests/export/test_export.py::test_%s ' $t; done)"

# group -> "module to mutate|fast tests that cover it"
declare -A GROUPS_=(
  [foreground]="jaxnerf_grid/masks/foreground.py|tests/masks/test_foreground.py tests/joins/test_join_foreground.py"
  [masking]="jaxnerf_grid/masks/write.py|tests/masks/test_write.py tests/masks/test_mask_domain.py::test_domain_verdict_counts_mostly_masked_frames tests/joins/test_join_foreground.py tests/cli/test_mask.py"
  [models]="jaxnerf_grid/nerf/models.py|tests/joins/test_join_nerfw.py tests/nerf/test_models.py"
  [evaluate]="jaxnerf_grid/eval/evaluate.py|tests/eval/test_evaluate.py tests/joins/test_join_eval.py"
  [report]="jaxnerf_grid/report/markdown.py|tests/report/test_markdown.py tests/joins/test_join_eval.py"
  [demo]="jaxnerf_grid/demo.py|tests/joins/test_join_demo.py"
  [geometry]="jaxnerf_grid/eval/geometry.py|tests/eval/test_geometry.py tests/joins/test_join_truth.py"
  [export_score]="jaxnerf_grid/export/score.py|tests/joins/test_join_truth.py tests/joins/test_join_export.py"
  [export_init]="jaxnerf_grid/export/__init__.py|tests/joins/test_join_export.py tests/export/test_export.py $BOX_BLOCKS"
  [export_ground]="jaxnerf_grid/export/ground.py|tests/joins/test_join_export.py tests/export/test_export.py"
  [export_measure]="jaxnerf_grid/export/measure.py|$MEASURE_BLOCKS tests/export/test_measure.py tests/joins/test_join_export.py"
  [export_field]="jaxnerf_grid/export/field.py|tests/joins/test_join_truth.py tests/joins/test_join_export.py"
  [export_run]="jaxnerf_grid/export/run.py|$EXPORT_RUN_BLOCKS"
  [export_survey]="jaxnerf_grid/export/survey.py|tests/export/test_survey.py tests/export/test_export_run.py tests/joins/test_join_export.py tests/export/test_geoid.py"
  [export_fuse]="jaxnerf_grid/export/fuse.py|$FUSE_BLOCKS tests/export/test_export_run.py tests/joins/test_join_export.py"
  [export_mesh]="jaxnerf_grid/export/mesh.py|$MESH_BLOCKS tests/export/test_export_run.py tests/joins/test_join_export.py"
  [export_geoid]="jaxnerf_grid/export/geoid.py|tests/export/test_geoid.py tests/export/test_export_run.py"
  [normalize]="jaxnerf_grid/data/normalize.py|tests/data/test_normalize.py tests/joins/test_join_poses.py tests/data/test_formats.py $NORMALIZE_BLOCKS"
  [poses]="jaxnerf_grid/capture/poses.py|tests/joins/test_join_poses.py $POSES_BLOCKS"
  [losses]="jaxnerf_grid/nerf/losses.py|tests/nerf/test_losses.py"
  [train]="jaxnerf_grid/train/loop.py|tests/joins/test_join_truth.py tests/train/test_loop.py::test_loss_weights_floor_and_switch tests/train/test_refine.py::test_grown_prior_flags_the_pixels_within_the_disc_of_a_masked_pixel"
)
ORDER=(foreground masking models evaluate report demo geometry export_score export_init export_ground export_measure
       export_field export_run export_survey export_fuse export_mesh export_geoid normalize poses losses train)

groups=()
globs=()
while (($#)); do
  if [[ $1 == -- ]]; then shift; globs=("$@"); break; fi
  [[ -n ${GROUPS_[$1]:-} ]] || { echo "mutation.sh: unknown group $1 (choose from ${ORDER[*]})" >&2; exit 2; }
  groups+=("$1"); shift
done
((${#groups[@]})) || groups=("${ORDER[@]}")

"$PYTHON" -c "import mutmut" 2>/dev/null || { echo "mutation.sh: mutmut missing: pip install -e '.[test]'" >&2; exit 2; }
export JAX_PLATFORMS=${JAX_PLATFORMS:-cpu}
export XLA_FLAGS=${XLA_FLAGS:---xla_force_host_platform_device_count=2}

for group in "${groups[@]}"; do
  module=${GROUPS_[$group]%%|*}
  tests=${TESTS:-${GROUPS_[$group]#*|}}
  work=$MUTATION_DIR/$group
  mkdir -p "$work"
  # a fresh copy of the tree (mutmut's own state under mutants/ is kept)
  (cd "$ROOT" && git ls-files -co --exclude-standard -z | tar --null -T - -cf -) | tar -xf - -C "$work"
  "$PYTHON" - "$work/pyproject.toml" "${TIMEOUT_MULTIPLIER:-15}" "$module" $tests <<'EOF'
import sys
path, timeout, module, tests = sys.argv[1], sys.argv[2], sys.argv[3], sys.argv[4:]
text = open(path).read().split("\n[tool.mutmut]")[0].rstrip("\n")
quote = lambda xs: "[" + ", ".join(f'"{x}"' for x in xs) + "]"
text += ("\n\n[tool.mutmut]\n"
         'source_paths = ["jaxnerf_grid"]\n'
         f"only_mutate = {quote([module])}\n"
         f"pytest_add_cli_args_test_selection = {quote(tests)}\n"
         'pytest_add_cli_args = ["-p", "no:cacheprovider"]\n'
         'process_isolation = "forkserver"\n'
         "use_git_change_detection = false\n"
         f"timeout_multiplier = {float(timeout)}\n")
open(path, "w").write(text)
EOF
  echo "== mutation.sh: $group: $module against $tests"
  (cd "$work" && "$PYTHON" -m mutmut run --max-children "$MAX_CHILDREN" "${globs[@]}") || true
  (cd "$work" && "$PYTHON" -m mutmut results --all true > results.txt 2>&1) || true
  "$PYTHON" - "$work" "$module" "${globs[@]}" <<'EOF'
import collections, fnmatch, pathlib, re, subprocess, sys
work, module, picked = pathlib.Path(sys.argv[1]), sys.argv[2], sys.argv[3:]
rows = [l.strip().rsplit(": ", 1) for l in (work / "results.txt").read_text().splitlines() if ": " in l]
if picked:  # only the mutants asked for
    rows = [r for r in rows if any(fnmatch.fnmatch(r[0], g) for g in picked)]
counts = collections.Counter(status for _, status in rows)
survivors = [name for name, status in rows if status == "survived"]
summary = f"{module}: " + ", ".join(f"{k} {v}" for k, v in sorted(counts.items())) + f" (of {len(rows)})"
(work / "summary.txt").write_text(summary + "\n")
with open(work / "survivors.txt", "w") as f:
    for name in survivors:
        shown = subprocess.run([sys.executable, "-m", "mutmut", "show", name], cwd=work, capture_output=True, text=True)
        f.write(shown.stdout + "\n")
print(summary)
EOF
done
