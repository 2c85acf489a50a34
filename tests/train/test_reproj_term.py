"""The L_reproj loss term (train.terms.Reprojection with its DepthMemory plugin): its gradient on
the rendered expected depth against central differences, zero at consistent depths, no value
before the partner frame has a depth, the term in a training run (log column, weighted sum,
exact resume with the depth memory checkpointed), and left out without a scene."""
import dataclasses
from types import SimpleNamespace

import numpy as np
import pytest

from d2gs_np.data.synthetic import make_scene
from d2gs_np.geometry.se3 import se3_exp
from d2gs_np.train.config import ExperimentConfig, LossConfig, PoseSolverConfig, TrainConfig
from d2gs_np.train.plugins import DepthMemory
from d2gs_np.train.terms import Reprojection, TermInputs, loss_terms
from d2gs_np.train.trainer import Trainer
from run_fixtures import copy_run_for_resume

W, H = 40, 24
K = np.array([[40.0, 0.0, 20.0], [0.0, 40.0, 12.0], [0.0, 0.0, 1.0]])
POSES = [np.eye(4), se3_exp(np.r_[0.2, 0.0, 0.01, 0.0, 0.03, 0.0])]
PLANE_Z = 3.0  # both cameras see a fronto-parallel plane z = 3 in world (frame 0) coordinates


def _true_depth(pose, scale=1.0):
    """(h, w) z-depth of the plane z = PLANE_Z seen from pose, at scale of (W, H)."""
    w, h = int(W * scale), int(H * scale)
    Ks = np.diag([scale, scale, 1.0]) @ K
    yy, xx = np.mgrid[0:h, 0:w] + 0.5
    rays = np.linalg.solve(Ks, np.stack([xx.ravel(), yy.ravel(), np.ones(w * h)])).T  # camera rays, z = 1
    Rw = np.linalg.inv(pose)[:3, :3]
    c = np.linalg.inv(pose)[:3, 3]
    lam = (PLANE_Z - c[2]) / (rays @ Rw.T)[:, 2]  # z-depth along each ray
    return lam.reshape(h, w)


def _matches(m=30, seed=0):
    rng = np.random.default_rng(seed)
    pts0 = np.c_[rng.uniform(6, 34, m), rng.uniform(5, 19, m)]
    d0 = PLANE_Z * np.ones(m)
    X = d0[:, None] * np.linalg.solve(K, np.c_[pts0, np.ones(m)].T).T
    X1 = X @ POSES[1][:3, :3].T + POSES[1][:3, 3]
    pts1 = (X1 @ K.T)[:, :2] / X1[:, 2:3]
    return [(0, 1, pts0, pts1)]


def _model():
    return SimpleNamespace(mid_pose=lambda k: POSES[k], Ks=[K, K], widths=(W, W), heights=(H, H))


def _term(weight=0.5):
    memory = DepthMemory(None, None, None, matches=_matches())
    return Reprojection(weight, memory, beta=10.0, robust_scale=1.0)


def _inputs(depth, frame, alpha=None):
    alpha = np.ones_like(depth) if alpha is None else alpha
    return TermInputs({"expected_depth": depth, "alpha": alpha}, None, None, _model(), frame, None)


def test_consistent_depths_cost_nothing_and_the_first_visit_has_no_partner():
    term = _term()
    v, saved = term.fwd(_inputs(_true_depth(POSES[0]), 0))
    assert v == 0.0 and saved is None  # frame 1 has not rendered yet
    assert term.bwd(saved).render == {}
    v1, saved1 = term.fwd(_inputs(_true_depth(POSES[1], 0.5), 1))  # the partner at half size
    assert saved1 is not None and v1 < 1e-6  # bilinear reads of a smooth depth: tiny but not 0
    v0, _ = term.fwd(_inputs(_true_depth(POSES[0]), 0))
    assert v0 < 1e-6


def test_gradient_on_the_expected_depth_matches_central_differences():
    # Frame 0's depth 8 % too far with a ripple, so residuals are O(1) px and the Cauchy weights
    # vary. Central differences at h = 1e-6 on depths ~3: truncation ~h^2 * 3rd derivative and
    # rounding ~1e-16 * value / h = 1e-10; 1e-7 absolute on gradients ~1e-3..1e-1 still catches a
    # missing direction, factor or weight.
    term = _term(weight=0.5)
    term.fwd(_inputs(_true_depth(POSES[1]), 1))  # the partner's depth in memory
    yy, xx = np.mgrid[0:H, 0:W]
    depth = _true_depth(POSES[0]) * (1.08 + 0.03 * np.sin(xx / 3.0) * np.cos(yy / 4.0))
    v, saved = term.fwd(_inputs(depth, 0))
    assert v > 0
    grad = term.bwd(saved).render["expected_depth"]
    assert grad.shape == depth.shape and np.count_nonzero(grad) > 20
    h = 1e-6
    rows, cols = np.nonzero(grad)
    pick = np.random.default_rng(1).choice(len(rows), 15, replace=False)
    for i, j in zip(rows[pick], cols[pick]):
        up, dn = depth.copy(), depth.copy()
        up[i, j] += h
        dn[i, j] -= h
        num = 0.5 * (term.fwd(_inputs(up, 0))[0] - term.fwd(_inputs(dn, 0))[0]) / (2 * h)
        assert grad[i, j] == pytest.approx(num, abs=1e-7, rel=1e-5)
    # a pixel no match reads has no gradient
    assert grad[0, 0] == 0.0


def test_pixels_without_static_cover_give_no_depth():
    term = _term()
    term.fwd(_inputs(_true_depth(POSES[1]), 1))
    depth = 1.1 * _true_depth(POSES[0])
    v_all, _ = term.fwd(_inputs(depth, 0))
    v_none, saved = term.fwd(_inputs(depth, 0, alpha=np.full_like(depth, 0.3)))  # alpha below 0.5
    assert v_all > 0 and v_none == 0.0 and saved is None


def test_left_out_without_a_scene():
    notes = []
    terms = loss_terms(LossConfig(lambda_reproj=0.001, lambda_freq=0.0), note=notes.append)
    assert [t.name for t in terms] == ["photometric"]
    assert any("L_reproj: left out" in n for n in notes)


TINY = dict(width=96, height=54, num_frames=6)  # SIFT finds 12-22 matches per pair at this size


def _config(iters, **train):
    base = dict(iters=iters, quiet=True, eval_every=0, log_every=1, checkpoint_every=0, prune_every=0)
    base.update(train)
    return ExperimentConfig(train=TrainConfig(**base), loss=LossConfig(lambda_reproj=0.05, lambda_freq=0.0),
                            pose_solver=PoseSolverConfig(mode="off"))


@pytest.fixture(scope="module")
def static_scene():
    return make_scene("static", 0, **TINY)


def test_training_logs_the_term_and_resumes_exactly(static_scene, tmp_path):
    cfg = _config(14, checkpoint_every=7)
    full = Trainer(static_scene, cfg, tmp_path / "full")
    assert [t.name for t in full.terms] == ["photometric", "reproj"]
    assert "reproj_depths" in [p.name for p in full.plugins] and "loss_reproj" not in full.left_out()
    full.run()
    assert any(n.startswith("L_reproj: ") and "matches in" in n for n in full.log.notes)
    rows = full.log.rows
    vals = [r["loss_reproj"] for r in rows]
    assert all(np.isfinite(vals)) and vals[0] == 0.0 and max(vals) > 0  # the first step has no partner
    r = max(rows, key=lambda r: r["loss_reproj"])
    assert r["loss"] == pytest.approx(r["loss_photometric"] + 0.05 * r["loss_reproj"], rel=1e-12)
    copy_run_for_resume(tmp_path / "full", tmp_path / "part")
    resumed = Trainer(static_scene, cfg, tmp_path / "part", resume=True)
    assert resumed.step_index == 7
    memory = next(p for p in resumed.plugins if p.name == "reproj_depths")
    assert len(memory.maps) > 0  # read from the checkpoint, not empty
    resumed.run()
    for name in full.params:
        np.testing.assert_array_equal(resumed.params[name], full.params[name], err_msg=name)


def test_the_term_changes_the_static_gaussians_only_through_depth(static_scene, tmp_path):
    # same seed, with and without the term: the runs differ (the depth gradient reaches the
    # Gaussians) once a partner depth exists
    a = Trainer(static_scene, _config(4), tmp_path / "a")
    a.run()
    cfg = dataclasses.replace(_config(4), loss=LossConfig())
    b = Trainer(static_scene, cfg, tmp_path / "b")
    b.run()
    assert not np.array_equal(a.params["static.means"], b.params["static.means"])
