"""``d2gs refcheck gsplat``: gsplat 1.5.3's PyTorch reference on the render cases (docs/refcheck.md §7).

Optional: needs ``torch`` and ``gsplat==1.5.3`` (the ``gsplat`` extra), imported lazily; CPU,
float64 (or float32 on request), autograd for every gradient (independent of our hand-derived
backward).

What runs is gsplat's own pure-PyTorch code wherever it runs on a CPU:
``_quat_scale_to_covar_preci`` (covariance), ``_fully_fused_projection`` (world to camera, EWA
projection with the clamped Jacobian, eps2d dilation, conics, radii, culling, antialiasing
compensation) and ``_isect_tiles`` (tile lists sorted by tile and float32 depth bits). gsplat's
torch rasterizer (``_rasterize_to_pixels``) cannot run on a CPU: it calls the CUDA kernel
``rasterize_to_indices_in_range`` and the ``nerfacc`` package. The per-pixel compositing is
therefore written here in torch, from the rules of gsplat's CUDA rasterizer as
docs/conventions.md §6 states them (alpha = min(0.999, o exp(-sigma)); skip when sigma < 0 or
alpha < 1/255; stop, exclusively, when T (1 - alpha) <= 1e-4), over each tile's sorted list
from ``_isect_tiles``; its gradients come from autograd.

The blur case renders each virtual view this way; its virtual poses come from a small torch
SE(3) (exp, log, inverse) written here from docs/method.md §4, so the endpoint gradients are
autograd's, independent of our hand-derived Jacobians. The deformation case has no gsplat
counterpart and is not run.
"""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from d2gs_np import constants as C
from d2gs_np.geometry.se3 import matrix_grad_to_left_tangent
from d2gs_np.refcheck.io import case_path, read_case, read_index, write_results

__all__ = ["GsplatUnavailable", "gsplat_status", "run_gsplat"]

GSPLAT_VERSION = "1.5.3"


class GsplatUnavailable(RuntimeError):
    """torch or gsplat cannot be imported (the message says why and how to install them)."""


def _import():
    try:
        import torch
    except Exception as e:  # ImportError, or a broken install raising OSError
        raise GsplatUnavailable(f"torch cannot be imported ({type(e).__name__}: {e}); install the optional "
                                f"extra with: pip install -e '.[gsplat]' (torch and gsplat=={GSPLAT_VERSION})") from e
    try:
        import gsplat
        from gsplat.cuda import _torch_impl as impl
    except Exception as e:
        raise GsplatUnavailable(f"gsplat cannot be imported ({type(e).__name__}: {e}); install it with: "
                                f"pip install gsplat=={GSPLAT_VERSION}") from e
    version = getattr(gsplat, "__version__", "unknown")
    if version != GSPLAT_VERSION:
        raise GsplatUnavailable(f"gsplat {version} is installed; the conventions followed are those of "
                                f"{GSPLAT_VERSION} (docs/conventions.md): pip install gsplat=={GSPLAT_VERSION}")
    return torch, impl


def gsplat_status():
    """(True, version text) when torch and gsplat import, else (False, the reason)."""
    try:
        torch, _ = _import()
    except GsplatUnavailable as e:
        return False, str(e)
    return True, f"torch {torch.__version__}, gsplat {GSPLAT_VERSION}"


def _composite(torch, means2d, conics, opacities, colors, depths, offsets, flatten_ids, width, height,
               tile_size):
    """Front-to-back compositing of one camera (autograd through every kept term).

    means2d (N,2), conics (N,3), opacities (N,), colors (N,3), depths (N,) tensors; offsets
    (th, tw) start of each tile's run in flatten_ids (sorted by tile, then float32 depth).
    Returns image (H,W,3) without background, depth (H,W), T_final (H,W).
    """
    dt = means2d.dtype
    th, tw = offsets.shape
    n_isect = flatten_ids.shape[0]
    starts = offsets.reshape(-1).tolist()
    ends = starts[1:] + [n_isect]
    rgb_rows, d_rows, t_rows = [], [], []
    img = [[None] * tw for _ in range(th)]
    for ty in range(th):
        for tx in range(tw):
            x0, y0 = tx * tile_size, ty * tile_size
            x1, y1 = min(x0 + tile_size, width), min(y0 + tile_size, height)
            ys, xs = torch.meshgrid(torch.arange(y0, y1, dtype=dt), torch.arange(x0, x1, dtype=dt), indexing="ij")
            px = torch.stack([xs.reshape(-1), ys.reshape(-1)], -1) + C.PIXEL_CENTER_OFFSET  # (P, 2)
            t = ty * tw + tx
            ids = flatten_ids[starts[t]:ends[t]].long()
            P = px.shape[0]
            if ids.numel() == 0:
                img[ty][tx] = (torch.zeros(P, 3, dtype=dt), torch.zeros(P, dtype=dt), torch.ones(P, dtype=dt))
                continue
            d = px[None, :, :] - means2d[ids][:, None, :]  # (M, P, 2): pixel - mean (sigma is even in d)
            c = conics[ids]
            sigma = (0.5 * (c[:, 0:1] * d[..., 0] ** 2 + c[:, 2:3] * d[..., 1] ** 2)
                     + c[:, 1:2] * d[..., 0] * d[..., 1])
            alpha = torch.clamp_max(opacities[ids][:, None] * torch.exp(-sigma), C.ALPHA_MAX)  # (M, P)
            with torch.no_grad():  # the discrete decisions, held fixed in the backward
                valid = (sigma >= 0) & (alpha >= C.ALPHA_THRESHOLD)
                a_eff = torch.where(valid, alpha, torch.zeros_like(alpha))
                T_after = torch.cumprod(1 - a_eff, dim=0)
                stop = valid & (T_after <= C.TRANSMITTANCE_MIN)
                stopped_before = (torch.cumsum(stop.to(torch.int64), dim=0) - stop.to(torch.int64)) > 0
                keep = valid & ~stop & ~stopped_before
            a = torch.where(keep, alpha, torch.zeros_like(alpha))
            T_incl = torch.cumprod(1 - a, dim=0)
            T_excl = torch.cat([torch.ones(1, P, dtype=dt), T_incl[:-1]], 0)
            w = a * T_excl  # (M, P)
            rgb = w.T @ colors[ids]  # (P, 3)
            dep = w.T @ depths[ids]
            img[ty][tx] = (rgb, dep, T_incl[-1])
    for ty in range(th):
        rows_rgb, rows_d, rows_t = [], [], []
        for tx in range(tw):
            x0, y0 = tx * tile_size, ty * tile_size
            h, w_ = min(tile_size, height - y0), min(tile_size, width - x0)
            rgb, dep, T = img[ty][tx]
            rows_rgb.append(rgb.reshape(h, w_, 3))
            rows_d.append(dep.reshape(h, w_))
            rows_t.append(T.reshape(h, w_))
        rgb_rows.append(torch.cat(rows_rgb, 1))
        d_rows.append(torch.cat(rows_d, 1))
        t_rows.append(torch.cat(rows_t, 1))
    return torch.cat(rgb_rows, 0), torch.cat(d_rows, 0), torch.cat(t_rows, 0)


def _render_view(torch, impl, g, viewmat, K, inp):
    """One view with gsplat's projection and tile lists and the torch compositing.

    g: dict of leaf tensors (means, quats, scales, opacities, colors, backgrounds (1,3)).
    viewmat: (1,4,4) tensor (a leaf or a function of leaves), K: (1,3,3).
    Returns (image, alpha, depth, expected_depth) (H,W,3)/(H,W) tensors and the projection
    (radii, means2d, depths, conics) with a camera axis of 1.
    """
    W, H, ts = int(inp["width"]), int(inp["height"]), int(inp["tile_size"])
    aa = bool(inp["antialiased"])
    covars, _ = impl._quat_scale_to_covar_preci(g["quats"], g["scales"], compute_covar=True, compute_preci=False)
    radii, means2d, depths, conics, comp = impl._fully_fused_projection(
        g["means"], covars, viewmat, K, W, H, eps2d=float(inp["eps2d"]), near_plane=float(inp["near_plane"]),
        far_plane=float(inp["far_plane"]), calc_compensations=aa)
    means2d.retain_grad()
    opac = g["opacities"][None] * comp if aa else g["opacities"][None].expand(1, -1)
    tw, th = -(-W // ts), -(-H // ts)
    _, isect_ids, flatten_ids = impl._isect_tiles(means2d.detach(), radii, depths.detach(), ts, tw, th)
    offsets = impl._isect_offset_encode(isect_ids, 1, tw, th)[0]
    rgb, dep, T = _composite(torch, means2d[0], conics[0], opac[0], g["colors"], depths[0], offsets, flatten_ids,
                             W, H, ts)
    image = rgb + T[..., None] * g["backgrounds"][0]
    alpha = 1 - T
    ed = dep / torch.clamp_min(alpha, C.EXPECTED_DEPTH_ALPHA_MIN)
    return (image, alpha, dep, ed), (radii, means2d, depths, conics)


def _leaves(torch, inp, names, dtype):
    tdt = torch.float64 if np.dtype(dtype) == np.float64 else torch.float32
    return {k: torch.tensor(np.asarray(inp[k], dtype), dtype=tdt, requires_grad=True) for k in names}


def _loss(torch, cot, dtype, image, alpha, dep, ed):
    t = lambda k: torch.tensor(np.asarray(cot[k], dtype))  # noqa: E731
    return ((t("image")[0] * image).sum() + (t("alpha")[0, ..., 0] * alpha).sum()
            + (t("depth")[0, ..., 0] * dep).sum() + (t("expected_depth")[0, ..., 0] * ed).sum())


def _image_outputs(image, alpha, dep, ed):
    return {"image": image.detach().numpy()[None], "alpha": alpha.detach().numpy()[None, ..., None],
            "depth": dep.detach().numpy()[None, ..., None], "expected_depth": ed.detach().numpy()[None, ..., None]}


def _grad(x, dtype):
    return np.zeros(tuple(x.shape), dtype) if x.grad is None else x.grad.numpy().copy()


_GAUSSIANS = ("means", "quats", "scales", "opacities", "colors")


def _run_render_case(torch, impl, inp, cot, dtype=np.float64):
    g = _leaves(torch, inp, _GAUSSIANS + ("viewmats", "backgrounds"), dtype)
    K = torch.tensor(np.asarray(inp["Ks"], dtype))
    (image, alpha, dep, ed), (radii, means2d, depths, conics) = _render_view(torch, impl, g, g["viewmats"], K, inp)
    _loss(torch, cot, dtype, image, alpha, dep, ed).backward()
    culled = (radii[0] <= 0).any(-1).numpy()
    m2d, con = means2d.detach().numpy().copy(), conics.detach().numpy().copy()
    m2d[0, culled] = 0.0  # our convention (docs/conventions.md §4): culled Gaussians report 0
    con[0, culled] = 0.0
    outputs = _image_outputs(image, alpha, dep, ed)
    outputs.update(radii=radii.numpy().astype(np.int32), means2d=m2d, depths=depths.detach().numpy(), conics=con)
    G = _grad(g["viewmats"], dtype)
    grads = {k: _grad(g[k], dtype) for k in _GAUSSIANS}
    grads.update(viewmats=G, backgrounds=_grad(g["backgrounds"], dtype), means2d=_grad(means2d, dtype),
                 viewmats_tangent=matrix_grad_to_left_tangent(np.asarray(inp["viewmats"][0], dtype).astype(np.float64),
                                                              G[0].astype(np.float64))[None])
    return outputs, grads


# --- SE(3) in torch, for the blur case (written from docs/method.md §4's formulas; autograd
# differentiates it, independently of our hand-derived endpoint Jacobians) ---------------------


def _hat(torch, w):
    z = torch.zeros((), dtype=w.dtype)
    return torch.stack([torch.stack([z, -w[2], w[1]]), torch.stack([w[2], z, -w[0]]),
                        torch.stack([-w[1], w[0], z])])


def _se3_exp(torch, xi):
    """exp of xi = (rho, phi): [[Exp(phi), V(phi) rho], [0, 1]]. The coefficients are functions
    of theta^2 with a Taylor branch below theta = 1e-3 (remainder ~theta^6 < 1e-18; the virtual
    pose at u = 0 is exactly exp(0)), and 1 - cos = 2 sin^2(theta / 2) against cancellation."""
    rho, phi = xi[:3], xi[3:]
    th2 = (phi * phi).sum()
    small = th2 < 1e-6
    th2s = torch.where(small, torch.ones_like(th2), th2)
    th = torch.sqrt(th2s)
    a = torch.where(small, 1 - th2 / 6 + th2**2 / 120, torch.sin(th) / th)
    b = torch.where(small, 0.5 - th2 / 24 + th2**2 / 720, 2 * torch.sin(th / 2) ** 2 / th2s)
    c = torch.where(small, 1.0 / 6 - th2 / 120 + th2**2 / 5040, (th - torch.sin(th)) / (th2s * th))
    Wm = _hat(torch, phi)
    I3 = torch.eye(3, dtype=xi.dtype)
    R = I3 + a * Wm + b * Wm @ Wm
    V = I3 + b * Wm + c * Wm @ Wm
    top = torch.cat([R, (V @ rho)[:, None]], 1)
    return torch.cat([top, torch.tensor([[0.0, 0.0, 0.0, 1.0]], dtype=xi.dtype)], 0)


def _se3_log(torch, T):
    """log of a rigid T with rotation angle in (0, pi) (the case's endpoints differ by ~1e-2 rad)."""
    R, t = T[:3, :3], T[:3, 3]
    v = torch.stack([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    s = torch.linalg.norm(v) / 2  # sin(theta)
    c = (torch.diagonal(R).sum() - 1) / 2  # cos(theta)
    th = torch.atan2(s, c)
    phi = th / (2 * s) * v
    Wm = _hat(torch, phi)
    I3 = torch.eye(3, dtype=T.dtype)
    one_minus_c = 2 * torch.sin(th / 2) ** 2  # no cancellation near theta = 0
    Vinv = I3 - 0.5 * Wm + (1 - th * s / (2 * one_minus_c)) / th**2 * Wm @ Wm
    return torch.cat([Vinv @ t, phi])


def _se3_inv(torch, T):
    R, t = T[:3, :3], T[:3, 3]
    top = torch.cat([R.T, (-R.T @ t)[:, None]], 1)
    return torch.cat([top, torch.tensor([[0.0, 0.0, 0.0, 1.0]], dtype=T.dtype)], 0)


def _run_blur_case(torch, impl, inp, cot, dtype=np.float64):
    """The mean of n renders at T_i = A exp(u_i log(A^-1 B)) T_hat, A = exp(xi_start), B = exp(xi_end)."""
    g = _leaves(torch, inp, _GAUSSIANS + ("xi_start", "xi_end", "backgrounds"), dtype)
    K = torch.tensor(np.asarray(inp["Ks"], dtype))
    T_hat = torch.tensor(np.asarray(inp["viewmats"][0], dtype))
    n = int(inp["num_virtual"])
    A, B = _se3_exp(torch, g["xi_start"]), _se3_exp(torch, g["xi_end"])
    delta = _se3_log(torch, _se3_inv(torch, A) @ B)
    poses, sums = [], None
    for i in range(n):
        T_i = A @ _se3_exp(torch, (i / (n - 1)) * delta) @ T_hat if n > 1 else T_hat.clone().requires_grad_(True)
        T_i.retain_grad()
        poses.append(T_i)
        outs, _ = _render_view(torch, impl, g, T_i[None], K, inp)
        sums = list(outs) if sums is None else [a + b for a, b in zip(sums, outs)]
    image, alpha, dep, ed = (x / n for x in sums)
    _loss(torch, cot, dtype, image, alpha, dep, ed).backward()
    outputs = _image_outputs(image, alpha, dep, ed)
    outputs["viewmats_virtual"] = np.stack([T.detach().numpy() for T in poses])
    tangents = [matrix_grad_to_left_tangent(T.detach().numpy().astype(np.float64), _grad(T, dtype).astype(np.float64))
                for T in poses]
    grads = {k: _grad(g[k], dtype) for k in _GAUSSIANS + ("xi_start", "xi_end")}
    grads["virtual_tangents"] = np.stack(tangents)
    return outputs, grads


_RUNNERS = {"render": _run_render_case, "blur": _run_blur_case}


def run_gsplat(export_dir, out_dir, cases=None, dtype="float64", log=print):
    """Run gsplat's reference on the render cases of an export; write their results to out_dir.

    dtype: "float64" (default: the reference) or "float32" (gsplat's torch code in float32, a
    float32 implementation to hold to the float32 tolerances).
    Returns the names of the cases run (render and blur; deformation cases are listed as not covered).
    Raises GsplatUnavailable (before any work) when torch or gsplat cannot be imported.
    """
    index = read_index(export_dir)
    if str(dtype) not in ("float64", "float32"):
        raise ValueError(f"dtype must be 'float64' or 'float32'; got {dtype!r}")
    torch, impl = _import()
    names = [e["name"] for e in index["cases"]]
    for name in cases or ():
        if name not in names:
            raise ValueError(f"case {name!r} is not in {export_dir}; it has: {', '.join(names)}")
    Path(out_dir).mkdir(parents=True, exist_ok=True)
    done = []
    for entry in index["cases"]:
        name = entry["name"]
        if cases and name not in cases:
            continue
        if entry["kind"] not in _RUNNERS:
            if log:
                log(f"[refcheck gsplat] {name}: not covered (gsplat has no {entry['kind']} model)")
            continue
        t0 = time.perf_counter()
        data = read_case(case_path(export_dir, name))
        outputs, grads = _RUNNERS[entry["kind"]](torch, impl, data["in"], data["cot"], np.dtype(str(dtype)))
        write_results(out_dir, name, outputs, grads)
        done.append(name)
        if log:
            log(f"[refcheck gsplat] {name}: ran in {time.perf_counter() - t0:.1f}s")
    return done
