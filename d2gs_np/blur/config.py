"""Settings of the blur model (docs/method.md §4): ``BlurConfig`` (the virtual views of a blurry
render) and ``TrajectoryConfig`` (the exposure endpoint model), with the argument checks they
share with the blur modules.

Plain data: importing this module imports neither the Numba renderer nor OpenCV nor CasADi, so
reading an experiment config (``train/config.py``) stays light.
"""
from __future__ import annotations

from dataclasses import dataclass

from d2gs_np.base.checks import check_choice, check_int, check_number

__all__ = [
    "N_SCHEDULES",
    "BlurConfig",
    "TRAJECTORY_KINDS",
    "EXPOSURE_PATHS",
    "ACTIVATIONS",
    "TrajectoryConfig",
]

N_SCHEDULES = ("fixed", "scale", "length")  # BlurConfig.n_schedule (d2gs_np.blur.views)


@dataclass(frozen=True)
class BlurConfig:
    """Blur formation settings.

    num_virtual: n, number of virtual sub-frames averaged per blurry frame (>= 1; 1 = sharp
        camera at the estimated pose, d2gs_np.blur.virtual_poses). Default 8 (docs/method.md §4).
    n_schedule: how many of them a training render at render scale r uses
        (d2gs_np.blur.views, ``views_at_scale``): "fixed", n at every scale; "scale", fewer while the progressive
        schedule renders small images, so the virtual views stay as far apart in pixels as n
        views are at full resolution (the blur's length in pixels scales with r); "length", per
        frame and step from the blur's current length in render pixels (``blur_length_px`` of
        the current endpoints and scene, ``views_for_length``): just enough views to keep
        neighbouring views at most ``view_spacing_px`` render pixels apart, at most n. It
        follows the render scale too, and gives a short blur few views. The default: it buys
        steps where the blur is short (why: docs/results.md §8).
    view_spacing_px: the largest gap, in render pixels, between neighbouring virtual views of
        the "length" schedule (> 0).
    backward_views: m, how many of a step's virtual views its backward runs through (0: all).
        The forward always renders and averages every view, so the loss is exact; with
        0 < m < n views the gradient is the unbiased stratified estimate of
        ``backward_subset``: the views are cut into m runs of neighbours, one view of each run
        is drawn at random and carries its run's share of the weight. The backward costs about
        twice the forward, so the backward of m = 2 of n = 8 views costs a quarter of the
        exact one. Views of one exposure see the scene from poses a few pixels apart, so their
        gradients are nearly the same and the estimate's noise is small. Default 2, the cheapest
        estimate that did not cost accuracy (why: docs/results.md §8).
    """

    num_virtual: int = 8
    n_schedule: str = "length"
    view_spacing_px: float = 1.0
    backward_views: int = 2

    def __post_init__(self):
        _check_n(self.num_virtual, "BlurConfig.num_virtual")
        check_choice(self.n_schedule, "BlurConfig.n_schedule", N_SCHEDULES)
        check_number(self.view_spacing_px, "BlurConfig.view_spacing_px", 0.0, lo_open=True, hint="pixels")
        _check_backward_views(self.backward_views, "BlurConfig.backward_views")


TRAJECTORY_KINDS = ("direct", "posenet")
EXPOSURE_PATHS = ("auto", "geodesic", "three_knot")  # TrajectoryConfig.path (d2gs_np.blur.virtual_poses)
ACTIVATIONS = ("tanh", "softplus")  # PoseNet hidden layers


@dataclass(frozen=True)
class TrajectoryConfig:
    """Endpoint parametrisation.

    kind: "direct" (per-frame xi blocks) or "posenet" (MLP of Eq. 8).
    init_spread: s, half the initial endpoint spread (xi_s = -s d, xi_e = +s d, |d| = 1); must
        be > 0 (zero spread is a critical point, see d2gs_np.blur.endpoints).
    hidden_layers, hidden_width: PoseNet size (docs/method.md §4: 2 hidden layers of 64).
    activation: "tanh" or "softplus" (PoseNet hidden layers).
    output_init_scale: PoseNet output-layer weight scale at initialisation (d2gs_np.blur.endpoints).
    init: "velocity" (default): the direct endpoints start on the camera's motion, estimated from
        the neighbouring estimated poses (``velocity_endpoints``), with init_spread only as a
        floor; "random": a tiny spread in a random direction. The velocity start matters: from a
        tiny random spread the endpoints open far too slowly (docs/results.md §8).
    velocity_window: h, the frames k-h..k+h the "velocity" start reads: 1 is the central
        difference of the two neighbours; h >= 2 fits a quadratic in time to the tangents of those
        frames relative to frame k by least squares (``velocity_endpoints``), which averages the
        independent part of a pose error over more frames at the cost of a bias where the path
        bends within the window (docs/method.md §4).
    centre: "auto" (default): when the scene flags its poses as exact (``poses_trusted``), the
        exposure stays centred on the given pose, xi_start = -xi_end, and only its spread is
        learned (at ``LearningRates.camera_spread``): trusted poses get no pose refinement, from
        the solver or from Adam; otherwise both endpoints are free. "on" / "off" force it
        ("on" needs kind "direct"). Why: docs/method.md §4; the suite's figures: docs/results.md §4.
    path: the camera's path through one exposure (d2gs_np.blur.virtual_poses): "geodesic" (default,
        Eq. 9) from the start to the end pose; "three_knot": exp(c(u)) T̂, c the quadratic through
        the tangents xi_start, xi_mid, xi_end at u = 0, 1/2, 1 (a third per-frame block
        ``camera.xi_mid``, starting at 0), for a shake that bends within an exposure, where the
        geodesic's midpoint, the deblurred view, is off the true mid-exposure pose
        (``examples/blur_ceiling.py``); the deblurred view is then exp(xi_mid) T̂. Needs kind
        "direct"; a centred exposure keeps xi_mid at 0. "auto" (default): chosen once per run by
        measured need (``train.components.decide_exposure_path``, docs/method.md §4): the three-knot
        path where the start poses are reliable (a kept bundle adjustment, or trusted poses) and
        the median frame's exposure bends by more than ``bend_px`` (``exposure_bend_px`` of those
        poses), else the geodesic. Until a run decides, "auto" renders as the geodesic.
    bend_px: the bend, in full-resolution pixels, beyond which "auto" takes the three-knot path:
        how far the quadratic through a frame's neighbouring poses leaves the chord of its
        exposure at mid-exposure. The best geodesic fit to a bent blur puts the deblurred view
        about a third of the bend off the true mid pose, so the default 0.4 px keeps that error
        near a tenth of a pixel (why this line: docs/results.md §4).
    """

    kind: str = "direct"
    init_spread: float = 1e-4
    hidden_layers: int = 2
    hidden_width: int = 64
    activation: str = "tanh"
    output_init_scale: float = 1e-5
    init: str = "velocity"
    velocity_window: int = 1
    centre: str = "auto"
    path: str = "auto"
    bend_px: float = 0.4

    def __post_init__(self):
        check_choice(self.centre, "TrajectoryConfig.centre", ("auto", "on", "off"))
        if self.centre == "on" and self.kind != "direct":
            raise ValueError("TrajectoryConfig.centre = 'on' needs kind 'direct' (a PoseNet's endpoints cannot be "
                             "tied row by row); use centre 'auto' or 'off'")
        check_choice(self.path, "TrajectoryConfig.path", EXPOSURE_PATHS)
        check_number(self.bend_px, "TrajectoryConfig.bend_px", 0.0, lo_open=True, hint="full-resolution pixels")
        if self.path == "three_knot" and self.kind != "direct":
            raise ValueError("TrajectoryConfig.path = 'three_knot' needs kind 'direct' (per-frame knot blocks); "
                             "use kind 'direct' or path 'geodesic'")
        check_int(self.velocity_window, "TrajectoryConfig.velocity_window", 1, hint="frames on each side")
        check_choice(self.init, "TrajectoryConfig.init", ("velocity", "random"))
        check_choice(self.kind, "TrajectoryConfig.kind", TRAJECTORY_KINDS)
        check_choice(self.activation, "TrajectoryConfig.activation", ACTIVATIONS)
        for name in ("hidden_layers", "hidden_width"):
            check_int(getattr(self, name), f"TrajectoryConfig.{name}", 1)
        check_number(self.init_spread, "TrajectoryConfig.init_spread", 0.0, 1.0, lo_open=True, hi_open=True,
                     hint="a tiny symmetry-breaking spread; 0 is a critical point")
        check_number(self.output_init_scale, "TrajectoryConfig.output_init_scale", 0.0)


# ---------------------------------------------------------------------------------------------
# Argument checks shared by the configs and the blur modules
# ---------------------------------------------------------------------------------------------


def _check_n(n, what="n (number of virtual poses)"):
    return check_int(n, what, 1)


def _check_backward_views(m, what):
    check_int(m, what, 0, hint="0: every view")
