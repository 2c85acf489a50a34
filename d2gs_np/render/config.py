"""Renderer configuration."""
from __future__ import annotations

from dataclasses import dataclass

from d2gs_np import constants as C


@dataclass(frozen=True)
class RenderConfig:
    """Options of the splatter; defaults are gsplat 1.5.3's (docs/conventions.md).

    near_plane, far_plane: camera-z culling bounds (exclusive).
    eps2d: low-pass dilation added to the 2D covariance.
    antialiased: scale opacity by sqrt(det_orig / det_dilated) (off by default).
    tile_size: side of the square screen tiles in pixels.
    """

    near_plane: float = C.NEAR_PLANE
    far_plane: float = C.FAR_PLANE
    eps2d: float = C.EPS2D
    antialiased: bool = False
    tile_size: int = C.TILE_SIZE

    def __post_init__(self):
        if not (0.0 < self.near_plane < self.far_plane):
            raise ValueError(
                f"RenderConfig needs 0 < near_plane < far_plane; got near_plane={self.near_plane}, "
                f"far_plane={self.far_plane}"
            )
        if self.eps2d < 0.0:
            raise ValueError(f"RenderConfig.eps2d must be >= 0; got {self.eps2d}")
        if int(self.tile_size) != self.tile_size or self.tile_size < 1:
            raise ValueError(f"RenderConfig.tile_size must be a positive integer; got {self.tile_size}")
