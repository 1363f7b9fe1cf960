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
the volume. The steps are capped (``max_step_deg``) and their mean is removed (a common turn of
all views only turns the volume). Levels run coarse to fine: a coarse binning has the capture
range for slips of a degree or more, a fine one the precision.

A detector or source spot that drifts during the scan moves each projection as a whole, and
matching the angle alone takes that shift for a turn. With ``shifts``, every view's column and
row shift is fitted with its angle (the reprojection's own gradients are the shifts' slopes;
three unknowns a view), the views are moved back by the shifts found before the next
reconstruction, and what an object's place on the table explains as well (a common shift, a
once-per-turn column shift) is left out. The angle's step and standard error are those of its
slope with the shifts' part projected out, so a view whose turn looks like a shift says so. On
a 120-view bead scan with a 0.1 px-a-view walk and two 1 px jumps, the shifts are found to
0.05 px RMS (correlation 0.98 and 1.00 with the truth) and the angles' RMS falls from 0.39 to
0.18 deg; without drift it costs nothing (0.063 and 0.065 deg). On the default scan (no drift)
the angles come out at 0.024 instead of 0.033 deg: the shifts also take up some of what the
volume gets wrong in each view, which otherwise leaks into its angle.

Measured on ``ctpipe validate``'s default scan (360 views, 0.2 deg jitter plus three 1 deg
jumps, per-view RMS 0.57 deg from the nominal angles): 0.05 deg after three iterations at
binning 4, 0.033 deg after three more at binning 2. At the true angles a step moves the views by
~0.04 deg RMS (binning 4): that is the method's floor here, set by the volume's imperfection;
views on either side of a wide gap between neighbours pull towards their nearer neighbours.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import gaussian_filter

from ctpipe.errors import InputError
from ctpipe.geometry import Geometry, check_geometry
from ctpipe.recon.feldkamp import FILTERS, bin_detector, fdk
from ctpipe.recon.volume import VolumeGrid

__all__ = ["ProjectionMatchingResult", "projection_matching", "matching_levels", "consistency_costs", "reconstruction_grid",
           "tangential_derivative", "band_pass", "as_line_integrals"]

# Views reprojected at a time: bounds the memory of the reprojections to a few chunks' worth.
_CHUNK_VIEWS = 32


@dataclass(frozen=True, eq=False)
class ProjectionMatchingResult:
    """What :func:`projection_matching` found.

    Attributes
    ----------
    angles_deg : ndarray of shape (V,)
        The matched angles, in the frame of the start angles (same mean).
    history : tuple of dict
        One entry per iteration: ``binning``, ``iteration``, ``step_rms_deg``, ``step_max_deg``,
        ``cost`` (band-passed residual energy relative to the data's, before the step) and
        ``seconds``.
    stopped : str
        Empty when every level ran; otherwise why matching stopped early.
    angle_se_deg : ndarray of shape (V,) or None
        Each view's standard error from the last iteration's Gauss-Newton fit: the spread of
        its step under the residual that fit leaves, its own spectrum taken as it is
        (:func:`_step_variance`), times :data:`SE_CALIBRATION`; inf where a view's slope carries
        no information; None when no iteration ran. It does not see a slow warp of the angles
        that the reconstruction absorbed: such errors it leaves to the gate
        (``docs/wholescan.md``).
    shifts_px : ndarray of shape (V, 2) or None
        With ``shifts``: each view's detector shift found (columns, rows; unbinned pixels),
        without its common and once-per-turn column part (:func:`_shift_gauge`); else None.
    """

    angles_deg: np.ndarray
    history: tuple[dict, ...]
    stopped: str = ""
    angle_se_deg: np.ndarray | None = None
    shifts_px: np.ndarray | None = None


def matching_levels(shape: tuple[int, int], iterations, *, level_px=(128, 256), binning=None) -> list[tuple[int, int]]:
    """``(binning, iterations)`` of each level for a detector of ``shape`` (rows, cols).

    With ``binning`` None, each level bins the detector to about ``level_px`` pixels a side
    (factor ``round(min(shape) / level_px)``, at least 1), so a 512^2 detector is matched at
    128^2 then 256^2 and a 2,048^2 one at the same sizes; levels that come out at the same
    factor are merged (their iterations add up). Levels that would leave fewer than 16 pixels a
    side are dropped.
    """
    side = min(shape)
    if binning is None:
        factors = [max(1, int(round(side / max(px, 1)))) for px in level_px]
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
    dv_dz = np.gradient(volume, grid.voxel_size_mm, axis=1)
    dv_dx = np.gradient(volume, grid.voxel_size_mm, axis=2)
    x = grid.axis_mm("x").astype(np.float32)[None, None, :]
    z = grid.axis_mm("z").astype(np.float32)[None, :, None]
    return (np.float32(math.pi / 180.0) * (z * dv_dx - x * dv_dz)).astype(np.float32)


def band_pass(images: np.ndarray, low_px: float, high_px: float) -> np.ndarray:
    """Difference of Gaussians over the last two axes: detail between ``low_px`` and ``high_px``.

    ``gaussian(low_px) - gaussian(high_px)``; ``low_px = 0`` keeps the finest detail.
    """
    images = np.asarray(images, dtype=np.float32)
    sigma = (0,) * (images.ndim - 2)
    fine = gaussian_filter(images, sigma + (low_px, low_px)) if low_px > 0 else images
    return fine - gaussian_filter(images, sigma + (high_px, high_px))


def as_line_integrals(projections: np.ndarray) -> tuple[np.ndarray, bool]:
    """Projections as line integrals (dark object on a bright field is taken as intensities).

    Returns the array (float32) and whether it was converted. Intensities are recognised by a
    border brighter than the centre and turned into ``-log(I / I_flat)`` with ``I_flat`` the
    99.5th percentile of each view.
    """
    p = np.asarray(projections, dtype=np.float32)
    _, rows, cols = p.shape
    border = np.concatenate([p[:, :, : max(cols // 16, 1)].ravel(), p[:, :, -max(cols // 16, 1):].ravel()])
    centre = p[:, rows // 4: rows - rows // 4, cols // 4: cols - cols // 4]
    if not float(np.median(border)) > float(np.median(centre)):
        return p, False
    flat = np.percentile(p.reshape(len(p), -1), 99.5, axis=1).astype(np.float32)
    floor = np.float32(1e-6) * np.maximum(flat, np.float32(1e-30))
    ratio = np.maximum(p, floor[:, None, None]) / np.maximum(flat, np.float32(1e-30))[:, None, None]
    return np.maximum(-np.log(ratio), 0.0).astype(np.float32), True


class _Level:
    """One binning: the binned data (as recorded, and moved back by the fitted shifts), the grid and the projector."""

    def __init__(self, projections: np.ndarray, geometry: Geometry, binning: int, max_voxels: int,
                 band_px: tuple[float, float], filter: str) -> None:
        from ctpipe.sim.projectors import VoxelProjector

        self.binning = binning
        raw, self.geometry = bin_detector(projections, geometry, binning)
        self.raw = np.ascontiguousarray(raw, dtype=np.float32)
        self.grid = reconstruction_grid(self.geometry, max_voxels)
        self.projector = VoxelProjector(self.geometry, self.grid)
        self.band_px = band_px
        self.filter = filter
        self.shift_to(None)

    def shift_to(self, shifts_px: np.ndarray | None) -> None:
        """Take the views moved back by ``shifts_px`` (V, 2: columns, rows; binned pixels) as the data.

        A view whose detector (or source) moved by ``(du, dv)`` shows ``P(u - du, v - dv)``; it is
        resampled to ``P(u, v)`` (linear interpolation, edges continued) before it is reconstructed
        and matched. ``None`` takes the views as they are.
        """
        if shifts_px is None or not np.any(shifts_px):
            self.data = self.raw
        else:
            from scipy.ndimage import shift as resample

            self.data = np.empty_like(self.raw)
            for k, (du, dv) in enumerate(np.asarray(shifts_px, dtype=np.float64)):
                self.data[k] = resample(self.raw[k], (-dv, -du), order=1, mode="nearest")

    def steps(self, angles_deg: np.ndarray, *, with_steps: bool = True,
              with_shifts: bool = False) -> tuple[np.ndarray, float, np.ndarray | None, np.ndarray | None]:
        """Gauss-Newton step of every view (degrees), the relative residual energy, with
        ``with_steps`` each view's standard error of its step (:func:`_step_variance`; else None),
        and with ``with_shifts`` each view's detector shift step (V, 2: columns, rows; binned
        pixels; else None).

        With shifts, the angle and the two shifts are fitted together, view by view: the
        reprojection's own column and row gradients are the shifts' slopes. The angle's step and
        standard error are those of its slope with the shifts' part projected out (Frisch-Waugh-
        Lovell: the same step as the joint fit), so a view whose turn looks like a shift gets the
        larger error it has.
        """
        volume = fdk(self.data, self.geometry, angles_deg, self.grid, filter=self.filter)
        derivative = tangential_derivative(volume, self.grid) if with_steps else None
        numerator = np.zeros(len(angles_deg))
        denominator = np.zeros(len(angles_deg))
        variance = np.zeros(len(angles_deg))
        shifts = np.zeros((len(angles_deg), 2)) if with_steps and with_shifts else None
        residual_energy = data_energy = 0.0
        if with_steps:
            # The volume and its derivative along the same rays in one pass (the derivative's
            # projection is the slope of every pixel with the view's angle).
            chunks = self.projector.forward_pair(volume, derivative, angles_deg, chunk_views=_CHUNK_VIEWS)
        else:
            parts = (slice(start, start + _CHUNK_VIEWS) for start in range(0, len(angles_deg), _CHUNK_VIEWS))
            chunks = ((part, self.projector.forward(volume, angles_deg[part]), None) for part in parts)
        for part, projected, projected_slope in chunks:
            # The data are band-passed here, a chunk of views at a time, rather than kept whole
            # next to the data: one copy of the views less (0.5 GB at 2,000 views of 256^2).
            filtered = band_pass(self.data[part], *self.band_px)
            data_energy += float(np.einsum("vij,vij->", filtered, filtered, dtype=np.float64))
            model = band_pass(projected, *self.band_px)
            residual = filtered - model
            residual_energy += float(np.einsum("vij,vij->", residual, residual, dtype=np.float64))
            if with_steps:
                slope = band_pass(projected_slope, *self.band_px)
                if shifts is not None:
                    # A view shifted by +d shows model(u - d) = model - d * d(model)/du.
                    moved = np.stack([-np.gradient(model, axis=2), -np.gradient(model, axis=1)], axis=1)
                    slope, shift_step = _project_out(slope, moved, residual)
                    shifts[part] = shift_step
                numerator[part] = np.einsum("vij,vij->v", slope, residual, dtype=np.float64)
                denominator[part] = np.einsum("vij,vij->v", slope, slope, dtype=np.float64)
                variance[part] = _step_variance(slope, residual, numerator[part], denominator[part])
        informative = denominator > 1e-12 * max(float(denominator.max(initial=0.0)), 1e-300)
        step = np.where(informative, numerator / np.where(informative, denominator, 1.0), 0.0)
        se = np.where(informative, SE_CALIBRATION * np.sqrt(variance), np.inf) if with_steps else None
        return step, residual_energy / max(data_energy, 1e-300), se, shifts


def _project_out(slope: np.ndarray, moved: np.ndarray, residual: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The angle slope with the shift slopes' span removed, and the shifts' own least-squares step.

    ``slope`` (v, rows, cols), ``moved`` (v, 2, rows, cols). Returns the residualised slope (its
    Gauss-Newton step on ``residual`` is the joint fit's angle step) and the shifts' step (v, 2)
    of the joint fit of ``residual`` on the angle and the two shifts.
    """
    gram = np.einsum("vaij,vbij->vab", moved, moved, dtype=np.float64)
    ridge = 1e-9 * np.trace(gram, axis1=1, axis2=2)[:, None, None] * np.eye(2) + 1e-300 * np.eye(2)
    gram = gram + ridge
    cross = np.einsum("vaij,vij->va", moved, slope, dtype=np.float64)
    along = np.linalg.solve(gram, cross[..., None])[..., 0]
    lone = slope - np.einsum("va,vaij->vij", along.astype(np.float32), moved)
    # Joint fit: angle step from the residualised slope, then the shifts on what it leaves.
    den = np.einsum("vij,vij->v", lone, lone, dtype=np.float64)
    num = np.einsum("vij,vij->v", lone, residual, dtype=np.float64)
    angle = np.where(den > 0, num / np.where(den > 0, den, 1.0), 0.0)
    rest = residual - angle[:, None, None].astype(np.float32) * slope
    shift = np.linalg.solve(gram, np.einsum("vaij,vij->va", moved, rest, dtype=np.float64)[..., None])[..., 0]
    return lone, shift


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
    power = np.abs(np.fft.rfft2(slope)) ** 2 * np.abs(np.fft.rfft2(left)) ** 2
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
    """Aitken extrapolation of the slowly converging low harmonics of the angle steps.

    A turn-periodic warp of the angles ``a cos(k theta) + b sin(k theta)`` of low order ``k`` is
    nearly an affine stretch of the object, which the reconstruction absorbs: matching removes
    only a fraction ``1 - rho`` of it per iteration, so successive steps in that mode shrink
    geometrically by ``rho``. The rest of the series is ``step * rho / (1 - rho)``; it is added
    for each harmonic whose ratio is positive and whose steps agree in direction, with the ratio
    capped at ``max_ratio`` (at most 4 times the step, so a mode that only looks slow cannot run
    away).
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
    if not max_step_deg > 0 or not max_voxels >= 8:
        raise InputError(f"max_step_deg must be > 0 and max_voxels >= 8, got {max_step_deg!r} and {max_voxels!r}")
    return angles


def projection_matching(projections: np.ndarray, geometry: Geometry, angles_deg, *, binning=(4, 2),
                        iterations=(3, 2), band_px: tuple[float, float] = (0.7, 4.0), max_voxels: int = 192,
                        filter: str = "ram-lak", max_step_deg: float = 1.0, shifts: bool = False,
                        progress: Callable[[int], object] | None = None) -> ProjectionMatchingResult:
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
        Reconstruct-and-match rounds at each level.
    band_px : (float, float)
        Difference-of-Gaussians band in binned pixels: the sigmas of the fine and coarse blur.
    max_voxels : int
        Largest grid edge; bounds time and memory at fine levels.
    filter : str
        FDK ramp-filter window (:data:`ctpipe.recon.feldkamp.FILTERS`); the sharp ``ram-lak`` matches best.
    max_step_deg : float
        Largest change of a view's angle in one iteration.
    shifts : bool
        Fit each view's detector shift (columns, rows) with its angle, for a detector or source
        that drifts during the scan; the data are moved back by the shifts found before each
        reconstruction. Shifts an object on the table explains (common, once per turn) are left
        out (:func:`_shift_gauge`).
    progress : callable, optional
        Called with 1 after every iteration.

    Returns
    -------
    ProjectionMatchingResult
        Stops early (keeping the last good angles and saying why in ``stopped``) if the angles
        leave what FDK can reconstruct, e.g. a short scan shrinking below 180 deg + fan.
    """
    binning, iterations = tuple(binning), tuple(iterations)
    angles = _check(projections, geometry, angles_deg, binning, iterations, band_px, max_voxels, filter, max_step_deg)
    data, _ = as_line_integrals(projections)
    history: list[dict] = []
    se = None
    shifts_px = np.zeros((len(angles), 2)) if shifts else None
    for factor, count in zip(binning, iterations):
        level = _Level(data, geometry, int(factor), int(max_voxels), band_px, filter)
        if shifts:
            level.shift_to(shifts_px / factor)
        previous = None
        for iteration in range(int(count)):
            start = time.perf_counter()
            try:
                step, cost, se, shift_step = level.steps(angles, with_shifts=shifts)
            except InputError as exc:
                return ProjectionMatchingResult(angles, tuple(history), f"binning {factor}, iteration {iteration}: {exc}",
                                                shifts_px=shifts_px)
            step = np.clip(step, -max_step_deg, max_step_deg)
            step -= step.mean()
            extra = _extrapolate_slow_modes(step, previous, np.deg2rad(angles)) if previous is not None else 0.0
            previous = step
            angles = angles + step + extra
            entry = {"binning": int(factor), "iteration": iteration, "cost": cost,
                     "step_rms_deg": float(np.sqrt(np.mean(step ** 2))), "step_max_deg": float(np.abs(step).max())}
            if shifts:
                shifts_px = _shift_gauge(shifts_px + np.clip(shift_step, -2.0, 2.0) * factor, np.deg2rad(angles))
                level.shift_to(shifts_px / factor)
                entry["shift_rms_px"] = float(np.sqrt(np.mean(shifts_px ** 2)))
            history.append({**entry, "seconds": time.perf_counter() - start})
            if progress is not None:
                progress(1)
    return ProjectionMatchingResult(angles, tuple(history), angle_se_deg=se, shifts_px=shifts_px)


def _shift_gauge(shifts_px: np.ndarray, theta_rad: np.ndarray) -> np.ndarray:
    """Per-view detector shifts (V, 2) without what moving the object would explain as well.

    A common shift of every view is an axis or a height the reconstruction takes up, and a
    once-per-turn column shift ``a cos(theta) + b sin(theta)`` is the object sitting elsewhere on
    the table: neither is a drift, so both are removed (the column's constant and first harmonic,
    the row's constant).
    """
    out = np.array(shifts_px, dtype=np.float64)
    basis = np.stack([np.ones_like(theta_rad), np.cos(theta_rad), np.sin(theta_rad)], axis=1)
    coeffs, *_ = np.linalg.lstsq(basis, out[:, 0], rcond=None)
    out[:, 0] -= basis @ coeffs
    out[:, 1] -= out[:, 1].mean()
    return out


def consistency_costs(projections: np.ndarray, geometry: Geometry, candidates: dict[str, np.ndarray], *,
                      binning: int = 4, band_px: tuple[float, float] = (0.7, 4.0), max_voxels: int = 192,
                      filter: str = "ram-lak") -> dict[str, float]:
    """How well each candidate set of angles explains the projections: reconstruct, reproject, compare.

    The band-passed residual energy relative to the data's (0 for perfectly consistent data),
    at one coarse binning. Wrong angles blur and smear the volume, so its reprojections miss the
    data; the lower the cost, the more consistent the angles. Used to choose between candidate
    angle sets (nominal, feature-based, projection-matched) without knowing the truth. A
    candidate FDK cannot reconstruct (NaN angles, a short scan below 180 deg + fan) costs inf.

    Parameters
    ----------
    candidates : dict of str to ndarray of shape (V,)
        Angle sets in degrees, by name.

    Returns
    -------
    dict of str to float
    """
    data, _ = as_line_integrals(projections)
    level = _Level(data, geometry, int(binning), int(max_voxels), band_px, filter)
    costs = {}
    for name, angles in candidates.items():
        angles = np.asarray(angles, dtype=np.float64)
        try:
            _check(projections, geometry, angles, (binning,), (1,), band_px, max_voxels, filter, 1.0)
            costs[name] = level.steps(angles, with_steps=False)[1]
        except InputError:
            costs[name] = math.inf
    return costs
