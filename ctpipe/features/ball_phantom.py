"""Is this a ball phantom? A few large round blobs that hold nearly all of what the views show.

``ctpipe estimate`` with the default pipeline asks this of three views spread over the scan
before detecting keypoints: a ball phantom (a ball bar, balls on a plate or in foam) has no
texture for keypoint detectors, and the default pipeline would refuse it, while the ball
calibration (:mod:`ctpipe.solve.balls`) is exact there. The measure is the share of the views'
small-scale structure (the line integrals less a grey opening wider than any ball: a holder or
a container wider than the balls is background) that lies on the discs the ball finder fits.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import ndimage

from ctpipe.features.balls import find_balls

__all__ = ["ball_phantom_share", "looks_like_ball_phantom"]

#: The share of the views' structure on the balls' discs above which the views are a ball phantom.
BALL_PHANTOM_SHARE = 0.6
#: More round blobs than this is a sample of beads or grains, not a calibration phantom.
MAX_BALLS = 60
#: Views are looked at binned to at most this many pixels a side.
_LOOK_PX = 512


def _line_integrals(view: np.ndarray) -> np.ndarray:
    """``view`` binned to at most :data:`_LOOK_PX` a side, as line integrals (balls bright)."""
    f = np.asarray(view, dtype=np.float64)
    factor = max(1, int(math.ceil(max(f.shape) / _LOOK_PX)))
    if factor > 1:
        rows, cols = (f.shape[0] // factor) * factor, (f.shape[1] // factor) * factor
        f = f[:rows, :cols].reshape(rows // factor, factor, cols // factor, factor).mean(axis=(1, 3))
    if float(np.median(f)) > 0.5 * (float(f.min()) + float(f.max())):     # dark balls on a bright field: counts
        f = -np.log(np.maximum(f, 0.5) / max(float(f.max()), 1.0)) if f.min() > 0 else -f
    return f


def ball_phantom_share(view: np.ndarray) -> tuple[float, int]:
    """``(share, balls)``: the share of the view's small-scale structure on the fitted discs, and their number."""
    g = _line_integrals(view)
    balls = find_balls(g, polarity="bright", centre_method="centroid", max_beads=MAX_BALLS + 1)
    if not len(balls):
        return 0.0, 0
    width = int(math.ceil(2.5 * float(np.max(balls[:, 2])))) + 3
    tophat = np.clip(g - ndimage.grey_opening(ndimage.gaussian_filter(g, 1.0), size=(width, width)), 0.0, None)
    rows, cols = np.mgrid[:g.shape[0], :g.shape[1]]
    on = np.zeros(g.shape, bool)
    for cx, cy, r, *_ in balls:
        on |= (cols - cx) ** 2 + (rows - cy) ** 2 <= (1.15 * r + 1.0) ** 2
    energy = float(np.sum(tophat ** 2))
    return (float(np.sum(tophat[on] ** 2)) / energy if energy > 0 else 0.0), len(balls)


def looks_like_ball_phantom(projections, views: int = 3) -> tuple[bool, str]:
    """Whether ``projections`` (V, rows, cols) show a ball phantom, and the evidence in words.

    Three views spread over the scan must each show 2 to :data:`MAX_BALLS` round blobs holding
    :data:`BALL_PHANTOM_SHARE` or more of their small-scale structure.
    """
    picked = np.unique(np.linspace(0, len(projections) - 1, min(views, len(projections))).round().astype(int))
    found = [ball_phantom_share(np.asarray(projections[k])) for k in picked]
    shares, counts = [s for s, _ in found], [n for _, n in found]
    yes = all(2 <= n <= MAX_BALLS and s >= BALL_PHANTOM_SHARE for s, n in found)
    what = ", ".join(f"{n} ({s:.0%})" for s, n in found)
    return yes, (f"{len(picked)} views show {what} round blobs (their share of the views' structure); a ball phantom "
                 f"has 2-{MAX_BALLS} holding {BALL_PHANTOM_SHARE:.0%} or more")
