"""Load a script of examples/ as a module, for the tests of tests/examples/ (importable from
tests/, see conftest.py)."""
import importlib.util
from pathlib import Path

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def load_example(file_name, module_name=None):
    """The module of ``examples/<file_name>`` (not run as a script: its ``main`` is not called)."""
    spec = importlib.util.spec_from_file_location(module_name or Path(file_name).stem, EXAMPLES / file_name)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod
