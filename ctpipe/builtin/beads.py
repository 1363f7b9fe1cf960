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
explain, 2 the disc is cut by the image border (before 1), 3 (the rim method only) the disc's
rim crosses the edge of a clipped background, which pulls its circle
(:mod:`ctpipe.features.ball_edges`); with the rim method, ``clipped_side`` the side a clipped
background cuts the rim on, from which the calibration models that pull
(:attr:`ctpipe.data.Features.clipped_side`), and ``centre_edge_px`` the radius of the circle whose
centre ``xy`` is: the rim's, or a hollow or coated ball's shell's inside where it shows one, which
no clip reaches (:attr:`ctpipe.data.Features.centre_edge_px`), and ``centre_se_px`` its centre's
standard error from that edge (:attr:`ctpipe.data.Features.centre_se_px`). A ball whose centre is off
the image is not reported.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar, Literal

import numpy as np

from ctpipe.data import Features
from ctpipe.errors import ConfigError
from ctpipe.features import bright_view, edge_centres, find_balls, rim_seeds
from ctpipe.features.balls import _AUTO_MIN_DIAMETER_PX, _OVERLAP, _TRUNCATED
from ctpipe.hookspecs import hookimpl
from ctpipe.images import block_mean
from ctpipe.stages import Detector, param

__all__ = ["BeadDetector"]

#: Where the rim places the balls, they are found at this fraction of ``fit_radius_px``.
_RIM_FIND_FRACTION = 0.5
#: The smallest radius (px) :func:`ctpipe.features.find_balls` looks for by default.
_SMALLEST_FOUND_RADIUS_PX = 0.5 * _AUTO_MIN_DIAMETER_PX


@dataclass(frozen=True)
class BeadDetector(Detector):
    """Balls of a calibration phantom: sub-pixel disc centres, radii and contrasts."""

    # Its fits and rim profiles are numpy's small calls in Python loops: nine 2000^2 views of a ball scan took 15.1 s
    # on two threads against 17.5 s on one (2 cores), so a pipeline detects large views on processes.
    holds_gil: ClassVar[bool] = True

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
    centre_method: Literal["auto", "fit", "centroid", "rim"] = param(
        "auto", doc="sub-pixel centre: least-squares fit of a blurred disc model, iterative weighted centroid, a "
                    "robust circle through the outer rim at full resolution (hollow and coated balls, overlaps, dust: "
                    "ctpipe.features.ball_edges), or auto: the rim for balls found on a binned image (fit_radius_px), "
                    "the disc fit otherwise")
    fit_radius_px: float | None = param(
        16.0, doc="balls larger than twice this radius (px) are found and fitted on the image binned to bring them "
                  "near it (near half of it where their rims place them): the fit's work grows with the ball's "
                  "area, its centre's error with the noise per ball (null: always the full image)", ge=4, le=1024)

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
            0 clean / 1 overlapping / 2 cut by the border / 3 rim across a clip edge, ``descriptors``
            ``[radius_px, contrast]``.
            Empty when there is none.
        """
        factor, radius_px, smallest_px = self._binning(image)
        # Large balls: found on the binned image (by the disc fit and, for the hollow balls it
        # refuses, the top-hat's centroid), placed on their rim at full resolution (measured on a 2000^2 view of solid
        # and hollow balls 110-190 px across: within 0.03 px of the ellipse centre, where the disc
        # fit was 0.6-1.7 px off on hollow and overlapping ones). Small ones: the disc fit, 0.0008
        # deg on the 16-view ball bar against 0.0099 by the rim.
        method = self.centre_method if self.centre_method != "auto" else "rim" if factor > 1 else "fit"
        if method == "rim" and radius_px is not None:
            factor = _rim_binning(factor, radius_px, smallest_px, self.fit_radius_px)
        work = image if factor == 1 else block_mean(image, factor)
        scale = 1.0 / factor
        options = dict(min_diameter_px=None if self.min_diameter_px is None else self.min_diameter_px * scale,
                       max_diameter_px=None if self.max_diameter_px is None else self.max_diameter_px * scale,
                       polarity=self.polarity, min_contrast_sigma=self.min_contrast_sigma, max_beads=self.max_beads)
        beads = find_balls(work, centre_method="fit" if method == "rim" else method, **options)
        if method == "rim":
            # The disc fit splits overlapping balls but refuses hollow ones; the top-hat's centroid
            # keeps those: every centroid that no fitted ball explains joins them.
            found = find_balls(work, centre_method="centroid", **options)
            if len(beads):
                distance = np.hypot(found[:, None, 0] - beads[None, :, 0], found[:, None, 1] - beads[None, :, 1])
                found = found[np.all(distance > 0.5 * beads[None, :, 2], axis=1)]
            beads = np.vstack([beads, found])
            bright = bright_view(image, self.polarity)
            found_before_seeds = len(beads)
            if radius_px is not None:
                beads, found_before_seeds = _with_rim_seeds(beads, rim_seeds(bright, radius_px), factor, work.shape)
            beads = beads[:self.max_beads]
        if factor > 1:   # back to the full image's pixels: a block's centre is (index + 0.5) factor - 0.5
            beads[:, :2] = (beads[:, :2] + 0.5) * factor - 0.5
            beads[:, 2] *= factor
        side = edge = se = None
        if method == "rim":
            beads, side, placed, edge, se = edge_centres(bright, beads, clipped_side=True, fitted=True,
                                                         edge_radius=True, centre_se=True)
            # A seed whose rim could not be fitted is no ball found (dust, a holder's edge): only a found ball keeps
            # its detected centre where its rim does not fit.
            keep = _distinct(beads) & (placed | (np.arange(len(beads)) < found_before_seeds))
            beads, side, edge, se = beads[keep], side[keep], edge[keep], se[keep]
        return Features.build(xy=beads[:, :2], size=2.0 * beads[:, 2], angle_deg=np.full(len(beads), np.nan),
                              response=beads[:, 3], class_id=beads[:, 4].astype(np.int32),
                              descriptors=beads[:, 2:4].astype(np.float32), norm="L2", clipped_side=side,
                              centre_edge_px=edge, centre_se_px=se)

    def _binning(self, image: np.ndarray) -> tuple[int, float | None, float | None]:
        """The binning the balls are fitted at (1, or what brings their radius near ``fit_radius_px``),
        their median radius and the smallest one's (px; None where they were not looked at).

        Their size is read off a coarse look (the image binned to about 256 px a side); balls too
        small to be seen there are fitted at full resolution.
        """
        if self.fit_radius_px is None or min(image.shape) < 512:
            return 1, None, None
        coarse = max(1, min(image.shape) // 256)
        look = find_balls(block_mean(image, coarse), polarity=self.polarity,
                          min_contrast_sigma=self.min_contrast_sigma, max_beads=self.max_beads,
                          centre_method="centroid")
        if not len(look):
            return 1, None, None
        radius_px = float(np.median(look[:, 2])) * coarse
        return max(1, int(radius_px // self.fit_radius_px)), radius_px, float(np.min(look[:, 2])) * coarse


def _with_rim_seeds(beads: np.ndarray, seeds: np.ndarray, factor: int,
                    shape: tuple[int, int]) -> tuple[np.ndarray, int]:
    """``beads`` (binned pixels, ``shape`` the binned image's) with the balls the rims show that they
    miss, and the blobs of several balls found as one replaced by those balls; and how many of the
    rows are found balls (the seeds' follow).

    The top-hat's centroid finds hollow balls that overlap as one blob, its centre between them and
    its radius larger. A found ball whose disc holds two rim seeds or more
    (:func:`ctpipe.features.ball_edges.rim_seeds`, full resolution) is such a blob: the seeds
    replace it. A seed no found ball holds is a ball of its own. Either is flagged overlapping (cut
    by the border where its circle crosses it). A found ball holding one seed starts the rim fit
    from the seed's centre and radius: a blob's centroid, a ball half hidden behind another, lies
    off the ball, its radius larger, and the rim fit settled on a circle through both (a simulated
    view: 25 px off, 113 px against 78). The rim fit places every one.
    """
    if not len(seeds):
        return beads, len(beads)
    xy = (seeds[:, :2] + 0.5) / factor - 0.5
    radius = seeds[:, 2] / factor
    held = np.zeros((len(beads), len(seeds)), bool)
    if len(beads):
        held = np.hypot(beads[:, None, 0] - xy[None, :, 0], beads[:, None, 1] - xy[None, :, 1]) <= beads[:, 2, None]
    blob = held.sum(axis=1) >= 2
    beads = np.array(beads, dtype=np.float64, copy=True)
    one = np.flatnonzero(held.sum(axis=1) == 1)
    seed_of = np.argmax(held[one], axis=1)
    beads[one, 0], beads[one, 1], beads[one, 2] = xy[seed_of, 0], xy[seed_of, 1], radius[seed_of]
    taken = np.any(held[~blob], axis=0)
    xy, radius = xy[~taken], radius[~taken]
    cut = (xy[:, 0] < radius) | (xy[:, 1] < radius) | (xy[:, 0] > shape[1] - 1 - radius) | \
        (xy[:, 1] > shape[0] - 1 - radius)
    contrast = np.full(len(xy), float(np.median(beads[:, 3])) if len(beads) else 0.0)
    new = np.column_stack([xy, radius, contrast, np.where(cut, float(_TRUNCATED), float(_OVERLAP))])
    return np.vstack([beads[~blob], new]), int(np.sum(~blob))


def _distinct(beads: np.ndarray) -> np.ndarray:
    """Which balls to keep where two rims settled on one ball (centres within a quarter radius): the first."""
    keep = np.ones(len(beads), bool)
    for k in range(1, len(beads)):
        distance = np.hypot(beads[:k, 0] - beads[k, 0], beads[:k, 1] - beads[k, 1])
        keep[k] = not np.any(keep[:k] & (distance < 0.25 * beads[k, 2]))
    return keep


def _rim_binning(factor: int, radius_px: float, smallest_px: float, fit_radius_px: float) -> int:
    """The binning balls are found at where their rims place them: their radius near half ``fit_radius_px``.

    The rim places the balls; the binned fit only finds them and splits overlapping ones, which it
    does as well at half the radius: on the mixed ball phantom's 2000^2 views (balls 110-190 px
    across), 1.06 s a view against 2.54, the rims' centres as close to the truth (median 0.031 px
    against 0.032), as many balls found (docs/calibration-phantoms.md). No coarser than keeps the
    smallest ball of the look at the finder's smallest radius, and no finer than ``factor``.
    """
    rim_factor = min(int(radius_px // (_RIM_FIND_FRACTION * fit_radius_px)),
                     int(smallest_px // _SMALLEST_FOUND_RADIUS_PX))
    return max(factor, rim_factor)


@hookimpl
def ctpipe_register_stages(registry) -> None:
    registry.add_detector("beads", BeadDetector)
