"""Shared pytest fixtures.

torchvision stand-in: the `lpips` package (used only as a test reference) imports
`torchvision.models` and builds its trunk with `torchvision.models.alexnet(pretrained=...)`.
torchvision has no CPU build here (the installed one raises on import) and CI does not have it,
so the `lpips_module` fixture installs a small stand-in into `sys.modules` *before* importing
lpips, unless a working torchvision exists (probed in a subprocess, so a broken torchvision is
never imported into the test process). The stand-in's `alexnet()` has the real torchvision
AlexNet `.features` layout with torch's default random initialisation; it has no pretrained
weights and refuses `pretrained=True`. Nothing here imports torch unless a fixture needs it.
"""

from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
import types
from pathlib import Path

import numpy as np
import pytest

# The suite compiles far more than it runs (a few steps of many configs): XLA's LLVM optimisation
# off cuts its CPU time by about a third (docs/TESTING.md). Set before any test creates the JAX
# backend, so the children the tests spawn inherit it too; a flag the caller gave is kept.
COMPILE_FAST_FLAGS = ("--xla_backend_optimization_level=0", "--xla_llvm_disable_expensive_passes=true")


def with_compile_fast_flags(xla_flags: str) -> str:
    """`xla_flags` (an XLA_FLAGS value) plus each of COMPILE_FAST_FLAGS whose name it lacks."""
    names = {flag.split("=")[0] for flag in xla_flags.split()}
    extra = [flag for flag in COMPILE_FAST_FLAGS if flag.split("=")[0] not in names]
    return " ".join([xla_flags.strip(), *extra]).strip()


os.environ["XLA_FLAGS"] = with_compile_fast_flags(os.environ.get("XLA_FLAGS", ""))


def _real_torchvision_works() -> bool:
    if importlib.util.find_spec("torchvision") is None:
        return False
    probe = subprocess.run([sys.executable, "-c", "import torchvision.models"],
                           capture_output=True, timeout=300)
    return probe.returncode == 0


def _no_pretrained(name: str, pretrained, weights):
    if pretrained or weights is not None:
        raise RuntimeError(f"torchvision stand-in: {name} has no pretrained weights (offline test stub)")


def _make_torchvision_stub() -> types.ModuleType:
    """Modules `torchvision` and `torchvision.models` with random-init AlexNet / VGG16 trunks."""
    from torch import nn

    class _Trunk(nn.Module):
        def __init__(self, features: nn.Sequential):
            super().__init__()
            self.features = features

    def alexnet(pretrained: bool = False, weights=None, progress: bool = True, **kwargs):
        """torchvision.models.alexnet stand-in: `.features` only, random init."""
        _no_pretrained("alexnet", pretrained, weights)
        return _Trunk(nn.Sequential(
            nn.Conv2d(3, 64, kernel_size=11, stride=4, padding=2), nn.ReLU(inplace=True),
            nn.MaxPool2d(kernel_size=3, stride=2),
            nn.Conv2d(64, 192, kernel_size=5, padding=2), nn.ReLU(inplace=True),
            nn.MaxPool2d(kernel_size=3, stride=2),
            nn.Conv2d(192, 384, kernel_size=3, padding=1), nn.ReLU(inplace=True),
            nn.Conv2d(384, 256, kernel_size=3, padding=1), nn.ReLU(inplace=True),
            nn.Conv2d(256, 256, kernel_size=3, padding=1), nn.ReLU(inplace=True),
            nn.MaxPool2d(kernel_size=3, stride=2),
        ))

    def vgg16(pretrained: bool = False, weights=None, progress: bool = True, **kwargs):
        """torchvision.models.vgg16 stand-in: `.features` only, random init."""
        _no_pretrained("vgg16", pretrained, weights)
        layers, c_in = [], 3
        for v in (64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M",
                  512, 512, 512, "M"):
            if v == "M":
                layers.append(nn.MaxPool2d(kernel_size=2, stride=2))
            else:
                layers += [nn.Conv2d(c_in, v, kernel_size=3, padding=1), nn.ReLU(inplace=True)]
                c_in = v
        return _Trunk(nn.Sequential(*layers))

    def _unavailable(name):
        def f(*args, **kwargs):
            raise NotImplementedError(f"torchvision stand-in: {name} is not provided")
        f.__name__ = name
        return f

    tv = types.ModuleType("torchvision")
    models = types.ModuleType("torchvision.models")
    models.alexnet = alexnet
    models.vgg16 = vgg16
    for name in ("squeezenet1_1", "resnet18", "resnet34", "resnet50", "resnet101", "resnet152"):
        setattr(models, name, _unavailable(name))
    for name in ("AlexNet_Weights", "VGG16_Weights", "SqueezeNet1_1_Weights"):
        setattr(models, name, types.SimpleNamespace(DEFAULT=None, IMAGENET1K_V1=None))
    tv.models = models
    tv.__version__ = "0.0+jaxnerf-grid-test-stub"
    tv.__jaxnerf_grid_stub__ = True
    return tv


def install_torchvision_stub_if_needed() -> bool:
    """Put the stand-in into sys.modules unless a working torchvision exists.
    Returns True when the stand-in is in use."""
    current = sys.modules.get("torchvision")
    if current is not None:
        return bool(getattr(current, "__jaxnerf_grid_stub__", False))
    if _real_torchvision_works():
        return False
    tv = _make_torchvision_stub()
    sys.modules["torchvision"] = tv
    sys.modules["torchvision.models"] = tv.models
    return True


@pytest.fixture(scope="session")
def lpips_module():
    """The `lpips` reference package, imported with the torchvision stand-in when needed."""
    pytest.importorskip("torch")
    if importlib.util.find_spec("lpips") is None:
        pytest.skip("lpips package not installed")
    install_torchvision_stub_if_needed()
    import lpips

    return lpips


@pytest.fixture(scope="session")
def real_images():
    """Real photographs from scikit-image, float32 [0,1] HWC: {"astronaut": [512,512,3],
    "chelsea": [300,451,3]}."""
    from skimage import data

    return {name: getattr(data, name)().astype(np.float32) / 255.0
            for name in ("astronaut", "chelsea")}


def _mapping_count() -> int:
    """The number of memory mappings of this process (Linux; 0 elsewhere)."""
    try:
        with open("/proc/self/maps", "rb") as maps:
            return sum(1 for _ in maps)
    except OSError:
        return 0


MAPPINGS_BEFORE_CLEARING = 16000  # a quarter of Linux's default vm.max_map_count (65530)


def _clear_compiled_programs() -> None:
    if "jax" in sys.modules:
        import gc

        sys.modules["jax"].clear_caches()
        gc.collect()


@pytest.fixture(autouse=True, scope="module")
def _free_compiled_programs():
    """Frees the XLA programs each test module compiled once the module ends.

    XLA:CPU keeps several memory mappings per compiled program, and jax's caches keep every program
    alive, so the whole suite in one process reached Linux's limit of 65530 mappings
    (vm.max_map_count) after about 700 tests: the next compile failed, and the crash handler that
    pycolmap installs then deadlocked while unwinding (the suite hung in futex waits; the process
    held 65317 mappings). Clearing the caches between modules keeps the count near one module's."""
    yield
    _clear_compiled_programs()
    if os.environ.get("JAXNERF_GRID_REPORT_MAPPINGS"):
        print(f" [mappings: {_mapping_count()}]", end="")


@pytest.fixture(autouse=True)
def _free_compiled_programs_in_a_long_module():
    """Within one module (tests/train/test_loop.py trains dozens of models), clears the caches after
    a test once the process holds more than MAPPINGS_BEFORE_CLEARING mappings."""
    yield
    if _mapping_count() > MAPPINGS_BEFORE_CLEARING:
        _clear_compiled_programs()


@pytest.fixture(autouse=True)
def _progress_bars_on_a_stopped_clock(monkeypatch):
    """The package's progress bars read a stopped clock unless the test gives one, so a bar in log
    mode (stderr not a terminal, as under pytest) prints only its final line, "... 0.0 s", however
    long a loaded machine takes: no test's output depends on its speed. The throttle itself is
    tested with a fake clock (tests/util/test_progress.py)."""
    from jaxnerf_grid.util import progress

    real_bar = progress.bar

    def bar(*args, clock=None, **kwargs):
        return real_bar(*args, clock=clock or (lambda: 0.0), **kwargs)

    monkeypatch.setattr(progress, "bar", bar)


# The files that take longest on the two-core CI machine (the durations it prints), longest first.
# CI runs the suite on two pytest-xdist workers, a whole file to a worker (`-n 2 --dist loadfile
# --no-loadscope-reorder`, README command 2): a worker takes the next file when it is nearly idle,
# so starting with the long files lets the two finish together (most of a test's time here is
# XLA compiling, on one core). Without xdist the order changes nothing a test depends on.
LONGEST_FIRST = ("train/test_robust_training.py", "train/test_distributed.py", "train/test_loop.py",
                 "cli/test_train_render_eval.py", "train/test_exact_resume.py", "cli/test_unprivileged.py",
                 "report/test_html.py", "joins/test_join_eval.py", "cli/test_bad_input.py",
                 "masks/test_dpt_parity.py", "experiments_and_benchmarks/test_experiments.py",
                 "joins/test_join_demo.py", "masks/test_mask_domain.py",
                 "experiments_and_benchmarks/test_step_profile.py", "render/test_videos.py", "nerf/test_models.py",
                 "nerf/test_hashgrid.py", "cli/test_hostile_corpus.py", "data/test_working_resolution.py")

# The slow tier: `pytest -m "not slow"` leaves it out (the inner loop), CI runs everything. A test is
# slow when its file is in SLOW_FILES (every test there trains, or runs a command in a child process),
# when it uses a module fixture of SLOW_FIXTURES (the fixture trains a run, exports one or runs
# COLMAP, once per file), or when SLOW names it (file::function, every parameter of it). Ranked by
# the suite's per-test times; tests/test_tiers.py checks that every name here still exists.
SLOW_FILES = {
    "cli/test_unprivileged.py", "joins/test_join_demo.py",
    "train/test_distributed.py", "train/test_exact_resume.py", "train/test_robust_training.py",
    "experiments_and_benchmarks/test_step_profile.py",
}
SLOW_FIXTURES = {
    "capture/test_poses.py": {"orbit_run", "per_photo_run", "sequential_run"},
    "cli/test_bad_input.py": {"scene"},
    "cli/test_hostile_corpus.py": {"scene"},
    "data/test_synthetic_scene.py": {"tiny"},
    "data/test_working_resolution.py": {"small_run"},
    "export/test_export.py": {"tiny_run"},
    "export/test_geoid.py": {"exports"},
    "joins/test_join_eval.py": {"ours", "nerfw"},
    "joins/test_join_eval_analytic.py": {"evaluated"},
    "joins/test_join_export.py": {"exported"},
    "render/test_videos.py": {"tiny_run"},
    "report/test_html.py": {"tiny_run"},
}
SLOW = {
    "cli/test_train_render_eval.py::test_train_render_eval",
    "cli/test_train_render_eval.py::test_demo_runs_the_recipe_on_a_given_dataset",
    "cli/test_train_render_eval.py::test_demo_takes_the_bounds_a_dataset_records",
    "cli/test_train_render_eval.py::test_train_takes_near_far_and_radius_from_the_datasets_scene_bounds",
    "cli/test_train_render_eval.py::test_demo_without_a_device_count_renders_on_every_core_and_trains_on_one",
    "train/test_loop.py::test_two_devices_match_one_device",
    "train/test_sparse_depth.py::test_the_depth_step_matches_on_one_and_two_devices_and_moves_the_parameters",
    "train/test_sparse_depth.py::test_the_robust_step_takes_the_depth_term_too",
    "train/test_sparse_depth.py::test_depth_on_without_a_model_trains_without_it_and_says_why",
    "train/test_loop.py::test_sparse_adam_leaves_untouched_table_rows_where_dense_adam_moves_them",
    "train/test_loop.py::test_grid_proposal_run_resumes_exactly",
    "train/test_loop.py::test_training_learns_and_chunked_render_is_consistent",
    "train/test_loop.py::test_non_finite_steps_are_skipped_and_logged",
    "train/test_refine.py::test_refine_two_devices_match_one_and_the_record_holds_the_frozen_weights",
    "train/test_refine.py::test_refine_resumes_exactly_on_either_side_of_the_switch",
    "masks/test_dpt_parity.py::test_parity_with_transformers",
    "masks/test_dpt_parity.py::test_auxiliary_head_and_patch16_resolution",
    "masks/test_dpt_parity.py::test_depth_head_with_projection",
    "masks/test_mask_domain.py::test_builtin_model_stays_quiet_on_everyday_photos_without_transients",
    "masks/test_mask_domain.py::test_rule_stays_quiet_on_the_synthetic_scenes",
    "nerf/test_hashgrid.py::test_every_method_runs_with_the_grid_field",
    "joins/test_join_eval.py::test_a_robust_run_reports_the_weights_training_used",
    "report/test_html.py::test_train_progress_page_is_rewritten_while_training",
    "report/test_html.py::test_a_grey_model_is_found_in_the_screenshot",  # headless Chromium
    "util/test_folders.py::test_poses_swap_killed_with_sigkill_is_finished_by_recover",
    "experiments_and_benchmarks/test_experiments.py::test_machinery_end_to_end",
    "experiments_and_benchmarks/test_experiments.py::test_throughput_times_a_case_with_and_without_computed_once",
    "experiments_and_benchmarks/test_experiments.py::test_train_only_trains_the_chosen_runs_and_reads_the_others_from_the_cache",
    "experiments_and_benchmarks/test_experiments.py::test_recorded_runs_stand_in_for_a_lost_cache",
    # the heaviest of the rest (compiles of a field, a DPT or a pool each), so the inner loop stays
    # under two minutes on two cores; every module is still imported by a fast test (test_tiers.py)
    "capture/test_poses.py::test_auto_sequential_matching_closes_an_orbit_and_registers_its_ends",
    "capture/test_poses.py::test_poses_dataset_loads_and_reprojects_within_a_pixel",
    "cli/test_mask.py::test_dpt_source_with_native_weights",
    "cli/test_train_render_eval.py::test_train_without_steps_takes_the_budgets_steps_and_records_why",
    "eval/test_lpips.py::test_matches_torch_lpips_random_and_real",
    "eval/test_metrics.py::test_ms_ssim_five_scales_matches_pytorch_msssim",
    "experiments_and_benchmarks/test_experiments.py::test_throughput_concat_case_traces_the_per_sample_colour_input_with_the_same_value",
    "experiments_and_benchmarks/test_strecha_gps_scale.py::test_the_known_scale_is_found_and_noise_moves_it_by_about_sigma_over_the_baseline",
    "export/test_conductors.py::test_fit_recovers_a_known_catenary_from_noisy_cluttered_detections",
    "export/test_conductors.py::test_spans_found_on_both_sides_and_none_in_clutter_alone",
    "export/test_conductors.py::test_track_finds_a_wire_over_textured_ground_with_its_sag_from_the_span_length",
    "export/test_conductors.py::test_seed_window_below_a_cross_arm_tip_finds_the_wire_its_insulator_hangs",
    "export/test_conductors.py::test_a_curve_between_two_wires_seen_on_each_from_its_side_is_dropped_and_both_wires_kept",
    "export/test_conductors.py::test_a_wire_few_photos_see_is_tracked_from_a_cross_arms_window_not_from_the_open_plane",
    "joins/test_join_export.py::test_a_given_box_around_the_top_hands_each_step_its_setting_and_metres",
    "joins/test_join_export.py::test_a_tower_tilted_1_degree_is_measured_within_0_3_degrees",
    "joins/test_join_export.py::test_the_auto_box_of_an_empty_scene_and_of_ground_alone_is_refused_in_words",
    "joins/test_join_export.py::test_the_progress_lines_and_the_views_timing_of_an_export_by_default",
    "joins/test_join_foreground.py::test_mask_command_takes_the_working_size_from_the_model",
    "joins/test_join_foreground.py::test_predict_maps_untiled_against_dpt_on_the_resized_photo",
    "joins/test_join_nerfw.py::test_transient_compositing_against_a_per_sample_loop",
    "masks/test_dpt_weights.py::test_conv_of_upsampled_map_against_torch",
    "masks/test_dpt_weights.py::test_forward_is_vmap_and_jit_safe",
    "masks/test_foreground.py::test_class_probabilities_sum_to_predict_maps_c",
    "masks/test_foreground.py::test_predict_maps_on_large_photo_bounded_and_full_resolution",
    "masks/test_foreground.py::test_predict_maps_tiled_against_per_window_reference",
    "masks/test_mask_domain.py::test_predict_maps_confidence_is_the_mean_max_probability_dpt_saw",
    "masks/test_photo_consistency.py::test_a_static_wall_is_confirmed_and_a_pasted_square_is_not",
    "masks/test_photo_consistency.py::test_confirmed_at_ids_splits_flat_ids_as_numpy_unravels_them",
    "masks/test_robust.py::test_random_residuals_and_priors_match_numpy",
    "masks/test_robust.py::test_strict_readmission_needs_the_residual_and_the_confirmation_of_a_flagged_pixel",
    "masks/test_write.py::test_dpt_masks_record_the_verdict_the_confidence_and_no_depth_without_a_depth_head",
    "nerf/test_fields.py::test_apply_matches_numpy_mlp",
    "nerf/test_fields.py::test_colour_branch_with_one_direction_per_ray_matches_the_concatenated_input",
    "nerf/test_fields.py::test_gradients_finite_and_errors",
    "nerf/test_fields.py::test_transient_and_appearance_heads_match_numpy",
    "nerf/test_hashgrid.py::test_encoding_gradient_matches_finite_differences",
    "nerf/test_hashgrid.py::test_encoding_matches_per_point_loop",
    "nerf/test_hashgrid.py::test_grid_field_matches_numpy_composition",
    "nerf/test_losses.py::test_interlevel_loss_batched_zero_when_bounded_and_only_proposal_learns",
    "nerf/test_models.py::test_coarse_render_matches_bruteforce_loop",
    "nerf/test_models.py::test_hierarchical_sampling_finds_sphere_surface",
    "nerf/test_models.py::test_nerfw_embeddings_and_static_part",
    "nerf/test_models.py::test_per_ray_keys_make_batches_consistent",
    "nerf/test_models.py::test_proposal_sampling_finds_sphere_surface_and_opaque_far_shows_the_far_colour",
    "nerf/test_volume.py::test_gradients_finite_at_extreme_densities",
    "train/test_loop.py::test_nerfw_appearance_fit_reduces_error",
    "train/test_ray_pool.py::test_sharded_uint8_batch_equals_the_float32_pools",
    "train/test_refine.py::test_frame_evidence_against_a_pixel_loop",
    "train/test_refine.py::test_rendered_points_lie_on_their_pixels_rays_at_the_rendered_z_depth",
    "capture/test_georef.py::test_poses_aligns_photos_with_gps_to_metres",
    "eval/test_metrics.py::test_evaluate_image_without_lpips",
    "joins/test_join_export.py::test_a_tower_without_cross_arms_looks_for_conductors_above_half_its_height",
    "joins/test_join_foreground.py::test_mask_command_dpt_source_against_eq6_to_8",
    "masks/test_photo_consistency.py::test_confirmation_errors_match_a_numpy_loop",
    "masks/test_write.py::test_overlays_are_scaled_to_the_preview_size_and_the_progress_is_shown_by_default",
    "masks/test_write.py::test_tiled_masks_record_the_tiling_and_use_its_overlap",
    "nerf/test_field_kinds.py::test_init_and_apply_dispatch_through_the_registry",
    "train/test_ray_pool.py::test_mask_floor_weights_are_coded_exactly",
    "train/test_robust_pool.py::test_lean_pool_batch_and_confirmation_equal_the_float32_pools",
    "train/test_robust_pool.py::test_refine_reads_the_same_weights_and_confirmation_from_the_lean_pool",
    "train/test_robust_pool.py::test_robust_steps_on_the_lean_pool_give_the_float32_pools_params",
}


def slow_reason(rel_path: str, function: str, fixtures) -> str | None:
    """Why the test `function` of tests/`rel_path` using `fixtures` is slow (None: it is not)."""
    if rel_path in SLOW_FILES:
        return "file"
    if SLOW_FIXTURES.get(rel_path, set()) & set(fixtures):
        return "fixture"
    if f"{rel_path}::{function}" in SLOW:
        return "named"
    return None


def _relative(item) -> str:
    """The test's file relative to tests/ ("train/test_loop.py")."""
    tests = Path(__file__).parent
    return item.path.relative_to(tests).as_posix() if item.path.is_relative_to(tests) else item.path.name


def pytest_collection_modifyitems(config, items):
    """Marks the slow tier (SLOW_FILES, SLOW_FIXTURES, SLOW), then a stable sort: the files of
    LONGEST_FIRST in that order, then every other file as collected."""
    for item in items:
        function = getattr(item, "originalname", item.name)
        if slow_reason(_relative(item), function, getattr(item, "fixturenames", ())):
            item.add_marker(pytest.mark.slow)
    rank = {name: i for i, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(_relative(item), len(rank)))
