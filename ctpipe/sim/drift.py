"""A misaligned scanner: per-view detector drift, a centre-of-rotation offset and a detector tilt.

The optional ``misalignment`` section of a scan spec (:mod:`ctpipe.sim.scan_spec`)::

    misalignment:
      cor_offset_px: 1.5          # the rotation axis images at column u0_px + 1.5 (every view)
      tilt_deg: 0.3               # the detector turned 0.3 deg in its own plane
      axis_offset_mm: 1.0         # the axis 1 mm off the source's perpendicular (a stage moved sideways)
      drift:                      # the whole projection shifts a little, differently in every view
        walk_px: 0.05             # random walk: normal steps of 0.05 px between views, view 0 at 0
        jumps: 2                  # persistent steps at 2 random views (1..V-1)
        jump_px: 0.5              # each jump 0.5 px with a random sign
        axis: both                # u (columns), v (rows) or both, drawn independently
        at: detector              # what moves: the detector, or the source spot (source: parallax across the sample)

Every key is optional and zero (or absent) by default. The scan is *simulated* with the true
detector, but the geometry it returns and writes stays the nominal one, the one the scanner's
file states: that difference is the misalignment a pipeline meets.

Conventions
-----------
Pixels are ``(x=col, y=row)`` and the principal point ``(u0_px, v0_px)`` as in
:mod:`ctpipe.geometry`. In view ``k`` the true principal point is::

    (u0_px + cor_offset_px + du[k],  v0_px + dv[k])

so a positive offset moves the whole projection towards larger columns (rows): a detector
moved by ``-offset * pitch`` mm in its plane. ``axis_offset_mm`` moves the axis itself sideways, off the source's
perpendicular to the detector (the principal point stays): a point of the object is at ``R(theta) X +
(axis_offset_mm, 0, SOD)`` in the camera frame, so the axis images ``axis_offset_mm * SDD / (SOD * pitch_u)`` columns
from the principal point and the cone's perspective is no longer centred on it. ``du``/``dv`` are the drift. A
source spot that moves sideways by ``s`` mm moves the image of the rotation axis by ``-s (M - 1) / pitch`` pixels
(``M`` the magnification); ``at: detector`` (the default) models it as that uniform shift, leaving out the
parallax across the sample's depth (a fraction ``depth / SOD`` of the shift), and ``at: source`` moves the spot,
parallax and all. The tilt turns the
detector's column direction by ``tilt_deg`` from the camera ``x`` axis towards the camera ``y``
axis (a right-handed rotation about the ray from the source to the detector, the ``z`` axis of
:mod:`ctpipe.model`) about the principal point: the rotation axis then images along
``col - u0 = tan(tilt) (row - v0) pitch_v / pitch_u``.

Randomness: :meth:`Misalignment.sample_offsets_px` draws from the generator it is given, per
axis (columns, then rows) the random walk, then the jumps; ``cor_offset_px`` and ``tilt_deg`` use none,
and a spec without ``drift`` draws nothing, so the jitter's and the noise's draws are unchanged.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from ctpipe.config import check_keys
from ctpipe.errors import ConfigError, InputError
from ctpipe.stages import ParamSpec, check_value

__all__ = ["DetectorDrift", "Misalignment", "parse_misalignment", "resample_to_detector"]


@dataclass(frozen=True)
class DetectorDrift:
    """Per-view shifts of the whole projection: a slow random walk plus occasional jumps.

    Attributes
    ----------
    walk_px : float
        Standard deviation (pixels) of the normal step between consecutive views; view 0 is at 0.
    jumps : int
        Number of persistent steps, at distinct random views ``1..V-1`` (a jump before view
        ``k`` shifts views ``k, k+1, ...``).
    jump_px : float
        Size (pixels) of every jump, with a random sign.
    axis : {"u", "v", "both"}
        Which detector axis drifts: ``u`` columns, ``v`` rows, or both (independent draws).
    at : {"detector", "source"}
        What moves: the detector (every point's image shifts alike), or the source spot, as a tube's does while it
        warms (the shifts are then the rotation axis's image's; a point nearer the spot moves further, by ``(SDD / z
        - 1) / (SDD / SOD - 1)`` times it at distance ``z`` from the spot: 4.1 to 5.7 times the spot's move across a
        phantom 40 mm deep at magnification 5.8; primitive phantoms only,
        :func:`ctpipe.sim.projectors.project_analytic`'s ``spot_offsets_px``).
    """

    walk_px: float = 0.0
    jumps: int = 0
    jump_px: float = 0.0
    axis: Literal["u", "v", "both"] = "both"
    at: Literal["detector", "source"] = "detector"

    def sample(self, n_views: int, rng: np.random.Generator) -> np.ndarray:
        """Offsets ``(du, dv)`` in pixels, ndarray of shape (n_views, 2), float64."""
        if self.jumps > max(n_views - 1, 0):
            raise InputError(f"drift.jumps: {self.jumps} jumps need at least {self.jumps + 1} views, got {n_views}")
        offsets = np.zeros((n_views, 2))
        for column, name in enumerate("uv"):
            if self.axis not in (name, "both"):
                continue
            steps = np.zeros(n_views)
            if self.walk_px > 0 and n_views > 1:
                steps[1:] = rng.normal(0.0, self.walk_px, n_views - 1)
            if self.jumps:
                where = rng.choice(n_views - 1, size=self.jumps, replace=False) + 1
                steps[where] += self.jump_px * rng.choice([-1.0, 1.0], size=self.jumps)
            offsets[:, column] = np.cumsum(steps)
        return offsets

    def to_dict(self) -> dict:
        return {"walk_px": self.walk_px, "jumps": self.jumps, "jump_px": self.jump_px, "axis": self.axis,
                **({"at": self.at} if self.at != "detector" else {})}


@dataclass(frozen=True)
class Misalignment:
    """How the true scanner differs from its nominal geometry (see the module docstring).

    Attributes
    ----------
    cor_offset_px : float
        Columns from ``u0_px`` to the image of the rotation axis, the same in every view.
    tilt_deg : float
        In-plane rotation of the detector about the principal point, degrees.
    drift : DetectorDrift or None
        Per-view shifts of the projection; None for none.
    axis_offset_mm : float
        How far the rotation axis lies off the source's perpendicular to the detector, along the camera ``x``, at the
        axis (mm): a stage moved sideways, or a detector yawed by ``asin(axis_offset_mm / SOD)`` (primitive phantoms
        only; :func:`ctpipe.sim.projectors.project_analytic`). The axis then images ``axis_offset_mm * SDD / (SOD *
        pitch_u)`` columns from the principal point, which ``cor_offset_px`` places.
    """

    cor_offset_px: float = 0.0
    tilt_deg: float = 0.0
    drift: DetectorDrift | None = None
    axis_offset_mm: float = 0.0

    def sample_offsets_px(self, n_views: int, rng: np.random.Generator, *, drift: bool = True) -> np.ndarray:
        """True minus nominal principal point per view, ``(du, dv)`` pixels, shape (n_views, 2), float64.

        ``drift=False`` leaves the drift out (and draws nothing): only the centre-of-rotation offset.
        """
        offsets = np.zeros((n_views, 2))
        if drift and self.drift is not None:
            offsets = self.drift.sample(n_views, rng)
        offsets[:, 0] += self.cor_offset_px
        return offsets

    def to_dict(self) -> dict:
        """The mapping that parses back to this misalignment."""
        return {"cor_offset_px": self.cor_offset_px, "tilt_deg": self.tilt_deg,
                "drift": None if self.drift is None else self.drift.to_dict(),
                **({"axis_offset_mm": self.axis_offset_mm} if self.axis_offset_mm else {})}


_FIELDS = {"cor_offset_px": ParamSpec("cor_offset_px", float, 0.0, "", ge=-10_000, le=10_000),
           "tilt_deg": ParamSpec("tilt_deg", float, 0.0, "", ge=-45, le=45),
           "axis_offset_mm": ParamSpec("axis_offset_mm", float, 0.0, "", ge=-100, le=100)}
_DRIFT_FIELDS = {"walk_px": ParamSpec("walk_px", float, 0.0, "", ge=0, le=100),
                 "jumps": ParamSpec("jumps", int, 0, "", ge=0, le=100_000),
                 "jump_px": ParamSpec("jump_px", float, 0.0, "", ge=0, le=1_000),
                 "axis": ParamSpec("axis", Literal["u", "v", "both"], "both", ""),
                 "at": ParamSpec("at", Literal["detector", "source"], "detector", "")}


def parse_misalignment(value: Any, path: str = "misalignment", *, n_views: int | None = None) -> Misalignment | None:
    """Validate a ``misalignment`` mapping (module docstring); None (absent) is a nominal scanner.

    ``n_views``, when given, checks that the drift's jumps fit between the views.
    """
    if value is None:
        return None
    check_keys(value, path, allowed=(*_FIELDS, "drift"))
    values = {key: check_value(_FIELDS[key], raw, f"{path}.{key}") for key, raw in value.items() if key != "drift"}
    drift = None
    if value.get("drift") is not None:
        raw = check_keys(value["drift"], f"{path}.drift", allowed=tuple(_DRIFT_FIELDS))
        params = {key: check_value(_DRIFT_FIELDS[key], item, f"{path}.drift.{key}") for key, item in raw.items()}
        drift = DetectorDrift(**params)
        if drift.jumps and drift.jump_px == 0:
            raise ConfigError(f"{path}.drift.jump_px: {drift.jumps} jumps need a size > 0 (pixels), got 0")
        if n_views is not None and drift.jumps > max(n_views - 1, 0):
            raise ConfigError(f"{path}.drift.jumps: {drift.jumps} jumps need at least {drift.jumps + 1} views, "
                              f"got {n_views}")
    return Misalignment(drift=drift, **values)


def _refuse_axis_offset(axis_offset_mm: float, spot_offsets_px=None) -> None:
    """Refuse an axis off the source's perpendicular, or a source spot that moves, where it cannot be projected: a
    voxel phantom (the analytic projector moves primitives view by view; the voxel projector has no such move)."""
    if axis_offset_mm:
        raise InputError(f"misalignment.axis_offset_mm: {axis_offset_mm:g} mm is simulated for primitive phantoms "
                         "only; leave it out (0) for a voxel phantom")
    if spot_offsets_px is not None:
        raise InputError("misalignment.drift.at: source is simulated for primitive phantoms only; use 'detector' "
                         "for a voxel phantom")


def resample_to_detector(projections: np.ndarray, geometry, offsets_px=None, tilt_deg: float = 0.0) -> np.ndarray:
    """Projections on the nominal detector, resampled onto the true (shifted, tilted) one.

    For projectors without per-view detector placement (the voxel projector): pixel
    ``(col, row)`` of view ``k`` of the true detector lies at camera ``(x, y)`` (module
    docstring), which the nominal detector images at ``(u0 + x / pitch_u, v0 + y / pitch_v)``;
    the value there is interpolated linearly. What the true detector sees beyond the nominal
    one's edge is unknown and taken as 0 (the analytic projector has no such edge).

    Parameters
    ----------
    projections : ndarray of shape (V, rows, cols)
    geometry : ctpipe.geometry.Geometry
        The nominal geometry.
    offsets_px : array_like of shape (V, 2) or None
        ``(du, dv)`` pixels of the true principal point from the nominal one.
    tilt_deg : float

    Returns
    -------
    ndarray of shape (V, rows, cols), float32
    """
    from scipy.ndimage import map_coordinates

    projections = np.asarray(projections)
    n_views, n_rows, n_cols = projections.shape
    offsets = np.zeros((n_views, 2)) if offsets_px is None else np.asarray(offsets_px, dtype=np.float64)
    if offsets.shape != (n_views, 2):
        raise InputError(f"offsets_px: must have shape (views, 2) = {(n_views, 2)}, got {offsets.shape}")
    pu, pv = geometry.pixel_pitch_u_mm, geometry.pixel_pitch_v_mm
    ct, st = np.cos(np.deg2rad(tilt_deg)), np.sin(np.deg2rad(tilt_deg))
    rows, cols = np.meshgrid(np.arange(n_rows, dtype=np.float64), np.arange(n_cols, dtype=np.float64), indexing="ij")
    out = np.empty(projections.shape, dtype=np.float32)
    for k in range(n_views):
        a = (cols - geometry.u0_px - offsets[k, 0]) * pu
        b = (rows - geometry.v0_px - offsets[k, 1]) * pv
        x, y = ct * a - st * b, st * a + ct * b
        out[k] = map_coordinates(projections[k], [geometry.v0_px + y / pv, geometry.u0_px + x / pu], order=1,
                                 mode="constant", cval=0.0)
    return out
