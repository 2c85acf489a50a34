"""Every threshold and epsilon of the project, named once.

Renderer values follow gsplat 1.5.3's reference renderer (see
``docs/conventions.md``, whose §11 lists them); the section of that page is given beside each.
Numerical epsilons carry a comment saying why they have the value they have.
"""

# --- Rendering (docs/conventions.md) ---------------------------------------
EPS2D = 0.3  # §3: low-pass dilation added to the 2D covariance, always applied
NEAR_PLANE = 0.01  # §4: Gaussians with camera z <= NEAR_PLANE are culled
FAR_PLANE = 1e10  # §4: Gaussians with camera z >= FAR_PLANE are culled
RADIUS_SIGMA = 3.33  # §4: per-axis screen radius = ceil(3.33 * sqrt(cov2d_ii))
TILE_SIZE = 16  # §5: square tile side in pixels
FOV_CLAMP_MARGIN = 0.3  # §3: x/z clamped to the fov widened by 0.3 * tan_fov, in J only
DET_MIN = 1e-10  # §3: det of the dilated 2D covariance is clamped below at this
ALPHA_MAX = 0.999  # §6: alpha = min(ALPHA_MAX, o * exp(-sigma)); not Inria's 0.99
ALPHA_THRESHOLD = 1.0 / 255.0  # §6: a Gaussian with alpha < 1/255 is skipped
TRANSMITTANCE_MIN = 1e-4  # §6: stop *before* a Gaussian that would bring T*(1-alpha) <= 1e-4
EXPECTED_DEPTH_ALPHA_MIN = 1e-10  # §7: expected depth = D / max(alpha, 1e-10)
PIXEL_CENTER_OFFSET = 0.5  # §2: pixel (i, j) has its centre at (j + 0.5, i + 0.5)

# --- Geometry ----------------------------------------------------------------
# Below this squared angle (theta < 0.5 rad) the Lie-group coefficient
# functions (sin(t)/t, (t - sin t)/t^3, ...) are evaluated from their Taylor
# series (8 terms, truncation < 1e-19). Above it the closed forms are used;
# their worst cancellation, (2t - 3 sin t + t cos t)/(2 t^5) near t = 0.58, loses
# about 2e-13 relative (measured against 160-digit arithmetic, tests/geometry);
# it multiplies terms of size theta^4 |rho|, so the pose error stays ~1e-16.
SERIES_ANGLE2 = 0.25
# so3_log takes the rotation axis from the symmetric part of R once
# cos(theta) < this (theta > 2*pi/3): there sin(theta) is small enough that
# dividing the skew part by it would amplify rounding, while the symmetric
# part (R + R^T)/2 - cos(theta) I = (1 - cos(theta)) a a^T is well conditioned.
LOG_SYMMETRIC_BRANCH_COS = -0.5
# Quaternion norms below this are rejected rather than normalised.
QUAT_NORM_MIN = 1e-12
# A rotation matrix whose R^T R deviates from I by more than this (max abs
# entry), or whose determinant deviates from +1 by more, is "not rigid".
RIGID_TOL = 1e-6
# A pose read from a file (docs/dataset_format.md §2) may be rigid only up to the rounding of its
# export: rounded to d decimals, each entry is off by e <= 0.5e-d, so max |R^T R - I| <= 2 sqrt(3) e
# = 1.7e-d and |det R - 1| <= sqrt(3) * 3 e = 2.6e-d (Cauchy-Schwarz on unit columns). The usual
# 6 decimals give up to 2.6e-6, above RIGID_TOL. Up to this tolerance (exports of 4 or more
# decimals, with a margin of 3.8) a loaded rotation is projected to the nearest one
# (``se3.nearest_rigid``); beyond it the matrix is a scale, a shear or a reflection, and refused.
POSE_ROUNDING_TOL = 1e-3

# --- Metrics ---------------------------------------------------------------------
# Trajectory metrics reject camera centres whose spread (mean squared distance
# from their centroid) is below this fraction of their mean squared norm: the
# points are then at one place up to float64 rounding (relative 1e-6 in
# position, far above the 1e-16 rounding) and a Sim(3) alignment is undefined.
TRAJECTORY_SPREAD_MIN_REL = 1e-12

# --- Scene initialisation, optimizer, SSIM -----------------------------------
# Initial squared neighbour distance is clamped below at this (3DGS's
# clamp_min(distCUDA2(points), 1e-7)): duplicate points would otherwise get
# log(0) = -inf log-scales.
INIT_DIST2_MIN = 1e-7
# Adam's denominator epsilon, sqrt(v_hat) + eps. 3DGS uses 1e-15 (not torch's
# 1e-8): gradients of Gaussian parameters are often ~1e-8 per pixel-sum, and a
# 1e-8 epsilon would silently shrink their steps.
ADAM_EPS = 1e-15
# SSIM stabilisers C1 = (K1 L)^2, C2 = (K2 L)^2 with K1 = 0.01, K2 = 0.03 and
# data range L = 1 (Wang et al. 2004; scikit-image's defaults): they keep the
# ratio finite on flat, dark patches.
SSIM_C1 = 0.01**2
SSIM_C2 = 0.03**2

# --- Trajectory model (PoseNet) -----------------------------------------------
# PoseNet standardises each input component (log T̂ and t) by its spread over the
# frames; a component whose standard deviation is below this (world units,
# radians, normalised time) is constant up to meaningless jitter, and dividing
# by it would blow float rounding up to O(1) inputs, so it is only centred.
POSENET_INPUT_STD_MIN = 1e-6

# Fast splatter shortcut (d2gs_np.render.binning, rasterize): a (Gaussian, pixel) pair with
# sigma > ln(opacity / ALPHA_THRESHOLD) + ALPHA_CUTOFF_SAFETY is skipped without evaluating exp.
# Then alpha <= exp(-1e-3) / 255 < 1/255 with a relative gap of 1e-3, far above the rounding of
# exp, log and the product in float32 (~1e-7) or float64, so the skip decision is exactly the
# one the full rule (alpha < 1/255) would take: a pure speed-up, the image is unchanged.
ALPHA_CUTOFF_SAFETY = 1e-3

# --- Reference-check kit (d2gs_np.refcheck, docs/refcheck.md §5) -------------------------------
# Default tolerances of `d2gs refcheck compare`, relative to the largest |entry| of each quantity
# in our (golden) result. float64: two correct float64 implementations of the same formulas
# differ by rounding only, O(10-1000) ulps of each quantity's scale (our Numba path against the
# NumPy reference, and gsplat's torch reference, on the whole suite: <= 1.3e-13, the tile-border
# case's quaternion gradients); 1e-10 leaves almost three orders of magnitude while any wrong
# term shows at >= 1e-6. float32 against our float64 golden computed from the same float32 inputs: float32
# rounds each operation at 6e-8 relative; chains of ~1e2 operations and sums over ~1e2 terms give
# ~1e-6 on outputs and a few 1e-6 on gradients (our own float32 path: docs/refcheck.md §5). 1e-4
# (outputs) and 1e-3 (gradients, longer chains and cancellations) are gsplat's own float32
# CUDA-against-torch tolerances (forward 1e-4, gradients a few 1e-3).
REFCHECK_RTOL_F64 = 1e-10
REFCHECK_RTOL_F32_OUTPUT = 1e-4
REFCHECK_RTOL_F32_GRAD = 1e-3
# Screen radii are ceil(3.33 sigma) (integers): float32 rounding can move a value that sits
# within ~1e-6 of an integer across it, so a float32 port may differ by one pixel there.
REFCHECK_RADII_ATOL_F32 = 1

# --- Pose solver (d2gs_np/pose/gauss_newton.py, docs/method.md §5) ---------------------------
# The SE(3) log of the solver takes theta / sin(theta) from its series in sin^2(theta) below this
# (|w| < 1e-3): four terms leave a truncation of ~(1e-6)^4 = 1e-24; above it atan2(s, c) / s
# divides by s >= 1e-3, which loses at most ~1e-13 relative.
GN_LOG_SERIES_SIN2 = 1e-6
# A match whose rendered depth (either frame) is not above this (world units) is dropped: an
# empty render reads 0 there, and a point at or behind the camera has no reprojection.
GN_MIN_DEPTH = 1e-6
# Levenberg-Marquardt lambda stays in [LM_DAMPING_MIN, LM_DAMPING_MAX]: below 1e-12 the damping
# no longer changes a float64 solve; at 1e16 the step is ~1e-16 of the gradient step, i.e. none,
# and the solver stops ("damping_limit") instead of multiplying lambda on towards overflow.
LM_DAMPING_MIN = 1e-12
LM_DAMPING_MAX = 1e16
# Marquardt scaling uses diag(J^T W J), floored at this times its largest entry, so a column the
# data do not see (a frame without matches) is still damped instead of giving a singular system.
DAMPING_DIAG_FLOOR = 1e-9
# Singular values of the final normal matrix below this times the largest count as zero for the
# covariance pseudo-inverse and its rank: float64 rounding of J^T J is ~1e-16 x cond, and
# directions observed only through points at 1e6 x the scene's depth fall below 1e-12.
COVARIANCE_RCOND = 1e-12
# The Schur-complement bundle adjustment (d2gs_np/pose/bundle.py, docs/dataset_format.md §8) inverts
# each point's damped 3x3 normal block from its eigendecomposition, with every eigenvalue raised to
# at least this times the block's largest: a point seen once, or along one ray, has a rank-2 block
# whose third eigenvalue is only the damping's. Cond <= 1e10 keeps the inverse's rounding (1e-16 x
# cond = 1e-6 relative, in a direction the camera rows barely see) harmless, while a genuinely
# observed depth direction (parallax 0.1 deg: eigenvalue ratio ~ (1.7e-3)^2 = 3e-6) is untouched.
BA_POINT_EIG_FLOOR = 1e-10
# The pose solver reads depths only where the static set's render has alpha >= this: the expected
# depth D / alpha of a pixel the static Gaussians barely cover is a guess (at alpha -> 0 it is a
# single faint Gaussian's depth), and such matches are dropped (and counted) instead.
POSE_DEPTH_ALPHA_MIN = 0.5

# The rasteriser's vectorisable exp(-sigma) (render/fast_exp.py ``exp_neg``) clamps its argument
# into [0, EXP_ARG_MAX]. Only sigma <= ln(opacity / ALPHA_THRESHOLD) + ALPHA_CUTOFF_SAFETY
# <= ln(255) + 1e-3 ~ 5.54 ever reaches a pixel (opacity <= 1); larger sigma is masked out, so the
# clamp only keeps those masked lanes finite. 8 > 5.54 with room, and keeps 2^-k in 4 bits (k <= 12).
EXP_ARG_MAX = 8.0

# --- Regularisers (docs/method.md §6) -------------------------------------------
# L_ts uses the smooth norm sqrt(|u|^2 + eps^2) - eps in place of |u|, which has no gradient at
# u = 0 (coincident neighbours, a Gaussian that does not move). 1e-6 world units / unit-free
# quaternion and colour residuals is far below any deformation that shows in a render (scenes
# span ~1-10 units), so the value differs from |u| by at most 1e-6, and the gradient u / sqrt(...)
# is the unit direction wherever |u| >> 1e-6 and goes smoothly to 0 at u = 0.
TS_NORM_EPS = 1e-6
# L_gs clamps the opacity to [OPACITY_ENTROPY_MIN, 1] inside the log (docs/method.md §6): log(o)
# is finite there, so -o log o and its gradient stay finite as o -> 0 (an opacity logit of -inf
# gives value 0 and gradient 0).
OPACITY_ENTROPY_MIN = 1e-6
# L_freq weights each phase difference by g(A_r) g(A_t), g(A) = A^2 / (A^2 + kappa^2): the phase
# of a coefficient with amplitude ~0 is undefined and its gradient grows as 1 / A. With the
# orthonormal FFT a bin's amplitude is on the pixels' scale: 8-bit quantisation noise
# (std 1 / (255 sqrt 12) ~ 1.1e-3 per pixel) gives amplitudes ~1e-3 in every bin, so a phase
# below that amplitude is noise and is gated out; above it the gate is ~1. g * dphi/dF is then
# bounded by 1 / (2 kappa).
FREQ_PHASE_GATE_AMPLITUDE = 1e-3
# An L_freq bin whose render amplitude is below this is treated as exactly 0 in the backward
# (the subgradient 0 of the cone |F| at F = 0): the FFT of an image with values ~1 rounds a true
# zero bin to ~1e-16 sqrt(H W) (< 1e-13 up to 10^6 pixels), and F / |F| of that rounding noise is a
# unit vector in a random direction, which would add an O(1) spurious gradient per such bin (a
# periodic or symmetric image has many). Real content is many orders of magnitude above it.
FREQ_AMPLITUDE_ZERO = 1e-12
# Width (in normalised radial frequency, 1 = Nyquist along an axis) of the cosine ramp of the
# L_freq high-pass mask around its cutoff: wide enough that the mask has no hard edge (ringing
# in the image domain), narrow against the cutoff 0.1.
FREQ_MASK_EDGE = 0.05
# Depth range of the initialisation (scene/initialize.py robust_depth_range) when every triangulated
# depth is the same (one point, or points on one fronto-parallel plane): [d / 1.2, 1.2 d] before
# the fill and sweep margins, so the plane sweep still gets near < far ([0.33, 2.2] x d in all).
ONE_DEPTH_RANGE_FACTOR = 1.2
# The robust depth range's spread: sigma = 1.4826 x the median absolute deviation of log depth
# (1.4826 makes the MAD a consistent estimate of a normal distribution's standard deviation).
MAD_TO_SIGMA = 1.4826
