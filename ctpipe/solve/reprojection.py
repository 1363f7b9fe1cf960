"""Projection matching: every view's angle against a reconstruction of the scan itself.

Pair estimates and feature tracks tie views to their neighbours; what they cannot pin is the
slow drift of a long chain. A reconstruction from all views is a common reference instead:
each view's angle is moved until the reprojection of the volume at that angle matches the
measured projection, then the volume is rebuilt with the new angles, and so on. Every view
is compared with the same object, so errors do not add up along the scan.

One iteration, at one detector binning:

1. ``V = FDK(P, theta)`` on a grid that covers the field of view (:func:`reconstruction_grid`);
2. for each view, the reprojection ``A_k V`` at ``theta_k`` and its derivative with respect to
   the angle, ``g_k = A_k D``, where ``D = z dV/dx - x dV/dz`` is the volume's change under a
   turn of the table (:func:`tangential_derivative`; one extra projection, no finite
   differences);
3. both the residual ``r_k = P_k - A_k V`` and ``g_k`` are band-passed (:func:`band_pass`, a
   difference of Gaussians) before the Gauss-Newton step ``delta_k = <g_k, r_k> / <g_k, g_k>``.

The band-pass is what makes it work. FDK of a wide cone leaves low-frequency errors in the
volume (cupping, the ends of a tall object) whose reprojections differ from the data by ~10 %,
and those differences correlate with ``g_k``: without the filter the step of every view is off by
tenths of a degree even at the true angles. The finest detail is cut as well, since the grid
cannot hold it. What remains, edges of a few pixels, moves with the angle and is reproduced by
the volume. The steps are capped (:func:`step_cap_deg`: what the band holds linear) and their
mean is removed (a common turn of all views only turns the volume). Levels run coarse to fine
(:func:`matching_levels`): a coarse binning has the capture range for slips of a degree or more,
a fine one the precision.

**A model whose minimum is at the truth.** Matching walks away from even the true angles when
the reference it matches against is not the object the data show, so what the scanner does is
part of the fit:

- *The detector* (``detector``): the column the axis images at and the detector's in-plane
  tilt are common to all views and fitted with the angles; the views are resampled onto the
  aligned detector (:func:`_align`) before the next reconstruction. An FDK with the axis a pixel
  off blurs every point into an arc, and matching against it bends the angles (a sweep scan with
  the axis 1.5 px off and a 0.3 deg tilt, started at the true angles, walked to 1.2 deg). On the
  first level the detector is aligned first, with the angles held, until its step is small.
- *A drifting detector or source* (``shifts``): every view's column and row shift is fitted
  with its angle (the reprojection's own gradients are the shifts' slopes; three unknowns a
  view), and what an object's place on the table explains as well (a once-per-turn column shift,
  a common row shift) is left out; the common column shift is the axis. The angle's step and
  standard error are those of its slope with the shifts' part projected out, so a view whose
  turn looks like a shift says so. On a 120-view bead scan with a 0.1 px-a-view walk and two
  1 px jumps, the shifts are found to 0.05 px RMS and the angles' RMS falls from 0.39 to 0.18 deg.
- *What does not turn* (``static``, :func:`static_part`): on a short scan a static table edge
  is consistent with no object and FDK smears it into the reference; the views' median is taken
  out. On a full turn the views' mean is (the projection of the object averaged over the turn).

**An optimiser that cannot walk away.** Every step is evaluated by the cost it leads to (a new
reconstruction and reprojection): it is kept only where the cost falls by more than twice what
fitting the unknowns to noise alone would take off it (:attr:`_Fit.noise_drop`, Akaike's
criterion), tried whole (with the slow modes' extrapolation on a full turn), then halved; a
level ends when no step is kept or when the steps are within their own noise. Started at the
true angles, a step that only follows noise or the volume's own errors is thus not taken.

Measured on ``ctpipe validate``'s default scan (360 views, 0.2 deg jitter plus three 1 deg
jumps, per-view RMS 0.57 deg from the nominal angles): see ``docs/wholescan.md``. Views on either
side of a wide gap between neighbours pull towards their nearer neighbours: the volume's own
imperfection sets the floor.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numba
import numpy as np
from scipy import fft as sp_fft
from numba import prange

from ctpipe._shared.jit import FASTMATH, njit
from ctpipe.errors import InputError
from ctpipe.geometry import Geometry, check_geometry
from ctpipe.recon.feldkamp import FILTERS, bin_detector, covers_full_circle, fdk
from ctpipe.recon.volume import VolumeGrid
from ctpipe.solve.bands import split_bands

__all__ = ["ProjectionMatchingResult", "projection_matching", "matching_levels", "consistency_costs", "reconstruction_grid",
           "tangential_derivative", "band_pass", "as_line_integrals", "static_part", "static_part_applies",
           "step_cap_deg", "HeldOutScore", "held_out_scores", "held_out_decisive", "slow_even_band_scores",
           "HELD_OUT_Z", "HELD_OUT_DECISIVE_Z"]

# Views reprojected at a time: bounds the memory of the reprojections to a few chunks' worth.
_CHUNK_VIEWS = 16


@dataclass(frozen=True, eq=False)
class ProjectionMatchingResult:
    """What :func:`projection_matching` found.

    Attributes
    ----------
    angles_deg : ndarray of shape (V,)
        The matched angles, in the frame of the start angles (same mean).
    history : tuple of dict
        One entry per evaluation: ``binning``, ``iteration`` (0: the level's start), ``kind``
        (``start``, ``step``, ``extrapolated``, ``half step``), ``cost`` (band-passed residual
        energy relative to the data's, at the angles evaluated), ``accepted`` (whether the cost
        fell), ``step_rms_deg`` and ``step_max_deg`` (the change tried), ``shift_rms_px``,
        ``tilt_deg`` and ``seconds``.
    stopped : str
        Empty when every level ran its steps or stopped at its noise; otherwise why a level
        stopped early (no step lowered the cost, or FDK refused the angles).
    angle_se_deg : ndarray of shape (V,) or None
        Each view's standard error from the last iteration's Gauss-Newton fit: the spread of
        its step under the residual that fit leaves, its own spectrum taken as it is
        (:func:`_step_variance`), times :data:`SE_CALIBRATION`; inf where a view's slope carries
        no information; None when no iteration ran. It does not see a slow warp of the angles
        that the reconstruction absorbed: such errors it leaves to the gate
        (``docs/wholescan.md``).
    shifts_px : ndarray of shape (V, 2) or None
        With ``shifts``: each view's detector shift found (columns, rows; unbinned pixels),
        without its common and once-per-turn column part and its common row part
        (:func:`_shift_gauge`; the common column part is ``axis_offset_px``); else None.
    axis_offset_px : float or None
        With ``detector``: the column the rotation axis images at, less the geometry's
        ``u0_px`` (unbinned pixels); else None.
    tilt_deg : float or None
        With ``detector``: the detector's in-plane tilt, degrees, in the convention of
        :mod:`ctpipe.solve.camera` (bundle adjustment's, and the written cone vectors'); a
        simulated ``misalignment.tilt_deg`` of ``t`` is found as ``-t``. Else None.
    held_out : dict of str to HeldOutScore or None
        With ``compare``: the matched angles (``matched``) and every angle set compared, scored
        on held-out views with the detector found (:meth:`_Level.held_out`), each against the
        first set compared: at the coarsest level where that is decisive
        (:func:`held_out_decisive`), else at the finest; else None.
    held_out_binning : int or None
        The binning (of the projections given) the held-out scores were made at; None without
        ``compare``.
    held_out_slow_even : dict of str to HeldOutScore or None
        Where the matched angles' held-out z against the first set compared is decisive
        (at or below ``-HELD_OUT_DECISIVE_Z``): the slow-even band of their change from it (the
        constant and the even harmonics up to the third, as the gate splits it) judged on its
        own, at the same level: ``band``, the matched angles against the same less that band,
        and ``without``, the matched angles less the band against the first set compared
        (:func:`slow_even_band_scores`). Else None.
    """

    angles_deg: np.ndarray
    history: tuple[dict, ...]
    stopped: str = ""
    angle_se_deg: np.ndarray | None = None
    shifts_px: np.ndarray | None = None
    axis_offset_px: float | None = None
    tilt_deg: float | None = None
    held_out: dict[str, HeldOutScore] | None = None
    held_out_binning: int | None = None
    held_out_slow_even: dict[str, HeldOutScore] | None = None


#: Standard errors by which matched angles must predict held-out views better than the nominal ones
#: to be returned instead (one-sided: 2.3 % of an angle set no better passing, on an exact error).
HELD_OUT_Z = 2.0


@dataclass(frozen=True)
class HeldOutScore:
    """How well one angle set predicts views it was not reconstructed from, against a reference set.

    Attributes
    ----------
    cost : float
        Band-passed residual energy of every view against an FDK of the other views' fold,
        relative to the data's (:meth:`_Level.held_out`).
    delta : float
        ``cost - cost(reference)``.
    delta_se : float
        Its standard error: the per-view differences in neighbouring blocks (Flyvbjerg and
        Petersen's blocking, as the conjugate rays' score: neighbouring views share structure).
    dof : int
        The blocks less one.
    """

    cost: float
    delta: float = 0.0
    delta_se: float = 0.0
    dof: int = 0

    @property
    def z(self) -> float:
        """``delta / delta_se``: below -2, these angles predict held-out views better than the reference's."""
        return self.delta / self.delta_se if self.delta_se > 0 else 0.0

    def to_dict(self) -> dict:
        return {"cost": self.cost, "delta": self.delta, "delta_se": self.delta_se, "dof": self.dof, "z": self.z}


def held_out_scores(level: "_Level", candidates: dict[str, np.ndarray], reference: str,
                    folds: int = 2) -> dict[str, HeldOutScore]:
    """:class:`HeldOutScore` of every candidate angle set (degrees) at one level, against ``reference``,
    each view predicted from the views of the other ``folds - 1`` folds (:meth:`_Level.held_out`)."""
    return _scores_against({name: level.held_out(angles, folds) for name, angles in candidates.items()}, reference)


def _scores_against(energies: dict[str, tuple[np.ndarray, np.ndarray]], reference: str) -> dict[str, HeldOutScore]:
    """:class:`HeldOutScore` of every angle set from its per-view held-out energies (:meth:`_Level.held_out`)."""
    from ctpipe.solve.conjugate import _blocked_se

    base, data = energies[reference]
    total = max(float(data.sum()), 1e-300)
    scores = {}
    for name, (residual, _) in energies.items():
        if name == reference:
            scores[name] = HeldOutScore(float(residual.sum()) / total)
            continue
        se, blocks = _blocked_se((residual - base) / total) if len(residual) > 2 else (math.inf, 1)
        scores[name] = HeldOutScore(float(residual.sum()) / total, float((residual - base).sum()) / total, se,
                                    blocks - 1)
    return scores


def matching_levels(shape: tuple[int, int], iterations, *, level_px=(128, 256), binning=None) -> list[tuple[int, int]]:
    """``(binning, iterations)`` of each level for a detector of ``shape`` (rows, cols).

    With ``binning`` None, the finest level bins the detector to about ``level_px[-1]`` pixels a
    side (factor ``round(min(shape) / level_px[-1])``, at least 1) and each coarser one by
    ``level_px[-1] / level_px[k]`` more, so a 512^2 detector is matched at 128^2 then 256^2, a
    2,048^2 one at the same sizes, and a 128^2 one at 64^2 then 128^2: a small detector keeps its
    coarse level (the capture range for slips) instead of running every level at full size.
    Levels that come out at the same factor are merged (their iterations add up); levels that
    would leave fewer than 16 pixels a side are dropped.
    """
    side = min(shape)
    if binning is None:
        finest = max(1, int(round(side / max(level_px[-1], 1))))
        factors = [finest * max(1, int(round(level_px[-1] / max(px, 1)))) for px in level_px]
    else:
        factors = [int(b) for b in binning]
    levels: list[tuple[int, int]] = []
    for factor, count in zip(factors, iterations):
        if side // factor < 16:
            continue
        if levels and levels[-1][0] == factor:
            levels[-1] = (factor, levels[-1][1] + int(count))
        else:
            levels.append((factor, int(count)))
    return [(b, n) for b, n in levels if n > 0]


def reconstruction_grid(geometry: Geometry, max_voxels: int) -> VolumeGrid:
    """A grid over the field of view: the cylinder every view sees, and its full height.

    The cylinder's radius is ``SOD sin(fan half-angle)``; its height reaches the top and bottom
    rays at the far side of the cylinder. Voxels are the detector pixel at the axis
    (``pitch * SOD / SDD``), or larger so that the cylinder's diameter takes at most
    ``max_voxels``; the height takes what it needs, up to twice that.
    """
    g = geometry
    half_u = max(g.u0_px + 0.5, g.detector_cols - 0.5 - g.u0_px) * g.pixel_pitch_u_mm
    half_v = max(g.v0_px + 0.5, g.detector_rows - 0.5 - g.v0_px) * g.pixel_pitch_v_mm
    radius = g.source_to_object_mm * math.sin(math.atan(half_u / g.source_to_detector_mm))
    half_height = half_v * (g.source_to_object_mm + radius) / g.source_to_detector_mm
    voxel = min(g.pixel_pitch_u_mm, g.pixel_pitch_v_mm) * g.source_to_object_mm / g.source_to_detector_mm
    voxel = max(voxel, 2.0 * radius / max_voxels, half_height / max_voxels)
    n_xz = max(int(math.ceil(2.0 * radius / voxel)), 8)
    n_y = max(int(math.ceil(2.0 * half_height / voxel)), 8)
    return VolumeGrid(n_xz, n_y, n_xz, voxel)


def tangential_derivative(volume: np.ndarray, grid: VolumeGrid) -> np.ndarray:
    """The change of ``volume`` per degree of turntable angle, float32 of ``grid.shape``.

    Turning the table by ``+delta`` shows the object turned by ``R(delta)``: the volume seen is
    ``V(R(delta)^-1 X)``, whose derivative at 0 is ``z dV/dx - x dV/dz`` (per radian). Its
    projection at ``theta`` is the derivative of the projection with respect to ``theta``.
    """
    # (n_y, n_z, n_x): x along the last axis, z along the middle one; np.gradient's numbers, in parallel.
    dv_dx, dv_dz = _image_gradients(np.ascontiguousarray(volume, dtype=np.float32), grid.voxel_size_mm)
    x = grid.axis_mm("x").astype(np.float32)[None, None, :]
    z = grid.axis_mm("z").astype(np.float32)[None, :, None]
    return (np.float32(math.pi / 180.0) * (z * dv_dx - x * dv_dz)).astype(np.float32)


def band_pass(images: np.ndarray, low_px: float, high_px: float) -> np.ndarray:
    """Difference of Gaussians over the last two axes: detail between ``low_px`` and ``high_px``.

    ``gaussian(low_px) - gaussian(high_px)``; ``low_px = 0`` keeps the finest detail. The same
    filter as :func:`scipy.ndimage.gaussian_filter` (kernels truncated at 4 sigma, mirrored
    edges: ``mode="reflect"``), both blurs in one parallel pass over the images.
    """
    images = np.asarray(images, dtype=np.float32)
    shape = images.shape
    stack = np.ascontiguousarray(images.reshape((-1,) + shape[-2:]))
    out = np.empty_like(stack)
    _difference_of_gaussians(stack, _gaussian_taps(low_px), _gaussian_taps(high_px), out)
    return out.reshape(shape)


def _gaussian_taps(sigma: float) -> np.ndarray:
    """:func:`scipy.ndimage.gaussian_filter1d`'s kernel (truncated at 4 sigma, summing to 1); [1] for 0."""
    if sigma <= 0:
        return np.ones(1, dtype=np.float64)
    radius = int(4.0 * float(sigma) + 0.5)
    x = np.arange(-radius, radius + 1, dtype=np.float64)
    taps = np.exp(-0.5 * (x / float(sigma)) ** 2)
    return taps / taps.sum()


@njit(cache=True, inline="always")
def _mirror(index: int, n: int) -> int:
    """``mode="reflect"``: (d c b a | a b c d | d c b a)."""
    period = 2 * n
    index %= period
    return index if index < n else period - 1 - index


@njit(cache=True, fastmath=FASTMATH, inline="always")
def _blur_down(image, taps, out):
    """``out`` = ``image`` (rows, cols) convolved along its rows' axis with ``taps``, mirrored edges."""
    rows, cols = image.shape
    radius = len(taps) // 2
    for i in range(rows):
        out[i, :] = 0.0
        for k in range(-radius, radius + 1):
            weight = np.float32(taps[k + radius])
            source = image[_mirror(i + k, rows)]
            for j in range(cols):
                out[i, j] += weight * source[j]


@njit(cache=True, fastmath=FASTMATH, inline="always")
def _add_blurred_across(row, taps, sign, padded, out):
    """``out += sign * (row convolved with taps)``, mirrored edges; ``padded``: scratch of len(row) + len(taps) - 1."""
    cols = len(row)
    radius = len(taps) // 2
    for j in range(cols + 2 * radius):
        padded[j] = row[_mirror(j - radius, cols)]
    for k in range(2 * radius + 1):
        weight = np.float32(sign * taps[k])
        for j in range(cols):
            out[j] += weight * padded[j + k]


@njit(parallel=True, fastmath=FASTMATH, cache=True)
def _difference_of_gaussians(images, fine_taps, coarse_taps, out):
    """``out = G(fine) * images - G(coarse) * images`` per image (V, rows, cols), rows then columns."""
    n_images, rows, cols = images.shape
    for index in prange(n_images):
        fine = np.empty((rows, cols), dtype=np.float32)
        coarse = np.empty((rows, cols), dtype=np.float32)
        _blur_down(images[index], fine_taps, fine)
        _blur_down(images[index], coarse_taps, coarse)
        padded_fine = np.empty(cols + len(fine_taps) - 1, dtype=np.float32)
        padded_coarse = np.empty(cols + len(coarse_taps) - 1, dtype=np.float32)
        for i in range(rows):
            row = out[index, i]
            row[:] = 0.0
            _add_blurred_across(fine[i], fine_taps, 1.0, padded_fine, row)
            _add_blurred_across(coarse[i], coarse_taps, -1.0, padded_coarse, row)


@njit(parallel=True, fastmath=FASTMATH, cache=True)
def _normal_equations(columns, residual, gram, rhs):
    """Per view, ``gram[v, a, b] = <columns[v, a], columns[v, b]>`` and ``rhs[v, a] = <columns[v, a], residual[v]>``.

    columns (V, K, rows, cols) and residual (V, rows, cols) float32; the sums in float64, the
    views in parallel (NumPy's ``einsum`` of the same runs on one thread).
    """
    n_views, size, rows, cols = columns.shape
    for v in prange(n_views):
        for a in range(size):
            for b in range(a, size):
                total = 0.0
                for i in range(rows):
                    for j in range(cols):
                        total += np.float64(columns[v, a, i, j]) * np.float64(columns[v, b, i, j])
                gram[v, a, b] = total
                gram[v, b, a] = total
            total = 0.0
            for i in range(rows):
                for j in range(cols):
                    total += np.float64(columns[v, a, i, j]) * np.float64(residual[v, i, j])
            rhs[v, a] = total


@njit(parallel=True, cache=True)
def _image_gradients(images, spacing):
    """``(np.gradient(images, spacing, axis=2), np.gradient(images, spacing, axis=1))`` of a (V, rows,
    cols) float32 stack, the images in parallel: central differences inside, one-sided at the
    edges, in float32 as NumPy computes them (the same numbers)."""
    n_images, rows, cols = images.shape
    along_u = np.empty_like(images)
    along_v = np.empty_like(images)
    inner = np.float32(2.0 * spacing)
    edge = np.float32(spacing)
    for k in prange(n_images):
        for i in range(rows):
            for j in range(1, cols - 1):
                along_u[k, i, j] = (images[k, i, j + 1] - images[k, i, j - 1]) / inner
            along_u[k, i, 0] = (images[k, i, 1] - images[k, i, 0]) / edge
            along_u[k, i, cols - 1] = (images[k, i, cols - 1] - images[k, i, cols - 2]) / edge
        for i in range(1, rows - 1):
            for j in range(cols):
                along_v[k, i, j] = (images[k, i + 1, j] - images[k, i - 1, j]) / inner
        for j in range(cols):
            along_v[k, 0, j] = (images[k, 1, j] - images[k, 0, j]) / edge
            along_v[k, rows - 1, j] = (images[k, rows - 1, j] - images[k, rows - 2, j]) / edge
    return along_u, along_v


def as_line_integrals(projections: np.ndarray, *, overwrite: bool = False) -> tuple[np.ndarray, bool]:
    """Projections as line integrals (dark object on a bright field is taken as intensities).

    Returns the array (float32) and whether it was converted. Intensities are recognised by a
    border brighter than the centre and turned into ``-log(I / I_flat)`` with ``I_flat`` the
    99.5th percentile of each view. The conversion goes a chunk of views at a time, into a new
    array, or with ``overwrite`` into ``projections`` itself where it is a float32 array (the
    caller's copy: 2,000 binned views are half a gigabyte each time).
    """
    p = np.asarray(projections, dtype=np.float32)
    _, rows, cols = p.shape
    border = np.concatenate([p[:, :, : max(cols // 16, 1)].ravel(), p[:, :, -max(cols // 16, 1):].ravel()])
    centre = p[:, rows // 4: rows - rows // 4, cols // 4: cols - cols // 4]
    if not float(np.median(border)) > float(np.median(centre)):
        return p, False
    out = p if overwrite and p is projections and p.flags.writeable else np.empty_like(p)
    for start in range(0, len(p), _CHUNK_VIEWS):
        views = p[start:start + _CHUNK_VIEWS]
        flat = np.percentile(views.reshape(len(views), -1), 99.5, axis=1).astype(np.float32)
        floor = np.float32(1e-6) * np.maximum(flat, np.float32(1e-30))
        ratio = np.maximum(views, floor[:, None, None]) / np.maximum(flat, np.float32(1e-30))[:, None, None]
        out[start:start + _CHUNK_VIEWS] = np.maximum(-np.log(ratio), 0.0)
    return out, True



def static_part(projections: np.ndarray, angles_deg, max_views: int = 180) -> np.ndarray:
    """The part of every view that does not tell the views apart, shape (rows, cols).

    On a full turn, the views' mean: exactly the projection of the object averaged over the turn
    (a rotationally symmetric object, plus anything that does not turn), so the views less it are
    still the projections of one object turning, and FDK's errors on the large symmetric part
    (a container's wall, the matrix) leave the residual. On a short scan, the per-pixel median
    over up to ``max_views`` evenly spread views: a table edge that does not turn is there
    consistent with no object, and the median holds it and none of the features that move
    across the detector (the mean would hold a smear of them).
    """
    if covers_full_circle(angles_deg):
        return np.mean(np.asarray(projections, dtype=np.float32), axis=0, dtype=np.float64).astype(np.float32)
    views = np.unique(np.linspace(0, len(projections) - 1, min(len(projections), max_views)).round().astype(int))
    return np.median(np.asarray(projections[views], dtype=np.float32), axis=0)


def static_part_applies(angles_deg) -> bool:
    """Whether matching should take the :func:`static_part` out: 16 views or more over 180 deg or more.

    Measured on sweep scans matched from their true angles (``docs/wholescan.md``): on a 250 deg
    trabecular scan with a static table edge (axis off, detector tilted) taking the median out
    took the matched angles from 5.7 to 0.39 deg RMS, on a bead scan from 0.086 to 0.062. On a
    full turn the median (not a linear function of the views) disturbed a Shepp-Logan scan, whose
    large elliptical outline it left as a moving edge in every view (0.62 deg from the truth,
    against 0 without), while the mean costs nothing there and takes the default validate scan
    from 0.022 to 0.017 deg.
    """
    angles = np.asarray(angles_deg, dtype=np.float64)
    if len(angles) < 16:
        return False
    step = float(np.median(np.abs(np.diff(angles))))
    return float(np.ptp(angles)) + step >= 180.0


def _align(raw: np.ndarray, geometry: Geometry, shift_px: tuple[float, float], tilt_rad: float) -> np.ndarray:
    """One view of ``raw`` (rows, cols) resampled onto the aligned detector.

    The aligned view at pixel ``X`` (mm from the principal point ``c``) is the recorded one at
    ``c + d + R(tilt) X``: a detector shifted by ``d = (du, dv)`` pixels and turned in its own
    plane by ``tilt`` shows the aligned view's content moved by ``d`` and turned by ``-tilt``
    (:mod:`ctpipe.sim.drift`'s convention: ``tilt`` here is minus its ``tilt_deg``). Cubic spline,
    edges continued.
    """
    from scipy.ndimage import affine_transform

    g = geometry
    c, s = math.cos(tilt_rad), math.sin(tilt_rad)
    ratio = g.pixel_pitch_u_mm / g.pixel_pitch_v_mm
    du, dv = float(shift_px[0]), float(shift_px[1])
    # Array index order (row, col): input = matrix @ output + offset.
    matrix = np.array([[c, s * ratio], [-s / ratio, c]])
    offset = np.array([g.v0_px + dv - c * g.v0_px - s * ratio * g.u0_px,
                       g.u0_px + du - c * g.u0_px + s / ratio * g.v0_px])
    return affine_transform(raw, matrix, offset, order=3, mode="nearest").astype(np.float32, copy=False)


@dataclass(frozen=True)
class _Fit:
    """One Gauss-Newton evaluation at one level: the cost at the angles it was made at, and the step from them.

    ``step_deg`` (V,) the angle steps, ``noise_deg`` (V,) their spread under the residual the fit
    leaves (:func:`_step_variance`, not calibrated), ``shift_px`` (V, 2) the per-view shift steps
    (binned pixels) or None, ``tilt_rad`` the detector tilt's step (0 unless fitted), ``axis_px``
    the axis column's step where it is fitted without per-view shifts (binned pixels, else 0),
    ``held`` the detector's steps
    ``(shift_px, tilt_rad, axis_px)`` of the same fit with the angles held, and ``noise_drop`` how
    much the cost would fall from fitting the per-view unknowns to noise alone: a step that lowers
    the cost by no more than that is not told apart from fitting noise.
    """

    cost: float
    step_deg: np.ndarray | None = None
    noise_deg: np.ndarray | None = None
    shift_px: np.ndarray | None = None
    tilt_rad: float = 0.0
    axis_px: float = 0.0
    held: tuple | None = None
    noise_drop: float = 0.0


class _Views:
    """Every view's line integrals as recorded, which a level bins and resamples onto its aligned detector.

    A level's aligned views sit beside the views as recorded, which it resamples from again
    whenever the alignment changes. Where the array is ours to spend (``spend``: a copy the
    caller handed over, as the refiner stage's binned views are), the views are kept instead
    as 16-bit codes, each view with its own offset and step (a step of its range / 65,534: a
    few 1e-5 of a line integral, far under the noise of a binned view), and the array itself
    takes the aligned views: at 2,000 views of 256^2 that is 0.26 GB beside the aligned views'
    0.52 GB, where a second float32 copy was 0.52 GB. Until the first alignment the array holds
    the views as recorded, exactly, and no codes are made. One level at a time aligns into it: a
    level made at binning 1 from the same views takes them back as recorded.
    """

    def __init__(self, views: np.ndarray, *, spend: bool = False) -> None:
        self.views = np.ascontiguousarray(views, dtype=np.float32)
        self.spend = (bool(spend) or self.views is not views) and self.views.flags.writeable   # a copy is ours
        self.codes: np.ndarray | None = None       # (V, rows, cols) int16, once the array is spent
        self.offset = self.step = None             # (V,) float32 each
        self.aligned_in_views = False              # whether ``views`` holds aligned views now
        self._aligned: np.ndarray | None = None    # the aligned copy of views not ours to spend

    def __len__(self) -> int:
        return len(self.views)

    def recorded(self, start: int, stop: int) -> np.ndarray:
        """Views ``start:stop`` as recorded (float32; decoded where the array holds aligned views)."""
        if self.codes is None:
            return self.views[start:stop]
        codes = self.codes[start:stop].astype(np.float32)
        codes += np.float32(32767.0)
        return codes * self.step[start:stop, None, None] + self.offset[start:stop, None, None]

    def binned(self, geometry: Geometry, factor: int) -> tuple[np.ndarray, Geometry]:
        """The views as recorded, binned ``factor x factor`` (:func:`bin_detector`), a chunk of views at a time."""
        if factor == 1:
            return self.unaligned(), geometry
        out = None
        for start in range(0, len(self), _CHUNK_VIEWS):
            part, coarse = bin_detector(self.recorded(start, start + _CHUNK_VIEWS), geometry, factor)
            if out is None:
                out = np.empty((len(self),) + part.shape[1:], dtype=np.float32)
            out[start:start + len(part)] = part
        return out, coarse

    def unaligned(self) -> np.ndarray:
        """All views as recorded, as one float32 array (the array itself, decoded into it if it holds aligned views)."""
        self._aligned = None
        if self.aligned_in_views:
            for start in range(0, len(self), _CHUNK_VIEWS):
                self.views[start:start + _CHUNK_VIEWS] = self.recorded(start, start + _CHUNK_VIEWS)
            self.aligned_in_views = False
        return self.views

    def aligned_out(self) -> np.ndarray:
        """The float32 array the aligned views are to be written into.

        :meth:`recorded` reads the views as recorded meanwhile (from the codes, where the array is spent).
        """
        if self.spend and self.codes is None:
            self._encode()
        if self.codes is not None:
            self.aligned_in_views = True
            return self.views
        if self._aligned is None:
            self._aligned = np.empty_like(self.views)
        return self._aligned

    def _encode(self) -> None:
        """The views as 16-bit codes; none where a view holds a value that is not finite (nothing to scale by)."""
        n = len(self)
        flat = self.views.reshape(n, -1)
        low, high = flat.min(axis=1), flat.max(axis=1)
        if not (np.all(np.isfinite(low)) and np.all(np.isfinite(high))):
            return
        self.offset = low.astype(np.float32)
        self.step = np.where(high > low, (high - low) / np.float32(65534.0), np.float32(1.0)).astype(np.float32)
        self.codes = np.empty(self.views.shape, dtype=np.int16)
        for start in range(0, n, _CHUNK_VIEWS):
            part = slice(start, start + _CHUNK_VIEWS)
            scaled = (self.views[part] - self.offset[part, None, None]) / self.step[part, None, None]
            self.codes[part] = np.rint(scaled - np.float32(32767.0)).astype(np.int16)


class _Level:
    """One binning: the binned data (as recorded, and resampled onto the aligned detector), the grid and the projector.

    ``projections``: an array (read, not written) or :class:`_Views` (the finest level's, shared
    with the levels binned from it).
    """

    def __init__(self, projections, geometry: Geometry, binning: int, max_voxels: int,
                 band_px: tuple[float, float], filter: str) -> None:
        from ctpipe.sim.projectors import VoxelProjector

        self.binning = binning
        views = projections if isinstance(projections, _Views) else _Views(projections)
        if binning == 1:
            self.raw, self.geometry = views, geometry
        else:
            binned, self.geometry = views.binned(geometry, binning)
            self.raw = _Views(binned, spend=True)     # a copy of this level's own
        self.grid = reconstruction_grid(self.geometry, max_voxels)
        self.projector = VoxelProjector(self.geometry, self.grid)
        self.band_px = band_px
        self.filter = filter
        self.align(None, 0.0)

    def align(self, shifts_px: np.ndarray | None, tilt_rad: float) -> None:
        """Take the views resampled onto the aligned detector as the data (:func:`_align`).

        ``shifts_px`` (V, 2: columns, rows; binned pixels) per view, ``tilt_rad`` the detector's
        in-plane turn; ``None`` and 0 take the views as they are.
        """
        if (shifts_px is None or not np.any(shifts_px)) and tilt_rad == 0.0:
            self.data = self.raw.unaligned()
            return
        shifts = np.zeros((len(self.raw), 2)) if shifts_px is None else np.asarray(shifts_px, dtype=np.float64)
        # The aligned views are written over the last aligned ones, or over the spent array's
        # views (:class:`_Views`): a new array beside them would hold another copy of the views
        # for the length of the resampling (0.52 GB at 2,000 views of 256^2).
        self.data = self.raw.aligned_out()

        def one(k: int) -> None:
            self.data[k] = _align(self.raw.recorded(k, k + 1)[0], self.geometry, shifts[k], tilt_rad)

        # SciPy's resampling lets go of the GIL: one thread per numba thread.
        with ThreadPoolExecutor(max_workers=numba.get_num_threads()) as pool:
            list(pool.map(one, range(len(self.raw))))

    def cost(self, angles_deg: np.ndarray) -> float:
        """Band-passed residual energy of the data against the reprojection of their FDK, relative to the data's."""
        volume = fdk(self.data, self.geometry, angles_deg, self.grid, filter=self.filter)
        residual_energy = data_energy = 0.0
        for start in range(0, len(angles_deg), _CHUNK_VIEWS):
            part = slice(start, start + _CHUNK_VIEWS)
            filtered = band_pass(self.data[part], *self.band_px)
            residual = filtered - band_pass(self.projector.forward(volume, angles_deg[part]), *self.band_px)
            data_energy += float(np.einsum("vij,vij->", filtered, filtered, dtype=np.float64))
            residual_energy += float(np.einsum("vij,vij->", residual, residual, dtype=np.float64))
        return residual_energy / max(data_energy, 1e-300)

    def held_out(self, angles_deg: np.ndarray, folds: int = 2) -> tuple[np.ndarray, np.ndarray]:
        """Each view's band-passed residual against a reference that does not contain it, and its data energy.

        The views are dealt into ``folds`` interleaved folds; each fold is reprojected from an FDK
        of the others. A reference built with a view in it bends towards that view's angle, right
        or wrong (the volume is the views' own backprojections), so its residual rewards angles
        it was made from; a held-out view's does not. Returns two arrays of shape (V,).
        """
        angles = np.asarray(angles_deg, dtype=np.float64)
        residual = np.zeros(len(angles))
        energy = np.zeros(len(angles))
        fold = np.arange(len(angles)) % folds
        for k in range(folds):
            # Two folds: the other fold is every second view, a view of the data and not a copy.
            others = self.data[1 - k::2] if folds == 2 else self.data[fold != k]
            volume = fdk(others, self.geometry, angles[fold != k], self.grid, filter=self.filter)
            views = np.flatnonzero(fold == k)
            for start in range(0, len(views), _CHUNK_VIEWS):
                part = views[start:start + _CHUNK_VIEWS]
                filtered = band_pass(self.data[part], *self.band_px)
                left = filtered - band_pass(self.projector.forward(volume, angles[part]), *self.band_px)
                residual[part] = np.einsum("vij,vij->v", left, left, dtype=np.float64)
                energy[part] = np.einsum("vij,vij->v", filtered, filtered, dtype=np.float64)
        return residual, energy

    def fit(self, angles_deg: np.ndarray, *, shifts: bool = False, detector: bool = False) -> _Fit:
        """The cost at ``angles_deg`` and the Gauss-Newton step from there.

        Per view, the angle (and with ``shifts`` its column and row shift); with ``detector``,
        the detector's in-plane tilt common to all views, and without ``shifts`` also the axis
        column (with them, the axis is the shifts' common part). The reprojection's own column
        and row gradients are the shifts' slopes and its gradient turned about the principal
        point the tilt's. Every view's unknowns are eliminated (Schur complement) to solve for
        the common ones, then solved with them. The angle's spread is that of its slope with
        the per-view shifts' part projected out (Frisch-Waugh-Lovell), so a view whose turn looks
        like a shift gets the larger error it has.
        """
        volume = fdk(self.data, self.geometry, angles_deg, self.grid, filter=self.filter)
        derivative = tangential_derivative(volume, self.grid)
        n = len(angles_deg)
        per_view = 3 if shifts else 1
        common = (1 if detector else 0) + (1 if detector and not shifts else 0)
        size = per_view + common
        gram = np.zeros((n, size, size))
        rhs = np.zeros((n, size))
        variance = np.zeros(n)
        residual_energy = data_energy = 0.0
        g = self.geometry
        rows, cols = g.shape
        # The tilt's slope uses each pixel's offset from the principal point in mm-consistent units.
        v_off = ((np.arange(rows) - g.v0_px) * (g.pixel_pitch_v_mm / g.pixel_pitch_u_mm)).astype(np.float32)[:, None]
        u_off = ((np.arange(cols) - g.u0_px) * (g.pixel_pitch_u_mm / g.pixel_pitch_v_mm)).astype(np.float32)[None, :]
        chunks = self.projector.forward_pair(volume, derivative, angles_deg, chunk_views=_CHUNK_VIEWS)
        for part, projected, projected_slope in chunks:
            filtered = band_pass(self.data[part], *self.band_px)
            data_energy += float(np.einsum("vij,vij->", filtered, filtered, dtype=np.float64))
            model = band_pass(projected, *self.band_px)
            residual = filtered - model
            residual_energy += float(np.einsum("vij,vij->", residual, residual, dtype=np.float64))
            slope = band_pass(projected_slope, *self.band_px)
            columns = [slope]
            if shifts or detector:
                grad_u, grad_v = _image_gradients(np.ascontiguousarray(model, dtype=np.float32), 1.0)
            if shifts:
                # A view shifted by +d shows model(u - d) = model - d * d(model)/du.
                columns += [-grad_u, -grad_v]
            if detector:
                # Content turned by +phi about the principal point: model(R(-phi) X) = model + phi * t.
                columns.append(grad_u * v_off - grad_v * u_off)
                if not shifts:
                    columns.append(-grad_u)
            stack = np.stack(columns, axis=1)
            _normal_equations(stack, np.ascontiguousarray(residual), gram[part], rhs[part])
            lone = slope if not shifts else _project_out(slope, stack[:, 1:3])
            lone_energy = np.einsum("vij,vij->v", lone, lone, dtype=np.float64)
            lone_num = np.einsum("vij,vij->v", lone, residual, dtype=np.float64)
            variance[part] = _step_variance(lone, residual, lone_num, lone_energy)
        solution, informative = _solve_blocks(gram, rhs, per_view)
        step = np.where(informative, solution[:, 0], 0.0)
        noise = np.where(informative, np.sqrt(variance), np.inf)
        # Fitting one unknown to pure noise lowers a view's residual energy by var(step) <s, s>;
        # each view has per_view unknowns of about that spread.
        drop = per_view * float(np.sum(np.where(informative, variance * gram[:, 0, 0], 0.0)))
        fit = _Fit(residual_energy / max(data_energy, 1e-300), step, noise,
                   solution[:, 1:3] if shifts else None,
                   float(solution[0, per_view]) if detector else 0.0,
                   float(solution[0, per_view + 1]) if detector and not shifts else 0.0,
                   noise_drop=drop / max(data_energy, 1e-300))
        if shifts or detector:
            # The same fit with every angle held: the detector's own step, for aligning it first.
            if per_view > 1:
                held, _ = _solve_blocks(gram[:, 1:, 1:], rhs[:, 1:], per_view - 1)
            else:
                pooled = gram[:, 1:, 1:][informative].sum(0)
                pooled += 1e-9 * np.trace(pooled) * np.eye(len(pooled)) + 1e-300 * np.eye(len(pooled))
                held = np.broadcast_to(np.linalg.solve(pooled, rhs[:, 1:][informative].sum(0)), (n, size - 1))
            fit = dataclasses.replace(fit, held=(held[:, :2] if shifts else None,
                                                 float(held[0, per_view - 1]) if detector else 0.0,
                                                 float(held[0, per_view]) if detector and not shifts else 0.0))
        return fit


def _solve_blocks(gram: np.ndarray, rhs: np.ndarray, per_view: int) -> tuple[np.ndarray, np.ndarray]:
    """Least squares with ``per_view`` unknowns of every view and the rest common to all views.

    ``gram`` (V, n, n) and ``rhs`` (V, n) are each view's normal equations over its own unknowns
    followed by the common ones. The views' own unknowns are eliminated (Schur complement), the
    common ones solved from the pooled reduced system, then each view's from its own equations.
    Returns (V, n) (the common unknowns repeated in every row) and which views carry information.
    """
    n_views, size, _ = gram.shape
    scale = np.maximum(np.einsum("vii->vi", gram), 1e-300)
    informative = gram[:, 0, 0] > 1e-12 * max(float(gram[:, 0, 0].max(initial=0.0)), 1e-300)
    own = gram[:, :per_view, :per_view] + 1e-9 * np.einsum("vi,ij->vij", scale[:, :per_view], np.eye(per_view))
    own[~informative] = np.eye(per_view)
    out = np.zeros((n_views, size))
    common = np.zeros(size - per_view)
    if size > per_view:
        cross = gram[:, :per_view, per_view:]
        solved_cross = np.linalg.solve(own, cross)                       # (V, p, q)
        solved_rhs = np.linalg.solve(own, rhs[:, :per_view, None])[..., 0]
        reduced = (gram[:, per_view:, per_view:] - np.einsum("vpa,vpb->vab", cross, solved_cross))[informative].sum(0)
        reduced_rhs = (rhs[:, per_view:] - np.einsum("vpa,vp->va", cross, solved_rhs))[informative].sum(0)
        reduced += 1e-9 * np.trace(reduced) * np.eye(len(reduced)) + 1e-300 * np.eye(len(reduced))
        common = np.linalg.solve(reduced, reduced_rhs)
        out[:, per_view:] = common
        view_rhs = rhs[:, :per_view] - cross @ common
    else:
        view_rhs = rhs[:, :per_view]
    out[:, :per_view] = np.linalg.solve(own, view_rhs[..., None])[..., 0]
    out[~informative, :per_view] = 0.0
    return out, informative


def _project_out(slope: np.ndarray, moved: np.ndarray) -> np.ndarray:
    """The angle slope (v, rows, cols) with the span of the shift slopes ``moved`` (v, 2, rows, cols) removed."""
    gram = np.einsum("vaij,vbij->vab", moved, moved, dtype=np.float64)
    ridge = 1e-9 * np.trace(gram, axis1=1, axis2=2)[:, None, None] * np.eye(2) + 1e-300 * np.eye(2)
    cross = np.einsum("vaij,vij->va", moved, slope, dtype=np.float64)
    along = np.linalg.solve(gram + ridge, cross[..., None])[..., 0]
    return slope - np.einsum("va,vaij->vij", along.astype(np.float32), moved)


#: How much larger a matched view's error is than the spread its residual alone implies. The fit
#: leaves errors the residual does not show (what the reference volume got wrong moves with the
#: view's own slope); measured with truth as the ratio of the errors to that spread: 3.3 on the
#: default ``ctpipe validate`` scan, 2.5 on ``tests/solve/test_reprojection.py``'s (which then have
#: 93 % and 98 % of views within two standard errors). The sweep checks it on scans it was not
#: set on (``docs/wholescan.md``).
SE_CALIBRATION = 2.5


def _step_variance(slope: np.ndarray, residual: np.ndarray, numerator: np.ndarray,
                   denominator: np.ndarray) -> np.ndarray:
    """Variance of each view's Gauss-Newton step ``<s, r> / <s, s>``, from what its fit leaves.

    The residual ``r' = r - step s`` left after the step is neither white nor the same in every
    view: it is band-passed data, and mostly what the reconstruction gets wrong. So its power
    spectrum is taken as it is (a sandwich estimate, one per view): ``var <s, r'> = sum_k
    |S(k)|^2 |R'(k)|^2 / N^2`` over the view's 2-D Fourier coefficients (``N`` pixels), over
    ``<s, s>^2``. Shapes (v, rows, cols) and (v,); returns (v,), degrees squared.
    """
    with np.errstate(divide="ignore", invalid="ignore"):
        step = np.where(denominator > 0, numerator / denominator, 0.0)
    left = residual - step[:, None, None].astype(np.float32) * slope
    n_pixels = slope.shape[1] * slope.shape[2]
    # SciPy's FFT over all cores (NumPy's runs on one: 2 of the default refine's 88 s on two cores).
    power = np.abs(sp_fft.rfft2(slope, workers=-1)) ** 2 * np.abs(sp_fft.rfft2(left, workers=-1)) ** 2
    # rfft2 keeps half the last axis: every column but the first (and the Nyquist one) stands for two.
    weights = np.full(power.shape[2], 2.0)
    weights[0] = 1.0
    if slope.shape[2] % 2 == 0:
        weights[-1] = 1.0
    spread = np.einsum("vij,j->v", power, weights) / n_pixels**2
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(denominator > 0, spread / denominator**2, np.inf)


def _extrapolate_slow_modes(step: np.ndarray, previous: np.ndarray, theta_rad: np.ndarray,
                            harmonics: int = 4, max_ratio: float = 0.8) -> np.ndarray:
    """Aitken extrapolation of the slowly converging low harmonics of the angle steps (a full turn only).

    A turn-periodic warp of the angles ``a cos(k theta) + b sin(k theta)`` of low order ``k`` is
    nearly an affine stretch of the object, which the reconstruction absorbs: matching removes
    only a fraction ``1 - rho`` of it per iteration, so successive steps in that mode shrink
    geometrically by ``rho``. The rest of the series is ``step * rho / (1 - rho)``; it is added
    for each harmonic whose ratio is positive and whose steps agree in direction, with the ratio
    capped at ``max_ratio`` (at most 4 times the step). The harmonics are those of a full turn:
    on a short scan they are neither orthogonal nor the modes a reconstruction absorbs, so
    :func:`projection_matching` extrapolates only full turns, and keeps an extrapolated step
    only where the cost falls with it.
    """
    columns = [np.ones_like(theta_rad)]
    for k in range(1, harmonics + 1):
        columns += [np.cos(k * theta_rad), np.sin(k * theta_rad)]
    basis = np.stack(columns, axis=1)
    coeffs, *_ = np.linalg.lstsq(basis, np.stack([step, previous], axis=1), rcond=None)
    extra = np.zeros_like(step)
    for k in range(1, harmonics + 1):
        now, before = coeffs[2 * k - 1: 2 * k + 1, 0], coeffs[2 * k - 1: 2 * k + 1, 1]
        energy = float(before @ before)
        if energy <= 0.0:
            continue
        rho = float(now @ before) / energy
        cosine = float(now @ before) / max(float(np.sqrt(energy * (now @ now))), 1e-300)
        if rho > 0.0 and cosine > 0.8:
            rho = min(rho, max_ratio)
            extra += basis[:, 2 * k - 1: 2 * k + 1] @ now * (rho / (1.0 - rho))
    return extra


def step_cap_deg(geometry: Geometry, grid: VolumeGrid, band_high_px: float) -> float:
    """The largest angle step one Gauss-Newton iteration is trusted with at one level, degrees.

    The step is linear in the angle error while the features move by less than the band-pass's
    coarse scale: a turn of ``delta`` moves a point at the edge of the grid (radius ``R``) by
    ``M R delta`` on the detector, so the cap is ``band_high_px * pitch / (M R)`` radians, the
    pitch and scale those of the level (``geometry`` binned). Not less than 0.05 deg.
    """
    radius_mm = 0.5 * grid.n_x * grid.voxel_size_mm
    moved_px = geometry.magnification * radius_mm / geometry.pixel_pitch_u_mm
    return max(math.degrees(band_high_px / max(moved_px, 1e-9)), 0.05)


def _check(projections, geometry, angles_deg, binning, iterations, band_px, max_voxels, filter, max_step_deg):
    check_geometry(geometry)
    p = np.asarray(projections)
    if p.ndim != 3 or p.shape[1:] != geometry.shape or not np.issubdtype(p.dtype, np.number):
        raise InputError(f"projections: must be a real array of shape (views, {geometry.detector_rows}, "
                         f"{geometry.detector_cols}), got {p.dtype} {p.shape}")
    angles = np.asarray(angles_deg, dtype=np.float64)
    if angles.shape != (len(p),) or not np.all(np.isfinite(angles)):
        raise InputError(f"angles_deg: must be {len(p)} finite angles, one per view, got shape {angles.shape}")
    if len(binning) != len(iterations) or not binning:
        raise InputError(f"binning and iterations: must be non-empty and of one length, got {list(binning)} and "
                         f"{list(iterations)}")
    for b in binning:
        if not (isinstance(b, (int, np.integer)) and 1 <= b <= min(geometry.shape) // 8):
            raise InputError(f"binning: each factor must be an integer from 1 to {min(geometry.shape) // 8} "
                             f"(at least 8 binned pixels a side), got {b!r}")
    low, high = band_px
    if not (0 <= low < high):
        raise InputError(f"band_px: must be (low, high) with 0 <= low < high, got {band_px!r}")
    if filter not in FILTERS:
        raise InputError(f"filter: {filter!r} is not supported. Try one of {FILTERS}")
    if not (max_step_deg is None or max_step_deg > 0) or not max_voxels >= 8:
        raise InputError(f"max_step_deg must be > 0 (or None: from the band) and max_voxels >= 8, got "
                         f"{max_step_deg!r} and {max_voxels!r}")
    return angles


#: Largest change of the per-view shifts (binned pixels) and of the detector tilt (radians) in one step.
_MAX_SHIFT_STEP_PX = 2.0
_MAX_TILT_STEP_RAD = math.radians(0.5)


def projection_matching(projections: np.ndarray, geometry: Geometry, angles_deg, *, binning=(4, 2),
                        iterations=(3, 2), band_px: tuple[float, float] = (0.7, 4.0), max_voxels: int = 192,
                        filter: str = "ram-lak", max_step_deg: float | None = None, shifts: bool = False,
                        detector: bool = False, static: bool = False, compare: dict[str, np.ndarray] | None = None,
                        progress: Callable[[int], object] | None = None,
                        overwrite: bool = False) -> ProjectionMatchingResult:
    """Refine every view's angle against the scan's own reconstruction (see the module docstring).

    Parameters
    ----------
    projections : ndarray of shape (V, rows, cols)
        Line integrals (or intensities, see :func:`as_line_integrals`).
    geometry : Geometry
    angles_deg : array_like of shape (V,)
        Start angles, degrees: the nominal ones, or better a whole-scan feature estimate.
    binning : sequence of int
        Detector binning of each level, coarse to fine.
    iterations : sequence of int
        Most Gauss-Newton steps at each level; a level ends sooner when a step no longer lowers
        the cost or when the steps are within their own noise.
    band_px : (float, float)
        Difference-of-Gaussians band in binned pixels: the sigmas of the fine and coarse blur.
    max_voxels : int
        Largest grid edge; bounds time and memory at fine levels.
    filter : str
        FDK ramp-filter window (:data:`ctpipe.recon.feldkamp.FILTERS`); the sharp ``ram-lak`` matches best.
    max_step_deg : float or None
        Largest change of a view's angle in one step; None: from the band at each level
        (:func:`step_cap_deg`).
    shifts : bool
        Fit each view's detector shift (columns, rows) with its angle, for a detector or source
        that drifts during the scan; the data are moved back by the shifts found before each
        reconstruction. Shifts an object on the table explains (a once-per-turn column shift, a
        common row shift) are left out (:func:`_shift_gauge`); the common column shift is the
        axis.
    detector : bool
        Fit the detector's in-plane tilt and the axis column (the centre of rotation) with the
        angles: both are common to every view, and an FDK made with them wrong is not the object,
        so matching against it walks the angles away from the truth.
    static : bool
        Match the views less their :func:`static_part` (what does not turn with the sample);
        :func:`static_part_applies` says where that is right.
    compare : dict of str to ndarray of shape (V,), optional
        Other angle sets (degrees) to score beside the matched ones on held-out views, on the
        detector found (:func:`held_out_scores`), each against the first: at the coarsest level
        where its z is decisive either way (:func:`held_out_decisive`), else at the finest.
    progress : callable, optional
        Called with 1 after every step tried.

    overwrite : bool
        ``projections`` (a float32 array) may be spent: converted to line integrals and less
        their static part in place, not copied (each copy of 2,000 binned views is half a
        gigabyte), then written over with the finest level's aligned views (:class:`_Views`).
    Returns
    -------
    ProjectionMatchingResult
        A step is kept only where the cost falls with it (tried whole, with the slow modes'
        extrapolation and without, then halved); a level ends when none does, or when the steps
        are within their noise. Stops early (keeping the last good angles and saying why in
        ``stopped``) if the angles leave what FDK can reconstruct, e.g. a short scan shrinking
        below 180 deg + fan.
    """
    binning, iterations = tuple(binning), tuple(iterations)
    angles = _check(projections, geometry, angles_deg, binning, iterations, band_px, max_voxels, filter, max_step_deg)
    data, converted = as_line_integrals(projections, overwrite=overwrite)
    ours = converted or (overwrite and data is projections and data.flags.writeable)
    if static:
        if ours:
            data -= static_part(data, angles)   # an array of our own or the caller's to spend: no copy
        else:
            data, ours = data - static_part(data, angles), True
    data = _Views(data, spend=ours)   # the finest level aligns into an array of ours (:class:`_Views`)
    theta = np.deg2rad(angles)
    full_turn = covers_full_circle(angles)
    history: list[dict] = []
    notes: list[str] = []
    fit: _Fit | None = None
    shifts_px = np.zeros((len(angles), 2))     # unbinned pixels, the axis column in the columns' common part
    tilt = 0.0
    for index, (factor, count) in enumerate(zip(binning, iterations)):
        level = _Level(data, geometry, int(factor), int(max_voxels), band_px, filter)
        level.align(shifts_px / factor, tilt)
        options = {"shifts": shifts, "detector": detector}
        cap = max_step_deg if max_step_deg is not None else step_cap_deg(level.geometry, level.grid, band_px[1])
        start = time.perf_counter()
        try:
            fit = level.fit(angles, **options)
        except InputError as exc:
            return _result(angles, theta, history, f"binning {factor}: {exc}", None, shifts_px if shifts else None,
                           tilt if detector else None, detector)
        history.append(_entry(factor, 0, "start", fit, None, start, shifts_px, tilt))
        state = (fit, angles, shifts_px, tilt)

        def attempt(iteration: int, proposals, *, last: bool = False) -> bool:
            """Try ``(kind, angle step, shift step, tilt step)`` in turn; keep the first that lowers the cost.

            The ``last`` step of a level needs only its cost: no step is taken from it (the next
            level starts with a fit of its own), so it is one reconstruction and one projection,
            not a Gauss-Newton evaluation; its standard errors are the fit's before it.
            """
            nonlocal state
            fit, angles, shifts_px, tilt = state
            for kind, angle_step, shift_step, tilt_step in proposals:
                start = time.perf_counter()
                trial_angles = angles + angle_step
                trial_shifts = _shift_gauge(shifts_px + shift_step, theta) if shifts or detector else shifts_px
                trial_tilt = tilt + tilt_step
                level.align(trial_shifts / factor, trial_tilt)
                try:
                    trial = (_Fit(level.cost(trial_angles), noise_deg=fit.noise_deg, noise_drop=fit.noise_drop)
                             if last else level.fit(trial_angles, **options))
                except InputError as exc:
                    notes.append(f"binning {factor}, step {iteration}: {exc}")
                    trial = None
                better = trial is not None and _lowers(fit, trial)
                history.append(_entry(factor, iteration, kind, trial, angle_step, start, trial_shifts, trial_tilt,
                                      accepted=better))
                if progress is not None:
                    progress(1)
                if better:
                    state = (trial, trial_angles, trial_shifts, trial_tilt)
                    return True
            level.align(shifts_px / factor, tilt)
            return False

        if index == 0 and fit.held is not None:
            # The detector first, the angles held: an axis a pixel or two off (or a tilted
            # detector) fitted together with the angles from the start bends them while the
            # linearisation is poor; a few steps of the detector alone bring it in range.
            _align_detector(lambda: (state[0].held, state[2]), factor, lambda shift_step, tilt_step: attempt(
                0, [("detector", np.zeros_like(angles), shift_step, tilt_step),
                    ("detector, half", np.zeros_like(angles), 0.5 * shift_step, 0.5 * tilt_step)]))
        previous = None
        for iteration in range(1, int(count) + 1):
            fit = state[0]
            step = np.clip(fit.step_deg, -cap, cap)
            step -= step.mean()
            shift_step, tilt_step = _detector_step((fit.shift_px, fit.tilt_rad, fit.axis_px), state[2], factor)
            extra = _extrapolate_slow_modes(step, previous, theta) if full_turn and previous is not None else None
            if iteration > 1 and _within_noise(fit, step if extra is None else step + extra):
                break       # what is left to take is noise: not worth a reconstruction
            proposals = ([("extrapolated", step + extra, shift_step, tilt_step)]
                         if extra is not None and np.any(extra) else [])
            proposals += [("step", step, shift_step, tilt_step),
                          ("half step", 0.5 * step, 0.5 * shift_step, 0.5 * tilt_step)]
            if not attempt(iteration, proposals, last=iteration == int(count)):
                notes.append(f"binning {factor}: stopped after {iteration - 1} steps, no step lowered the cost")
                break
            taken = history[-1]
            previous = step * (0.5 if taken["kind"] == "half step" else 1.0)
        fit, angles, shifts_px, tilt = state
    result = _result(angles, theta, history, "; ".join(notes), fit, shifts_px if shifts else None,
                     tilt if detector else None, detector)
    if compare:
        candidates = {name: np.asarray(values, dtype=np.float64) for name, values in compare.items()}
        reference = next(iter(candidates))
        candidates["matched"] = angles
        # On the scanner's detector (the axis and the tilt found), not on the views moved by the
        # per-view shifts: those were fitted with the matched angles, and would favour them.
        common = np.zeros_like(shifts_px)
        common[:, 0] = _axis_part(shifts_px[:, 0], theta) if shifts or detector else 0.0

        band = None

        def scored(at: _Level) -> tuple[dict[str, HeldOutScore], int]:
            nonlocal band
            at.align(common / at.binning, tilt)
            energies = {name: at.held_out(values) for name, values in candidates.items()}
            scores = _scores_against(energies, reference)
            if scores["matched"].z <= -HELD_OUT_DECISIVE_Z:
                band = slow_even_band_scores(at, candidates[reference], angles,
                                             energies={"reference": energies[reference],
                                                       "matched": energies["matched"]})
            return scores, at.binning

        scores = None
        if len(binning) > 1 and int(binning[0]) != level.binning:
            # The matched alignment is not read again (the test aligns the views anew): its copy
            # goes before the coarse level's views are made beside it.
            level.align(None, 0.0)
            # Two stages: the coarsest level first (a sixth of the cost or less), the finest only
            # where the coarse one leaves the answer in doubt (`HELD_OUT_DECISIVE_Z`).
            scores, scored_at = scored(_Level(data, geometry, int(binning[0]), int(max_voxels), band_px, filter))
            if not held_out_decisive(scores, reference):
                scores = None
        if scores is None:
            scores, scored_at = scored(level)
        result = dataclasses.replace(result, held_out=scores, held_out_binning=scored_at, held_out_slow_even=band)
    return result


def slow_even_band_scores(level: "_Level", reference_deg: np.ndarray, matched_deg: np.ndarray, *,
                          harmonics: int = 3, energies: dict | None = None) -> dict[str, HeldOutScore]:
    """The slow-even band of a correction judged by held-out views on its own.

    The band (the constant and the even harmonics of the turn up to ``harmonics`` of
    ``matched_deg - reference_deg``, as :func:`ctpipe.solve.bands.split_bands` splits it) is what
    neither the conjugate rays (they see it only through the fan) nor a test of the whole
    correction can vouch for: a sweep scan whose matched angles fixed two 2 deg jumps and added a
    4 deg twice-per-turn warp scored z -5.1 against the nominal angles as a whole. Returns
    ``band`` (the matched angles against the same less the band: below ``-HELD_OUT_Z`` the
    held-out views show the band itself better) and ``without`` (the matched angles less the
    band against ``reference_deg``). ``energies`` may hold the held-out energies
    (:meth:`_Level.held_out`) already made at this level, on its present alignment, of
    ``reference_deg`` (key ``reference``) and ``matched_deg`` (``matched``).
    """
    reference = np.asarray(reference_deg, dtype=np.float64)
    matched = np.asarray(matched_deg, dtype=np.float64)
    correction = matched - reference
    correction -= np.median(correction)
    without = matched - split_bands(correction, reference, harmonics)["slow-even"]
    made = dict(energies or {})
    for name, values in (("reference", reference), ("matched", matched), ("without", without)):
        if name not in made:
            made[name] = level.held_out(values)
    return {"band": _scores_against(made, "without")["matched"],
            "without": _scores_against(made, "reference")["without"]}


#: How far past the held-out threshold the coarsest level's z must be, either way, to decide
#: without the finest level's test: three times `HELD_OUT_Z`. Measured on the default scan and six
#: sweep scenarios, with the true and the nominal angles (docs/wholescan.md): where the coarse
#: level's |z| was 6 or more (-25.6, -6.5), the finest level's had the same sign and was larger
#: (-26.0, -11.3); between, the two levels disagreed (-2.7 and -1.3, -0.2 and -2.1). The gate takes
#: held-out evidence this strong on its own, where the conjugate rays do not contradict it
#: (:func:`ctpipe.solve.gate.gate_angles`).
HELD_OUT_DECISIVE_Z = 3.0 * HELD_OUT_Z


def held_out_decisive(scores: dict[str, "HeldOutScore"], reference: str) -> bool:
    """Whether every angle set's held-out z against ``reference`` is beyond `HELD_OUT_DECISIVE_Z`, either way."""
    return all(abs(score.z) >= HELD_OUT_DECISIVE_Z for name, score in scores.items() if name != reference)


#: Most steps of the detector alone (the angles held) before the first level's angle steps.
_DETECTOR_STEPS = 3


def _lowers(fit: _Fit, trial: _Fit) -> bool:
    """Whether ``trial`` is kept over ``fit``: its cost lower by more than twice what fitting the
    unknowns to noise would take off it (Akaike's criterion: each unknown pays two units of the noise)."""
    return fit.cost - trial.cost > 2.0 * fit.noise_drop


def _align_detector(current, factor: int, try_step) -> bool:
    """The detector alone, the angles held: up to :data:`_DETECTOR_STEPS` steps of the axis column and
    the in-plane tilt, while they move enough to be worth a reconstruction and ``try_step`` keeps one.

    ``current()`` gives the fit's detector steps ``(shift_px or None, tilt_rad, axis_px)`` and the
    unbinned shifts (V, 2) they step from; ``try_step(shift_step, tilt_step)`` tries the step (whole,
    then halved: its own business) and says whether one was kept. Shared by :func:`projection_matching`'s
    first level and :func:`consistency_costs`' aligned costs, so a start is costed on the detector
    matching from it would find. Returns whether the detector was off enough to try a step.
    """
    moved = False
    for _ in range(_DETECTOR_STEPS):
        held, shifts_px = current()
        shift_step, tilt_step = _detector_step(held, shifts_px, factor)
        if not _detector_moves(shift_step, tilt_step, factor):
            break
        moved = True
        if not try_step(shift_step, tilt_step):
            break
    return moved


def _detector_step(found: tuple, shifts_px: np.ndarray, factor: int) -> tuple[np.ndarray, float]:
    """A fit's detector steps ``(shift_px or None, tilt_rad, axis_px)`` (binned) as capped steps of the
    unbinned shifts (V, 2) and the tilt (radians)."""
    shift_px, tilt_rad, axis_px = found
    step = np.zeros_like(shifts_px)
    if shift_px is not None:
        step = np.clip(shift_px, -_MAX_SHIFT_STEP_PX, _MAX_SHIFT_STEP_PX) * factor
    step[:, 0] += float(np.clip(axis_px, -_MAX_SHIFT_STEP_PX, _MAX_SHIFT_STEP_PX)) * factor
    return step, float(np.clip(tilt_rad, -_MAX_TILT_STEP_RAD, _MAX_TILT_STEP_RAD))


def _detector_moves(shift_step: np.ndarray, tilt_step: float, factor: int) -> bool:
    """Whether a detector step is worth a reconstruction: its common column shift above 0.05 binned
    pixels or its tilt above 0.01 deg (per-view drift is left to the joint steps)."""
    return abs(float(np.mean(shift_step[:, 0]))) > 0.05 * factor or abs(math.degrees(tilt_step)) > 0.01


def _within_noise(fit: _Fit, step: np.ndarray) -> bool:
    """Whether a step is no larger than its own noise: the views' steps within their spread on the whole."""
    finite = np.isfinite(fit.noise_deg) & (fit.noise_deg > 0)
    if not finite.any():
        return True
    return float(np.mean((step[finite] / fit.noise_deg[finite]) ** 2)) < 1.0


def _entry(factor: int, iteration: int, kind: str, fit: _Fit | None, change_deg, start: float, shifts_px, tilt,
           accepted: bool = True) -> dict:
    entry = {"binning": int(factor), "iteration": iteration, "kind": kind,
             "cost": math.inf if fit is None else fit.cost, "accepted": bool(accepted)}
    if fit is not None and fit.noise_deg is not None:
        finite = np.isfinite(fit.noise_deg)
        # The spread of the next step under the residual alone (not calibrated): what "within noise" compares with.
        entry["noise_rms_deg"] = float(np.sqrt(np.mean(fit.noise_deg[finite] ** 2))) if finite.any() else math.inf
        entry["noise_drop"] = fit.noise_drop
    if change_deg is not None:
        change = np.asarray(change_deg, dtype=np.float64)
        entry.update(step_rms_deg=float(np.sqrt(np.mean(change ** 2))), step_max_deg=float(np.abs(change).max()))
    entry.update(shift_rms_px=float(np.sqrt(np.mean(shifts_px ** 2))), tilt_deg=math.degrees(tilt),
                 seconds=time.perf_counter() - start)
    return entry


def _result(angles, theta, history, stopped, fit: _Fit | None, shifts_px, tilt, detector: bool) -> ProjectionMatchingResult:
    se = None if fit is None or fit.noise_deg is None else SE_CALIBRATION * fit.noise_deg
    axis = None
    drift = None
    if shifts_px is not None or detector:
        full = np.zeros((len(angles), 2)) if shifts_px is None else shifts_px
        axis = _axis_part(full[:, 0], theta)
        drift = None if shifts_px is None else full - np.array([axis, 0.0])
    return ProjectionMatchingResult(angles, tuple(history), stopped, angle_se_deg=se, shifts_px=drift,
                                    axis_offset_px=axis if detector else None,
                                    tilt_deg=None if tilt is None else math.degrees(tilt))


def _axis_part(columns: np.ndarray, theta_rad: np.ndarray) -> float:
    """The column shift common to every view: the constant of :func:`_shift_gauge`'s fit."""
    basis = np.stack([np.ones_like(theta_rad), np.cos(theta_rad), np.sin(theta_rad)], axis=1)
    return float(np.linalg.lstsq(basis, columns, rcond=None)[0][0])


def _shift_gauge(shifts_px: np.ndarray, theta_rad: np.ndarray) -> np.ndarray:
    """Per-view detector shifts (V, 2) without what moving the object would explain as well.

    A once-per-turn column shift ``a cos(theta) + b sin(theta)`` is the object sitting elsewhere
    on the table, and a common row shift the object higher or lower: the reconstruction takes up
    both, so both are removed. A common column shift is the axis imaged off the principal point's
    column, which no reconstruction takes up (it blurs every off-axis point into an arc): it is
    kept, and is the axis offset. The once-per-turn part is fitted with the constant, so on a
    short scan, where the three are not orthogonal, the constant is not taken for part of it.
    """
    out = np.array(shifts_px, dtype=np.float64)
    basis = np.stack([np.ones_like(theta_rad), np.cos(theta_rad), np.sin(theta_rad)], axis=1)
    coeffs, *_ = np.linalg.lstsq(basis, out[:, 0], rcond=None)
    out[:, 0] -= basis[:, 1:] @ coeffs[1:]
    out[:, 1] -= out[:, 1].mean()
    return out


def consistency_costs(projections: np.ndarray, geometry: Geometry, candidates: dict[str, np.ndarray], *,
                      binning: int = 4, band_px: tuple[float, float] = (0.7, 4.0), max_voxels: int = 192,
                      filter: str = "ram-lak", static: bool = False, detector: bool = False) -> dict[str, float]:
    """How well each candidate set of angles explains the projections: reconstruct, reproject, compare.

    The band-passed residual energy relative to the data's (0 for perfectly consistent data),
    at one coarse binning. Wrong angles blur and smear the volume, so its reprojections miss the
    data; the lower the cost, the more consistent the angles. Used to choose between candidate
    angle sets (nominal, feature-based, projection-matched) without knowing the truth. A
    candidate FDK cannot reconstruct (NaN angles, a short scan below 180 deg + fan) costs inf.
    With ``static``, the views less their :func:`static_part`, as :func:`projection_matching`
    matches them. With ``detector``, each candidate is costed on the detector aligned to it (the
    axis column and the in-plane tilt, the angles held: :func:`_detector_aligned_cost`), as
    matching from it would be: an axis off by a pixel or two makes every candidate's residual
    and hides their difference (on an unseen sweep scan with the axis 1.5 px off and the
    detector tilted 0.3 deg, a pair-chained start scored 0.254 against the nominal angles' 0.262
    as recorded, 0.201 against 0.104 aligned; matched from the start it ended at 1.35 deg RMS,
    from the nominal angles at 0.62).

    Parameters
    ----------
    candidates : dict of str to ndarray of shape (V,)
        Angle sets in degrees, by name.

    Returns
    -------
    dict of str to float
    """
    data, _ = as_line_integrals(projections)
    if static:
        data = data - static_part(data, next(iter(candidates.values())))
    level = _Level(data, geometry, int(binning), int(max_voxels), band_px, filter)
    costs = {}
    # Where the first candidate's detector needs no step, none is aligned: a fit costs twice a
    # plain cost, and on an aligned scanner changes the costs in the fourth digit.
    align = detector
    for name, angles in candidates.items():
        angles = np.asarray(angles, dtype=np.float64)
        try:
            _check(projections, geometry, angles, (binning,), (1,), band_px, max_voxels, filter, 1.0)
            if align:
                costs[name], align = _detector_aligned_cost(level, angles)
            else:
                costs[name] = level.cost(angles)
        except InputError:
            costs[name] = math.inf
    return costs


def _detector_aligned_cost(level: _Level, angles_deg: np.ndarray) -> tuple[float, bool]:
    """The cost at ``angles_deg`` with the detector aligned to them (the axis column and the in-plane
    tilt), and whether it was off enough to try a step.

    The steps :func:`projection_matching` takes first on its first level, the angles held: up to
    :data:`_DETECTOR_STEPS` of them, each tried whole then halved and kept where the cost falls by
    more than fitting noise would take off it. The level is left unaligned.
    """
    theta = np.deg2rad(angles_deg)
    level.align(None, 0.0)
    state = (level.fit(angles_deg, detector=True), np.zeros((len(angles_deg), 2)), 0.0)

    def try_step(shift_step, tilt_step) -> bool:
        nonlocal state
        fit, shifts_px, tilt = state
        for scale in (1.0, 0.5):
            trial_shifts = _shift_gauge(shifts_px + scale * shift_step, theta)
            trial_tilt = tilt + scale * tilt_step
            level.align(trial_shifts / level.binning, trial_tilt)
            trial = level.fit(angles_deg, detector=True)
            if _lowers(fit, trial):
                state = (trial, trial_shifts, trial_tilt)
                return True
        return False

    moved = _align_detector(lambda: (state[0].held, state[1]), level.binning, try_step)
    level.align(None, 0.0)
    return state[0].cost, moved
