"""Scenes shared by the training tests of this folder (module scope: made once per test file)."""
import pytest

from run_fixtures import tiny_dynamic_scene


@pytest.fixture(scope="module")
def trusted_scene():
    """The tiny "dynamic" clip with true poses flagged as exact."""
    return tiny_dynamic_scene(trusted=True)


@pytest.fixture(scope="module")
def noisy_scene():
    """The same clip with the preset's noisy poses."""
    return tiny_dynamic_scene(trusted=False)
