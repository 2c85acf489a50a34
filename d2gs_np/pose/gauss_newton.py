"""Pose refinement by Gauss-Newton / Levenberg-Marquardt on reprojection residuals (docs/method.md §5).

Unknowns. Every frame k has its exposure endpoints ``T_s,k``, ``T_e,k`` (cam_T_world). The solver
perturbs them on the LEFT (docs/method.md §4, ``geometry/se3.py``): ``exp(a_k) T_s,k`` and
``exp(b_k) T_e,k`` with ``x_k = (a_k, b_k)``, 12 numbers, each tangent (rho, phi) translation
first. ``x`` is the total perturbation from the endpoints the problem was built with (no
re-linearisation on the manifold), so the residual function of ``x`` is one fixed function that
``scipy.optimize.least_squares`` can minimise too (the cross-check). The residuals see only the
mid pose ``M_k = T_s exp(log(T_s^-1 T_e) / 2)`` (geodesic midpoint), so:

- the spread ``b_k - a_k`` is held by a prior residual ``(b_k - a_k) / spread_sigma`` (6 rows);
- the gauge (a global rigid motion, and the scale the depths fix only softly) is held by keeping
  the frames in ``fixed`` (frame 0 by default) out of the unknowns;
- optionally (``PoseProblem.prior_poses``), each free frame's mid pose is held near a given pose
  G_k (the poses the video came with) by 6 rows ``(c(M_k) - c(G_k)) / sigma_t`` (camera centres)
  and ``log(R(M_k) R(G_k)^T) / sigma_r`` (rotation), the maximum a posteriori form of "the given
  poses are right to about sigma". Why (docs/method.md §5): without it the depths of a partly
  trained scene, biased low by semi-transparent Gaussians, pulled the cameras together call after
  call, while the centre-aligned ATE, blind to it, fell (docs/results.md §11);
- Levenberg-Marquardt damping makes every step solvable even where the data leave directions
  unobserved (a frame without matches, matches on a line, points at infinity).

Residuals of a match p (frame k) <-> p' (frame j), Eq. 10 written as a cycle: lift p' with the
rendered depth ``D_j(p')`` in camera j, map to the world with ``M_j``, into camera k with ``M_k``,
project with K_k to p'' at camera depth ``z_k(p'')``::

    r_pix   = p'' - p                                  (2 rows, pixels)
    r_depth = beta (z_k(p'') - D_k(p)) / D_k(p)        (1 row)

``beta`` (``GaussNewtonConfig.beta``) weighs a relative depth error against pixels; the paper's
100 makes a 1 % depth error cost as much as a 1 px reprojection error. Depths are constants of
the problem (read from a render at the current mid poses, refreshed between solver calls).

The mid poses, the match residuals and the prior rows, with their exact Jacobians, are CasADi
functions (``pose/symbolic.py``); the chain rule dr/dx_k = dr/dM_k dM_k/dx_k is one matrix product
per match.

Robust loss and damping (IRLS; ``pose/lm.py``, shared with the bundle adjustment). Each data
residual r_i (not the prior rows) carries rho(r) = r^2/2 (``none``), Huber
``r^2/2 if |r| <= d else d|r| - d^2/2`` or Cauchy ``d^2/2 log(1 + (r/d)^2)``, with
d = ``robust_scale``; elementwise, as ``least_squares``'s ``loss="huber"`` / ``"cauchy"`` with
``f_scale = d`` (``lm.robust_cost``). Each iteration solves the weighted normal equations
``(H + lam D) dx = -g``, ``H = J^T W J``, ``g = J^T W r``, W the IRLS weights (``rho'(r)/r``),
D = diag(H) floored at ``DAMPING_DIAG_FLOOR`` x max(max diag(H), 1) (Marquardt scaling that still
damps a column without data). A step is accepted only if the robust cost decreases
(``lm.accept_step``), so the cost never rises; lam shrinks by ``damping_down`` after an accepted
step and grows by ``damping_up`` after a rejected one, within [LM_DAMPING_MIN, LM_DAMPING_MAX]
(``lm.FixedFactors``; the system is solved as (H/lam + D) dx = -g/lam once lam > 1, so a huge lam
stays finite and gives a tiny step). Stops when the relative cost decrease of an accepted step
falls below ``ftol``, when the step is below ``xtol`` (relative to |x|), at ``max_iters``, or when
lam reaches its limit.

Covariance. At the end, ``pinv(H)`` of the final normal equations (unit residual variance, prior
rows included) over the free unknowns, with its numerical rank (singular values above
``COVARIANCE_RCOND`` x the largest): a rank below 12 x (free frames) names unobserved directions.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
from numba import njit

from d2gs_np.constants import COVARIANCE_RCOND, DAMPING_DIAG_FLOOR, GN_MIN_DEPTH
from d2gs_np.geometry.se3 import check_rigid
from d2gs_np.geometry.sampling import bilinear_fwd
from d2gs_np.pose.config import GaussNewtonConfig
from d2gs_np.pose.linalg import cholesky_solve
from d2gs_np.pose.lm import FixedFactors, accept_step, at_damping_limit, damping_start, finite_or_inf, robust_cost
from d2gs_np.pose.symbolic import NUM_VARS, flat_to_pose, mapped, pose_to_flat

__all__ = [
    "PairObservations",
    "PoseProblem",
    "GaussNewtonResult",
    "sample_depth",
    "pair_observations",
    "solve",
]


# ---------------------------------------------------------------------------------------------
# Problem assembly
# ---------------------------------------------------------------------------------------------


def sample_depth(depth_map, pts):
    """Bilinear read of an (H, W) depth map at (M, 2) points in our pixel convention (centres at
    +0.5); points outside the image give NaN. Returns (M,). (``geometry.sampling.bilinear_fwd``,
    which L_reproj differentiates.)"""
    return bilinear_fwd(np.asarray(depth_map, dtype=np.float64), pts)[0]


@dataclass
class PairObservations:
    """Matches of frame k with frame j and the rendered depths at them (valid ones only)."""

    k: int
    j: int
    pts_k: np.ndarray  # (M, 2)
    pts_j: np.ndarray  # (M, 2)
    depth_k: np.ndarray  # (M,) D_k(p) > GN_MIN_DEPTH
    depth_j: np.ndarray  # (M,) D_j(p')
    dropped: int = 0  # matches dropped for a zero, negative, non-finite or out-of-image depth


def pair_observations(k, j, pts_k, pts_j, depth_k, depth_j) -> PairObservations:
    """Observations of one pair; matches whose depth (either side) is not finite and above
    GN_MIN_DEPTH are dropped (a render with nothing there, or a point behind the camera), and
    counted in ``dropped``. depth_k, depth_j: (M,) depths at the points, or (H, W) depth maps
    (then read bilinearly at the points)."""
    pts_k = np.asarray(pts_k, dtype=np.float64).reshape(-1, 2)
    pts_j = np.asarray(pts_j, dtype=np.float64).reshape(-1, 2)
    if pts_k.shape != pts_j.shape:
        raise ValueError(f"pts_k and pts_j must both be (M, 2); got {pts_k.shape} and {pts_j.shape}")
    dk = np.asarray(depth_k, dtype=np.float64)
    dj = np.asarray(depth_j, dtype=np.float64)
    dk = sample_depth(dk, pts_k) if dk.ndim == 2 else dk.reshape(-1)
    dj = sample_depth(dj, pts_j) if dj.ndim == 2 else dj.reshape(-1)
    if dk.shape != (len(pts_k),) or dj.shape != (len(pts_k),):
        raise ValueError(f"depth_k and depth_j must be (M,) = ({len(pts_k)},) or (H, W) maps; got {np.shape(depth_k)} "
                         f"and {np.shape(depth_j)}")
    with np.errstate(invalid="ignore"):
        ok = np.isfinite(dk) & np.isfinite(dj) & (dk > GN_MIN_DEPTH) & (dj > GN_MIN_DEPTH) \
            & np.isfinite(pts_k).all(1) & np.isfinite(pts_j).all(1)
    return PairObservations(int(k), int(j), pts_k[ok], pts_j[ok], dk[ok], dj[ok], int((~ok).sum()))


@dataclass
class PoseProblem:
    """The endpoints to refine, the intrinsics and the observations (module docstring)."""

    starts: np.ndarray  # (N, 4, 4) exposure-start cam_T_world
    ends: np.ndarray  # (N, 4, 4) exposure-end cam_T_world
    Ks: np.ndarray  # (N, 3, 3)
    pairs: list  # list[PairObservations]
    fixed: tuple = (0,)  # frames held fixed (the gauge)
    prior_poses: np.ndarray = None  # (N, 4, 4) cam_T_world the free mid poses are held near; None: no prior
    prior_sigma: tuple = (1.0, 1.0)  # (sigma_t world units, sigma_r radians) of the prior rows

    def __post_init__(self):
        for name in ("starts", "ends"):
            T = np.ascontiguousarray(getattr(self, name), dtype=np.float64)
            if T.ndim != 3 or T.shape[1:] != (4, 4):
                raise ValueError(f"PoseProblem.{name} must be (N, 4, 4) cam_T_world poses; got {T.shape}")
            check_rigid(T, f"PoseProblem.{name}")
            setattr(self, name, T)
        N = len(self.starts)
        if self.ends.shape[0] != N:
            raise ValueError(f"PoseProblem.starts and ends must have the same N; got {N} and {len(self.ends)}")
        self.Ks = np.ascontiguousarray(self.Ks, dtype=np.float64)
        if self.Ks.shape != (N, 3, 3) or not np.all(np.isfinite(self.Ks)):
            raise ValueError(f"PoseProblem.Ks must be finite (N, 3, 3) = ({N}, 3, 3); got {self.Ks.shape}")
        self.fixed = tuple(int(f) for f in self.fixed)
        if any(not 0 <= f < N for f in self.fixed):
            raise ValueError(f"PoseProblem.fixed must hold frame indices in [0, {N}); got {self.fixed}")
        for p in self.pairs:
            if not isinstance(p, PairObservations):
                raise TypeError(f"PoseProblem.pairs must hold PairObservations (pair_observations); got "
                                f"{type(p).__name__}")
            if not (0 <= p.k < N and 0 <= p.j < N) or p.k == p.j:
                raise ValueError(f"PoseProblem: pair ({p.k}, {p.j}) must name two different frames in [0, {N})")
        if self.prior_poses is not None:
            G = np.ascontiguousarray(self.prior_poses, dtype=np.float64)
            if G.shape != (N, 4, 4):
                raise ValueError(f"PoseProblem.prior_poses must be (N, 4, 4) = ({N}, 4, 4) cam_T_world poses; got "
                                 f"{G.shape}")
            check_rigid(G, "PoseProblem.prior_poses")
            self.prior_poses = G
            sig = tuple(float(v) for v in self.prior_sigma)
            if len(sig) != 2 or not all(math.isfinite(v) and v > 0 for v in sig):
                raise ValueError(f"PoseProblem.prior_sigma must be two finite numbers > 0 (sigma_t in world units, "
                                 f"sigma_r in radians); got {self.prior_sigma!r}")
            self.prior_sigma = sig
        self.free = np.array([k for k in range(N) if k not in self.fixed], dtype=np.int64)
        self._build_obs()

    @property
    def num_frames(self) -> int:
        return len(self.starts)

    @property
    def num_params(self) -> int:
        return NUM_VARS * len(self.free)

    @property
    def num_matches(self) -> int:
        return int(self._ks.shape[0])

    @property
    def dropped(self) -> int:
        return int(sum(p.dropped for p in self.pairs))

    def _build_obs(self):
        pairs = [p for p in self.pairs if len(p.pts_k)]
        if pairs:
            self._ks = np.concatenate([np.full(len(p.pts_k), p.k) for p in pairs])
            self._js = np.concatenate([np.full(len(p.pts_k), p.j) for p in pairs])
            obs = np.concatenate([np.column_stack([p.pts_k, p.pts_j, p.depth_k, p.depth_j]) for p in pairs])
        else:
            self._ks = self._js = np.zeros(0, dtype=np.int64)
            obs = np.zeros((0, 6))
        intr = np.stack([self.Ks[:, 0, 0], self.Ks[:, 1, 1], self.Ks[:, 0, 2], self.Ks[:, 1, 2]], axis=1)  # (N, 4)
        self._cam = np.concatenate([intr[self._ks], intr[self._js]], axis=1)  # (M, 8)
        self._obs = obs
        self._flat_s = pose_to_flat(self.starts)
        self._flat_e = pose_to_flat(self.ends)

    # ------------------------------------------------------------------ evaluation
    def full_x(self, x_free):
        """(12 F,) unknowns of the free frames -> (N, 12) with zeros for the fixed ones."""
        x = np.zeros((self.num_frames, NUM_VARS))
        x[self.free] = np.asarray(x_free, dtype=np.float64).reshape(len(self.free), NUM_VARS)
        return x

    def poses(self, x_free):
        """(starts, ends, mids) (N, 4, 4) each at the unknowns x."""
        x = self.full_x(x_free)
        f = mapped("mid", self.num_frames)
        mid, _, s, e = f(x.T, self._flat_s.T, self._flat_e.T)
        return flat_to_pose(np.array(s).T), flat_to_pose(np.array(e).T), flat_to_pose(np.array(mid).T)

    @property
    def num_prior_rows(self) -> int:
        """Rows of the pose prior: 6 per free frame when ``prior_poses`` is given, else 0."""
        return 0 if self.prior_poses is None else 6 * len(self.free)

    def residuals(self, x_free, beta, spread_sigma, jacobian=True):
        """Residual vector and its Jacobian at x: (r (3M + 6F + P,), J (3M + 6F + P, 12F) or None).
        Rows: 3 per match (u, v, depth) in match order, then 6 spread-prior rows per free frame,
        then (with ``prior_poses``) P = 6 pose-prior rows per free frame."""
        N, F, M, P = self.num_frames, len(self.free), self.num_matches, self.num_prior_rows
        x = self.full_x(x_free)
        mid, dmid, _, _ = mapped("mid", N)(x.T, self._flat_s.T, self._flat_e.T)
        mid = np.array(mid).T  # (N, 12)
        dmid = np.array(dmid).reshape(12, N, 12).transpose(1, 0, 2)  # (N, 12 out, 12 in)
        xf = x[self.free]
        prior = (xf[:, 6:] - xf[:, :6]) / spread_sigma  # (F, 6)
        r = np.empty(3 * M + 6 * F + P)
        r[3 * M:3 * M + 6 * F] = prior.reshape(-1)
        if P:
            sig = np.tile(np.asarray(self.prior_sigma, dtype=np.float64)[:, None], (1, F))
            rp, jp = mapped("prior", F)(mid[self.free].T, pose_to_flat(self.prior_poses[self.free]).T, sig)
            r[3 * M + 6 * F:] = np.array(rp).T.reshape(-1)
        J = None
        if M:
            obs = np.concatenate([self._obs, np.full((M, 1), float(beta))], axis=1)
            rr, jk, jj = mapped("match", M)(mid[self._ks].T, mid[self._js].T, self._cam.T, obs.T)
            r[:3 * M] = np.array(rr).T.reshape(-1)
        if not jacobian:
            return r, None
        col = np.full(N, -1, dtype=np.int64)
        col[self.free] = np.arange(F)
        J = np.zeros((3 * M + 6 * F + P, NUM_VARS * F))
        if M:
            jk = np.array(jk).reshape(3, M, 12).transpose(1, 0, 2)  # (M, 3, 12) dr/dM_k
            jj = np.array(jj).reshape(3, M, 12).transpose(1, 0, 2)
            gk = np.einsum("mab,mbc->mac", jk, dmid[self._ks])  # (M, 3, 12) dr/dx_k
            gj = np.einsum("mab,mbc->mac", jj, dmid[self._js])
            rows = np.arange(3 * M).reshape(M, 3)
            for g, frames in ((gk, self._ks), (gj, self._js)):
                c = col[frames]
                keep = c >= 0
                ri = rows[keep][:, :, None]  # (m, 3, 1)
                ci = (NUM_VARS * c[keep])[:, None, None] + np.arange(12)[None, None, :]  # (m, 1, 12)
                J[ri, ci] = g[keep]
        eye = np.eye(6) / spread_sigma
        for i in range(F):
            J[3 * M + 6 * i:3 * M + 6 * i + 6, NUM_VARS * i:NUM_VARS * i + 6] = -eye
            J[3 * M + 6 * i:3 * M + 6 * i + 6, NUM_VARS * i + 6:NUM_VARS * i + 12] = eye
        if P:
            jp = np.array(jp).reshape(6, F, 12).transpose(1, 0, 2)  # (F, 6, 12) dr/dM
            gp = np.einsum("fab,fbc->fac", jp, dmid[self.free])  # (F, 6, 12) dr/dx
            base = 3 * M + 6 * F
            for i in range(F):
                J[base + 6 * i:base + 6 * i + 6, NUM_VARS * i:NUM_VARS * i + 12] = gp[i]
        return r, J


# ---------------------------------------------------------------------------------------------
# The solver
# ---------------------------------------------------------------------------------------------


def _cost(problem, r, config):
    """The robust cost of the data rows plus the plain squares of the prior rows (+inf if not finite),
    and the IRLS weight of every row (1 on the prior rows)."""
    n = 3 * problem.num_matches
    data, w = robust_cost(r[:n], config.robust, config.robust_scale)
    with np.errstate(over="ignore", invalid="ignore"):
        total = data + 0.5 * float(np.sum(r[n:] ** 2))
    return finite_or_inf(total), np.concatenate([w, np.ones(len(r) - n)])


@dataclass
class GaussNewtonResult:
    status: str  # converged_cost | converged_step | max_iters | damping_limit | no_unknowns
    x: np.ndarray  # (N, 12) endpoint perturbations (a, b) found; zeros for fixed frames
    starts: np.ndarray  # (N, 4, 4) refined exposure starts exp(a) T_s
    ends: np.ndarray  # (N, 4, 4) refined exposure ends exp(b) T_e
    mids: np.ndarray  # (N, 4, 4) their geodesic midpoints
    costs: list  # robust cost: initial, then after every iteration
    times: list  # wall seconds since the start, at each entry of costs
    damping: list  # lambda after every iteration
    iterations: int
    accepted: int
    covariance: np.ndarray  # (12F, 12F) pinv of the final normal matrix
    rank: int  # numerical rank of the final normal matrix
    num_params: int  # 12 F
    num_matches: int
    dropped: int  # matches dropped for invalid depths (PoseProblem.dropped)
    free: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))

    @property
    def wall_time(self) -> float:
        return self.times[-1] if self.times else 0.0


@njit(cache=True)
def _normal_equations_kernel(J, w, r):
    """H = J^T W J, g = J^T W r over the non-zero entries of each row (a match row touches at
    most 24 columns, a prior row 2), in a fixed order."""
    n_rows, n = J.shape
    H = np.zeros((n, n))
    g = np.zeros(n)
    cols = np.empty(n, dtype=np.int64)
    for i in range(n_rows):
        m = 0
        for c in range(n):
            if J[i, c] != 0.0:
                cols[m] = c
                m += 1
        wi = w[i]
        for a in range(m):
            ca_ = cols[a]
            va = wi * J[i, ca_]
            g[ca_] += va * r[i]
            for b in range(m):
                H[ca_, cols[b]] += va * J[i, cols[b]]
    return H, g


def _normal_equations(J, w, r):
    """H = J^T W J, g = J^T W r (a Numba loop over the sparse rows: LAPACK/BLAS calls on these
    small matrices cost far more than their arithmetic where the cores are shared)."""
    return _normal_equations_kernel(np.ascontiguousarray(J), np.ascontiguousarray(w), np.ascontiguousarray(r))


def _solve_damped(H, g, lam):
    """dx of (H + lam D) dx = -g, D = diag(H) floored; scaled by 1/lam when lam > 1 so that a huge
    lam never overflows. The matrix is symmetric positive definite (H is PSD, D > 0): Cholesky."""
    d = np.diag(H).copy()
    d = np.maximum(d, DAMPING_DIAG_FLOOR * max(float(d.max(initial=0.0)), 1.0))
    if lam > 1.0:
        A, b = H / lam + np.diag(d), -g / lam
    else:
        A, b = H + lam * np.diag(d), -g
    dx, ok = cholesky_solve(np.ascontiguousarray(A), np.ascontiguousarray(b))
    if not ok or not np.all(np.isfinite(dx)):
        dx = np.linalg.lstsq(A, b, rcond=None)[0]
    return dx


def _covariance(H):
    """(pinv(H), numerical rank) from one symmetric eigendecomposition."""
    if H.size == 0:
        return np.zeros((0, 0)), 0
    s, V = np.linalg.eigh(0.5 * (H + H.T))
    top = float(np.max(np.abs(s)))
    keep = s > COVARIANCE_RCOND * top if top > 0 else np.zeros(len(s), dtype=bool)
    inv = np.where(keep, 1.0 / np.where(keep, s, 1.0), 0.0)
    return (V * inv) @ V.T, int(keep.sum())


def solve(problem: PoseProblem, config: GaussNewtonConfig = None, x0=None) -> GaussNewtonResult:
    """Levenberg-Marquardt with IRLS on the problem's residuals (module docstring). x0: optional
    (12 F,) start (default 0: the endpoints the problem was built with)."""
    config = GaussNewtonConfig() if config is None else config
    if not isinstance(config, GaussNewtonConfig):
        raise TypeError(f"config must be a GaussNewtonConfig; got {type(config).__name__}")
    if not isinstance(problem, PoseProblem):
        raise TypeError(f"problem must be a PoseProblem; got {type(problem).__name__}")
    t0 = time.perf_counter()
    n = problem.num_params
    x = np.zeros(n) if x0 is None else np.array(x0, dtype=np.float64).reshape(-1)
    if x.shape != (n,) or not np.all(np.isfinite(x)):
        raise ValueError(f"x0 must be a finite ({n},) vector (12 per free frame); got shape {x.shape}")
    args = (config.beta, config.spread_sigma)
    r, J = problem.residuals(x, *args)
    cost, w = _cost(problem, r, config)
    if not math.isfinite(cost):
        raise ValueError("the initial residuals are not finite (a lifted point behind a camera?); check the poses "
                         "and depths the problem was built with")
    costs, times, damping = [cost], [time.perf_counter() - t0], []
    damp, schedule = damping_start(config.damping_init), FixedFactors(config.damping_up, config.damping_down)
    status, iters, accepted = ("no_unknowns" if n == 0 else "max_iters"), 0, 0
    while n and iters < config.max_iters:
        iters += 1
        H, g = _normal_equations(J, w, r)
        step_ok = False
        while True:
            dx = _solve_damped(H, g, damp.lam)
            x_new = x + dx
            r_new, J_new = problem.residuals(x_new, *args)
            cost_new, w_new = _cost(problem, r_new, config)
            if accept_step(cost, cost_new):
                step_ok = True
                damp = schedule.accepted(damp)
                break
            if at_damping_limit(damp):
                break
            damp = schedule.rejected(damp)
        damping.append(damp.lam)
        if not step_ok:
            costs.append(cost)
            times.append(time.perf_counter() - t0)
            status = "damping_limit"
            break
        accepted += 1
        decrease = (cost - cost_new) / max(cost, np.finfo(float).tiny)
        x, r, J, cost, w = x_new, r_new, J_new, cost_new, w_new
        costs.append(cost)
        times.append(time.perf_counter() - t0)
        if decrease < config.ftol:
            status = "converged_cost"
            break
        if np.linalg.norm(dx) < config.xtol * (np.linalg.norm(x) + config.xtol):
            status = "converged_step"
            break
    cov, rank = _covariance(_normal_equations(J, w, r)[0])
    starts, ends, mids = problem.poses(x)
    times[-1] = time.perf_counter() - t0
    return GaussNewtonResult(status=status, x=problem.full_x(x), starts=starts, ends=ends, mids=mids, costs=costs,
                             times=times, damping=damping, iterations=iters, accepted=accepted, covariance=cov,
                             rank=rank, num_params=n, num_matches=problem.num_matches, dropped=problem.dropped,
                             free=problem.free.copy())
