"""Renderer configuration."""
from __future__ import annotations

from dataclasses import dataclass

from d2gs_np import constants as C
from d2gs_np.base.checks import check_bool, check_int, check_number


@dataclass(frozen=True)
class RenderConfig:
    """Options of the splatter; defaults are gsplat 1.5.3's (docs/conventions.md).

    near_plane, far_plane: camera-z culling bounds (exclusive).
    eps2d: low-pass dilation added to the 2D covariance.
    antialiased: scale opacity by sqrt(det_orig / det_dilated) (off by default).
    tile_size: side of the square screen tiles in pixels.
    raster_float32: with float64 inputs, run the binning, the compositing and its backward
        (most of a forward + backward) in float32; the projection, its backward and every
        output and gradient stay float64. A speed option for training (the rasteriser's loops
        vectorise over twice the lanes); its error against the float64 render is measured in
        tests/render/test_raster_float32.py and examples/bench_render.py. No effect on float32
        inputs. Off by default: the reference path is float64 throughout.
    """

    near_plane: float = C.NEAR_PLANE
    far_plane: float = C.FAR_PLANE
    eps2d: float = C.EPS2D
    antialiased: bool = False
    tile_size: int = C.TILE_SIZE
    raster_float32: bool = False

    def __post_init__(self):
        if not (0.0 < self.near_plane < self.far_plane):
            raise ValueError(
                f"RenderConfig needs 0 < near_plane < far_plane; got near_plane={self.near_plane}, "
                f"far_plane={self.far_plane}"
            )
        check_number(self.eps2d, "RenderConfig.eps2d", 0.0)
        check_int(self.tile_size, "RenderConfig.tile_size", 1, hint="pixels")
        for name in ("antialiased", "raster_float32"):
            check_bool(getattr(self, name), f"RenderConfig.{name}")
