"""Losses: SSIM (scikit-image semantics, exact backward) and the photometric L1 + SSIM loss."""
from d2gs_np.losses.photometric import photometric_bwd, photometric_fwd
from d2gs_np.losses.ssim import SSIM_WINDOW, ssim_bwd, ssim_fwd, ssim_map

__all__ = ["SSIM_WINDOW", "ssim_map", "ssim_fwd", "ssim_bwd", "photometric_fwd", "photometric_bwd"]
