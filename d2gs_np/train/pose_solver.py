"""The "pose_solver" step plugin: Gauss-Newton pose refinement between Adam steps (docs/method.md §5).

Every ``pose_solver.every`` schedule steps (``entered_period``, so it follows a time budget), if at
least ``pose_solver.min_steps`` real steps passed since the previous call (or the start):

1. correspondences of the video (``correspond.py``), computed on the first call and cached in the
   run folder (a resumed run reads the file); the per-pair report goes to the run log once;
2. fresh depths: the expected depth of a sharp render of the STATIC set at every involved
   frame's current mid-exposure pose (``Model.mid_pose``), at ``render_scale`` of the frame size;
   pixels the static set covers with alpha below POSE_DEPTH_ALPHA_MIN give no depth (their
   matches are dropped and counted);
3. the solver (``pose/gauss_newton.py``) over the exposure endpoints of every frame, frame 0
   fixed, with a prior on the poses training started from (``Model.start_poses``: the given
   poses or their bundle adjustment, ``pose_init.py``);
   a converged solve is then checked against KLT point tracks (computed once per run, no
   rendered depth): if its poses raise the tracks' reprojection RMS by more than
   ``track_tolerance`` it is not written (``track_check``);
4. the update. The refined mid pose M'_k is written into the reference pose ``poses_ref`` and
   the endpoint perturbations stay relative to it: with the blur model the endpoints are
   ``exp(xi_s) T̂``, ``exp(xi_e) T̂`` and their geodesic midpoint is ``C_k T̂`` with
   ``C_k = mid(exp(xi_s), exp(xi_e))`` (the midpoint is right-invariant), so
   ``T̂'_k = C_k^-1 M'_k`` moves the mid pose to M'_k exactly and keeps the spread the endpoints
   had (the solver's prior held it too). Without the blur model ``T̂'_k = M'_k``. With the
   ``posenet`` trajectory model the network reads log T̂ as input, so its endpoints move a
   little with T̂ and the written mid pose is M'_k only to first order; the ``direct`` model
   (the default) is exact;
5. the Adam moments (m, v) of the changed rows of ``camera.xi_start`` / ``camera.xi_end`` are
   reset to zero (they were accumulated for the old reference pose; the rows' step counts,
   which drive the bias correction and the learning-rate decay, are kept);
6. ``Model.validate`` on the written model, and a run-log line: cost before and after,
   iterations, status, matches used and dropped, the covariance rank, wall time, and ATE before
   and after when the scene has true poses.

Its state (the history of calls) is checkpointed through ``state_dict``; everything else it
uses is recomputed deterministically, so a resumed run is exact.
"""
from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from d2gs_np.geometry import trajectory
from d2gs_np.blur import endpoints as traj_model
from d2gs_np.constants import POSE_DEPTH_ALPHA_MIN
from d2gs_np.pose.correspond import correspondences
from d2gs_np.geometry.camera import camera_center, scale_intrinsics
from d2gs_np.geometry.se3 import se3_exp, se3_interpolate, se3_inverse
from d2gs_np.pose import gauss_newton as gn
from d2gs_np.pose.config import THEN_WITHOUT_SOLVER
from d2gs_np.pose.given import track_reprojection_rms
from d2gs_np.render.api import _render_fwd
from d2gs_np.scene.gaussians import STATIC
from d2gs_np.scene.render_inputs import _render_inputs_fwd
from d2gs_np.train.checkpoint import atomic_write_text
from d2gs_np.train.config import ExperimentConfig
from d2gs_np.train.plugins import Plugin
from d2gs_np.train.state import TrainState, entered_period
from d2gs_np.pose.tracks import klt_tracks

__all__ = ["PoseSolver", "use_pose_solver", "static_depth", "write_mid_poses", "hold_trajectory_scale",
           "HISTORY_FILE"]

HISTORY_FILE = "pose_solver.json"


def use_pose_solver(scene, config: ExperimentConfig, note=None, adjusted_then: str = "") -> bool:
    """Whether a run has the pose solver (``PoseSolverConfig.mode``), saying why in the log.
    ``adjusted_then``: what refines the run's start poses when they are a kept bundle adjustment
    (``PoseInitConfig.then``; "" when they are the given poses)."""
    say = note if note is not None else (lambda m: None)
    pc = config.pose_solver
    if pc.mode == "off":
        say("pose solver: off (config pose_solver.mode = off)")
        return False
    if pc.mode == "on":
        say(f"pose solver: on (config pose_solver.mode = on), every {pc.every} steps")
        return True
    if getattr(scene, "poses_trusted", None):
        say("pose solver: left out (the scene flags its poses as exact: poses_trusted)")
        return False
    if adjusted_then in THEN_WITHOUT_SOLVER:
        how = "held as exact" if adjusted_then == "hold" else "refined by Adam alone"
        say(f"pose solver: left out (the bundle adjustment was kept and its poses are {how}: "
            f"pose_init.then = {adjusted_then})")
        return False
    if config.train.iters <= max(pc.every, pc.min_steps):
        say(f"pose solver: left out (a run of {config.train.iters} steps ends before its first call at step "
            f"{max(pc.every, pc.min_steps)}; set pose_solver.every and min_steps lower or mode = on)")
        return False
    say(f"pose solver: on (poses not flagged exact), every {pc.every} steps")
    return True


def static_depth(model, k: int, pose, scale: float = 1.0):
    """(H', W') expected depth of a sharp render of the static set at ``pose`` for frame k's time
    and intrinsics at ``scale`` of its size; NaN where the static alpha < POSE_DEPTH_ALPHA_MIN."""
    w = max(1, int(round(model.widths[k] * scale)))
    h = max(1, int(round(model.heights[k] * scale)))
    K = scale_intrinsics(model.Ks[k], w / model.widths[k], h / model.heights[k])
    scene = {n: v for n, v in model.params.items() if n.startswith(f"{STATIC}.")}
    ri, _ = _render_inputs_fwd(scene, float(model.times[k]), model.config.deform)
    out, _ = _render_fwd(ri["means"], ri["quats"], ri["scales"], ri["opacities"], ri["colors"],
                         np.asarray(pose, dtype=np.float64), K, w, h, model.background, model.config.render)
    return np.where(out["alpha"] >= POSE_DEPTH_ALPHA_MIN, out["expected_depth"], np.nan)


# Solver statuses whose result the plugin writes (PoseSolverConfig.accept = "converged").
CONVERGED = ("converged_cost", "converged_step")

class PoseSolver(Plugin):
    name = "pose_solver"

    def __init__(self, scene, config: ExperimentConfig, run_dir=None, note=None):
        self.config, self.pc = config, config.pose_solver
        self.images = [f.image for f in scene.frames]
        self.masks = [f.mask for f in scene.frames]
        self.gt = np.stack([f.gt_cam_T_world for f in scene.frames]) if scene.has_gt_poses and \
            scene.num_frames >= 3 else None
        self.run_dir = None if run_dir is None else Path(run_dir)
        self.note = note if note is not None else (lambda m: None)
        self.history = []  # one dict per call
        self._corr = None
        self._tracks = None
        self.seed, self.track_config = config.train.seed, config.pose_init.tracks

    # ------------------------------------------------------------------ state
    def state_dict(self):
        return {"history": self.history}

    def load_state_dict(self, state):
        self.history = list(state.get("history", []))

    # ------------------------------------------------------------------ the step
    def correspondences(self):
        if self._corr is None:
            self._corr = correspondences(self.images, self.masks, self.pc.correspond, self.run_dir)
            used = self._corr.used
            self.note(f"pose solver: {sum(p.num_matches for p in used)} matches in {len(used)} of "
                      f"{len(self._corr.pairs)} frame pairs" + (" (read from the cache)" if self._corr.from_cache else ""))
            if not self._corr.from_cache:
                for line in self._corr.report():
                    self.note(f"  {line}")
        return self._corr

    def tracks(self):
        """KLT tracks through the frames (none in the masks), once per run: the independent check
        of a solve (``PoseSolverConfig.track_check``)."""
        if self._tracks is None:
            masks = self.masks if all(m is not None for m in self.masks) else None
            # the same tracks as the bundle adjustment before training (pose_init.tracks)
            of, ot, uv, nt, _ = klt_tracks(self.images, self.track_config, masks=masks, seed=self.seed)
            self._tracks = (of, ot, uv, nt)
        return self._tracks

    def on_init(self, model):
        if self.pc.track_check:
            self.tracks()

    def on_step(self, state: TrainState) -> TrainState:
        if not entered_period(state, self.pc.every):
            return state
        since = state.step - (self.history[-1]["step"] if self.history else 0)
        if since < self.pc.min_steps:  # the scene has not trained enough since (PoseSolverConfig.min_steps)
            return state
        state, entry = self.refine(state)
        entry["step"] = int(state.step)
        self.history.append(entry)
        if self.run_dir is not None:
            atomic_write_text(self.run_dir / HISTORY_FILE, json.dumps(self.history, indent=1))
        return state.replace(record=state.record.replace(pose_solver=entry))

    def refine(self, state: TrainState):
        """(state with refined poses, a summary dict) of one solver call."""
        t0 = time.perf_counter()
        model = state.model
        pairs = self.correspondences().used
        if not pairs:
            self.note(f"step {state.step}: pose solver skipped (no frame pair has enough matches)")
            return state, {"status": "no_pairs"}
        try:
            problem, res, C = self.solve(model, pairs)
        except ValueError as e:  # e.g. a lifted point exactly on a camera plane: non-finite residuals
            self.note(f"step {state.step}: pose solver skipped ({e})")
            return state, {"status": "skipped", "reason": str(e)}
        mids = problem.poses(np.zeros(problem.num_params))[2]
        if model.components.blur and model.config.trajectory.path == "three_knot":
            mids = model.mid_poses()  # the middle knots, as solve() moved them
        ate_before = self._ate(mids)
        entry = {"status": res.status, "cost_before": float(res.costs[0]), "cost_after": float(res.costs[-1]),
                 "iterations": int(res.iterations), "accepted": int(res.accepted), "matches": int(res.num_matches),
                 "dropped": int(res.dropped), "rank": int(res.rank), "num_params": int(res.num_params),
                 "solver_seconds": float(res.wall_time)}
        ate_after = ate_before
        trusted = self.pc.accept == "always" or (res.status in CONVERGED and res.rank == res.num_params)
        entry["written"] = bool(res.accepted and trusted)
        if res.accepted and not trusted:
            self.note(f"step {state.step}: pose solver result not written ({res.status}, rank {res.rank}/"
                      f"{res.num_params}): only converged, fully observed solves move the poses "
                      "(pose_solver.accept = converged)")
        if res.accepted and trusted and self.pc.track_check:
            rms0, _ = track_reprojection_rms(mids, model.Ks, self.tracks())
            rms1, _ = track_reprojection_rms(res.mids, model.Ks, self.tracks())
            entry["track_rms_before"], entry["track_rms_after"] = rms0, rms1
            if np.isfinite(rms0) and not rms1 <= rms0 * (1.0 + self.pc.track_tolerance):
                trusted = entry["written"] = False
                self.note(f"step {state.step}: pose solver result not written: it raises the point tracks' "
                          f"reprojection rms {rms0:.3f} -> {rms1:.3f} px (pose_solver.track_check, tolerance "
                          f"{self.pc.track_tolerance:.0%})")
        if res.accepted and trusted:
            changed = [int(k) for k in problem.free if np.any(res.x[k] != 0)]
            state = write_mid_poses(state, res.mids, changed, C)
            entry["changed_frames"] = len(changed)
            ate_after = self._ate(state.model.mid_poses())
        if ate_before is not None:
            entry["ate_before"], entry["ate_after"] = ate_before, ate_after
        entry["seconds"] = time.perf_counter() - t0
        ate = "" if ate_before is None else f"; ATE {ate_before:.4g} -> {ate_after:.4g}"
        self.note(f"step {state.step}: pose solver {res.status}: cost {res.costs[0]:.4g} -> {res.costs[-1]:.4g} in "
                  f"{res.iterations} iterations ({res.accepted} accepted), {res.num_matches} matches "
                  f"({res.dropped} dropped: no depth), rank {res.rank}/{res.num_params}, "
                  f"{entry['seconds']:.2f}s{ate}")
        return state, entry

    def solve(self, model, pairs):
        """(problem, result, C) of one solver call on ``model`` with the matched ``pairs``: depths
        rendered at the current mid poses, endpoints from the trajectory model, frame 0 fixed."""
        frames = sorted({p.k for p in pairs} | {p.j for p in pairs})
        starts, ends, C = self._endpoints(model)
        mids = se3_interpolate_batch(starts, ends)
        s = self.pc.render_scale
        depth = {k: static_depth(model, k, mids[k], s) for k in frames}
        obs = [gn.pair_observations(p.k, p.j, p.pts_k, p.pts_j, gn.sample_depth(depth[p.k], p.pts_k * s),
                                    gn.sample_depth(depth[p.j], p.pts_j * s)) for p in pairs]
        prior = {}
        if self.pc.prior_rot_deg > 0:
            depths = np.concatenate([np.r_[o.depth_k, o.depth_j] for o in obs])
            scale = float(np.median(depths)) if depths.size else 1.0
            prior = {"prior_poses": model.start_poses,
                     "prior_sigma": (self.pc.prior_trans_rel * scale, np.deg2rad(self.pc.prior_rot_deg))}
        problem = gn.PoseProblem(starts, ends, model.Ks, obs, fixed=(0,), **prior)
        res = gn.solve(problem, self.pc.gauss_newton)
        if self.pc.hold_scale and res.accepted:
            res.mids = hold_trajectory_scale(mids, res.mids, anchor=0)
        knots = traj_model.mid_knots(model.params, model.config.trajectory,
                                     np.arange(model.num_frames, dtype=np.int64)) if model.components.blur else None
        if knots is not None and res.accepted:
            # three-knot path: the solver moved each exposure rigidly (its geodesic midpoint by D_k);
            # move the middle knot, the frame's mid pose, with it
            res.mids = np.stack([res.mids[k] @ se3_inverse(mids[k]) @ C[k] @ model.poses_ref[k]
                                 for k in range(model.num_frames)])
        return problem, res, C

    def _endpoints(self, model):
        """(starts, ends, C): the exposure endpoints (N, 4, 4) and C_k, the frame's mid pose
        over T̂: the midpoint of exp(xi_s), exp(xi_e), or exp(xi_mid) on the three-knot path (None
        without the blur model, where both endpoints are T̂)."""
        if not model.components.blur:
            return model.poses_ref.copy(), model.poses_ref.copy(), None
        idx = np.arange(model.num_frames, dtype=np.int64)
        (xs, xe), _ = traj_model._endpoints_fwd(model.params, model.config.trajectory, idx, model.poses_ref,
                                                model.times)
        Es, Ee = se3_exp(xs), se3_exp(xe)
        xm = traj_model.mid_knots(model.params, model.config.trajectory, idx)
        C = se3_interpolate_batch(Es, Ee) if xm is None else se3_exp(np.asarray(xm, np.float64))
        return Es @ model.poses_ref, Ee @ model.poses_ref, C

    def _ate(self, mids):
        return None if self.gt is None else float(trajectory.ate(mids, self.gt))


def write_mid_poses(state: TrainState, mids, frames, C=None) -> TrainState:
    """The state with the mid-exposure poses of ``frames`` moved to ``mids[k]`` (module docstring,
    step 4): ``poses_ref[k] = C_k^-1 mids[k]`` (C: the (N, 4, 4) midpoints of exp(xi_s), exp(xi_e);
    None without the blur model: ``poses_ref[k] = mids[k]``), the Adam moments of those camera
    rows reset, the model validated."""
    model = state.model
    new_ref = np.array(model.poses_ref, dtype=np.float64, order="C")
    for k in frames:
        new_ref[k] = mids[k] if C is None else se3_inverse(C[k]) @ mids[k]
    new_model = model.replace(poses_ref=np.ascontiguousarray(new_ref)).validate()
    return state.replace(model=new_model, adam=_reset_rows(state.adam, model.params, list(frames)))


def hold_trajectory_scale(before, after, anchor=0):
    """``after`` (N, 4, 4) cam_T_world with its camera centres rescaled about frame ``anchor``'s
    centre so that their summed distance from it equals that of ``before``; rotations unchanged.
    A trajectory whose centres all coincide with the anchor's (no size to hold) is returned as is."""
    after = np.asarray(after, dtype=np.float64)
    c_b, c_a = camera_center(before), camera_center(after)
    size_b = np.linalg.norm(c_b - c_b[anchor], axis=1).sum()
    size_a = np.linalg.norm(c_a - c_a[anchor], axis=1).sum()
    if not (size_a > 0 and size_b > 0 and np.isfinite(size_a) and np.isfinite(size_b)):
        return after.copy()
    lam = size_b / size_a  # the similarity x -> lam x + (1 - lam) c_anchor, no rotation
    return trajectory.sim3_apply_to_poses(lam, np.eye(3), (1.0 - lam) * c_a[anchor], after)


def se3_interpolate_batch(starts, ends):
    """(N, 4, 4) geodesic midpoints of (N, 4, 4) start and end poses."""
    return np.stack([se3_interpolate(a, b, 0.5) for a, b in zip(starts, ends)])


def _reset_rows(adam_state, params, rows):
    """Adam state with the moments of ``rows`` of the per-frame camera blocks set to zero."""
    if not rows:
        return adam_state
    new = {slot: dict(blocks) if isinstance(blocks, dict) else blocks for slot, blocks in adam_state.items()}
    for name in (traj_model.XI_START, traj_model.XI_END, traj_model.XI_MID):
        if name not in params:
            continue
        for slot in ("m", "v"):
            if name in new.get(slot, {}):
                a = new[slot][name].copy()
                a[rows] = 0.0
                new[slot][name] = a
    return new
