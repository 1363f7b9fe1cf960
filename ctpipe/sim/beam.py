"""A polychromatic X-ray beam: a tube spectrum through materials with energy-dependent attenuation.

The scan spec's optional ``beam`` section (off by default: without it a scan is
monochromatic, each object attenuating by its ``density_per_mm``)::

    beam:
      kvp: 120                      # tube voltage, kV peak (10-500)
      anode: W                      # target: W, Mo or Rh
      anode_angle_deg: 12           # take-off angle of the target (5-45)
      filter_mm: {Al: 1.0, Cu: 0.1} # filtration (tube window included): material -> thickness, mm
      energy_bins: 32               # energy bins of the computation (1-256)
      detector_response: energy-integrating   # or photon-counting

or, for a monochromatic source at a known energy (a synchrotron, or a check against a closed
form): ``beam: {energy_kev: 60}``.

Physics. The tube spectrum (photons per keV) is ``spekpy``'s for the anode, kVp and angle, on
its 0.5 keV grid; the filters attenuate it there, ``exp(-mu_f(E) t_f)`` with ``mu_f`` from
``xraydb`` at the material's usual density. The grid is then summed into ``energy_bins`` equal
bins from its lowest energy to the kVp; each bin keeps its weight ``w_b`` (photons, or photons x
E for an energy-integrating detector, which sums the energy photons deposit) and its weighted
mean energy ``E_b``; empty bins are dropped, the weights normalised to sum 1. A ray whose path
holds ``L_m = integral of rho_m`` (g/cm^3 x mm) of each material ``m`` transmits::

    T = sum_b w_b exp(-sum_m mu_m(E_b)/rho_m x rho_m L_m)        (T = 1 with no object)

and the detector sees ``I0 T``: the flat field is ``I0`` photons and :mod:`~ctpipe.sim.acquisition`
draws Poisson counts as for a monochromatic scan (photon-equivalent counts: the extra variance of
an energy-integrating detector is not modelled). The simulator hands ``-log T`` on as the line
integrals, so a noise-free scan gives exactly what the flat-field correction of a noisy one
estimates. ``L_m`` comes from the analytic projector run once per material, each material's
primitives at their mass density; an object without a material (and a voxel phantom) counts as
water with the attenuation ``density_per_mm`` at 60 keV. A detector blur blurs ``T`` (the
intensities), not the line integrals. Spectra and attenuation tables are cached per beam.

What it does to a scan: the low energies are absorbed first, so the beam hardens along a ray
and ``-log T`` grows less than linearly with thickness; FDK reconstructs a uniform object
darker in its centre than at its edge (cupping) and draws dark streaks between metal parts.
More filtration or a higher kVp reduce both.

``spekpy`` (spectra) and ``xraydb`` (attenuation) are MIT-licensed and optional:
``pip install 'ctpipe[beam]'`` (spekpy is about 200 MB installed).
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from ctpipe.config import check_keys
from ctpipe.errors import ConfigError
from ctpipe.sim.materials import (INSTALL_BEAM, MATERIALS, REFERENCE_KEV, beam_libraries_missing,
                                  element_density_g_cm3, mass_attenuation_cm2_g, resolve_material)
from ctpipe.stages import ParamSpec, check_value

__all__ = ["Beam", "parse_beam", "beam_spectrum", "effective_energy_kev", "polychromatic_line_integrals", "ANODES",
           "DETECTOR_RESPONSES", "MAX_ENERGY_TERMS"]

#: Anode (target) materials spekpy models.
ANODES = ("W", "Mo", "Rh")
#: How the detector weights a photon: by its energy (scintillator + photodiode) or by one count.
DETECTOR_RESPONSES = ("energy-integrating", "photon-counting")

_FIELDS = {
    "kvp": ParamSpec("kvp", float, None, "", ge=10, le=500),
    "anode": ParamSpec("anode", Literal["W", "Mo", "Rh"], "W", ""),
    "anode_angle_deg": ParamSpec("anode_angle_deg", float, 12.0, "", ge=5, le=45),
    "energy_bins": ParamSpec("energy_bins", int, 32, "", ge=1, le=256),
    "detector_response": ParamSpec("detector_response", Literal["energy-integrating", "photon-counting"],
                                   "energy-integrating", ""),
    "energy_kev": ParamSpec("energy_kev", float, None, "", ge=1, le=500),
}
_THICKNESS = ParamSpec("", float, None, "", ge=0, le=1000)
_CHUNK_VIEWS = 8

#: The most energy-bin terms (pixels x views x energy bins) one polychromatic simulation takes on:
#: each is an exponential and a weighted sum in float64, about 9 ns with two materials (measured on
#: 8 views of 512^2 and 32 bins), so 1e11 is about 15 minutes, as the projectors' limits.
MAX_ENERGY_TERMS = 1e11


@dataclass(frozen=True)
class Beam:
    """A validated ``beam`` section (see the module docstring).

    Attributes
    ----------
    kvp : float or None
        Tube voltage (kV peak); None for a monochromatic beam.
    anode : str
    anode_angle_deg : float
    filter_mm : tuple of (str, float)
        Filter material names and thicknesses (mm), in the order given.
    energy_bins : int
    detector_response : str
        One of :data:`DETECTOR_RESPONSES`.
    energy_kev : float or None
        The one energy of a monochromatic beam (then ``kvp`` is None).
    """

    kvp: float | None = 120.0
    anode: str = "W"
    anode_angle_deg: float = 12.0
    filter_mm: tuple = ()
    energy_bins: int = 32
    detector_response: str = "energy-integrating"
    energy_kev: float | None = None

    def to_dict(self) -> dict:
        """The mapping that parses back to this beam."""
        if self.energy_kev is not None:
            return {"energy_kev": self.energy_kev}
        return {"kvp": self.kvp, "anode": self.anode, "anode_angle_deg": self.anode_angle_deg,
                "filter_mm": dict(self.filter_mm), "energy_bins": self.energy_bins,
                "detector_response": self.detector_response}


def parse_beam(value: Any, path: str = "beam") -> Beam | None:
    """Validate a ``beam`` mapping; ``None`` (absent) is the monochromatic default.

    Raises
    ------
    ConfigError
        Unknown key, a value out of range, an unknown filter material, ``kvp`` and ``energy_kev``
        both or neither, or spekpy/xraydb not installed (the message gives the pip command).
    """
    if value is None:
        return None
    check_keys(value, path, allowed=(*_FIELDS, "filter_mm"))
    missing = beam_libraries_missing()
    if missing:
        raise ConfigError(f"{path}: a polychromatic beam needs {' and '.join(missing)}, not installed: {INSTALL_BEAM}")
    fields = {key: check_value(_FIELDS[key], raw, f"{path}.{key}") for key, raw in value.items() if key in _FIELDS}
    mono = fields.get("energy_kev") is not None
    if mono == (fields.get("kvp") is not None):
        raise ConfigError(f"{path}: give exactly one of kvp (a tube spectrum) or energy_kev (one energy), "
                          f"got {dict(value)!r}")
    if mono and set(value) - {"energy_kev"}:
        raise ConfigError(f"{path}: energy_kev (a monochromatic beam) takes no other key, got "
                          f"{', '.join(sorted(set(value) - {'energy_kev'}))}")
    filters = value.get("filter_mm") or {}
    if not isinstance(filters, Mapping):
        raise ConfigError(f"{path}.filter_mm: must be a mapping material -> thickness in mm "
                          f"(e.g. {{Al: 1.0, Cu: 0.1}}), got {filters!r}")
    checked = []
    for name, thickness in filters.items():
        where = f"{path}.filter_mm.{name}"
        _filter_material(name, where)
        checked.append((str(name), check_value(_THICKNESS, thickness, where)))
    return Beam(**{"kvp": None, **fields}, filter_mm=tuple(checked))


def _filter_material(name, path: str):
    """The material of a filter and its density (g/cm^3): a built-in name or an element symbol."""
    material = resolve_material(name, path)
    if material.density_g_cm3 is not None:
        return material, material.density_g_cm3
    density = element_density_g_cm3(material.formula)
    if density is None:
        raise ConfigError(f"{path}: a filter is a built-in material ({', '.join(MATERIALS)}) or an element symbol "
                          f"(Sn, Ag), got the formula {name!r}")
    return material, density


@functools.lru_cache(maxsize=32)
def _tube_spectrum(kvp: float, anode: str, angle_deg: float) -> tuple[np.ndarray, np.ndarray]:
    import spekpy

    energies, fluence = spekpy.Spek(kvp=kvp, th=angle_deg, targ=anode, dk=0.5).get_spectrum()
    energies, fluence = np.asarray(energies, np.float64), np.asarray(fluence, np.float64)
    energies.flags.writeable = fluence.flags.writeable = False
    return energies, fluence


@functools.lru_cache(maxsize=32)
def beam_spectrum(beam: Beam) -> tuple[np.ndarray, np.ndarray]:
    """The beam's energy bins: ``(energies_kev, weights)``, each float64 of shape (B,), weights summing to 1.

    Weights are photons (photon-counting) or photons x energy (energy-integrating) after the
    filters, per bin; the energies are the bins' weighted mean energies.
    """
    if beam.energy_kev is not None:
        return np.array([beam.energy_kev]), np.array([1.0])
    energies, fluence = _tube_spectrum(float(beam.kvp), beam.anode, float(beam.anode_angle_deg))
    transmitted = fluence.copy()
    for name, thickness in beam.filter_mm:
        material, density = _filter_material(name, "beam.filter_mm")
        transmitted *= np.exp(-mass_attenuation_cm2_g(material, energies) * density * thickness * 0.1)
    if beam.detector_response == "energy-integrating":
        transmitted *= energies
    step = energies[1] - energies[0] if len(energies) > 1 else 1.0
    edges = np.linspace(energies[0] - step / 2, float(beam.kvp), beam.energy_bins + 1)
    index = np.clip(np.searchsorted(edges, energies, side="right") - 1, 0, beam.energy_bins - 1)
    weight = np.bincount(index, transmitted, beam.energy_bins)
    mean = np.bincount(index, transmitted * energies, beam.energy_bins)
    keep = weight > weight.sum() * 1e-12
    if not keep.any():
        raise ConfigError("beam.filter_mm: the filters absorb the whole spectrum; use thinner filters or a higher kvp")
    return mean[keep] / weight[keep], weight[keep] / weight[keep].sum()


def _water_per_mm() -> float:
    """Water's attenuation (1/mm per g/cm^3) at the reference energy, from xraydb as the beam's own tables."""
    return float(mass_attenuation_cm2_g(MATERIALS["water"], [REFERENCE_KEV])[0]) * 0.1


def _groups(phantom) -> list[tuple[str, Any]]:
    """``(material name, primitives at mass density g/cm^3)`` per material of a primitive phantom.

    Objects without a material join water, their mass density the water that attenuates like
    their ``density_per_mm`` at :data:`~ctpipe.sim.materials.REFERENCE_KEV`.
    """
    from ctpipe.sim.primitives import Primitives

    p = phantom.primitives
    water_per_mm = _water_per_mm()
    grey = p.material < 0
    water_index = p.materials.index("water") if "water" in p.materials else None
    groups = []
    for m, name in enumerate(p.materials):
        mask = p.material == m
        if name == "water":
            mask = mask | grey
        if not mask.any():
            continue
        sub = p.subset(mask)
        rho = np.where(sub.material < 0, sub.density_per_mm / water_per_mm, sub.mass_density_g_cm3)
        groups.append((name, Primitives(sub.kind, sub.centre_mm, sub.half_size_mm, sub.rotation, rho)))
    if water_index is None and grey.any():
        sub = p.subset(grey)
        groups.append(("water", Primitives(sub.kind, sub.centre_mm, sub.half_size_mm, sub.rotation,
                                           sub.density_per_mm / water_per_mm)))
    return groups


def polychromatic_line_integrals(phantom, beam: Beam, geometry, angles_deg, *, supersample: int = 1,
                                 blur_px: float = 0.0, progress: Callable[[int], object] | None = None,
                                 detector_offsets_px=None, detector_tilt_deg: float = 0.0,
                                 axis_offset_mm: float = 0.0, spot_offsets_px=None) -> np.ndarray:
    """``-log T`` of every pixel (see the module docstring), float32 of shape (V, rows, cols).

    Parameters
    ----------
    phantom : ctpipe.sim.phantoms.Phantom
        Primitive or voxel phantom.
    beam : Beam
    geometry : Geometry
    angles_deg : array_like of shape (V,)
        Turntable angles, degrees.
    supersample, blur_px, progress, detector_offsets_px, detector_tilt_deg, axis_offset_mm, spot_offsets_px
        As for :func:`ctpipe.sim.simulator.project_phantom` (a misaligned detector included); the
        blur acts on ``T``.
    """
    from ctpipe.sim.projectors import VoxelProjector, project_analytic

    angles = np.asarray(angles_deg, dtype=np.float64).reshape(-1)
    if phantom.primitives is None:   # before any projection: only primitives are moved off the axis
        from ctpipe.sim.drift import _refuse_axis_offset

        _refuse_axis_offset(axis_offset_mm, spot_offsets_px)
    energies, weights = beam_spectrum(beam)
    water_per_mm = _water_per_mm()
    if phantom.primitives is not None:
        groups = _groups(phantom)
        names = [name for name, _ in groups]
    else:
        names = ["water"]
    # mu/rho (cm^2/g) x 0.1: attenuation per (g/cm^3 x mm), shape (M, B).
    mu = np.array([mass_attenuation_cm2_g(resolve_material(name, "material"), energies) * 0.1 for name in names])
    out = np.empty((angles.size, geometry.detector_rows, geometry.detector_cols), np.float32)
    tiny = np.finfo(np.float64).tiny
    for start in range(0, angles.size, _CHUNK_VIEWS):
        stop = min(start + _CHUNK_VIEWS, angles.size)
        chunk = angles[start:stop]
        offsets = None if detector_offsets_px is None else np.asarray(detector_offsets_px)[start:stop]
        spot = None if spot_offsets_px is None else np.asarray(spot_offsets_px)[start:stop]
        if phantom.primitives is not None:
            paths = [project_analytic(prims, geometry, chunk, supersample=supersample, detector_offsets_px=offsets,
                                      detector_tilt_deg=detector_tilt_deg, axis_offset_mm=axis_offset_mm,
                                      spot_offsets_px=spot).astype(np.float64)
                     for _, prims in groups]
        else:
            path = VoxelProjector(geometry, phantom.grid).forward(phantom.volume, chunk)
            if offsets is not None or detector_tilt_deg != 0:
                from ctpipe.sim.drift import resample_to_detector

                path = resample_to_detector(path, geometry, offsets, detector_tilt_deg)
            paths = [path.astype(np.float64) / water_per_mm]
        transmitted = np.zeros(paths[0].shape if paths else out[start:stop].shape)
        for b, w in enumerate(weights):
            exponent = np.zeros_like(transmitted)
            for m, path in enumerate(paths):
                exponent += mu[m, b] * path
            transmitted += w * np.exp(-exponent)
        if blur_px > 0:
            from scipy.ndimage import gaussian_filter

            for k in range(len(transmitted)):
                transmitted[k] = gaussian_filter(transmitted[k], sigma=float(blur_px))
        out[start:stop] = 0.0 - np.log(np.maximum(transmitted, tiny))  # 0.0 -: no -0.0 where T = 1
        if progress is not None:
            progress(stop)
    return out


def effective_energy_kev(beam: Beam) -> float:
    """The weighted mean energy of the beam's bins (keV): a one-number summary for reports."""
    energies, weights = beam_spectrum(beam)
    return float(np.sum(energies * weights))

