"""Scan specs: what ``ctpipe simulate PHANTOM --scan SCAN.yaml`` acquires::

    geometry: {...}                                  # as in a scan folder (ctpipe.io.scan_folder)
    angles: {n_views: 360, range_deg: 360.0, start_deg: 0.0}   # see ctpipe.sim.jitter.nominal_angles_deg
                                                     # (closing_view: true, the last view a turn on: AngleSpec)
    jitter: [{gaussian: {sigma_deg: 0.2}}, {jumps: {count: 3, size_deg: 1.0}}]   # ctpipe.sim.jitter
    noise: {photons_per_pixel: 100000, flat_frames: 8, dark_frames: 4, dark_counts: 100}
                                                     # ctpipe.sim.acquisition; null: exact line integrals
    projector: {kind: analytic, supersample: 2, blur_px: 0.5}   # the phantom picks the projector
    detector: {scatter_fraction: 0.05, psf_sigma_px: 0.8, dead_pixels: 20, gain_drift_sigma: 0.005}
                                                     # ctpipe.sim.detector; null: an ideal detector
    beam: {kvp: 120, anode: W, filter_mm: {Al: 1.0}, energy_bins: 32}   # ctpipe.sim.beam: polychromatic
    misalignment: {cor_offset_px: 1.5, tilt_deg: 0.3, drift: {walk_px: 0.05, jumps: 2, jump_px: 0.5}}
                                                     # ctpipe.sim.drift; null: the nominal scanner
    holder: {origin: sample_bottom, turning: [{cylinder: {...}}], static: [{box: {...}}]}   # ctpipe.sim.holders
    seed: 0

``geometry`` and ``angles`` are required; ``jitter`` defaults to none, ``noise`` to null,
``projector`` to ``{kind: analytic, supersample: 1, blur_px: 0}``, ``seed`` to 0, ``detector`` to
null (no artefacts).
``beam`` defaults to none: a monochromatic scan, each object attenuating by its ``density_per_mm``.
``misalignment`` defaults to null (the scanner is exactly its nominal geometry).
``holder`` defaults to null: no sample holder; ``{origin, turning: [...], static: [...]}`` adds objects
that turn with the sample and objects that do not (:mod:`ctpipe.sim.holders`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from ctpipe.config import check_keys, load_yaml, parse_geometry
from ctpipe.errors import ConfigError
from ctpipe.geometry import Geometry
from ctpipe.sim.acquisition import NoiseModel, parse_noise
from ctpipe.sim.beam import Beam, parse_beam
from ctpipe.sim.detector import DetectorModel, parse_detector
from ctpipe.sim.drift import Misalignment, parse_misalignment
from ctpipe.sim.holders import Holder, parse_holder
from ctpipe.sim.jitter import Jitter, nominal_angles_deg, parse_jitter
from ctpipe.stages import ParamSpec, check_value

__all__ = ["AngleSpec", "ProjectorSpec", "ScanSpec", "parse_scan_spec", "load_scan_spec"]


@dataclass(frozen=True)
class AngleSpec:
    """Nominal angles: ``n_views`` over ``range_deg`` from ``start_deg``.

    With ``closing_view`` the last of the ``n_views`` is taken at ``start_deg + range_deg`` even for
    a full turn, the first view again (steps ``range_deg / (n_views - 1)``), as scanners that record
    a closing image do: a Nikon scan of ``Projections`` views and its closing image is
    ``{n_views: Projections + 1, closing_view: true}`` (:mod:`ctpipe.io.nikon`).
    """

    n_views: int
    range_deg: float = 360.0
    start_deg: float = 0.0
    closing_view: bool = False

    def nominal_angles_deg(self) -> np.ndarray:
        """Shape (n_views,), float64; see :func:`ctpipe.sim.jitter.nominal_angles_deg`."""
        return nominal_angles_deg(self.n_views, self.range_deg, self.start_deg, self.closing_view)

    def to_dict(self) -> dict:
        return {"n_views": self.n_views, "range_deg": self.range_deg, "start_deg": self.start_deg,
                **({"closing_view": True} if self.closing_view else {})}


@dataclass(frozen=True)
class ProjectorSpec:
    """How line integrals are computed.

    The phantom picks the projector: primitives are projected exactly, a voxel phantom by the
    voxel projector. ``kind`` is ``analytic`` only; ``voxel`` (a primitive phantom projected
    through its voxelisation) was accepted but never done, so it is refused rather than ignored.
    """

    kind: Literal["analytic"] = "analytic"
    supersample: int = 1
    blur_px: float = 0.0

    def to_dict(self) -> dict:
        return {"kind": self.kind, "supersample": self.supersample, "blur_px": self.blur_px}


@dataclass(frozen=True)
class ScanSpec:
    """A validated scan spec (see the module docstring)."""

    geometry: Geometry
    angles: AngleSpec
    jitter: Jitter = field(default_factory=Jitter)
    noise: NoiseModel | None = None
    projector: ProjectorSpec = field(default_factory=ProjectorSpec)
    seed: int = 0
    detector: DetectorModel | None = None
    beam: Beam | None = None
    misalignment: Misalignment | None = None
    holder: Holder | None = None

    @property
    def n_views(self) -> int:
        return self.angles.n_views

    def nominal_angles_deg(self) -> np.ndarray:
        """Commanded angles, shape (n_views,), float64, degrees."""
        return self.angles.nominal_angles_deg()

    def to_dict(self) -> dict:
        """The mapping that parses back to this spec."""
        return {"geometry": self.geometry.to_dict(), "angles": self.angles.to_dict(), "jitter": self.jitter.to_dict(),
                "noise": None if self.noise is None else self.noise.to_dict(), "projector": self.projector.to_dict(),
                "seed": self.seed, **({} if self.detector is None else {"detector": self.detector.to_dict()}),
                **({} if self.beam is None else {"beam": self.beam.to_dict()}),
                **({} if self.misalignment is None else {"misalignment": self.misalignment.to_dict()}),
                **({} if self.holder is None else {"holder": self.holder.to_dict()})}


_ANGLE_FIELDS = {"n_views": ParamSpec("n_views", int, None, "", ge=1, le=100_000),
                 "range_deg": ParamSpec("range_deg", float, 360.0, "", gt=0, le=36_000),
                 "start_deg": ParamSpec("start_deg", float, 0.0, "", ge=-36_000, le=36_000),
                 "closing_view": ParamSpec("closing_view", bool, False, "")}
_PROJECTOR_FIELDS = {"kind": ParamSpec("kind", Literal["analytic"], "analytic", ""),
                     "supersample": ParamSpec("supersample", int, 1, "", ge=1, le=16),
                     "blur_px": ParamSpec("blur_px", float, 0.0, "", ge=0, le=64)}
_SEED = ParamSpec("seed", int, 0, "", ge=0)


def _fields(value: Any, path: str, table: dict[str, ParamSpec], required: tuple[str, ...] = ()) -> dict:
    check_keys(value, path, allowed=tuple(table), required=required)
    return {key: check_value(table[key], raw, f"{path}.{key}") for key, raw in value.items()}


def parse_scan_spec(mapping: Any, path: str = "scan") -> ScanSpec:
    """Validate a scan spec mapping; errors name the YAML path, the value and what is allowed."""
    check_keys(mapping, path, allowed=("geometry", "angles", "jitter", "noise", "projector", "seed", "detector",
                                      "beam", "misalignment", "holder"),
               required=("geometry", "angles"))
    geometry = parse_geometry(mapping["geometry"], f"{path}.geometry")
    angles = AngleSpec(**_fields(mapping["angles"], f"{path}.angles", _ANGLE_FIELDS, required=("n_views",)))
    jitter = parse_jitter(mapping.get("jitter"), f"{path}.jitter")
    noise = parse_noise(mapping.get("noise"), f"{path}.noise")
    projector = ProjectorSpec(**_fields(mapping.get("projector") or {}, f"{path}.projector", _PROJECTOR_FIELDS))
    seed = check_value(_SEED, mapping.get("seed", 0), f"{path}.seed")
    detector = parse_detector(mapping.get("detector"), f"{path}.detector",
                              (geometry.detector_rows, geometry.detector_cols))
    beam = parse_beam(mapping.get("beam"), f"{path}.beam")
    misalignment = parse_misalignment(mapping.get("misalignment"), f"{path}.misalignment", n_views=angles.n_views)
    holder = parse_holder(mapping.get("holder"), f"{path}.holder")
    if holder is not None and beam is not None and len(holder.static):
        raise ConfigError(f"{path}.holder.static: a static holder is not simulated under a polychromatic beam yet; "
                          f"leave out beam or the static objects")
    return ScanSpec(geometry, angles, jitter, noise, projector, seed, detector=detector, beam=beam,
                    misalignment=misalignment, holder=holder)


def load_scan_spec(path: str | Path) -> ScanSpec:
    """Read and validate a scan spec YAML file."""
    return parse_scan_spec(load_yaml(path), path=str(path))
