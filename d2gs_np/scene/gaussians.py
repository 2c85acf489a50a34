"""Gaussian scene parameters: static and dynamic sets as named, unconstrained blocks.

The trainable state of a scene is a plain ``dict[str, np.ndarray]`` of C-contiguous blocks whose
keys are also the optimizer's labels (docs/method.md §2):

    static.means (Ns, 3)            static.log_scales (Ns, 3)      static.quats (Ns, 4) raw wxyz
    static.opacity_logits (Ns,)     static.colors (Ns, 3)
    dynamic.<the same five> (Nd rows)
    dynamic.deform_means (Nd, K, 3) dynamic.deform_quats (Nd, K, 4) dynamic.deform_colors (Nd, K, 3)

with K = P + 2L (``DeformConfig.num_coefs``). A scene whose movers are tracked as rigid objects
(``MotionInitConfig.rigid``, ``scene/rigid.py``) also has one rigid path per cluster and each dynamic
Gaussian's cluster:

    rigid.means (C, 3)  rigid.quats (C, 4) raw wxyz  rigid.deform_means (C, K, 3)  rigid.deform_quats (C, K, 4)
    dynamic.cluster (Nd,)  integer ids stored as floats, -1 (no cluster) or 0..C-1; not trained

The static keys are always present (possibly with
0 rows). A scene without moving pixels has *no* ``dynamic.*`` keys (docs/method.md §9); a dynamic set
pruned down to 0 rows keeps its keys with 0 rows, so optimizer state stays in step.

Activations are explicit: scales = exp(log_scales), opacities = sigmoid(opacity_logits). Colours
are plain RGB (no SH), stored as they are used. Quaternions are stored raw; the renderer
normalises them (docs/conventions.md §1).

All blocks of one params dict share one float dtype (float64 by default, float32 opt-in).
"""
from __future__ import annotations

import numbers

import numpy as np
from scipy.spatial import cKDTree

from d2gs_np.constants import INIT_DIST2_MIN
from d2gs_np.scene.config import DeformConfig

__all__ = [
    "STATIC",
    "DYNAMIC",
    "GAUSSIAN_FIELDS",
    "DEFORM_FIELDS",
    "sigmoid",
    "logit",
    "opacity_fwd",
    "opacity_bwd",
    "scale_fwd",
    "scale_bwd",
    "neighbour_log_scales",
    "make_gaussians",
    "init_params",
    "validate_params",
    "has_dynamic",
    "num_static",
    "num_dynamic",
    "prune",
    "select_rows",
    "append_gaussians",
    "RIGID",
    "RIGID_FIELDS",
    "CLUSTER",
    "has_rigid",
    "num_clusters",
    "SCENE_PREFIXES",
]

STATIC = "static"
DYNAMIC = "dynamic"
GAUSSIAN_FIELDS = ("means", "log_scales", "quats", "opacity_logits", "colors")
DEFORM_FIELDS = ("deform_means", "deform_quats", "deform_colors")
RIGID = "rigid"  # the clusters' rigid paths (scene/rigid.py)
RIGID_FIELDS = ("means", "quats", "deform_means", "deform_quats")
CLUSTER = f"{DYNAMIC}.cluster"  # each dynamic Gaussian's cluster id
SCENE_PREFIXES = (f"{STATIC}.", f"{DYNAMIC}.", f"{RIGID}.")  # the blocks that make the scene (not the camera's)
_RIGID_TRAILING = {"means": (3,), "quats": (4,), "deform_means": ("K", 3), "deform_quats": ("K", 4)}
# Trailing shape of each field (after the row axis); "K" is the number of deformation coefficients.
_TRAILING = {
    "means": (3,),
    "log_scales": (3,),
    "quats": (4,),
    "opacity_logits": (),
    "colors": (3,),
    "deform_means": ("K", 3),
    "deform_quats": ("K", 4),
    "deform_colors": ("K", 3),
    "cluster": (),
}


def _fields(prefix, clustered=False):
    """The fields of one set; the dynamic set's ``cluster`` only in a scene with rigid clusters."""
    return GAUSSIAN_FIELDS + ((DEFORM_FIELDS + (("cluster",) if clustered else ())) if prefix == DYNAMIC else ())


# ---------------------------------------------------------------------------------------------
# Activations
# ---------------------------------------------------------------------------------------------


def sigmoid(x):
    """1 / (1 + exp(-x)), evaluated without overflow for any finite x; keeps the dtype."""
    x = np.asarray(x)
    e = np.exp(-np.abs(x))  # in (0, 1]: never overflows
    return np.where(x >= 0, 1.0 / (1.0 + e), e / (1.0 + e)).astype(x.dtype, copy=False)


def logit(p):
    """Inverse of ``sigmoid``: log(p / (1 - p)) for p in (0, 1); keeps the dtype."""
    p = np.asarray(p)
    if not np.all((p > 0.0) & (p < 1.0)):
        raise ValueError("logit needs probabilities strictly inside (0, 1); clip them first")
    return np.log(p) - np.log1p(-p)


def opacity_fwd(opacity_logits):
    """Opacities o = sigmoid(logits) (N,), and the saved output for the backward."""
    o = sigmoid(opacity_logits)
    return o, o


def opacity_bwd(saved, v_opacities):
    """v_logits = v_o * o (1 - o) (N,)."""
    o = saved
    return v_opacities * (o * (1.0 - o))


def scale_fwd(log_scales):
    """Linear scales exp(log_scales) (N, 3), and the saved output for the backward."""
    s = np.exp(log_scales)
    return s, s


def scale_bwd(saved, v_scales):
    """v_log_scales = v_scales * exp(log_scales) (N, 3)."""
    return v_scales * saved


# ---------------------------------------------------------------------------------------------
# Construction
# ---------------------------------------------------------------------------------------------


def neighbour_log_scales(points, num_neighbours=3, isolated_scale=0.01):
    """Isotropic initial log-scales from the local point density, as 3DGS does.

    points (N, 3). Each point gets log(sqrt(mean squared distance to its ``num_neighbours``
    nearest other points)), the squared distance clamped below at INIT_DIST2_MIN (3DGS's
    ``clamp_min(distCUDA2(...), 1e-7)``), repeated on the 3 axes -> (N, 3). With fewer than
    ``num_neighbours`` other points the available ones are used; a lone point gets
    log(isolated_scale).
    """
    points = np.asarray(points)
    N = points.shape[0]
    dtype = points.dtype
    if N <= 1:
        return np.full((N, 3), np.log(isolated_scale), dtype=dtype)
    k = min(num_neighbours, N - 1)
    dist, _ = cKDTree(points.astype(np.float64)).query(points.astype(np.float64), k=k + 1)
    dist2 = np.maximum(np.mean(dist[:, 1:] ** 2, axis=1), INIT_DIST2_MIN)  # column 0 is the point itself
    return np.repeat((0.5 * np.log(dist2))[:, None], 3, axis=1).astype(dtype)


def _check_float_array(name, x, dtype=None):
    if not isinstance(x, np.ndarray):
        raise TypeError(f"{name} must be a numpy array; got {type(x).__name__}")
    if x.dtype not in (np.float64, np.float32):
        raise TypeError(f"{name} must be float64 or float32; got {x.dtype}")
    if dtype is not None and x.dtype != dtype:
        raise TypeError(f"{name} has dtype {x.dtype}, expected {dtype} like the other blocks; cast to one dtype")
    if not np.all(np.isfinite(x)):
        raise ValueError(f"{name} contains NaN or inf; every entry must be finite")


def _shape_text(field):
    dims = ("N",) + tuple(str(d) for d in _TRAILING[field])
    return "(" + ", ".join(dims) + ("," if len(dims) == 1 else "") + ")"


def make_gaussians(prefix, means, log_scales, quats, opacity_logits, colors, deform_means=None,
                   deform_quats=None, deform_colors=None, cluster=None):
    """Validated, C-contiguous blocks of one Gaussian set, keyed ``f"{prefix}.{field}"``.

    prefix: "static" or "dynamic".
    means (N, 3), log_scales (N, 3), quats (N, 4) raw wxyz, opacity_logits (N,), colors (N, 3).
    deform_means (N, K, 3), deform_quats (N, K, 4), deform_colors (N, K, 3): required for the
    dynamic set, not allowed for the static one.
    cluster (N,): the dynamic rows' cluster ids (scene with rigid clusters only), or None.
    Returns a new dict; the arrays are copies.
    """
    if prefix not in (STATIC, DYNAMIC):
        raise ValueError(f"prefix must be {STATIC!r} or {DYNAMIC!r}; got {prefix!r}")
    blocks = dict(means=means, log_scales=log_scales, quats=quats, opacity_logits=opacity_logits, colors=colors)
    deform = dict(deform_means=deform_means, deform_quats=deform_quats, deform_colors=deform_colors)
    if prefix == DYNAMIC:
        missing = [k for k, v in deform.items() if v is None]
        if missing:
            raise ValueError(f"the dynamic set needs deformation coefficients; missing {missing}")
        blocks.update(deform)
        if cluster is not None:
            blocks["cluster"] = cluster
    elif cluster is not None:
        raise ValueError("only the dynamic set has clusters; pass cluster only with prefix='dynamic'")
    elif any(v is not None for v in deform.values()):
        raise ValueError("the static set has no deformation; pass deform_* only with prefix='dynamic'")
    _check_float_array(f"{prefix}.means", means)
    dtype = means.dtype
    N = means.shape[0] if means.ndim == 2 else -1
    K = deform_means.shape[1] if prefix == DYNAMIC and getattr(deform_means, "ndim", 0) == 3 else -1
    out = {}
    for field, x in blocks.items():
        name = f"{prefix}.{field}"
        _check_float_array(name, x, dtype)
        shape = (N,) + tuple(K if s == "K" else s for s in _TRAILING[field])
        if x.shape != shape or N < 0:
            raise ValueError(f"{name} must have shape {_shape_text(field)}; got {x.shape}")
        out[name] = np.ascontiguousarray(x).copy()
    return out


def init_params(static_means, static_colors, dynamic_means=None, dynamic_colors=None,
                deform_config=DeformConfig(), rng=None, init_opacity=0.1, deform_init_std=0.0,
                isolated_scale=0.01):
    """Initial scene parameters from point positions and colours.

    static_means (Ns, 3), static_colors (Ns, 3): initial static points (RGB in [0, 1]).
    dynamic_means (Nd, 3), dynamic_colors (Nd, 3): initial dynamic points, or None for a scene
        without moving pixels (then no ``dynamic.*`` keys are created).
    deform_config: DeformConfig, fixes K for the coefficient blocks.
    rng: np.random.Generator; used only when deform_init_std > 0.
    init_opacity: initial opacity of every Gaussian (3DGS uses 0.1); stored as its logit.
    deform_init_std: standard deviation of the initial deformation coefficients (0: all zero, so
        the deformation starts as the identity map; the gradient w.r.t. the coefficients is not
        zero there, so zero is a valid start).
    isolated_scale: scale of a point with no neighbour at all.

    Scales: isotropic, sqrt of the mean squared distance to the 3 nearest neighbours among *all*
    initial points (static and dynamic together), as 3DGS. Quaternions: identity (1, 0, 0, 0).
    The dtype is that of ``static_means``; every array argument must share it.
    """
    _check_float_array("static_means", static_means)
    dtype = static_means.dtype
    if static_means.ndim != 2 or static_means.shape[1] != 3:
        raise ValueError(f"static_means must have shape (N, 3); got {static_means.shape}")
    if not isinstance(deform_config, DeformConfig):
        raise TypeError(f"deform_config must be a DeformConfig; got {type(deform_config).__name__}")
    if not (isinstance(init_opacity, numbers.Real) and 0.0 < init_opacity < 1.0):
        raise ValueError(f"init_opacity must be in (0, 1); got {init_opacity!r}")
    if not (isinstance(deform_init_std, numbers.Real) and deform_init_std >= 0.0):
        raise ValueError(f"deform_init_std must be >= 0; got {deform_init_std!r}")
    if deform_init_std > 0.0 and not isinstance(rng, np.random.Generator):
        raise TypeError("deform_init_std > 0 needs rng=np.random.default_rng(seed)")
    if (dynamic_means is None) != (dynamic_colors is None):
        raise ValueError("pass both dynamic_means and dynamic_colors, or neither")

    sets = [(STATIC, static_means, static_colors)]
    if dynamic_means is not None:
        _check_float_array("dynamic_means", dynamic_means, dtype)
        if dynamic_means.ndim != 2 or dynamic_means.shape[1] != 3:
            raise ValueError(f"dynamic_means must have shape (N, 3); got {dynamic_means.shape}")
        sets.append((DYNAMIC, dynamic_means, dynamic_colors))
    all_points = np.concatenate([s[1] for s in sets], axis=0)
    all_log_scales = neighbour_log_scales(all_points, isolated_scale=isolated_scale)
    opacity_logit = float(logit(np.float64(init_opacity)))

    params = {}
    start = 0
    for prefix, means, colors in sets:
        N = means.shape[0]
        log_scales = all_log_scales[start:start + N]
        start += N
        quats = np.zeros((N, 4), dtype=dtype)
        quats[:, 0] = 1.0
        extra = {}
        if prefix == DYNAMIC:
            K = deform_config.num_coefs
            for field, D in (("deform_means", 3), ("deform_quats", 4), ("deform_colors", 3)):
                if deform_init_std > 0.0:
                    extra[field] = (deform_init_std * rng.standard_normal((N, K, D))).astype(dtype)
                else:
                    extra[field] = np.zeros((N, K, D), dtype=dtype)
        if not isinstance(colors, np.ndarray) or colors.shape != (N, 3):
            shape = getattr(colors, "shape", type(colors).__name__)
            raise ValueError(f"{prefix}_colors must have shape ({N}, 3) like {prefix}_means; got {shape}")
        params.update(make_gaussians(prefix, means, log_scales, quats, np.full(N, opacity_logit, dtype=dtype),
                                     colors, **extra))
    return params


# ---------------------------------------------------------------------------------------------
# Queries and checks
# ---------------------------------------------------------------------------------------------


def has_dynamic(params):
    """True when the scene has a dynamic set (possibly with 0 rows)."""
    return f"{DYNAMIC}.means" in params


def has_rigid(params):
    """True when the scene's movers are rigid clusters (``rigid.*`` blocks, ``scene/rigid.py``)."""
    return f"{RIGID}.means" in params


def num_clusters(params):
    """Number of rigid clusters (0 without them)."""
    return params[f"{RIGID}.means"].shape[0] if has_rigid(params) else 0


def num_static(params):
    """Number of static Gaussians."""
    return params[f"{STATIC}.means"].shape[0]


def num_dynamic(params):
    """Number of dynamic Gaussians (0 when the scene has no dynamic set)."""
    return params[f"{DYNAMIC}.means"].shape[0] if has_dynamic(params) else 0


def validate_params(params, deform_config=None):
    """Raise a clear error unless ``params`` follows the block layout of this module.

    Checks: a dict; exactly the expected keys (the static five, and either all or none of the
    dynamic eight); numpy float arrays of one dtype; shapes consistent within each set; C order;
    finite entries; and, when ``deform_config`` is given, K == deform_config.num_coefs.
    """
    if not isinstance(params, dict):
        raise TypeError(f"params must be a dict of arrays; got {type(params).__name__}")
    expected = {f"{STATIC}.{f}" for f in _fields(STATIC)}
    clustered = any(k.startswith(f"{RIGID}.") for k in params) or CLUSTER in params
    dynamic_keys = {f"{DYNAMIC}.{f}" for f in _fields(DYNAMIC, clustered)}
    if any(k in params for k in dynamic_keys) or clustered:
        expected |= dynamic_keys
    if clustered:
        expected |= {f"{RIGID}.{f}" for f in RIGID_FIELDS}
    missing, unexpected = sorted(expected - params.keys()), sorted(params.keys() - expected)
    if missing or unexpected:
        raise ValueError(f"params keys do not follow the scene layout: missing {missing}, unexpected {unexpected}")
    dtype = None
    for prefix in (STATIC, DYNAMIC) if has_dynamic(params) else (STATIC,):
        means = params[f"{prefix}.means"]
        _check_float_array(f"{prefix}.means", means, dtype)
        dtype = means.dtype
        N = means.shape[0] if means.ndim == 2 else -1
        K = -1
        if prefix == DYNAMIC:
            dm = params[f"{DYNAMIC}.deform_means"]
            K = dm.shape[1] if getattr(dm, "ndim", 0) == 3 else -1
            if deform_config is not None and K != deform_config.num_coefs:
                raise ValueError(
                    f"dynamic.deform_means has K={K} coefficients but deform_config expects "
                    f"{deform_config.num_coefs} (P={deform_config.degree}, L={deform_config.order})"
                )
        for field in _fields(prefix, clustered):
            name = f"{prefix}.{field}"
            x = params[name]
            _check_float_array(name, x, dtype)
            shape = (N,) + tuple(K if s == "K" else s for s in _TRAILING[field])
            if x.shape != shape or N < 0 or (K == -1 and prefix == DYNAMIC):
                raise ValueError(
                    f"{name} must have shape {_shape_text(field)} with N = rows of {prefix}.means; got {x.shape}"
                )
            if not x.flags.c_contiguous:
                raise ValueError(f"{name} must be C-contiguous; use np.ascontiguousarray")
    if clustered:
        _validate_rigid(params, dtype, K)


def _validate_rigid(params, dtype, K):
    """The rigid blocks' shapes (C rows, the dynamic set's K) and the cluster ids' range."""
    C = params[f"{RIGID}.means"].shape[0] if params[f"{RIGID}.means"].ndim == 2 else -1
    for field in RIGID_FIELDS:
        name = f"{RIGID}.{field}"
        x = params[name]
        _check_float_array(name, x, dtype)
        shape = (C,) + tuple(K if s == "K" else s for s in _RIGID_TRAILING[field])
        if C < 0 or x.shape != shape:
            dims = ", ".join(("C",) + tuple(str(d) for d in _RIGID_TRAILING[field]))
            raise ValueError(f"{name} must have shape ({dims}) with C = rows of {RIGID}.means and K = the "
                             f"dynamic set's; got {x.shape}")
        if not x.flags.c_contiguous:
            raise ValueError(f"{name} must be C-contiguous; use np.ascontiguousarray")
    ids = params[CLUSTER]
    if np.any(ids != np.round(ids)) or np.any(ids < -1) or np.any(ids > C - 1):
        bad = ids[(ids != np.round(ids)) | (ids < -1) | (ids > C - 1)][:3]
        raise ValueError(f"{CLUSTER} must hold whole numbers from -1 (no cluster) to {C - 1} (C = {C} clusters); "
                         f"got {bad.tolist()}")


# ---------------------------------------------------------------------------------------------
# Pruning and densification
# ---------------------------------------------------------------------------------------------


def _check_mask(name, mask, n):
    mask = np.asarray(mask)
    if mask.dtype != np.bool_:
        raise TypeError(f"{name} must be a boolean array; got dtype {mask.dtype}")
    if mask.shape != (n,):
        raise ValueError(f"{name} must have shape ({n},) (one flag per Gaussian of the set); got {mask.shape}")
    return mask


def prune(params, keep_static, keep_dynamic=None):
    """A new params dict keeping the rows flagged True.

    keep_static (Ns,) bool; keep_dynamic (Nd,) bool, or None to keep the whole dynamic set (and
    required to be None for a scene without one). A dynamic set pruned to 0 rows keeps its keys.
    Use ``d2gs_np.optim.adam_select`` with the same masks to keep the optimizer state in step.
    """
    keep_static = _check_mask("keep_static", keep_static, num_static(params))
    if keep_dynamic is not None:
        if not has_dynamic(params):
            raise ValueError("keep_dynamic given but the scene has no dynamic set; pass keep_dynamic=None")
        keep_dynamic = _check_mask("keep_dynamic", keep_dynamic, num_dynamic(params))
    out = select_rows(params, STATIC, keep_static)
    return out if keep_dynamic is None else select_rows(out, DYNAMIC, keep_dynamic)


def select_rows(params, prefix, keep):
    """A new params dict keeping the rows flagged True of one set (``prefix`` "static" or
    "dynamic"); the other set's blocks are shared, not copied. ``keep`` (N_set,) bool."""
    if prefix not in (STATIC, DYNAMIC):
        raise ValueError(f"prefix must be {STATIC!r} or {DYNAMIC!r}; got {prefix!r}")
    n = num_static(params) if prefix == STATIC else num_dynamic(params)
    mask = _check_mask("keep", keep, n)
    out = dict(params)
    for field in _fields(prefix, CLUSTER in params):
        name = f"{prefix}.{field}"
        out[name] = np.ascontiguousarray(params[name][mask])
    return out


def append_gaussians(params, new):
    """A new params dict with the rows of ``new`` appended to their sets (for densification).

    new: dict of blocks keyed like ``params`` (e.g. from ``make_gaussians``), holding every field
    of each set it extends; it may create the dynamic set when ``params`` has none. Blocks must
    have the dtype and trailing shape of the existing ones. Use ``d2gs_np.optim.adam_extend``
    to give the optimizer zero moments for the new rows.
    """
    if not isinstance(new, dict):
        raise TypeError(f"new must be a dict of arrays; got {type(new).__name__}")
    out = dict(params)
    dtype = params[f"{STATIC}.means"].dtype
    prefixes = {k.split(".", 1)[0] for k in new}
    unknown = prefixes - {STATIC, DYNAMIC}
    if unknown:
        raise ValueError(f"new has blocks of unknown sets {sorted(unknown)}; keys must start with 'static.' or 'dynamic.'")
    for prefix in sorted(prefixes):
        clustered = prefix == DYNAMIC and CLUSTER in params
        fields = _fields(prefix, clustered)
        names = [f"{prefix}.{f}" for f in fields]
        if clustered and CLUSTER not in new:
            # rows seeded in world coordinates (not cloned from a cluster's rows): no cluster
            new = {**new, CLUSTER: np.full(len(new[f"{prefix}.means"]), -1.0, dtype=dtype)}
        missing = sorted(set(names) - new.keys())
        unexpected = sorted({k for k in new if k.startswith(prefix + ".")} - set(names))
        if missing or unexpected:
            raise ValueError(f"new {prefix} rows need exactly the fields {names}: missing {missing}, unexpected {unexpected}")
        add = make_gaussians(prefix, **{f: new[f"{prefix}.{f}"] for f in fields})
        for name in names:
            _check_float_array(name, add[name], dtype)
            if name in params:
                if add[name].shape[1:] != params[name].shape[1:]:
                    raise ValueError(
                        f"new {name} has trailing shape {add[name].shape[1:]}, existing rows have {params[name].shape[1:]}"
                    )
                out[name] = np.concatenate([params[name], add[name]], axis=0)
            else:
                out[name] = add[name]
    return out
