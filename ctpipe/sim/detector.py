"""Detector artefacts: scatter, blur, stuck pixels, gain errors that make rings, lag, and a tube whose output wanders.

The optional ``detector:`` section of a scan spec (:mod:`ctpipe.sim.scan_spec`); every key
defaults to "off", and a scan without the section is simulated exactly as before::

    detector: {scatter_fraction: 0.05, scatter_sigma_px: 50, psf_sigma_px: 0.8,
               dead_pixels: 20, hot_pixels: 10, dead_columns: 1,
               gain_sigma: 0.05, gain_drift_sigma: 0.005, lag_fraction: 0.02,
               dust_specks: 30, flux_sigma: 0.005, saturation_fraction: 0.9}

One frame of a pixel is recorded in this order (``p`` the line integral, ``I0`` the
unattenuated counts of :class:`~ctpipe.sim.acquisition.NoiseModel`)::

    primary  = I0 (1 + f_v) exp(-p)                                        (f_v: the tube's output, per view)
    scatter  = scatter_fraction * G(scatter_sigma_px) * (p primary)       (smooth, object-dependent)
    counts   = Poisson(primary + scatter)                                  (photons arrive)
    counts   = G(psf_sigma_px) * counts                                    (scintillator blur)
    signal_v = (1 - lag_fraction) counts_v + lag_fraction signal_(v-1)     (charge left over)
    frame    = min(gain * signal + Poisson(dark_counts), saturation_fraction I0)
    dead pixels and columns read 0, hot pixels the full scale, in every frame

The tube's output is not steady: with ``flux_sigma`` each projection's beam is ``I0 (1 + N(0,
flux_sigma))``, the flats' ``I0`` (a microfocus tube's output wanders by tenths of a per cent to a
few per cent over a scan). Where the background is not clipped, a view's flat-corrected line
integrals are all ``-log(1 + f)`` off; where the clip holds the background flat, it hides the
change there but not under the object, so the depth at which the clip cuts a faint edge differs
from view to view.

Dust that settled after the flats were taken multiplies the projections' mean counts (before the
photons arrive) and is not in the flats: a flat-field residue, a few dark specks fixed on the
detector in every view.

``G(s) *`` is a Gaussian blur of standard deviation ``s`` pixels (reflected at the detector
edges). The scatter source ``p exp(-p)`` is the single-scatter estimate of the photons a ray
loses to scatter that still head for the detector: zero with no object (the flats have none),
zero behind an opaque part, largest for ``p = 1``. A slab wide against ``scatter_sigma_px``
therefore has a scatter-to-primary ratio ``scatter_fraction * p``, and its flat-corrected line
integral reads ``p - log(1 + scatter_fraction * p)``: too low, most where the object is thickest
(the cupping and the streaks between dense parts that real scans show).

Gains: every pixel has a fixed gain ``1 + N(0, gain_sigma)``, the same in the flats and the
projections, so the flat correction removes it (this is why flats are taken); on top of it the
projections' gain differs from the flats' by a further ``N(0, gain_drift_sigma)`` per pixel (the
detector warmed up or the beam moved between the flats and the scan). That part survives the
flat correction: a fixed error ``-log(1 + delta)`` in one pixel of every view, which FDK turns
into a ring around the axis at radius ``|col - u0| * pitch_u * SOD / SDD`` in that pixel's
slice. Dead pixels (read 0) and dead columns carry no information: the flat correction gives
them ``p = 0`` and FDK a ring at their radius too. Hot pixels are stuck at the full scale, taken
as ``4 (I0 + dark_counts)`` (flats are exposed at about a quarter of the detector's range), in
the projections, flats and darks alike. Lag: a first-order exponential (the detector keeps
``lag_fraction`` of its signal for the next frame), so a step in the signal leaves a residue
that shrinks by ``lag_fraction`` per frame; the flats, recorded in a steady beam, have none and
the first view starts in its own steady state.

Without ``noise`` in the scan spec the same chain runs without the Poisson draws, with
``I0 = 1`` and no dark current, and the scan's projections are the flat-corrected ``-log`` of
those noise-free intensities (the artefacts are exact, as the tests need them); the scan keeps no
intensities, as any noise-free scan.

The pattern (which pixels are dead, hot or in a dead column; the gains) is drawn once per scan
from the scan's ``rng``, before the detector noise, in this order and each only when its key is
non-zero: stuck pixels, dead columns, gains, gain drifts, dust; then the tube's output in each
view, where ``flux_sigma`` is set. Frames are made one view at a time:
the scan needs a float64 frame or two, never a float64 copy of the stack.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from ctpipe.config import check_keys
from ctpipe.errors import ConfigError, InputError
from ctpipe.stages import ParamSpec, check_value

__all__ = ["DetectorModel", "DetectorPattern", "parse_detector", "draw_pattern", "scatter_counts", "record",
           "detected_line_integrals", "MAX_STUCK_FRACTION", "FULL_SCALE_PER_FLAT"]

#: At most this fraction of the detector may be dead or hot (a detector worse than that is
#: replaced, and :func:`ctpipe.io.flatfield.log_transform` refuses half of it dead).
MAX_STUCK_FRACTION = 0.1
#: Hot pixels read this many times the mean flat (``I0 + dark_counts``): the detector's full scale.
FULL_SCALE_PER_FLAT = 4.0

_FIELDS = {
    "scatter_fraction": ParamSpec("scatter_fraction", float, 0.0,
                                  "scatter-to-primary ratio per unit line integral (0: no scatter)", ge=0, le=10),
    "scatter_sigma_px": ParamSpec("scatter_sigma_px", float, 50.0,
                                  "standard deviation of the scatter kernel, detector pixels", gt=0, le=10_000),
    "psf_sigma_px": ParamSpec("psf_sigma_px", float, 0.0,
                              "standard deviation of the Gaussian detector blur, pixels (0: none)", ge=0, le=64),
    "dead_pixels": ParamSpec("dead_pixels", int, 0, "pixels that read 0 in every frame", ge=0),
    "hot_pixels": ParamSpec("hot_pixels", int, 0, "pixels stuck at the full scale in every frame", ge=0),
    "dead_columns": ParamSpec("dead_columns", int, 0, "whole detector columns that read 0", ge=0),
    "gain_sigma": ParamSpec("gain_sigma", float, 0.0,
                            "relative std of the per-pixel gain, same in flats and projections", ge=0, le=0.5),
    "gain_drift_sigma": ParamSpec("gain_drift_sigma", float, 0.0,
                                  "relative std of the per-pixel gain change between flats and projections (rings)",
                                  ge=0, le=0.5),
    "lag_fraction": ParamSpec("lag_fraction", float, 0.0,
                              "fraction of a frame's signal carried into the next frame", ge=0, lt=1),
    "dust_specks": ParamSpec("dust_specks", int, 0,
                             "specks of dust on the detector since the flats were taken (a flat-field residue)",
                             ge=0, le=100_000),
    "flux_sigma": ParamSpec("flux_sigma", float, 0.0,
                            "relative std of the tube's output in each projection about the flats' (0: steady)",
                            ge=0, le=0.2),
    "saturation_fraction": ParamSpec("saturation_fraction", float, 0.0,
                                     "full well as a fraction of the open beam's counts: frames clip there, the "
                                     "background reads flat (0: no clipping)", ge=0, le=10),
}


@dataclass(frozen=True)
class DetectorModel:
    """Detector artefacts of a scan (see the module docstring); the defaults are all off.

    Parameters
    ----------
    scatter_fraction : float
        Scatter-to-primary ratio per unit line integral, >= 0 (a wide slab of line integral
        ``p`` has ``SPR = scatter_fraction * p``).
    scatter_sigma_px : float
        Standard deviation of the scatter kernel in detector pixels, > 0.
    psf_sigma_px : float
        Standard deviation of the Gaussian detector blur in pixels, >= 0.
    dead_pixels, hot_pixels : int
        Pixels that read 0, or the full scale, in every frame.
    dead_columns : int
        Whole columns that read 0 in every frame.
    gain_sigma : float
        Relative standard deviation of the per-pixel gain common to flats and projections.
    gain_drift_sigma : float
        Relative standard deviation of the per-pixel gain change from the flats to the projections.
    lag_fraction : float
        Fraction of each frame's signal read again in the next frame, in [0, 1).
    dust_specks : int
        Specks of dust that settled on the detector after the flats were taken: each a Gaussian
        of 1-3 px standard deviation absorbing 5-40 % at its centre, in the projections only.
    flux_sigma : float
        Relative standard deviation of the tube's output in each projection about its output in
        the flats, in [0, 0.2]: every projection's beam is ``I0 (1 + N(0, flux_sigma))``, drawn
        anew for each view.
    saturation_fraction : float
        The detector's full well as a fraction of the open beam's counts ``I0``: every frame
        (flats included) clips there, so where the beam reaches it the flat-corrected line
        integral reads exactly 0 and a faint edge is cut (0: no clipping).
    """

    scatter_fraction: float = 0.0
    scatter_sigma_px: float = 50.0
    psf_sigma_px: float = 0.0
    dead_pixels: int = 0
    hot_pixels: int = 0
    dead_columns: int = 0
    gain_sigma: float = 0.0
    gain_drift_sigma: float = 0.0
    lag_fraction: float = 0.0
    dust_specks: int = 0
    flux_sigma: float = 0.0
    saturation_fraction: float = 0.0

    def __post_init__(self) -> None:
        for key, spec in _FIELDS.items():
            object.__setattr__(self, key, check_value(spec, getattr(self, key), f"detector.{key}"))

    def to_dict(self) -> dict:
        return {key: getattr(self, key) for key in _FIELDS}

    def stuck_pixels(self, rows: int) -> int:
        """Pixels that carry no signal on a detector of ``rows`` rows (upper bound: overlaps count twice)."""
        return self.dead_pixels + self.hot_pixels + self.dead_columns * rows


def parse_detector(value: Any, path: str = "detector", shape: tuple[int, int] | None = None) -> DetectorModel | None:
    """Validate a ``detector`` mapping; ``null`` (or no section) means an ideal detector.

    ``shape`` ``(rows, cols)`` of the detector, when given, bounds the stuck pixels and columns.
    Errors are one-line :class:`~ctpipe.errors.ConfigError` naming ``path.<key>``.
    """
    if value is None:
        return None
    check_keys(value, path, allowed=tuple(_FIELDS))
    model = DetectorModel(**{key: check_value(_FIELDS[key], raw, f"{path}.{key}") for key, raw in value.items()})
    if shape is not None:
        rows, cols = shape
        if model.dead_columns > cols:
            raise ConfigError(f"{path}.dead_columns: must be at most the detector's {cols} columns, "
                              f"got {model.dead_columns}")
        stuck, limit = model.stuck_pixels(rows), MAX_STUCK_FRACTION * rows * cols
        if stuck > limit:
            raise ConfigError(f"{path}: dead_pixels + hot_pixels + dead_columns x {rows} rows = {stuck} pixels, more "
                              f"than {100 * MAX_STUCK_FRACTION:.0f} % of the {rows} x {cols} detector "
                              f"({int(limit)}); use fewer")
    return model


@dataclass(frozen=True, eq=False)
class DetectorPattern:
    """One scan's draw of a :class:`DetectorModel`: which pixels are stuck, the gains.

    Attributes
    ----------
    dead, hot : ndarray of shape (rows, cols), bool
        Pixels that read 0 (dead pixels and columns), pixels stuck at the full scale.
    flat_gain, projection_gain : ndarray of shape (rows, cols), float64, or None
        Gains of the flat fields and of the projections (None: 1 everywhere).
    dust : ndarray of shape (rows, cols), float64, or None
        Transmission of the dust on the detector in the projections (None: no dust).
    """

    dead: np.ndarray
    hot: np.ndarray
    flat_gain: np.ndarray | None
    projection_gain: np.ndarray | None
    dust: np.ndarray | None = None


def draw_pattern(model: DetectorModel, shape: tuple[int, int], rng: np.random.Generator) -> DetectorPattern:
    """Draw the stuck pixels and gains of ``model`` on a ``shape`` (rows, cols) detector (module docstring order)."""
    rows, cols = shape
    dead = np.zeros(rows * cols, bool)
    hot = np.zeros(rows * cols, bool)
    stuck = model.dead_pixels + model.hot_pixels
    if stuck:
        if stuck > rows * cols:
            raise ConfigError(f"detector: {stuck} dead and hot pixels do not fit on {rows} x {cols} pixels")
        chosen = rng.choice(rows * cols, size=stuck, replace=False)
        dead[chosen[:model.dead_pixels]] = True
        hot[chosen[model.dead_pixels:]] = True
    dead, hot = dead.reshape(shape), hot.reshape(shape)
    if model.dead_columns:
        dead[:, rng.choice(cols, size=model.dead_columns, replace=False)] = True
    hot &= ~dead
    flat_gain = projection_gain = None
    if model.gain_sigma > 0:
        # Clipped so that no live pixel gets a gain <= 0 (a 0.5 sigma is 2 std from 0).
        flat_gain = np.maximum(1.0 + model.gain_sigma * rng.standard_normal(shape), 0.01)
    if model.gain_drift_sigma > 0:
        drift = np.maximum(1.0 + model.gain_drift_sigma * rng.standard_normal(shape), 0.01)
        projection_gain = drift if flat_gain is None else flat_gain * drift
    elif flat_gain is not None:
        projection_gain = flat_gain
    dust = None
    if model.dust_specks:
        # Centre (row, col), standard deviation 1-3 px and depth 5-40 % of each speck, drawn at once.
        specks = rng.uniform([0.0, 0.0, 1.0, 0.05], [rows, cols, 3.0, 0.4], size=(model.dust_specks, 4))
        dust = np.ones(shape)
        for row, col, sigma, depth in specks:
            r0, r1 = max(int(row - 4 * sigma), 0), min(int(row + 4 * sigma) + 1, rows)
            c0, c1 = max(int(col - 4 * sigma), 0), min(int(col + 4 * sigma) + 1, cols)
            rr, cc = np.mgrid[r0:r1, c0:c1]
            dust[r0:r1, c0:c1] *= 1.0 - depth * np.exp(-((rr - row) ** 2 + (cc - col) ** 2) / (2.0 * sigma ** 2))
    return DetectorPattern(dead, hot, flat_gain, projection_gain, dust)


def _blur(frame: np.ndarray, sigma_px: float) -> np.ndarray:
    """Gaussian blur of a float64 frame, reflected at the edges; wide kernels on a coarser grid."""
    from scipy.ndimage import gaussian_filter, map_coordinates

    step = int(sigma_px // 4)
    if step <= 1:
        return gaussian_filter(frame, sigma_px, mode="reflect")
    # A kernel of sigma >= 8 px blurs away everything a block of sigma/4 px holds: average the
    # blocks, blur them and interpolate back (bilinear). The block mean and the interpolation add
    # variances step^2/12 and step^2/6, taken off the coarse kernel so the total stays sigma^2.
    # The frame is first mirrored (about its edge pixels' outer sides, as mode="reflect") by
    # 4 sigma, so the blocks need not fit the frame and its edges blur as the exact filter does.
    rows, cols = frame.shape
    margin = step * int(np.ceil(4.0 * sigma_px / step))
    padded = np.pad(frame, ((margin, margin + -rows % step), (margin, margin + -cols % step)), mode="symmetric")
    coarse = padded.reshape(padded.shape[0] // step, step, padded.shape[1] // step, step).mean(axis=(1, 3))
    coarse = gaussian_filter(coarse, np.sqrt(sigma_px ** 2 - step ** 2 / 4.0) / step, mode="nearest")
    r = (np.arange(rows) + margin - (step - 1) / 2.0) / step
    c = (np.arange(cols) + margin - (step - 1) / 2.0) / step
    rr, cc = np.meshgrid(r, c, indexing="ij")
    return map_coordinates(coarse, [rr, cc], order=1, mode="nearest")


def scatter_counts(primary: np.ndarray, line_integrals: np.ndarray, model: DetectorModel) -> np.ndarray:
    """Mean scatter counts of one view, float64 (rows, cols): ``scatter_fraction * G * (p * primary)``.

    Parameters
    ----------
    primary : ndarray of shape (rows, cols)
        Mean primary counts ``I0 exp(-p)``.
    line_integrals : ndarray of shape (rows, cols)
        ``p`` of the same view.
    """
    source = np.asarray(line_integrals, np.float64) * primary
    return model.scatter_fraction * _blur(source, model.scatter_sigma_px)


class _Frames:
    """Makes the frames of one scan one at a time, holding the lag's previous signal."""

    def __init__(self, model: DetectorModel, pattern: DetectorPattern, i0: float, dark: float,
                 rng: np.random.Generator | None):
        self.model, self.pattern, self.i0, self.dark, self.rng = model, pattern, i0, dark, rng
        self.full_scale = FULL_SCALE_PER_FLAT * (i0 + dark)
        self.previous: np.ndarray | None = None

    def _detect(self, mean: np.ndarray) -> np.ndarray:
        counts = mean if self.rng is None else self.rng.poisson(mean).astype(np.float64)
        if self.model.psf_sigma_px > 0:
            counts = _blur(counts, self.model.psf_sigma_px)
        return counts

    def _read(self, signal: np.ndarray, gain: np.ndarray | None, beam: bool = True) -> np.ndarray:
        if gain is not None and beam:
            signal = signal * gain
        if self.dark > 0 and self.rng is not None:
            signal = signal + self.rng.poisson(self.dark, size=signal.shape)
        elif self.dark > 0:
            signal = signal + self.dark
        if self.model.saturation_fraction > 0:
            signal = np.minimum(signal, self.model.saturation_fraction * self.i0)
        signal = np.where(self.pattern.dead, 0.0, signal)
        return np.where(self.pattern.hot, self.full_scale, signal)

    def projection(self, line_integrals: np.ndarray, flux: float = 1.0) -> np.ndarray:
        p = np.asarray(line_integrals, np.float64)
        mean = (self.i0 * flux) * np.exp(-p)
        if self.model.scatter_fraction > 0:
            mean = mean + scatter_counts(mean, p, self.model)
        if self.pattern.dust is not None:
            mean = mean * self.pattern.dust
        signal = self._detect(mean)
        lag = self.model.lag_fraction
        if lag > 0:
            if self.previous is not None:
                signal = (1.0 - lag) * signal + lag * self.previous
            self.previous = signal
        return self._read(signal, self.pattern.projection_gain)

    def flat(self, shape: tuple[int, int]) -> np.ndarray:
        return self._read(self._detect(np.full(shape, self.i0)), self.pattern.flat_gain)

    def dark_frame(self, shape: tuple[int, int]) -> np.ndarray:
        return self._read(np.zeros(shape), None, beam=False)


def _views(line_integrals) -> np.ndarray:
    p = np.asarray(line_integrals)
    if p.ndim != 3 or not np.issubdtype(p.dtype, np.floating):
        raise InputError(f"line_integrals: must be a float array of shape (views, rows, cols), "
                          f"got {p.dtype} of shape {p.shape}")
    return p


def _pattern(model, shape, rng, pattern: DetectorPattern | None) -> DetectorPattern:
    if pattern is None:
        return draw_pattern(model, shape, rng)
    for name in ("dead", "hot", "flat_gain", "projection_gain", "dust"):
        value = getattr(pattern, name)
        if value is not None and np.shape(value) != tuple(shape):
            raise InputError(f"pattern.{name}: must have the detector's shape {tuple(shape)}, got {np.shape(value)}")
    return pattern


def _flux(model: DetectorModel, views: int, rng: np.random.Generator) -> np.ndarray:
    """Each projection's beam as a share of the flats' (module docstring), drawn from ``rng`` where it varies."""
    if model.flux_sigma == 0:
        return np.ones(views)
    return np.maximum(1.0 + model.flux_sigma * rng.standard_normal(views), 0.01)


def record(line_integrals, noise, model: DetectorModel, rng: np.random.Generator, *,
           pattern: DetectorPattern | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Record a noisy scan through ``model``'s detector: what :func:`ctpipe.sim.acquisition.acquire` does, with artefacts.

    Parameters
    ----------
    line_integrals : ndarray of shape (V, rows, cols)
        Exact line integrals at the true angles.
    noise : ctpipe.sim.acquisition.NoiseModel
    model : DetectorModel
    rng : numpy.random.Generator
        Draws the pattern (:func:`draw_pattern`), the tube's output in each projection (where ``flux_sigma`` is
        set), then the projections view by view, the flats and the darks.
    pattern : DetectorPattern or None
        A given pattern (e.g. a real detector's defect map) instead of one drawn from ``rng``.

    Returns
    -------
    intensities : ndarray of shape (V, rows, cols), float32
    flats : ndarray of shape (flat_frames, rows, cols), float32
    darks : ndarray of shape (dark_frames, rows, cols), float32, or None when dark_frames is 0
    """
    p = _views(line_integrals)
    shape = p.shape[1:]
    frames = _Frames(model, _pattern(model, shape, rng, pattern), noise.photons_per_pixel, noise.dark_counts, rng)
    flux = _flux(model, len(p), rng)
    intensities = np.empty(p.shape, np.float32)
    for v in range(len(p)):
        intensities[v] = frames.projection(p[v], flux[v])
    flats = np.stack([frames.flat(shape).astype(np.float32) for _ in range(noise.flat_frames)])
    darks = None
    if noise.dark_frames:
        darks = np.stack([frames.dark_frame(shape).astype(np.float32) for _ in range(noise.dark_frames)])
    return intensities, flats, darks


def detected_line_integrals(line_integrals, model: DetectorModel, rng: np.random.Generator, *,
                            pattern: DetectorPattern | None = None, out: np.ndarray | None = None) -> np.ndarray:
    """Noise-free scan through ``model``'s detector: flat-corrected ``-log`` with ``I0 = 1``, float32 (V, rows, cols).

    The chain of the module docstring without Poisson draws or dark current; pixels whose flat
    is 0 (dead) get 0, as :func:`ctpipe.io.flatfield.log_transform` gives them, and the
    transmission is clipped below at 1e-6 as there. ``rng`` draws only the pattern, unless
    ``pattern`` gives it (as in :func:`record`), and the tube's output in each projection. ``out`` may
    be ``line_integrals`` itself (each view is read before it is written): no second stack.
    """
    p = _views(line_integrals)
    out = np.empty(p.shape, np.float32) if out is None else out
    shape = p.shape[1:]
    frames = _Frames(model, _pattern(model, shape, rng, pattern), 1.0, 0.0, None)
    flux = _flux(model, len(p), rng)
    flat = frames.flat(shape)
    alive = flat > 0
    beam = np.where(alive, flat, 1.0)
    for v in range(len(p)):
        transmission = np.maximum(frames.projection(p[v], flux[v]) / beam, 1e-6)
        out[v] = np.where(alive, -np.log(transmission), 0.0)
    return out
