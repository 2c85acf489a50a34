"""Reference-check kit for faster implementations (docs/refcheck.md).

``export`` writes named golden cases (inputs in gsplat's layout, the upstream gradient, our
outputs and every gradient) as ``NAME.npz`` + ``cases.json``; ``compare_dirs`` checks another
implementation's results for the same cases; ``run`` evaluates an export with our own code;
``gsplat_runner`` (optional, needs torch and gsplat) runs gsplat's PyTorch reference on it.
"""
from d2gs_np.refcheck.cases import CASES, DEFAULT_CASES, Case, build_case
from d2gs_np.refcheck.compare import compare_dirs, default_rtol, format_table, parse_rtol
from d2gs_np.refcheck.compute import compute
from d2gs_np.refcheck.export import export, run
from d2gs_np.refcheck.io import read_case, read_index

__all__ = ["CASES", "DEFAULT_CASES", "Case", "build_case", "compare_dirs", "default_rtol", "format_table",
           "parse_rtol", "compute", "export", "run", "read_case", "read_index"]
