"""A small big_mover's rigid path against its panel's true turn (tests/scene)."""
import numpy as np


def angle_deg(R):
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))))


def big_mover_path_errors(dynamic_depth, fits, **scene_kw):
    """big_mover, 12 frames 120 x 68, blurred, true poses (plus ``scene_kw``), its seeds at
    ``dynamic_depth``: for each rigid_fit in ``fits``, (median over frames of the fitted path's
    rotation error relative to the middle frame against the panel's, degrees; initialize_deformation's
    info)."""
    from d2gs_np.data.suite import build_suite_world, make_suite_scene, mover_pose, resolve
    from d2gs_np.scene.config import DeformConfig, InitConfig, MotionInitConfig
    from d2gs_np.scene.initialize import initialize_points
    from d2gs_np.scene.motion_init import initialize_deformation
    from d2gs_np.scene.rigid import cluster_poses

    kw = dict(width=120, height=68, num_frames=12, num_test_views=0, rot_noise_deg=0.0, trans_noise=0.0,
              subframes=8, **scene_kw)
    scene = make_suite_scene("big_mover", 0, **kw)
    mover = build_suite_world(resolve("big_mover", 0, **kw)).movers[0]
    _, _, d, _, info = initialize_points(scene, InitConfig(dynamic_points=400, dynamic_depth=dynamic_depth),
                                         np.random.default_rng(0))
    times = [f.time for f in scene.frames]
    mid = len(times) // 2
    true = [mover_pose(mover, t)[0] @ mover_pose(mover, times[mid])[0].T for t in times]
    out = {}
    for fit in fits:
        cfg = DeformConfig()
        _, _, minfo = initialize_deformation(scene, d, info["dynamic_source_frames"], info["dynamic_source_pixels"],
                                             cfg, MotionInitConfig(rigid=True, rigid_fit=fit),
                                             depth_maps=info["dynamic_depth_maps"])
        B = minfo["rigid"]["blocks"]
        assert len(B["rigid.means"]) == 1
        Rs = [cluster_poses(B, t, cfg)[0][0] for t in times]
        err = float(np.median([angle_deg(Rs[k] @ Rs[mid].T @ true[k].T) for k in range(len(times))]))
        out[fit] = (err, minfo)
    return out


def single_mover_frames(renders, K):
    """Frames of one rendered mover, the camera at the world's origin: renders [(image (H, W, 3), mask
    (H, W) bool)] -> (frames, component labels, track members (frame, centroid, component))."""
    from types import SimpleNamespace

    from d2gs_np.scene.motion_init import mask_components

    frames, labels, members = [], [], []
    for k, (image, mask) in enumerate(renders):
        H, W = mask.shape
        frames.append(SimpleNamespace(image=image, mask=mask, cam_T_world=np.eye(4), K=K, width=W, height=H,
                                      time=float(k)))
        lab, cents, _ = mask_components(mask, 10)
        labels.append(lab)
        members.append((k, cents[0], 0))
    return frames, labels, members
