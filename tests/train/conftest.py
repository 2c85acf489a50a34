"""Scenes shared by the training tests of this folder (module scope: made once per test file)."""
import pytest

from d2gs_np.data.synthetic import make_scene
from run_fixtures import tiny_dynamic_scene

TINY = dict(width=48, height=27, num_frames=6)  # the regularisers' tests (a file may define its own)


@pytest.fixture(scope="module")
def trusted_scene():
    """The tiny "dynamic" clip with true poses flagged as exact."""
    return tiny_dynamic_scene(trusted=True)


@pytest.fixture(scope="module")
def noisy_scene():
    """The same clip with the preset's noisy poses."""
    return tiny_dynamic_scene(trusted=False)


@pytest.fixture(scope="module")
def dynamic_scene():
    """The synthetic "dynamic" preset at 48x27, 6 frames."""
    return make_scene("dynamic", 0, **TINY)


@pytest.fixture(scope="module")
def static_scene():
    """The synthetic "static" preset (no moving pixels) at 48x27, 6 frames."""
    return make_scene("static", 0, **TINY)
