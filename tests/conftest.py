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
