"""Shared pytest set-up: helper modules in tests/ importable (``import render_fixtures``), the
``slow`` tier, threads that do not spin, and one Numba thread per pytest-xdist worker.

The tier: ``pytest -m "not slow"`` is the inner loop; CI runs everything. Tests are marked slow
here and nowhere else, each with its reason (``pytest --collect-only -v -m slow`` lists them), when

- they train: the test, a fixture of its module it uses, or a function of its module that either
  calls, constructs a ``Trainer`` (its initialisation alone fits the scene: seconds), runs the
  command line's ``train``/``demo`` or an experiment sweep (``TRAINING_CALLS``,
  ``TRAINING_COMMANDS``). A call inside ``pytest.raises``, or asserted to exit with status 2, is
  refused before any work and does not count. A test outside the tier that completes a Trainer's
  construction fails (``_guard_trainer``), so the rule cannot miss one silently;
- they are named in ``SLOW_TESTS`` (a test, or a module fixture whose users are all slow): a
  notebook executed, an example run end to end, or more than about 1.5 s on a quiet machine with a
  warm Numba cache for another reason (measured: docs/results.md §16).
"""
import ast
import os
import sys
from functools import cache

import pytest

TESTS = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, TESTS)
os.environ.setdefault("MPLBACKEND", "Agg")
# Idle OpenBLAS and OpenMP (Numba's threading layer) threads busy-wait for work: beside a second
# pytest-xdist worker, or any other load on two cores, they take the core from the thread that
# computes (docs/results.md §16). One OpenBLAS thread (the tests' small problems
# gain nothing from a second) and OpenMP threads that sleep when idle; neither changes a result
# (the pinned run's parameters are the same to the bit). Set before NumPy and Numba's threads load.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

TRAINING_CALLS = {
    "Trainer": "constructs a Trainer",
    "run_experiment": "runs an experiment sweep (a training run per cell)",
    "run_cell": "runs one experiment cell (a training run)",
    "set_up_run": "sets up a run (bundle adjustment and the scene's initialisation)",
}
TRAINING_COMMANDS = {"train", "demo", "experiment"}  # main([<command>, ...]) of d2gs_np.cli

_SUITE_IMPORT = "imports the 24-frame 240x135 suite clip end to end"
# "file::name" (parameters left out; name is a test, or a fixture of that file): why it is slow.
SLOW_TESTS = {
    "test_notebooks.py::test_notebook_runs": "executes a notebook",
    "examples/test_exposure_bend.py::crossing": "ray-casts a suite clip and bundle-adjusts its poses (about 4 s)",
    "examples/test_exposure_bend.py::test_a_straight_exposure_has_no_true_bend_and_a_scene_without_exposures_is_refused":
        "ray-casts a suite clip and bundle-adjusts its poses (about 4 s)",
    "examples/test_suite_runner.py::test_suite_runner_writes_the_table_and_resumes":
        "runs examples/suite.py end to end (three training cells)",
    "examples/test_suite_runner.py::test_ablation_writes_its_table":
        "runs examples/suite.py end to end (two training cells)",
    "video/test_import.py::test_image_folder_import_registers_the_blurry_suite_frames": _SUITE_IMPORT,
    "video/test_import.py::test_video_file_round_trip": _SUITE_IMPORT + ", from an encoded video",
    "video/test_import_movers.py::test_motion_masks_find_the_mover": _SUITE_IMPORT,
    "video/test_import_movers.py::test_movers_neither_pull_the_poses_nor_escape_the_masks": _SUITE_IMPORT,
    "video/test_import_movers.py::test_a_large_mover_does_not_take_the_place_of_the_static_world": _SUITE_IMPORT,
    "video/test_import.py::test_sparse_points_seed_the_initialisation":
        "ray-casts the 24-frame suite clip and initialises points from it twice",
    "video/test_import.py::test_untextured_and_unregistrable_frames_are_named":
        "ray-casts the 24-frame suite clip (its first 6 frames are registered)",
    "video/test_import.py::test_register_video_with_given_tracks_is_the_same_registration":
        "registers a 10-frame 240x135 suite clip twice",
    "importers/test_colmap_sfm.py::test_pycolmap_backend_registers_the_blurry_suite_clip":
        _SUITE_IMPORT + " through pycolmap, twice (the masked round)",
    "video/test_real_clip.py::test_the_real_clip_imports_with_sub_pixel_reprojection":
        "imports 23 frames of a real video end to end",
    "video/test_real_clip.py::test_a_stretch_across_the_cut_is_refused_naming_the_frames":
        "decodes and tracks a stretch of a real video before refusing it",
    "video/test_segment.py::test_static_motion_never_leaves_a_worse_trajectory":
        "registers a 16-frame two-layer world, then its static group again",
    "video/test_segment.py::test_groups_that_never_share_a_frame_leave_the_registration_alone":
        "registers a 16-frame two-layer world",
    "scene/test_initialize.py::result": "initialises points (stereo seeds) on a 120x68 8-frame scene",
    "scene/test_initialize.py::test_counts_follow_the_config_and_rng_is_respected":
        "initialises points on a 120x68 8-frame scene three times",
    "scene/test_initialize.py::test_dynamic_depth_is_the_scaled_median_static_depth_of_the_frame":
        "initialises points on a 120x68 8-frame scene",
    "scene/test_initialize.py::test_no_moving_pixels_give_no_dynamic_points":
        "initialises points on a 96x54 scene twice",
    "scene/test_stereo.py::cube": "ray-casts a cube_sign suite scene",
    "scene/test_motion_init.py::test_default_motion_init_follows_the_true_movers":
        "ray-casts a 12-frame 120x68 suite scene and tracks its movers",
    "pose/test_given.py::noisy_room": "ray-casts a photo_room suite scene",
    "pose/test_bundle.py::test_bundle_adjustment_recovers_poses_with_noise_and_outliers":
        "runs a bundle adjustment with outliers to convergence",
    "render/test_render_fast.py::test_float32_kernels_compute_in_float32":
        "types every kernel's float32 specialisation afresh (Numba type inference)",
    "refcheck/test_refcheck.py::test_cli_export_compare_and_exit_codes":
        "exports and compares the whole default case suite",
    "test_cli.py::test_make_scene_writes_a_suite_scene_with_overrides": "ray-casts a suite scene",
}


@pytest.hookimpl(tryfirst=True)  # before -m selects on the mark
def pytest_collection_modifyitems(config, items):
    for item in items:
        if not isinstance(item, pytest.Function):
            continue
        rel = os.path.relpath(str(item.path), TESTS).replace(os.sep, "/")
        reason = _listed_reason(rel, item.originalname, item.fixturenames)
        if reason is None:
            reason = _training_reason(str(item.path), item.originalname, item.fixturenames)
        if reason is not None:
            item.add_marker(pytest.mark.slow(reason=reason))
    stale = sorted(k for k in SLOW_TESTS if k.split("::")[1] not in _defined_names(k.split("::")[0]))
    if stale:
        raise pytest.UsageError(f"SLOW_TESTS in tests/conftest.py names no function of its file: {stale}; update it")


def pytest_report_collectionfinish(config, items):
    if config.option.collectonly and config.option.verbose > 0:
        return [f"slow: {i.nodeid}: {i.get_closest_marker('slow').kwargs['reason']}"
                for i in items if i.get_closest_marker("slow")]
    return []


def _defined_names(rel):
    path = os.path.join(TESTS, rel)
    return set(_module_calls(path)) if os.path.exists(path) else set()


def _listed_reason(rel, test_name, fixture_names):
    for name in (test_name, *fixture_names):
        key = f"{rel}::{name}"
        if key in SLOW_TESTS:
            return SLOW_TESTS[key] if name == test_name else f"uses the fixture {name!r}, which {SLOW_TESTS[key]}"
    return None


def _training_reason(path, test_name, fixture_names):
    """Why the test ``test_name`` of module ``path`` trains (itself, through the module's functions
    it calls, or through a fixture of its module it uses), or None."""
    module = _module_calls(path)
    for name in (test_name, *fixture_names):
        reason = _trains(module, name, frozenset())
        if reason is not None:
            return reason if name == test_name else f"uses the fixture {name!r}, which {reason}"
    return None


def _trains(module, name, visiting):
    if name not in module or name in visiting:
        return None
    direct, referenced = module[name]
    if direct is not None:
        return direct
    for other in sorted(referenced):
        reason = _trains(module, other, visiting | {name})
        if reason is not None:
            return f"{reason} (in {other})"
    return None


@cache
def _module_calls(path):
    """{top-level function of the module: (what its own training call does or None, the names it uses)}."""
    with open(path, encoding="utf-8") as f:
        tree = ast.parse(f.read(), path)
    out = {}
    for node in tree.body:
        if isinstance(node, ast.FunctionDef):
            refused = _refused_calls(node)
            calls = [c for c in ast.walk(node) if isinstance(c, ast.Call) and id(c) not in refused]
            direct = next((r for r in map(_call_reason, calls) if r is not None), None)
            out[node.name] = (direct, {n.id for n in ast.walk(node) if isinstance(n, ast.Name)})
    return out


def _call_reason(call):
    func = call.func
    name = func.id if isinstance(func, ast.Name) else func.attr if isinstance(func, ast.Attribute) else None
    if name in TRAINING_CALLS:
        return TRAINING_CALLS[name]
    if name == "main" and call.args and isinstance(call.args[0], ast.List) and call.args[0].elts:
        first = call.args[0].elts[0]
        if isinstance(first, ast.Constant) and first.value in TRAINING_COMMANDS:
            return f"runs the command line's {first.value!r}"
    return None


def _refused_calls(func):
    """ids of the calls in ``func`` refused before any work: inside ``with pytest.raises(...)``, or
    asserted to return the command line's error status 2."""
    refused = set()
    for node in ast.walk(func):
        if isinstance(node, ast.With) and any(
                isinstance(w.context_expr, ast.Call) and isinstance(w.context_expr.func, ast.Attribute)
                and w.context_expr.func.attr == "raises" for w in node.items):
            refused |= {id(c) for stmt in node.body for c in ast.walk(stmt) if isinstance(c, ast.Call)}
        if (isinstance(node, ast.Compare) and isinstance(node.left, ast.Call) and len(node.comparators) == 1
                and isinstance(node.comparators[0], ast.Constant) and node.comparators[0].value == 2):
            refused.add(id(node.left))
    return refused


# The guard: a test outside the slow tier that completes a Trainer's construction fails.
_running = {"item": None}


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    _guard_trainer()
    _running["item"] = item
    try:
        yield
    finally:
        _running["item"] = None


def _guard_trainer():
    """Wrap ``Trainer.__init__`` once its module is imported (the test modules that train import it
    at collection, so before the first test runs)."""
    trainer = sys.modules.get("d2gs_np.train.trainer")
    if trainer is None or getattr(trainer.Trainer.__init__, "tier_guard", False):
        return
    real_init = trainer.Trainer.__init__

    def init(self, *args, **kwargs):
        real_init(self, *args, **kwargs)
        item = _running["item"]
        if item is not None and item.get_closest_marker("slow") is None:
            pytest.fail(f"{item.nodeid} constructed a Trainer outside the slow tier: tests/conftest.py's rule "
                        "missed it; name it in SLOW_TESTS with the reason", pytrace=False)

    init.tier_guard = True
    trainer.Trainer.__init__ = init


def pytest_configure(config):
    # pytest-xdist runs one worker per core: one Numba thread each, not one per core each (a test
    # may still ask for more, up to NUMBA_NUM_THREADS)
    if os.environ.get("PYTEST_XDIST_WORKER"):
        import numba
        numba.set_num_threads(1)
