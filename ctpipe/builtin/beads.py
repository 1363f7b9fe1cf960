"""The ``beads`` detector: balls of a calibration phantom, sub-pixel centres of the discs they project.

All balls look alike, so descriptors are of no use; what a calibration needs is each centre, to
a small fraction of a pixel, and to know which centres to trust. The method (noise and defects,
a scale space on an image pyramid, a top-hat background, least-squares fits of a blurred disc
model, crowds of overlapping balls), its accuracy and its cost are described in
:mod:`ctpipe.features.balls`, which holds the numerics; this module declares the stage's
parameters and packs what :func:`ctpipe.features.find_balls` finds.

Output: ``xy`` the centre, ``size`` the diameter, ``angle_deg`` NaN, ``response`` the contrast
(the fitted peak line integral, in the units of the image, or of ``-log`` of a dark one),
``descriptors`` ``[radius_px, contrast]`` (float32, L2) and in ``class_id`` a quality flag:
0 clean, 1 the disc overlaps another (centres closer than the sum of the radii: balls at
different depths projecting onto each other) or belongs to a crowd the model does not fully
explain, 2 the disc is cut by the image border (before 1). A ball whose centre is off the
image is not reported.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from ctpipe.data import Features
from ctpipe.errors import ConfigError
from ctpipe.features import find_balls
from ctpipe.hookspecs import hookimpl
from ctpipe.stages import Detector, param

__all__ = ["BeadDetector"]


@dataclass(frozen=True)
class BeadDetector(Detector):
    """Balls of a calibration phantom: sub-pixel disc centres, radii and contrasts."""

    min_diameter_px: float | None = param(
        None, doc="smallest projected ball diameter, px (null: 10 px, and the balls' own size decides)", ge=2,
        le=4096)
    max_diameter_px: float | None = param(
        None, doc="largest projected ball diameter, px (null: a third of the image, and the balls' own size decides)",
        ge=2, le=4096)
    polarity: Literal["auto", "bright", "dark"] = param(
        "auto", doc="bright discs on dark (line integrals), dark on bright (raw intensities), or decide per image")
    min_contrast_sigma: float = param(5.0, doc="smallest ball height above background, in noise standard deviations",
                                      gt=0, le=1e6)
    max_beads: int = param(1000, doc="keep at most this many balls, highest contrast first", ge=1, le=1_000_000)
    centre_method: Literal["fit", "centroid"] = param(
        "fit", doc="sub-pixel centre: least-squares fit of a blurred disc model, or iterative weighted centroid")

    def __post_init__(self) -> None:
        super().__post_init__()
        if (self.min_diameter_px is not None and self.max_diameter_px is not None
                and self.min_diameter_px > self.max_diameter_px):
            raise ConfigError(f"BeadDetector.min_diameter_px: must be <= max_diameter_px ({self.max_diameter_px:g}), "
                              f"got {self.min_diameter_px:g}")

    def detect(self, image: np.ndarray) -> Features:
        """Find the balls of ``image``.

        Parameters
        ----------
        image : ndarray of shape (rows, cols)
            Line integrals (float) or raw intensities (any integer or float dtype).

        Returns
        -------
        Features
            One keypoint per ball, highest contrast first: ``xy`` the centre (x=col, y=row, px),
            ``size`` the diameter (px), ``response`` the contrast (image units), ``class_id``
            0 clean / 1 overlapping / 2 cut by the border, ``descriptors`` ``[radius_px, contrast]``.
            Empty when there is none.
        """
        beads = find_balls(image, min_diameter_px=self.min_diameter_px, max_diameter_px=self.max_diameter_px,
                           polarity=self.polarity, min_contrast_sigma=self.min_contrast_sigma,
                           max_beads=self.max_beads, centre_method=self.centre_method)
        return Features.build(xy=beads[:, :2], size=2.0 * beads[:, 2], angle_deg=np.full(len(beads), np.nan),
                              response=beads[:, 3], class_id=beads[:, 4].astype(np.int32),
                              descriptors=beads[:, 2:4].astype(np.float32), norm="L2")


@hookimpl
def ctpipe_register_stages(registry) -> None:
    registry.add_detector("beads", BeadDetector)
