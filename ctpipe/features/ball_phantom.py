"""Is this a ball phantom? A few large round blobs that hold nearly all of what the views show.

``ctpipe estimate`` with the default pipeline asks this of nine views spread over the scan
before detecting keypoints: a ball phantom (a ball bar, balls on a plate or in foam) has no
texture for keypoint detectors, and the default pipeline would refuse it, while the ball
calibration (:mod:`ctpipe.solve.balls`) is exact there. The measure is the share of the views'
small-scale structure (the line integrals less a grey opening a quarter of the detector wide: a
holder or a container wider than that is background) that lies in round blobs of one size, or
in blobs of two to four such balls merged where they overlap.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import ndimage
from scipy.spatial import ConvexHull

from ctpipe.features.ball_edges import bright_view
from ctpipe.images import block_mean


__all__ = ["ball_phantom_share", "looks_like_ball_phantom"]

#: The share of the views' structure in round blobs above which the views are a ball phantom: set
#: between the classes measured (docs/calibration-phantoms.md): ball phantoms 69-100 %, samples 0-18 %
#: (a cloud of 40 beads in a cylinder, 33-56 %, falls either side, and runs the default pipeline).
BALL_PHANTOM_SHARE = 0.5
#: More round blobs than this is a sample of beads or grains, not a calibration phantom.
MAX_BALLS = 60
#: Views are looked at binned to at most this many pixels a side.
_LOOK_PX = 512


def _line_integrals(view: np.ndarray) -> np.ndarray:
    """``view`` binned to at most :data:`_LOOK_PX` a side, as line integrals (balls bright)."""
    factor = max(1, int(math.ceil(max(view.shape) / _LOOK_PX)))
    return bright_view(view if factor == 1 else block_mean(view, factor))


def ball_phantom_share(view: np.ndarray) -> tuple[float, int]:
    """``(share, balls)``: the share of the view's small-scale structure in round blobs of one size, and their number.

    Plain numpy and scipy (no compiled kernels: the check runs before the pipeline, on inputs not
    yet known good). The structure is what rises above a grey opening a quarter of the detector
    wide by more than four noise deviations of a pixel (after a 1 px blur, fourteen of its own)
    and by a tenth of its brightest part;
    each connected blob of it is round when its second moments are within 25 % of each other and
    it fills 80 % of the disc of its own moments. Balls that overlap merge into a blob that is
    not round, and a holder narrower than the opening stays in the structure: a real phantom's
    share is below 1 (69-100 % measured), a sample's far lower (0-18 %).
    """
    g = _line_integrals(view)
    diagonal = (g[:-1:2, :-1:2] - g[:-1:2, 1::2] - g[1::2, :-1:2] + g[1::2, 1::2]) / 2.0
    noise = max(float(np.median(np.abs(diagonal))) / 0.6745, 1e-3 * float(np.ptp(g)) + 1e-12)
    g = ndimage.gaussian_filter(g, 1.0)          # the noise of a pixel falls 3.5-fold
    width = max(8, min(g.shape) // 4)
    tophat = np.clip(g - ndimage.grey_opening(g, size=(width, width)), 0.0, None)
    # Above the noise, and above a tenth of the brightest structure: a ball's chord profile falls
    # from its peak to a tenth within its last half percent of radius, while the blur and the
    # noise between balls a few pixels apart would otherwise join them into one blob.
    labels, count = ndimage.label(tophat > max(4.0 * noise, 0.1 * float(np.percentile(tophat, 99.9))))
    if count == 0:
        return 0.0, 0
    energy = tophat ** 2
    total = float(energy.sum())
    index = np.arange(1, count + 1)
    area = ndimage.sum_labels(np.ones_like(g), labels, index)
    weight = ndimage.sum_labels(energy, labels, index)
    rows, cols = np.mgrid[:g.shape[0], :g.shape[1]].astype(np.float64)
    mean_r = ndimage.mean(rows, labels, index)
    mean_c = ndimage.mean(cols, labels, index)
    var_r = ndimage.mean(rows ** 2, labels, index) - mean_r ** 2
    var_c = ndimage.mean(cols ** 2, labels, index) - mean_c ** 2
    cov = ndimage.mean(rows * cols, labels, index) - mean_r * mean_c
    spread = np.sqrt(np.maximum(((var_r - var_c) / 2.0) ** 2 + cov ** 2, 0.0))
    major, minor = (var_r + var_c) / 2.0 + spread, np.maximum((var_r + var_c) / 2.0 - spread, 1e-12)
    radius = np.sqrt(2.0 * (major + minor))                   # a uniform disc of radius R has variance R^2 / 4
    round_ = (minor / np.maximum(major, 1e-12) >= 0.75 ** 2) & (area >= 0.8 * np.pi * radius ** 2) & (radius >= 3.0)
    distance = ndimage.distance_transform_edt(labels > 0)
    inscribed = np.asarray(ndimage.maximum(distance, labels, index))
    if not round_.any() and not np.any(inscribed >= 3.0):
        return 0.0, 0
    # One size of ball (within 2.5x of the round blobs' median radius). Where every ball overlaps
    # another (a ball bar seen end-on, seven balls at three heights), no blob is round: the size is the
    # blobs' median inscribed radius, the largest disc inside each.
    typical = float(np.median(radius[round_])) if round_.any() else float(np.median(inscribed[inscribed >= 3.0]))
    balls = round_ & (radius <= 2.5 * typical) & (radius >= typical / 2.5)
    merged = _merged_balls(inscribed, area, labels, index, typical, None if round_.any() else distance) * ~round_
    share = float(weight[balls].sum() + weight[merged > 0].sum()) / total if total > 0 else 0.0
    return share, int(balls.sum() + merged.sum())


def _merged_balls(inscribed: np.ndarray, area: np.ndarray, labels: np.ndarray, index: np.ndarray,
                  typical: float, distance: np.ndarray | None = None) -> np.ndarray:
    """How many balls each blob holds where it is two or more merged where they overlap, else 0.

    Balls that overlap on the detector (twice a turn for two at one height) merge into one blob
    that is not round. Such a blob holds 1.15 to 4.5 times the area of the largest disc inside it
    (``inscribed``, the distance transform's maximum, a radius within 2.5x of ``typical``, as round balls must
    be) and is convex but for the notches where its discs meet (its area over its convex hull's
    at least 0.8: 0.85 for three equal balls touching in a row, more where they overlap). On 16
    layouts of the mixed phantom drawn at random, the views' share went from 4-99 % to 25-99 %
    (one view below 50 % in 144); the samples' stayed below 35 % (the bead cylinder 2-24 % ->
    5-34 %).

    With ``distance`` (the blobs' distance transform), a blob must also show its discs: two or
    more separate cores where it is at least 0.9 of its largest inscribed radius (two equal discs
    whose centres lie more than 0.87 radius apart; an ellipse has one core along its long axis).
    Asked where no blob is round and the blobs alone set the size, which would otherwise take the
    elongated blobs of a sample for merged balls (three of nine Shepp-Logan views 59-84 %).
    """
    discs = area / (np.pi * np.maximum(inscribed, 1e-9) ** 2)
    merged = np.zeros(len(index), dtype=np.int64)
    one_size = np.abs(np.log(np.maximum(inscribed, 1e-9) / typical)) <= math.log(2.5)
    candidates = one_size & (discs >= 1.15) & (discs <= 4.5)
    for k in np.flatnonzero(candidates):
        blob = labels == index[k]
        rows, cols = np.nonzero(blob)
        corners = np.concatenate([np.column_stack([rows + dr, cols + dc]) for dr in (-0.5, 0.5) for dc in (-0.5, 0.5)])
        if area[k] < 0.8 * ConvexHull(corners).volume:
            continue
        if distance is not None:
            _, cores = ndimage.label(blob & (distance >= 0.9 * inscribed[k]))
            if cores < 2:
                continue
        merged[k] = max(2, int(round(discs[k])))
    return merged


def looks_like_ball_phantom(projections, views: int = 9) -> tuple[bool, str]:
    """Whether ``projections`` (V, rows, cols) show a ball phantom, and the evidence in words.

    Most of ``views`` views spread over the scan must each show 2 to :data:`MAX_BALLS` balls
    (round blobs, or balls merged where they overlap) holding :data:`BALL_PHANTOM_SHARE` or more
    of their small-scale structure. Most, not all: twice a turn a ball bar's balls line up along
    the rays and two balls at one height overlap, and a view that happens to fall there says
    little about the scan (measured on 16 layouts of the mixed phantom drawn at random: 0-44 % of
    the views fail, every layout passes by the majority of five; docs/calibration-phantoms.md). Nine,
    not five: a Nikon folder of seven coated balls at three heights (17 views, one in five of them with
    two to five balls merged in one blob) was taken for a sample when views 8, 12 and 16 of the five
    asked for were three of its four such views; by nine, 6 of 9 pass.
    """
    picked = np.unique(np.linspace(0, len(projections) - 1, min(views, len(projections))).round().astype(int))
    found = [ball_phantom_share(np.asarray(projections[k])) for k in picked]
    passed = sum(2 <= n <= MAX_BALLS and s >= BALL_PHANTOM_SHARE for s, n in found)
    yes = bool(found) and passed > len(found) // 2
    what = ", ".join(f"{n} ({s:.0%})" for s, n in found)
    return yes, (f"{len(picked)} views show {what} balls (their share of the views' structure); a ball phantom "
                 f"has 2-{MAX_BALLS} holding {BALL_PHANTOM_SHARE:.0%} or more in most views")
