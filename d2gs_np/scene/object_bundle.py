"""Object-level bundle adjustment of one tracked mover (``MotionInitConfig.rigid_fit = "bundle"``).

A small mover seen almost affinely shows a turn out of the image plane only as foreshortening over
several frames; two frames hold little of it, and depth maps with a smooth 10 % error tilt a 35 px
object by tens of degrees, anew in every frame (docs/method.md §8). Here the object's pose at every
frame of its track and its shape are fitted together to what the frames saw:

- points: a regular grid of the object's pixels in every frame of the track (its region eroded, see
  ``motion_init._object_region``), each carried ``window`` frames forwards and backwards by the
  track's pair maps (``motion_init._pair_map``), kept while it stays inside the object's region;
- residuals, each in its own unit: the reprojection of every observation (pixels); the log depth of
  the point in each frame's camera against the depth map there (``depth_sigma``, a relative error),
  where the map is within the depth gate (``motion_init.PAIR_DEPTH_GATE``) of its region's median;
  the second difference of the pose path (its turn per frame in degrees over ``accel_deg``, its
  travel per frame over the object's size times the same angle), which holds the frames where the
  track is short;
- the soft-L1 loss (scale 1) over the observations' residuals (flow that slid off a turning face is an
  outlier), plain squares over the path's: a robust loss there would let a track's end turn away;
- unknowns: each member's pose (a left rotation increment and a translation) but the reference
  member's, which fixes the gauge, and every point's position in the object's frame. The scale is
  the depth maps'.

Pure functions on plain arrays: ``bundle_residuals`` and its Jacobian ``bundle_jacobian``
(hand-derived, sparse), ``track_observations`` (from a track's pair maps and regions) and
``bundle_poses``; ``motion_init.bundle_track`` runs them on a track of the library's frames.
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.optimize import least_squares

from d2gs_np.constants import PIXEL_CENTER_OFFSET
from d2gs_np.geometry.camera import unproject_points
from d2gs_np.geometry.so3 import hat, left_jacobian, left_jacobian_inv, right_jacobian_inv, so3_exp, so3_log

BUNDLE_GRID = 60  # points seeded per frame of the track, on a regular grid over the object
BUNDLE_MIN_POINTS = 12  # a track with fewer points seen twice keeps its given poses
BUNDLE_Z_MIN = 1e-6  # camera depths below this fraction of the depth maps' median are clamped (no gradient)
BUNDLE_MAX_NFEV = 200
BUNDLE_BORDER_PX = 3.0  # observations within this of the image's border are dropped


def bundle_residuals(R0, t0, X0, x, obs, cams, depth_sigma, accel_deg, size, ref):
    """Residual vector of the object bundle at the unknowns x.

    R0 (M, 3, 3), t0 (M, 3): the members' poses (object -> world) x is relative to; X0 (P, 3): the
    points in the object frame. x: [rotation increments (F, 3), translation increments (F, 3),
    point increments (P, 3)] for the F = M - 1 members other than ``ref``; R = so3_exp(dphi) R0.
    obs: dict(point (O,), member (O,), uv (O, 2), depth (O,) NaN where not a residual). cams:
    dict(T (M, 4, 4) cam_T_world, K (M, 3, 3), z_min). Returns (2 O + D + 6 (M - 2),) residuals.
    """
    R, t, X, _ = _unpack(R0, t0, X0, x, ref)
    m, p = obs["member"], obs["point"]
    pc, z = _camera_points(R, t, X, m, p, cams)
    K = cams["K"][m]
    u = K[:, 0, 0] * pc[:, 0] / z + K[:, 0, 2]
    v = K[:, 1, 1] * pc[:, 1] / z + K[:, 1, 2]
    r = [np.c_[u - obs["uv"][:, 0], v - obs["uv"][:, 1]].ravel()]
    d = np.isfinite(obs["depth"])
    r.append((np.log(z[d]) - np.log(obs["depth"][d])) / depth_sigma)
    if accel_deg > 0 and len(R) >= 3:
        phi = so3_log(R[1:] @ np.swapaxes(R[:-1], 1, 2))  # (M - 1, 3) turn per step, world frame
        r.append(np.degrees(np.diff(phi, axis=0)).ravel() / accel_deg)
        r.append(np.diff(t, 2, axis=0).ravel() / (size * np.radians(accel_deg)))
    return np.concatenate(r)


def bundle_jacobian(R0, t0, X0, x, obs, cams, depth_sigma, accel_deg, size, ref):
    """Sparse Jacobian (csr) of ``bundle_residuals`` with respect to x (same arguments)."""
    R, t, X, dphi = _unpack(R0, t0, X0, x, ref)
    M, P = len(R), len(X)
    free = np.array([n for n in range(M) if n != ref])
    slot = np.full(M, -1)
    slot[free] = np.arange(len(free))
    F = len(free)
    ncol = 6 * F + 3 * P
    m, p = obs["member"], obs["point"]
    O = len(m)
    pc, z = _camera_points(R, t, X, m, p, cams)
    clamped = pc[:, 2] < cams["z_min"]
    K = cams["K"][m]
    Rc = cams["T"][m, :3, :3]
    # d(u, v)/d(camera point), zero where the depth is clamped
    duv = np.zeros((O, 2, 3))
    duv[:, 0, 0] = K[:, 0, 0] / z
    duv[:, 0, 2] = -K[:, 0, 0] * pc[:, 0] / z ** 2
    duv[:, 1, 1] = K[:, 1, 1] / z
    duv[:, 1, 2] = -K[:, 1, 1] * pc[:, 1] / z ** 2
    duv[clamped] = 0.0
    RX = np.einsum("oij,oj->oi", R[m], X[p])
    Jl = left_jacobian(dphi)  # (M, 3, 3); identity at the reference member (dphi = 0)
    dpc_dphi = -Rc @ hat(RX) @ Jl[m]  # (O, 3, 3)
    dpc_dt = Rc
    dpc_dX = Rc @ R[m]
    rows, cols, vals = [], [], []

    def put(row0, block, col0, free_rows=None):
        # block (n, a, b) at rows row0[:, None] + range(a) and columns col0[:, None] + range(b)
        n, a, b = block.shape
        rr = np.broadcast_to(row0[:, None, None] + np.arange(a)[None, :, None], (n, a, b))
        cc = np.broadcast_to(col0[:, None, None] + np.arange(b)[None, None, :], (n, a, b))
        keep = np.ones(n, bool) if free_rows is None else free_rows
        rows.append(rr[keep].ravel())
        cols.append(cc[keep].ravel())
        vals.append(block[keep].ravel())

    on = slot[m] >= 0
    row_uv = 2 * np.arange(O)
    put(row_uv, duv @ dpc_dphi, 3 * np.maximum(slot[m], 0), on)
    put(row_uv, duv @ dpc_dt, 3 * F + 3 * np.maximum(slot[m], 0), on)
    put(row_uv, duv @ dpc_dX, 6 * F + 3 * p)
    row = 2 * O
    d = np.flatnonzero(np.isfinite(obs["depth"]))
    dz = (~clamped[d])[:, None] / (z[d, None] * depth_sigma)  # d(log z / sigma)/dz
    row_d = row + np.arange(len(d))
    put(row_d, (dz[:, None, :] * dpc_dphi[d, 2:3, :]), 3 * np.maximum(slot[m[d]], 0), on[d])
    put(row_d, (dz[:, None, :] * dpc_dt[d, 2:3, :]), 3 * F + 3 * np.maximum(slot[m[d]], 0), on[d])
    put(row_d, (dz[:, None, :] * dpc_dX[d, 2:3, :]), 6 * F + 3 * p[d])
    row += len(d)
    if accel_deg > 0 and M >= 3:
        phi = so3_log(R[1:] @ np.swapaxes(R[:-1], 1, 2))
        # phi_n = log(R_{n+1} R_n^T): d/d eps_{n+1} = J_l^-1(phi_n), d/d eps_n = -J_r^-1(phi_n), where
        # eps_k = J_l(dphi_k) d dphi_k is member k's left perturbation
        A_next = left_jacobian_inv(phi) @ Jl[1:]
        A_prev = -right_jacobian_inv(phi) @ Jl[:-1]
        scale = np.degrees(1.0) / accel_deg
        n = np.arange(M - 2)
        # a_n = phi_{n+1} - phi_n depends on members n, n + 1, n + 2
        for k, blk in ((n + 2, A_next[1:]), (n + 1, A_prev[1:] - A_next[:-1]), (n, -A_prev[:-1])):
            put(row + 3 * n, scale * blk, 3 * np.maximum(slot[k], 0), slot[k] >= 0)
        row += 3 * (M - 2)
        tscale = 1.0 / (size * np.radians(accel_deg))
        for k, c in ((n, 1.0), (n + 1, -2.0), (n + 2, 1.0)):
            put(row + 3 * n, np.broadcast_to(c * tscale * np.eye(3), (M - 2, 3, 3)).copy(),
                3 * F + 3 * np.maximum(slot[k], 0), slot[k] >= 0)
        row += 3 * (M - 2)
    return sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(row, ncol))


def _soft_l1_first(n):
    """scipy's loss callable: soft-L1 on the first n residuals (the observations), plain squares on the
    rest (the path's smoothness, which a robust loss would let a track's end break)."""
    def loss(z):
        out = np.empty((3, len(z)))
        out[0], out[1], out[2] = z, 1.0, 0.0
        a = z[:n]
        t = np.sqrt(1.0 + a)
        out[0, :n], out[1, :n], out[2, :n] = 2.0 * (t - 1.0), 1.0 / t, -0.5 / (t * (1.0 + a))
        return out
    return loss


def _unpack(R0, t0, X0, x, ref):
    M, P = len(R0), len(X0)
    free = [n for n in range(M) if n != ref]
    F = len(free)
    dphi = np.zeros((M, 3))
    dt = np.zeros((M, 3))
    dphi[free] = x[:3 * F].reshape(F, 3)
    dt[free] = x[3 * F:6 * F].reshape(F, 3)
    R = so3_exp(dphi) @ R0
    return R, t0 + dt, X0 + x[6 * F:].reshape(P, 3), dphi


def _camera_points(R, t, X, m, p, cams):
    Xw = np.einsum("oij,oj->oi", R[m], X[p]) + t[m]
    pc = np.einsum("oij,oj->oi", cams["T"][m, :3, :3], Xw) + cams["T"][m, :3, 3]
    return pc, np.maximum(pc[:, 2], cams["z_min"])


def track_observations(fwd, bwd, regions, depths, window, depth_gate, grid=BUNDLE_GRID):
    """The bundle's points and observations for the M members of one track: fwd / bwd (M - 1) maps of
    (P, 2) pixels from member n to n + 1 and back (``motion_init._pair_map``), regions (M) (H, W) bool
    the object's (eroded) region, depths (M) (H, W) the depth maps (NaN or non-positive where
    unknown), kept within ``depth_gate`` of their region's median. Returns dict(seed_member (P,),
    seed_depth (P,), seed_uv (P, 2), point (O,), member (O,), uv (O, 2), depth (O,) the depth map
    there, NaN outside the gate)."""
    from d2gs_np.scene.initialize import sample_image_bilinear

    M = len(regions)
    maps = [np.nan_to_num(np.asarray(d, np.float64), nan=0.0, posinf=0.0, neginf=0.0)[..., None] for d in depths]
    med = []
    for n in range(M):
        ys, xs = np.nonzero(regions[n])
        dv = sample_image_bilinear(maps[n], np.c_[xs, ys] + PIXEL_CENTER_OFFSET)[:, 0]
        med.append(float(np.median(dv[dv > 0])) if (dv > 0).any() else np.nan)

    def gated(n, uv):
        dz = sample_image_bilinear(maps[n], uv)[:, 0]
        ok = (dz > med[n] / depth_gate) & (dz < depth_gate * med[n])
        return np.where(ok, dz, np.nan)

    seed_member, seed_uv, seed_depth = [], [], []
    point, member, uv = [], [], []
    for n in range(M):
        ys, xs = np.nonzero(regions[n])
        stride = max(1, int(np.ceil(np.sqrt(len(xs) / grid))))
        on = (ys % stride == 0) & (xs % stride == 0)
        px = np.c_[xs[on], ys[on]] + PIXEL_CENTER_OFFSET
        dz = gated(n, px)
        px, dz = px[np.isfinite(dz)], dz[np.isfinite(dz)]  # seeds on the object's own depth only
        ids = len(seed_member) + np.arange(len(px))
        seed_member += [n] * len(px)
        seed_uv.append(px)
        seed_depth.append(dz)
        point.append(ids)
        member.append(np.full(len(ids), n))
        uv.append(px)
        for step in (1, -1):
            cur, cid, k = px, ids, n
            for _ in range(window):
                nk = k + step
                if nk < 0 or nk >= M or not len(cur):
                    break
                cur = (fwd[k] if step == 1 else bwd[nk])(cur)
                h, w = regions[nk].shape
                ok = np.isfinite(cur).all(axis=1)
                # inside the image, off its border: the flow there sees a replicated border, not the object
                ok &= np.all((cur >= BUNDLE_BORDER_PX) & (cur <= np.array([w, h]) - BUNDLE_BORDER_PX), axis=1)
                qi = np.clip(np.floor(np.nan_to_num(cur)).astype(np.int64), 0, [w - 1, h - 1])
                ok &= regions[nk][qi[:, 1], qi[:, 0]]
                cur, cid, k = cur[ok], cid[ok], nk
                point.append(cid)
                member.append(np.full(len(cid), nk))
                uv.append(cur)
    cat = (lambda a, shape: np.concatenate(a) if a else np.zeros(shape))
    out = dict(seed_member=np.asarray(seed_member, np.int64), seed_uv=cat(seed_uv, (0, 2)),
               seed_depth=cat(seed_depth, (0,)), point=cat(point, (0,)).astype(np.int64),
               member=cat(member, (0,)).astype(np.int64), uv=cat(uv, (0, 2)))
    out["depth"] = np.concatenate([gated(n, out["uv"][out["member"] == n]) for n in range(M)]) if len(out["point"]) \
        else np.zeros(0)
    order = np.concatenate([np.flatnonzero(out["member"] == n) for n in range(M)]) if len(out["point"]) \
        else np.zeros(0, np.int64)
    for key in ("point", "member", "uv"):  # in the depth's order (grouped by member)
        out[key] = out[key][order]
    return out


def bundle_poses(cameras, obs, r, poses, depth_sigma, accel_deg, max_nfev=BUNDLE_MAX_NFEV):
    """Object -> world poses [(R, t)] of a track's members refined by the object bundle from
    ``poses`` (the same list, e.g. ``motion_init._chained_poses``' in member order); member r keeps
    its pose. cameras: [(cam_T_world, K)] per member; obs: ``track_observations``'. Returns (poses,
    info dict(points, observations, nfev, rms_px)); the given poses and info["points"] = 0 where the
    track has too few points seen twice or the solve fails."""
    R0 = np.stack([np.asarray(R, np.float64) for R, _ in poses])
    t0 = np.stack([np.asarray(t, np.float64) for _, t in poses])
    info = dict(points=0, observations=0, nfev=0, rms_px=float("nan"))
    if len(poses) < 2 or not len(obs["seed_member"]):
        return list(poses), info
    seen = np.bincount(obs["point"], minlength=len(obs["seed_member"]))
    if int((seen >= 2).sum()) < BUNDLE_MIN_POINTS:
        return list(poses), info
    keep = seen[obs["point"]] >= 2  # a point seen once holds nothing
    renum = np.cumsum(seen >= 2) - 1
    sm = obs["seed_member"][seen >= 2]
    X0 = []
    for i in np.flatnonzero(seen >= 2):
        n = obs["seed_member"][i]
        T, K = cameras[n]
        Xw = unproject_points(obs["seed_uv"][i][None], obs["seed_depth"][i:i + 1], T, K)[0]
        X0.append(R0[n].T @ (Xw - t0[n]))
    X0 = np.stack(X0)
    o = dict(point=renum[obs["point"][keep]], member=obs["member"][keep], uv=obs["uv"][keep],
             depth=obs["depth"][keep])
    cams = dict(T=np.stack([np.asarray(T, np.float64) for T, _ in cameras]),
                K=np.stack([np.asarray(K, np.float64) for _, K in cameras]),
                z_min=BUNDLE_Z_MIN * float(np.nanmedian(obs["seed_depth"])))
    size = float(np.sqrt(np.median(((X0 - np.median(X0, axis=0)) ** 2).sum(axis=1))))
    if not size > 0:
        return list(poses), info
    args = (R0, t0, X0)
    kw = dict(obs=o, cams=cams, depth_sigma=depth_sigma, accel_deg=accel_deg, size=size, ref=r)
    x0 = np.zeros(6 * (len(poses) - 1) + 3 * len(X0))
    robust = 2 * len(o["point"]) + int(np.isfinite(o["depth"]).sum())
    sol = least_squares(lambda x: bundle_residuals(*args, x, **kw), x0, jac=lambda x: bundle_jacobian(*args, x, **kw),
                        loss=_soft_l1_first(robust), x_scale="jac", method="trf", tr_solver="lsmr",
                        max_nfev=max_nfev)
    if not np.all(np.isfinite(sol.x)):
        return list(poses), info
    R, t, _, _ = _unpack(*args, sol.x, r)
    uv = sol.fun[:2 * len(o["point"])].reshape(-1, 2)
    info = dict(points=len(X0), observations=len(o["point"]), nfev=int(sol.nfev),
                rms_px=float(np.sqrt(np.mean((uv ** 2).sum(axis=1)))), seeded=int(len(sm)))
    return [(R[n], t[n]) for n in range(len(R))], info
