"""The X-ray detector: Beer-Lambert counts with Poisson noise, flat and dark fields, ``-log``.

A pixel whose ray has line integral ``p`` (the sum of attenuation x length, dimensionless)
sees, in one frame::

    I = Poisson(I0 exp(-p)) + Poisson(dark_counts)      (a projection)
    F = Poisson(I0)         + Poisson(dark_counts)      (a flat field: no object)
    D =                       Poisson(dark_counts)      (a dark field: no beam)

with ``I0 = photons_per_pixel``, the unattenuated photons a pixel counts in one frame. A sum of
independent Poisson counts is a Poisson count of the summed mean, so the beam and the dark
current of a frame are drawn as one. The
reconstruction starts from the flat/dark-corrected line integrals of
:func:`ctpipe.io.flatfield.log_transform`, the correction every real scan needs too.

Every array this module returns is float32 (Poisson counts below 2^24 are exact in it); the
arithmetic is float64, one view at a time, so that a 360-view 512^2 scan needs no float64
copy of the whole stack. Each view draws from a stream of its own, spawned from the caller's
``rng`` (:meth:`numpy.random.Generator.spawn`), so the views are drawn in parallel (NumPy's
samplers let go of the GIL) and the scan is the same whatever the number of threads.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import numpy as np

from ctpipe._shared.resources import available_cores
from ctpipe.config import check_keys
from ctpipe.errors import InputError
from ctpipe.stages import ParamSpec, check_value

__all__ = ["NoiseModel", "parse_noise", "beer_lambert", "acquire"]


@dataclass(frozen=True)
class NoiseModel:
    """Detector exposure and the calibration frames of a noisy acquisition.

    Parameters
    ----------
    photons_per_pixel : float
        ``I0``: mean counts of an unattenuated pixel in one frame (> 0).
    flat_frames : int
        Flat fields recorded (>= 1); their mean is the reference ``I0``.
    dark_frames : int
        Dark fields recorded (>= 0); with 0 the offset is taken as 0.
    dark_counts : float
        Mean dark-current counts per pixel and frame (>= 0), added to every frame.
    """

    photons_per_pixel: float
    flat_frames: int = 8
    dark_frames: int = 4
    dark_counts: float = 0.0

    def __post_init__(self) -> None:
        for key, spec in _NOISE_FIELDS.items():
            object.__setattr__(self, key, check_value(spec, getattr(self, key), f"noise.{key}"))

    def to_dict(self) -> dict:
        return {key: getattr(self, key) for key in _NOISE_FIELDS}


#: Largest photon count per pixel and frame: numpy's Poisson sampler refuses means beyond ~1e19
#: ("lam value too large"), and real detectors count well under 1e6.
MAX_PHOTONS = 1e12

_NOISE_FIELDS = {
    "photons_per_pixel": ParamSpec("photons_per_pixel", float, None, "", gt=0, le=MAX_PHOTONS),
    "flat_frames": ParamSpec("flat_frames", int, 8, "", ge=1, le=10_000),
    "dark_frames": ParamSpec("dark_frames", int, 4, "", ge=0, le=10_000),
    "dark_counts": ParamSpec("dark_counts", float, 0.0, "", ge=0, le=MAX_PHOTONS),
}


def parse_noise(value: Any, path: str = "noise") -> NoiseModel | None:
    """Validate a ``noise`` mapping; ``null`` or ``photons_per_pixel: null`` means noise-free."""
    if value is None:
        return None
    check_keys(value, path, allowed=tuple(_NOISE_FIELDS), required=("photons_per_pixel",))
    spec = ParamSpec("photons_per_pixel", float | None, None, "", gt=0, le=MAX_PHOTONS)
    if check_value(spec, value["photons_per_pixel"], f"{path}.photons_per_pixel") is None:
        return None
    values = {key: check_value(_NOISE_FIELDS[key], raw, f"{path}.{key}") for key, raw in value.items()}
    return NoiseModel(**values)


def _stack(line_integrals) -> np.ndarray:
    p = np.asarray(line_integrals)
    if p.ndim not in (2, 3) or not np.issubdtype(p.dtype, np.floating):
        raise InputError(f"line_integrals: must be a float array of shape (views, rows, cols) or (rows, cols), "
                         f"got {p.dtype} of shape {p.shape}")
    return p


def beer_lambert(line_integrals, photons_per_pixel: float, dark_counts: float = 0.0) -> np.ndarray:
    """Noise-free mean counts ``I0 exp(-p) + dark_counts``, float32 of the input's shape."""
    p = _stack(line_integrals)
    return (photons_per_pixel * np.exp(-p.astype(np.float64)) + dark_counts).astype(np.float32)


def acquire(line_integrals, noise: NoiseModel, rng: np.random.Generator
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Record a scan with Poisson noise (see the module docstring).

    Parameters
    ----------
    line_integrals : ndarray of shape (V, rows, cols)
        Exact line integrals at the true angles.
    noise : NoiseModel
    rng : numpy.random.Generator
        Spawns one stream per view and one for the flats and darks; draws nothing itself.

    Returns
    -------
    intensities : ndarray of shape (V, rows, cols), float32
    flats : ndarray of shape (flat_frames, rows, cols), float32
    darks : ndarray of shape (dark_frames, rows, cols), float32, or None when dark_frames is 0
    """
    p = _stack(line_integrals)
    if p.ndim == 2:
        p = p[None]
    i0, dark = noise.photons_per_pixel, noise.dark_counts
    shape = p.shape[1:]

    def frame(stream: np.random.Generator, mean: np.ndarray | float) -> np.ndarray:
        # Poisson(mean) + Poisson(dark) is Poisson(mean + dark): one draw per pixel, not two.
        return stream.poisson(np.asarray(mean, dtype=np.float64) + dark, size=shape).astype(np.float32)

    *streams, calibration = rng.spawn(len(p) + 1)
    intensities = np.empty(p.shape, np.float32)

    def view(v: int) -> None:
        intensities[v] = frame(streams[v], i0 * np.exp(-p[v].astype(np.float64)))

    # 360 views of 512^2: 5.0 s drawn one after the other, 1.8 s on two threads.
    with ThreadPoolExecutor(max_workers=available_cores()) as pool:
        list(pool.map(view, range(len(p))))
    flats = np.stack([frame(calibration, i0) for _ in range(noise.flat_frames)])
    darks = None
    if noise.dark_frames:
        darks = np.stack([calibration.poisson(dark, size=shape).astype(np.float32) for _ in range(noise.dark_frames)])
    return intensities, flats, darks
