"""Phantoms as data: YAML files of analytic primitives, seeded generators or a voxel array.

A phantom file is validated as strictly as a pipeline file: unknown keys, wrong types and
out-of-range values raise :class:`~ctpipe.errors.ConfigError` naming the YAML path, the value
and what is allowed.

Schema
------
::

    name: granular                  # optional; default: the file name without .yaml
    description: ...                # optional, one paragraph
    units: mm                       # optional; only mm is allowed
    objects:                        # a list of one-key mappings {kind: parameters}
      - ellipsoid: {centre_mm: [x, y, z], semi_axes_mm: [a, b, c], rotation_deg: [rx, ry, rz],
                    density_per_mm: 0.02}
      - sphere:    {centre_mm: [x, y, z], radius_mm: r, density_per_mm: 0.02}
      - cylinder:  {centre_mm: [x, y, z], radius_mm: r, height_mm: h, rotation_deg: [...],
                    density_per_mm: 0.02}          # or radii_mm: [r_x, r_z] for an elliptic one
      - box:       {centre_mm: [x, y, z], size_mm: [s_x, s_y, s_z], rotation_deg: [...],
                    density_per_mm: 0.02}
      - sphere:    {radius_mm: 2, material: aluminium, density_g_cm3: 2.7}   # a material instead of,
                                                    # or as well as, density_per_mm (see below)
      - beads:                      # spheres in a cylinder (the paper's synthetic sample)
          container: {radius_mm: 40, height_mm: 80, centre_mm: [0, 0, 0], density_per_mm: 0.01,
                      wall_mm: 0, wall_density_per_mm: 0}
          count: 300
          radius_mm: [1.0, 3.0]          # uniform range of the bead radii
          density_per_mm: [0.02, 0.06]   # uniform range of the bead material
          min_gap_mm: 0.5                # between neighbouring beads (and the container)
          seed: 1
      - grains:                     # grains and voids in a cylinder: a granular/porous sample
          container: {...}               # as for beads
          count: 3000
          size_mm: [1.5, 5.0]            # uniform range of each grain's longest diameter
          aspect: [0.5, 1.0]             # the two shorter axes as fractions of the longest
          density_per_mm: [0.02, 0.08]   # uniform range of the grain material
          void_fraction: 0.25            # this fraction of the grains are empty pores
          min_gap_mm: 0.2                # negative lets grains overlap loosely
          seed: 7
      - trabecular:                 # trabecular bone: a cortical tube, rods and plates of bone in marrow
          radius_mm: 24                  # outer radius (the cortical shell's)
          height_mm: 50
          centre_mm: [0, 0, 0]           # optional
          cortical_mm: 2.0               # shell thickness; 0: none (default 1.0)
          spacing_mm: 3.5                # lattice spacing of the struts' nodes (default 2.0)
          thickness_mm: [0.6, 1.2]       # uniform range of rod diameters and plate thicknesses (default [0.3, 0.6])
          plate_fraction: 0.3            # this fraction of the struts are plates, 0.4-0.8 spacing wide (default 0.3)
          bone_volume_fraction: 0.12     # BV/TV of the core, 0-0.6
          marrow: water                  # or air (a dry bone) (default water)
          seed: 11
      - electronic:                 # a board with copper traces, chips on solder balls, metal pads
          board_mm: [50, 60, 1.6]        # x (lateral), y (along the axis), z (thickness): it stands upright
          centre_mm: [0, 0, 0]           # optional
          traces: 40                     # copper traces along x or y on either face (default 30)
          trace_width_mm: [0.2, 0.6]     # (default [0.2, 0.5])
          trace_thickness_mm: 0.1        # (default 0.1)
          chips: 5                       # on the +z face, 1 mm apart (default 4)
          chip_size_mm: [5, 12]          # uniform range of each side (default [4, 10])
          chip_thickness_mm: 1.2         # (default 1.2)
          ball_radius_mm: 0.3            # solder balls on a 4-radius grid under each chip (default 0.3)
          pads_per_side: 4               # tungsten bond pads around each chip's top (default 4)
          seed: 5
      - foam:                       # a closed-cell foam: a solid cylinder with spherical voids
          radius_mm: 20
          height_mm: 40
          centre_mm: [0, 0, 0]           # optional
          material: pmma                 # a built-in material (default pmma)
          density_g_cm3: 1.18            # of the solid (default: the material's usual)
          porosity: 0.3                  # volume fraction of the cells, at most 0.4
          cell_radius_mm: [0.6, 2.5]     # uniform range of cell radii (default [0.5, 1.5])
          wall_mm: 0.15                  # least wall between cells and to the outside (default 0.1)
          seed: 13
    voxels:                         # instead of objects: a voxel array
      file: sample.npy              # .npy or .tif, relative to the YAML file; volume[iy, iz, ix]
      voxel_size_mm: 0.5
      centre_mm: [0, 0, 0]          # optional
      scale: 1.0                    # optional factor to 1/mm

Conventions
-----------
Positions are in the object frame of :mod:`ctpipe.recon.volume` (``x`` lateral, ``y`` the rotation
axis pointing down the detector rows, ``z`` towards the detector at angle 0), lengths in mm,
densities are linear attenuation coefficients in 1/mm and *add* where objects overlap (a void
is an object of negative density). ``centre_mm`` and ``rotation_deg`` default to zeros.

``rotation_deg: [rx, ry, rz]`` is ``scipy.spatial.transform.Rotation.from_euler("xyz",
[rx, ry, rz], degrees=True)``: extrinsic rotations about the object-frame ``x``, then ``y``,
then ``z`` axes. Its matrix maps the shape's local axes to the object frame, as in
:mod:`ctpipe.sim.primitives`. A cylinder's own axis is its local ``y``, so an unrotated cylinder
stands along the rotation axis; ``height_mm`` is its full length.

Materials: ``ellipsoid``, ``sphere``, ``cylinder`` and ``box`` may name a ``material`` (a
built-in name of :data:`ctpipe.sim.materials.MATERIALS` - water, pmma, aluminium, titanium,
iron, steel, copper, tungsten, hydroxyapatite, bone, air - or a chemical formula such as
``Ca5(PO4)3OH``) with its mass density ``density_g_cm3`` (default: the built-in material's usual
density; required for a formula; negative for a void, as mass densities add like attenuation).
A scan with a polychromatic ``beam`` (:mod:`ctpipe.sim.beam`) attenuates such an object with the
material's ``mu(E)``; a monochromatic scan uses ``density_per_mm``, which defaults to
``mu/rho`` at :data:`ctpipe.sim.materials.REFERENCE_KEV` (60 keV) times the density. Objects
without a material (and the generators' objects) count as water of that ``density_per_mm`` at
60 keV under a beam.

``trabecular`` puts a node at every ``spacing_mm`` of a cubic lattice filling the core (the
cylinder inside the cortical shell), jitters it by up to 0.2 spacing per axis and joins each node
to its +x, +y and +z neighbours by a strut: a rod (cylinder) or a plate (box) of bone (ICRU
cortical, 1.92 g/cm^3). Struts are kept in a random order until their volume reaches
``bone_volume_fraction`` of the core's (error if the lattice holds less); with water marrow
each strut also removes its volume of water, so it replaces the marrow exactly (two primitives
per strut). Struts overlap only where they meet at nodes, counting twice there. ``electronic``
builds the part of :data:`ELECTRONIC_MATERIALS`: a board standing in the x-y plane, traces on
both faces, chips placed at random without overlap, each on a grid of solder balls with pads on
its top. ``foam`` draws cell radii until their volume reaches ``porosity`` of the cylinder's and
packs them whole and ``wall_mm`` apart as ``beads`` are placed (a void is the solid's negative).
The three name materials (for a polychromatic beam) and carry their ``density_per_mm`` at
60 keV, so they scan monochromatically without xraydb.

Generators (``beads``, ``grains``, ``trabecular``, ``electronic``, ``foam``) draw from
``numpy.random.default_rng(seed)`` only, so the same file always gives the same primitives.
The ``density_per_mm`` of ``beads`` and ``grains`` is the *material* of the bead or grain,
which replaces the container's matrix (the primitive added is ``material - matrix``); a void is
material 0. Beads and grains are placed whole inside the container's
cavity, their bounding spheres at least ``min_gap_mm`` apart, so that the replacement is exact;
with a negative gap the overlapping parts count twice. A container of density 0 is only a
region: no primitive is emitted for it. ``wall_mm > 0`` adds a tube of ``wall_density_per_mm``
around the cavity (outer radius ``radius_mm + wall_mm``, same height).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from ctpipe.config import check_keys, load_yaml
from ctpipe.errors import ConfigError, InputError
from ctpipe.recon.volume import VolumeGrid
from ctpipe.sim.materials import MATERIALS, REFERENCE_KEV, mass_attenuation_cm2_g, resolve_material
from ctpipe.sim.primitives import KINDS, Primitives
from ctpipe.stages import ParamSpec, check_value

__all__ = ["Phantom", "load_phantom", "parse_phantom", "parse_objects", "list_phantoms", "OBJECT_KINDS",
           "rotation_from_deg", "ELECTRONIC_MATERIALS"]

_ELLIPSOID, _CYLINDER, _BOX = (KINDS.index(k) for k in ("ellipsoid", "cylinder", "box"))

#: Object kinds a phantom's ``objects`` list accepts.
OBJECT_KINDS = ("ellipsoid", "sphere", "cylinder", "box", "beads", "grains", "trabecular", "electronic", "foam")


@dataclass(frozen=True, eq=False)
class Phantom:
    """A validated phantom: analytic primitives or a voxel array, and its extent.

    Attributes
    ----------
    name, description : str
    primitives : Primitives or None
        The analytic objects (None for a voxel phantom).
    volume : ndarray of shape ``grid.shape`` = (n_y, n_z, n_x), float32, or None
        Attenuation in 1/mm on ``grid`` (None for a primitive phantom).
    grid : VolumeGrid or None
    radius_mm : float
        Largest distance of the object from the rotation axis (an upper bound, tight for
        shapes centred on the axis).
    half_height_mm : float
        Largest ``|y|`` of the object: it lies within ``-half_height_mm <= y <= half_height_mm``.
    source : str
        The file it came from, or the YAML path it was parsed at.
    """

    name: str
    description: str
    primitives: Primitives | None
    volume: np.ndarray | None
    grid: VolumeGrid | None
    radius_mm: float
    half_height_mm: float
    source: str = ""


# ---------------------------------------------------------------------------------------------
# Value checks


_NUMBER = ParamSpec("", float, None, "")
_POSITIVE = ParamSpec("", float, None, "", gt=0)
_NON_NEGATIVE = ParamSpec("", float, None, "", ge=0)
_SEED = ParamSpec("seed", int, None, "", ge=0)


def _number(mapping: Mapping, key: str, path: str, spec: ParamSpec = _NUMBER, default: Any = None) -> float:
    if key not in mapping:
        if default is None:
            raise ConfigError(f"{path}.{key}: missing; it is required")
        return default
    return check_value(spec, mapping[key], f"{path}.{key}")


def _vector(mapping: Mapping, key: str, path: str, n: int, *, positive: bool = False,
            default: tuple | None = None) -> np.ndarray:
    if key not in mapping:
        if default is None:
            raise ConfigError(f"{path}.{key}: missing; it is required")
        return np.asarray(default, dtype=np.float64)
    value = mapping[key]
    spec = ParamSpec("", tuple[float, ...], None, "", gt=0 if positive else None)
    what = f"a list of {n} {'numbers > 0' if positive else 'numbers'}"
    if not isinstance(value, (list, tuple)) or len(value) != n:
        raise ConfigError(f"{path}.{key}: must be {what}, got {value!r}")
    try:
        check_value(spec, value, f"{path}.{key}")
    except ConfigError:
        raise ConfigError(f"{path}.{key}: must be {what}, got {value!r}") from None
    return np.asarray(value, dtype=np.float64)


def _range(mapping: Mapping, key: str, path: str, *, low: float | None = None, positive: bool = False) -> tuple:
    """A ``[min, max]`` pair (a single number means both)."""
    if key not in mapping:
        raise ConfigError(f"{path}.{key}: missing; it is required")
    value = mapping[key]
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        value = [value, value]
    bound = "> 0" if positive else (f">= {low:g}" if low is not None else "")
    what = f"a number or a list [min, max] of numbers {bound}".rstrip()
    ok = isinstance(value, (list, tuple)) and len(value) == 2
    if ok:
        try:
            check_value(ParamSpec("", tuple[float, ...], None, "", gt=0 if positive else None, ge=low), list(value), "")
        except ConfigError:
            ok = False
    if not ok or value[0] > value[1]:
        raise ConfigError(f"{path}.{key}: must be {what} with min <= max, got {mapping[key]!r}")
    return float(value[0]), float(value[1])


def rotation_from_deg(angles_deg) -> np.ndarray:
    """Matrix of ``rotation_deg`` (see the module docstring), shape (3, 3), float64."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_euler("xyz", np.asarray(angles_deg, dtype=np.float64), degrees=True).as_matrix()


# ---------------------------------------------------------------------------------------------
# Objects


class _Builder:
    """Collects primitives as lists of rows (kind, centre, half sizes, rotation, density)."""

    def __init__(self) -> None:
        self.kind: list[np.ndarray] = []
        self.centre: list[np.ndarray] = []
        self.half: list[np.ndarray] = []
        self.rotation: list[np.ndarray] = []
        self.density: list[np.ndarray] = []
        self.material: list[np.ndarray] = []
        self.mass_density: list[np.ndarray] = []
        self.materials: list[str] = []

    def add(self, kind, centre, half, rotation, density, material: str | None = None,
            mass_density_g_cm3: float = 0.0) -> None:
        kind = np.atleast_1d(np.asarray(kind, dtype=np.int32))
        n = len(kind)
        self.kind.append(kind)
        self.centre.append(np.asarray(centre, dtype=np.float64).reshape(n, 3))
        self.half.append(np.asarray(half, dtype=np.float64).reshape(n, 3))
        self.rotation.append(np.asarray(rotation, dtype=np.float64).reshape(n, 3, 3))
        self.density.append(np.asarray(density, dtype=np.float64).reshape(n))
        if material is not None and material not in self.materials:
            self.materials.append(material)
        self.material.append(np.full(n, -1 if material is None else self.materials.index(material), np.int32))
        self.mass_density.append(np.full(n, mass_density_g_cm3, np.float64))

    def build(self) -> Primitives:
        if not self.kind:
            return Primitives.concatenate([])
        return Primitives(np.concatenate(self.kind), np.concatenate(self.centre), np.concatenate(self.half),
                          np.concatenate(self.rotation), np.concatenate(self.density), np.concatenate(self.material),
                          np.concatenate(self.mass_density), tuple(self.materials))


def _density(mapping: Mapping, path: str) -> float:
    return _number(mapping, "density_per_mm", path)


_MATERIAL_KEYS = ("density_per_mm", "material", "density_g_cm3")


def _attenuation(mapping: Mapping, path: str) -> tuple[float, str | None, float]:
    """``(density_per_mm, material name or None, density_g_cm3)`` of a primitive (see the module docstring)."""
    if "material" not in mapping:
        if "density_g_cm3" in mapping:
            raise ConfigError(f"{path}.density_g_cm3: needs a material (e.g. material: aluminium)")
        if "density_per_mm" not in mapping:
            raise ConfigError(f"{path}.density_per_mm: missing; it is required (attenuation, 1/mm), unless the "
                              f"object names a material (e.g. material: aluminium)")
        return _density(mapping, path), None, 0.0
    material = resolve_material(mapping["material"], f"{path}.material")
    if "density_g_cm3" not in mapping and material.density_g_cm3 is None:
        raise ConfigError(f"{path}.density_g_cm3: missing; a chemical formula ({material.name}) needs its density")
    rho = _number(mapping, "density_g_cm3", path, ParamSpec("", float, None, "", ge=-30, le=30),
                  default=material.density_g_cm3)
    if "density_per_mm" in mapping:
        return _density(mapping, path), material.name, rho
    mu_rho = material.mu_rho_reference_cm2_g
    if mu_rho is None:
        mu_rho = float(mass_attenuation_cm2_g(material, [REFERENCE_KEV])[0])
    return mu_rho * rho * 0.1, material.name, rho  # cm^2/g x g/cm^3 = 1/cm = 0.1/mm


def _add_ellipsoid(builder: _Builder, p: Any, path: str) -> None:
    check_keys(p, path, allowed=("centre_mm", "semi_axes_mm", "rotation_deg", *_MATERIAL_KEYS),
               required=("semi_axes_mm",))
    builder.add(_ELLIPSOID, _vector(p, "centre_mm", path, 3, default=(0, 0, 0)),
                _vector(p, "semi_axes_mm", path, 3, positive=True),
                rotation_from_deg(_vector(p, "rotation_deg", path, 3, default=(0, 0, 0))), *_attenuation(p, path))


def _add_sphere(builder: _Builder, p: Any, path: str) -> None:
    check_keys(p, path, allowed=("centre_mm", "radius_mm", *_MATERIAL_KEYS), required=("radius_mm",))
    radius = _number(p, "radius_mm", path, _POSITIVE)
    builder.add(_ELLIPSOID, _vector(p, "centre_mm", path, 3, default=(0, 0, 0)), [radius] * 3, np.eye(3),
                *_attenuation(p, path))


def _add_cylinder(builder: _Builder, p: Any, path: str) -> None:
    check_keys(p, path, allowed=("centre_mm", "radius_mm", "radii_mm", "height_mm", "rotation_deg", *_MATERIAL_KEYS),
               required=("height_mm",))
    if ("radius_mm" in p) == ("radii_mm" in p):
        raise ConfigError(f"{path}: give exactly one of radius_mm (circular) or radii_mm [r_x, r_z] (elliptic)")
    if "radius_mm" in p:
        r_x = r_z = _number(p, "radius_mm", path, _POSITIVE)
    else:
        r_x, r_z = _vector(p, "radii_mm", path, 2, positive=True)
    half_height = _number(p, "height_mm", path, _POSITIVE) / 2.0
    builder.add(_CYLINDER, _vector(p, "centre_mm", path, 3, default=(0, 0, 0)), [r_x, half_height, r_z],
                rotation_from_deg(_vector(p, "rotation_deg", path, 3, default=(0, 0, 0))), *_attenuation(p, path))


def _add_box(builder: _Builder, p: Any, path: str) -> None:
    check_keys(p, path, allowed=("centre_mm", "size_mm", "rotation_deg", *_MATERIAL_KEYS), required=("size_mm",))
    builder.add(_BOX, _vector(p, "centre_mm", path, 3, default=(0, 0, 0)),
                _vector(p, "size_mm", path, 3, positive=True) / 2.0,
                rotation_from_deg(_vector(p, "rotation_deg", path, 3, default=(0, 0, 0))), *_attenuation(p, path))


@dataclass(frozen=True)
class _Container:
    centre_mm: np.ndarray
    radius_mm: float
    height_mm: float
    density_per_mm: float
    wall_mm: float
    wall_density_per_mm: float


def _parse_container(value: Any, path: str) -> _Container:
    check_keys(value, path, allowed=("centre_mm", "radius_mm", "height_mm", "density_per_mm", "wall_mm",
                                     "wall_density_per_mm"), required=("radius_mm", "height_mm"))
    return _Container(_vector(value, "centre_mm", path, 3, default=(0, 0, 0)),
                      _number(value, "radius_mm", path, _POSITIVE), _number(value, "height_mm", path, _POSITIVE),
                      _number(value, "density_per_mm", path, default=0.0),
                      _number(value, "wall_mm", path, _NON_NEGATIVE, default=0.0),
                      _number(value, "wall_density_per_mm", path, default=0.0))


def _add_container(builder: _Builder, c: _Container) -> None:
    half_height = c.height_mm / 2.0
    if c.wall_mm > 0 and c.wall_density_per_mm != 0:
        # A tube is the outer cylinder plus an inner one that cancels the wall material.
        builder.add(_CYLINDER, c.centre_mm, [c.radius_mm + c.wall_mm, half_height, c.radius_mm + c.wall_mm], np.eye(3),
                    c.wall_density_per_mm)
        if c.density_per_mm - c.wall_density_per_mm != 0:
            builder.add(_CYLINDER, c.centre_mm, [c.radius_mm, half_height, c.radius_mm], np.eye(3),
                        c.density_per_mm - c.wall_density_per_mm)
    elif c.density_per_mm != 0:
        builder.add(_CYLINDER, c.centre_mm, [c.radius_mm, half_height, c.radius_mm], np.eye(3), c.density_per_mm)


#: The largest fraction of a container that placed objects' bounding spheres may fill (see :func:`_place`).
_MAX_PACKING = 0.45


def _place(bounding_mm: np.ndarray, c: _Container, gap_mm: float, rng: np.random.Generator, path: str,
           what: str) -> np.ndarray:
    """Centres (N, 3) for spheres of radii ``bounding_mm`` inside the cavity, ``gap_mm`` apart.

    Random sequential addition, largest first, with a hash grid for the neighbour test. Spheres
    (each widened by half the gap) that would fill more than :data:`_MAX_PACKING` of the cavity are
    refused at once: random sequential addition of equal spheres jams at 38 % (Talbot, Tarjus and
    Van Tassel), a spread of sizes placed largest first gets a little further, and beyond that the
    placement would try 2,000 spots for each of up to 200,000 objects (hours) before failing.
    """
    n = len(bounding_mm)
    widened = np.maximum(bounding_mm + gap_mm / 2.0, 0.0)
    filled = float(np.sum(widened ** 3)) * 4.0 / 3.0 * math.pi / (math.pi * c.radius_mm ** 2 * c.height_mm)
    if filled > _MAX_PACKING:
        raise ConfigError(f"{path}: the {n} {what}s (as spheres {gap_mm:g} mm apart) would fill {filled:.0%} of the "
                          f"container, more than the {_MAX_PACKING:.0%} random placement reaches; lower count or "
                          f"the sizes, or let them overlap with a smaller (even negative) min_gap_mm")
    order = np.argsort(-bounding_mm, kind="stable")
    centres = np.zeros((n, 3))
    cell = 2.0 * float(bounding_mm.max()) + max(gap_mm, 0.0)
    grid: dict[tuple[int, int, int], list[int]] = {}
    max_tries = 2000
    for placed, index in enumerate(order):
        r = float(bounding_mm[index])
        reach_r = c.radius_mm - r - max(gap_mm, 0.0)
        reach_y = c.height_mm / 2.0 - r - max(gap_mm, 0.0)
        if reach_r < 0 or reach_y < 0:
            raise ConfigError(f"{path}: a {what} of bounding radius {r:g} mm does not fit in the container "
                              f"(radius {c.radius_mm:g} mm, height {c.height_mm:g} mm)")
        for _ in range(max_tries):
            u, phi, y = rng.random(3)
            rho = reach_r * math.sqrt(u)
            p = c.centre_mm + np.array([rho * math.cos(2 * math.pi * phi), (2 * y - 1) * reach_y,
                                        rho * math.sin(2 * math.pi * phi)])
            key = tuple(int(k) for k in np.floor(p / cell))
            clear = True
            for dx in (-1, 0, 1):
                for dy in (-1, 0, 1):
                    for dz in (-1, 0, 1):
                        for other in grid.get((key[0] + dx, key[1] + dy, key[2] + dz), ()):
                            limit = r + bounding_mm[other] + gap_mm
                            d = p - centres[other]
                            if d @ d < limit * limit:
                                clear = False
                                break
                        if not clear:
                            break
                    if not clear:
                        break
                if not clear:
                    break
            if clear:
                centres[index] = p
                grid.setdefault(key, []).append(index)
                break
        else:
            raise ConfigError(f"{path}: placed only {placed} of {n} {what}s in the container; lower count or the "
                              f"sizes, or let them overlap with a smaller (even negative) min_gap_mm")
    return centres


def _generator_common(p: Any, path: str) -> tuple[_Container, int, float, np.random.Generator]:
    container = _parse_container(p["container"], f"{path}.container")
    count = check_value(ParamSpec("count", int, None, "", ge=1, le=200_000), p["count"], f"{path}.count")
    gap = _number(p, "min_gap_mm", path, default=0.0)
    seed = check_value(_SEED, p["seed"], f"{path}.seed")
    return container, count, gap, np.random.default_rng(seed)


def _add_beads(builder: _Builder, p: Any, path: str) -> None:
    check_keys(p, path, allowed=("container", "count", "radius_mm", "density_per_mm", "min_gap_mm", "seed"),
               required=("container", "count", "radius_mm", "density_per_mm", "seed"))
    container, count, gap, rng = _generator_common(p, path)
    r_lo, r_hi = _range(p, "radius_mm", path, positive=True)
    d_lo, d_hi = _range(p, "density_per_mm", path)
    radii = rng.uniform(r_lo, r_hi, count)
    material = rng.uniform(d_lo, d_hi, count)
    centres = _place(radii, container, gap, rng, path, "bead")
    _add_container(builder, container)
    builder.add(np.full(count, _ELLIPSOID), centres, np.repeat(radii[:, None], 3, axis=1),
                np.broadcast_to(np.eye(3), (count, 3, 3)), material - container.density_per_mm)


def _add_grains(builder: _Builder, p: Any, path: str) -> None:
    from scipy.spatial.transform import Rotation

    check_keys(p, path, allowed=("container", "count", "size_mm", "aspect", "density_per_mm", "void_fraction",
                                 "min_gap_mm", "seed"),
               required=("container", "count", "size_mm", "density_per_mm", "seed"))
    container, count, gap, rng = _generator_common(p, path)
    s_lo, s_hi = _range(p, "size_mm", path, positive=True)
    a_lo, a_hi = (1.0, 1.0) if "aspect" not in p else _range(p, "aspect", path, positive=True)
    if a_hi > 1:
        raise ConfigError(f"{path}.aspect: must be fractions in (0, 1] of the longest axis, got {p['aspect']!r}")
    d_lo, d_hi = _range(p, "density_per_mm", path)
    void_fraction = _number(p, "void_fraction", path, ParamSpec("", float, None, "", ge=0, le=1), default=0.0)
    semi_major = rng.uniform(s_lo, s_hi, count) / 2.0
    semi = semi_major[:, None] * np.column_stack([np.ones(count), rng.uniform(a_lo, a_hi, (count, 2))])
    rotation = Rotation.random(count, random_state=rng).as_matrix().reshape(count, 3, 3)
    material = rng.uniform(d_lo, d_hi, count)
    material[rng.random(count) < void_fraction] = 0.0
    centres = _place(semi_major, container, gap, rng, path, "grain")
    _add_container(builder, container)
    keep = material != container.density_per_mm  # a grain of the matrix material is invisible
    builder.add(np.full(int(keep.sum()), _ELLIPSOID), centres[keep], semi[keep], rotation[keep],
                material[keep] - container.density_per_mm)


# ---------------------------------------------------------------------------------------------
# Families that look like what labs scan: trabecular bone, an electronic part


def _mu_per_mm(material: str, rho_g_cm3: float) -> float:
    """Monochromatic attenuation (1/mm) at :data:`REFERENCE_KEV` of a built-in material at ``rho_g_cm3``."""
    return MATERIALS[material].mu_rho_reference_cm2_g * rho_g_cm3 * 0.1  # cm^2/g x g/cm^3 = 1/cm = 0.1/mm


def _count(mapping: Mapping, key: str, path: str, default: int, low: int = 0, high: int = 100_000) -> int:
    return check_value(ParamSpec(key, int, None, "", ge=low, le=high), mapping.get(key, default), f"{path}.{key}")


def _frames(direction: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Rotations (N, 3, 3) whose local ``y`` is ``direction`` (N, 3, unit) and local ``x`` a random normal to it."""
    a = rng.normal(size=direction.shape)
    e_x = a - np.sum(a * direction, axis=1, keepdims=True) * direction
    e_x /= np.linalg.norm(e_x, axis=1, keepdims=True)
    e_z = np.cross(e_x, direction)
    return np.stack([e_x, direction, e_z], axis=2)  # columns: the local axes in the object frame


_MAX_STRUTS = 6000


def _add_trabecular(builder: _Builder, p: Any, path: str) -> None:
    """Trabecular bone: a cortical tube around a jittered lattice of rods and plates of bone in marrow."""
    check_keys(p, path, allowed=("centre_mm", "radius_mm", "height_mm", "cortical_mm", "spacing_mm", "thickness_mm",
                                 "plate_fraction", "bone_volume_fraction", "marrow", "seed"),
               required=("radius_mm", "height_mm", "bone_volume_fraction", "seed"))
    centre = _vector(p, "centre_mm", path, 3, default=(0, 0, 0))
    radius = _number(p, "radius_mm", path, _POSITIVE)
    height = _number(p, "height_mm", path, _POSITIVE)
    cortical = _number(p, "cortical_mm", path, _NON_NEGATIVE, default=1.0)
    spacing = _number(p, "spacing_mm", path, _POSITIVE, default=2.0)
    t_lo, t_hi = (0.3, 0.6) if "thickness_mm" not in p else _range(p, "thickness_mm", path, positive=True)
    plate_fraction = _number(p, "plate_fraction", path, ParamSpec("", float, None, "", ge=0, le=1), default=0.3)
    bvf = _number(p, "bone_volume_fraction", path, ParamSpec("", float, None, "", gt=0, le=0.6))
    marrow = check_value(ParamSpec("marrow", str, None, ""), p.get("marrow", "water"), f"{path}.marrow")
    if marrow not in ("water", "air"):
        raise ConfigError(f"{path}.marrow: must be one of water, air, got {marrow!r}")
    rng = np.random.default_rng(check_value(_SEED, p["seed"], f"{path}.seed"))
    core_r = radius - cortical
    if t_hi >= spacing / 2:
        raise ConfigError(f"{path}.thickness_mm: must stay below half of spacing_mm ({spacing:g}), "
                          f"got {p['thickness_mm']!r}")
    # Nodes jitter by up to 0.2 spacing along each axis (0.3 radially), rods reach half their
    # thickness past them: so every rod stays in the core; a plate that would not becomes a rod.
    margin = 0.3 * spacing + t_hi / 2
    if core_r <= margin + spacing or height / 2 <= margin + spacing:
        raise ConfigError(f"{path}: radius_mm - cortical_mm ({core_r:g}) and height_mm / 2 ({height / 2:g}) must "
                          f"exceed 1.3 spacing_mm + half the largest thickness ({margin + spacing:g}); "
                          f"lower spacing_mm")
    axis = np.arange(-core_r + margin, core_r - margin + 1e-9, spacing)
    axis_y = np.arange(-height / 2 + margin, height / 2 - margin + 1e-9, spacing)
    n_struts_max = 3 * len(axis) ** 2 * len(axis_y)
    if n_struts_max > 20 * _MAX_STRUTS:
        raise ConfigError(f"{path}.spacing_mm: a lattice of about {n_struts_max} struts is too many (at most "
                          f"{20 * _MAX_STRUTS}); raise spacing_mm or shrink the bone")
    ix, iy, iz = np.meshgrid(np.arange(len(axis)), np.arange(len(axis_y)), np.arange(len(axis)), indexing="ij")
    inside = np.hypot(axis[ix], axis[iz]) <= core_r - margin
    index = np.full(ix.shape, -1)
    index[inside] = np.arange(int(inside.sum()))
    nodes = np.column_stack([axis[ix[inside]], axis_y[iy[inside]], axis[iz[inside]]])
    nodes += rng.uniform(-0.2 * spacing, 0.2 * spacing, nodes.shape)
    starts, ends = [], []
    for step in ((1, 0, 0), (0, 1, 0), (0, 0, 1)):  # each node to its +x, +y and +z neighbour
        a = index[: index.shape[0] - step[0], : index.shape[1] - step[1], : index.shape[2] - step[2]]
        b = index[step[0]:, step[1]:, step[2]:]
        both = (a >= 0) & (b >= 0)
        starts.append(a[both])
        ends.append(b[both])
    starts, ends = np.concatenate(starts), np.concatenate(ends)
    order = rng.permutation(len(starts))
    starts, ends = starts[order], ends[order]
    n = len(starts)
    vector = nodes[ends] - nodes[starts]
    length = np.linalg.norm(vector, axis=1)
    direction = vector / length[:, None]
    thickness = rng.uniform(t_lo, t_hi, n)
    plate = rng.random(n) < plate_fraction
    width = rng.uniform(0.4, 0.8, n) * spacing
    rotation = _frames(direction, rng)
    half = np.column_stack([thickness / 2, length / 2, np.where(plate, width, thickness) / 2])
    signs = np.array([[a, b, c] for a in (-1, 1) for b in (-1, 1) for c in (-1, 1)], dtype=np.float64)
    corners = ((nodes[starts] + nodes[ends]) / 2)[:, None, :] + np.einsum("nij,knj->nki", rotation,
                                                                         signs[:, None, :] * half[None])
    outside = (np.hypot(corners[..., 0], corners[..., 2]).max(axis=1) > core_r) | \
        (np.abs(corners[..., 1]).max(axis=1) > height / 2)
    plate &= ~outside
    half[:, 2] = np.where(plate, width, thickness) / 2
    volume = np.where(plate, thickness * length * width, math.pi * (thickness / 2) ** 2 * length)
    core_volume = math.pi * core_r ** 2 * height
    target = bvf * core_volume
    reach = np.cumsum(volume)
    if reach[-1] < target:
        raise ConfigError(f"{path}.bone_volume_fraction: {bvf:g} is more than this lattice holds "
                          f"({reach[-1] / core_volume:.3f}); lower spacing_mm or raise thickness_mm")
    keep = int(np.searchsorted(reach, target)) + 1
    if keep > _MAX_STRUTS:
        raise ConfigError(f"{path}: the bone_volume_fraction needs {keep} struts (at most {_MAX_STRUTS}); raise "
                          f"thickness_mm or spacing_mm")
    centres = centre + (nodes[starts[:keep]] + nodes[ends[:keep]]) / 2
    rotation, half = rotation[:keep], half[:keep]
    kinds = np.where(plate[:keep], _BOX, _CYLINDER)
    bone_rho = MATERIALS["bone"].density_g_cm3
    mu_bone, mu_water = _mu_per_mm("bone", bone_rho), _mu_per_mm("water", 1.0)
    core = [core_r, height / 2, core_r]
    if cortical > 0:
        builder.add(_CYLINDER, centre, [radius, height / 2, radius], np.eye(3), mu_bone, "bone", bone_rho)
        builder.add(_CYLINDER, centre, core, np.eye(3), -mu_bone, "bone", -bone_rho)
    builder.add(kinds, centres, half, rotation, np.full(keep, mu_bone), "bone", bone_rho)
    if marrow == "water":  # the struts replace marrow: water everywhere in the core, less under each strut
        builder.add(_CYLINDER, centre, core, np.eye(3), mu_water, "water", 1.0)
        builder.add(kinds, centres, half, rotation, np.full(keep, -mu_water), "water", -1.0)



#: Materials of the electronic part: (name for the beam, mass density g/cm^3). The board is a
#: stand-in for FR4 (epoxy and glass, 1.85 g/cm^3) and the chip body for silicon in its mould
#: (2.33 g/cm^3): built-in materials of about their attenuation, so the part loads without xraydb.
ELECTRONIC_MATERIALS = {"board": ("pmma", 1.85), "trace": ("copper", 8.96), "chip": ("aluminium", 2.33),
                        "pad": ("tungsten", 19.25), "ball": ("copper", 8.96)}


def _add_electronic(builder: _Builder, p: Any, path: str) -> None:
    """An electronic part: a board with copper traces on both faces, chips on BGA solder balls, metal pads."""
    check_keys(p, path, allowed=("centre_mm", "board_mm", "traces", "trace_width_mm", "trace_thickness_mm", "chips",
                                 "chip_size_mm", "chip_thickness_mm", "ball_radius_mm", "pads_per_side", "seed"),
               required=("board_mm", "seed"))
    centre = _vector(p, "centre_mm", path, 3, default=(0, 0, 0))
    width, height, thick = _vector(p, "board_mm", path, 3, positive=True)
    n_traces = _count(p, "traces", path, 30, high=5000)
    w_lo, w_hi = (0.2, 0.5) if "trace_width_mm" not in p else _range(p, "trace_width_mm", path, positive=True)
    trace_t = _number(p, "trace_thickness_mm", path, _POSITIVE, default=0.1)
    n_chips = _count(p, "chips", path, 4, high=200)
    c_lo, c_hi = (4.0, 10.0) if "chip_size_mm" not in p else _range(p, "chip_size_mm", path, positive=True)
    chip_t = _number(p, "chip_thickness_mm", path, _POSITIVE, default=1.2)
    ball_r = _number(p, "ball_radius_mm", path, _POSITIVE, default=0.3)
    pads = _count(p, "pads_per_side", path, 4, high=100)
    rng = np.random.default_rng(check_value(_SEED, p["seed"], f"{path}.seed"))
    if c_hi + 2.0 > min(width, height):
        raise ConfigError(f"{path}.chip_size_mm: chips up to {c_hi:g} mm do not fit on a {width:g} x {height:g} mm "
                          f"board with 1 mm margins")
    if w_hi >= min(width, height) / 2:
        raise ConfigError(f"{path}.trace_width_mm: must stay below half the board's width and height, got "
                          f"{p['trace_width_mm']!r}")
    mu = {part: _mu_per_mm(name, rho) for part, (name, rho) in ELECTRONIC_MATERIALS.items()}

    def add(part, kinds, centres, half, rotation=None):
        name, rho = ELECTRONIC_MATERIALS[part]
        k = np.atleast_1d(kinds)
        rot = np.broadcast_to(np.eye(3), (len(k), 3, 3)) if rotation is None else rotation
        builder.add(k, centre + np.asarray(centres).reshape(-1, 3), half, rot, np.full(len(k), mu[part]), name, rho)

    add("board", _BOX, [0, 0, 0], [width / 2, height / 2, thick / 2])
    # Traces: straight runs along x or y on either face.
    along_x = rng.random(n_traces) < 0.5
    face = np.where(rng.random(n_traces) < 0.5, 1.0, -1.0)
    span = np.where(along_x, width, height)
    length = rng.uniform(0.2, 0.8, n_traces) * span
    trace_w = rng.uniform(w_lo, w_hi, n_traces)
    half_run = np.where(along_x, (width - length) / 2, (height - length) / 2)
    half_across = np.where(along_x, (height - trace_w) / 2, (width - trace_w) / 2)
    run = rng.uniform(-1, 1, n_traces) * half_run
    across = rng.uniform(-1, 1, n_traces) * half_across
    trace_centres = np.column_stack([np.where(along_x, run, across), np.where(along_x, across, run),
                                     face * (thick + trace_t) / 2])
    trace_half = np.column_stack([np.where(along_x, length, trace_w) / 2, np.where(along_x, trace_w, length) / 2,
                                  np.full(n_traces, trace_t / 2)])
    if n_traces:
        add("trace", np.full(n_traces, _BOX), trace_centres, trace_half)
    # Chips: rectangles on the +z face, 1 mm apart, each on a grid of solder balls, pads around its top.
    placed: list[tuple[float, float, float, float]] = []
    for i in range(n_chips):
        for _ in range(500):
            sx, sy = rng.uniform(c_lo, c_hi, 2)
            x = rng.uniform(-(width - sx) / 2 + 1, (width - sx) / 2 - 1)
            y = rng.uniform(-(height - sy) / 2 + 1, (height - sy) / 2 - 1)
            if all(abs(x - ox) > (sx + osx) / 2 + 1 or abs(y - oy) > (sy + osy) / 2 + 1 for ox, oy, osx, osy in placed):
                placed.append((x, y, sx, sy))
                break
        else:
            raise ConfigError(f"{path}.chips: placed only {i} of {n_chips} chips on the board; fewer or smaller chips")
    base = thick / 2 + trace_t  # balls stand on the traces' level
    for x, y, sx, sy in placed:
        add("chip", _BOX, [x, y, base + 2 * ball_r + chip_t / 2], [sx / 2, sy / 2, chip_t / 2])
        pitch = 4 * ball_r
        nx, ny = max(int((sx - pitch) // pitch) + 1, 1), max(int((sy - pitch) // pitch) + 1, 1)
        gx, gy = np.meshgrid((np.arange(nx) - (nx - 1) / 2) * pitch, (np.arange(ny) - (ny - 1) / 2) * pitch)
        balls = np.column_stack([x + gx.ravel(), y + gy.ravel(), np.full(gx.size, base + ball_r)])
        add("ball", np.full(len(balls), _ELLIPSOID), balls, np.full((len(balls), 3), ball_r))
        if pads:
            pad = min(0.5, 0.8 * min(sx, sy) / (2 * pads))
            top = base + 2 * ball_r + chip_t + 0.05
            t = (np.arange(pads) + 0.5) / pads - 0.5
            inset_x, inset_y = sx / 2 - 2 * pad, sy / 2 - 2 * pad
            ring = np.concatenate([np.column_stack([t * 2 * inset_x, np.full(pads, s * inset_y)]) for s in (-1, 1)]
                                  + [np.column_stack([np.full(pads, s * inset_x), t * 2 * inset_y]) for s in (-1, 1)])
            pad_centres = np.column_stack([x + ring[:, 0], y + ring[:, 1], np.full(len(ring), top)])
            add("pad", np.full(len(ring), _BOX), pad_centres, np.tile([pad / 2, pad / 2, 0.05], (len(ring), 1)))


_MAX_CELLS = 20_000


def _add_foam(builder: _Builder, p: Any, path: str) -> None:
    """A closed-cell foam: a solid cylinder with spherical cells (voids) of random sizes, ``porosity`` of it."""
    check_keys(p, path, allowed=("centre_mm", "radius_mm", "height_mm", "material", "density_g_cm3", "porosity",
                                 "cell_radius_mm", "wall_mm", "seed"),
               required=("radius_mm", "height_mm", "porosity", "seed"))
    material = resolve_material(p.get("material", "pmma"), f"{path}.material")
    if material.name not in MATERIALS:
        raise ConfigError(f"{path}.material: must be a built-in material ({', '.join(MATERIALS)}), got "
                          f"{p['material']!r}")
    rho = _number(p, "density_g_cm3", path, ParamSpec("", float, None, "", gt=0, le=30),
                  default=material.density_g_cm3)
    # Random sequential packing of the cells jams near 0.4 (they stay whole and apart).
    porosity = _number(p, "porosity", path, ParamSpec("", float, None, "", gt=0, le=0.4))
    r_lo, r_hi = (0.5, 1.5) if "cell_radius_mm" not in p else _range(p, "cell_radius_mm", path, positive=True)
    wall = _number(p, "wall_mm", path, _NON_NEGATIVE, default=0.1)
    container = _Container(_vector(p, "centre_mm", path, 3, default=(0, 0, 0)),
                           _number(p, "radius_mm", path, _POSITIVE), _number(p, "height_mm", path, _POSITIVE),
                           0.0, 0.0, 0.0)
    rng = np.random.default_rng(check_value(_SEED, p["seed"], f"{path}.seed"))
    target = porosity * math.pi * container.radius_mm ** 2 * container.height_mm
    mean_cell = 4.0 / 3.0 * math.pi * np.mean(rng.uniform(r_lo, r_hi, 256) ** 3)
    if target / mean_cell > _MAX_CELLS:
        raise ConfigError(f"{path}.cell_radius_mm: about {int(target / mean_cell)} cells make that porosity (at most "
                          f"{_MAX_CELLS}); use larger cells or a smaller foam")
    radii: list[float] = []
    volume = 0.0
    while volume < target:
        r = float(rng.uniform(r_lo, r_hi))
        radii.append(r)
        volume += 4.0 / 3.0 * math.pi * r ** 3
    cells = np.array(radii)
    if r_hi + wall > min(container.radius_mm, container.height_mm / 2):
        raise ConfigError(f"{path}.cell_radius_mm: cells up to {r_hi:g} mm (and wall_mm {wall:g}) do not fit in the "
                          f"foam's radius and half height")
    try:
        centres = _place(cells, container, wall, rng, path, "cell")
    except ConfigError:
        raise ConfigError(f"{path}.porosity: random packing does not place {len(cells)} cells for porosity "
                          f"{porosity:g}; lower porosity or wall_mm, or widen cell_radius_mm") from None
    mu = material.mu_rho_reference_cm2_g * rho * 0.1
    half_height = container.height_mm / 2.0
    builder.add(_CYLINDER, container.centre_mm, [container.radius_mm, half_height, container.radius_mm], np.eye(3),
                mu, material.name, rho)
    builder.add(np.full(len(cells), _ELLIPSOID), centres, np.repeat(cells[:, None], 3, axis=1),
                np.broadcast_to(np.eye(3), (len(cells), 3, 3)), np.full(len(cells), -mu), material.name, -rho)


_OBJECT_BUILDERS = {"ellipsoid": _add_ellipsoid, "sphere": _add_sphere, "cylinder": _add_cylinder, "box": _add_box,
                    "beads": _add_beads, "grains": _add_grains,
                    "trabecular": _add_trabecular, "electronic": _add_electronic, "foam": _add_foam}


def _parse_objects(value: Any, path: str) -> Primitives:
    if not isinstance(value, list) or not value:
        raise ConfigError(f"{path}: must be a non-empty list of one-key mappings {{kind: parameters}} with kind one "
                          f"of {', '.join(OBJECT_KINDS)}, got {value!r}")
    builder = _Builder()
    for i, item in enumerate(value):
        where = f"{path}[{i}]"
        if not isinstance(item, Mapping) or len(item) != 1:
            raise ConfigError(f"{where}: must be a one-key mapping {{kind: parameters}} with kind one of "
                              f"{', '.join(OBJECT_KINDS)}, got {item!r}")
        ((kind, params),) = item.items()
        if kind not in _OBJECT_BUILDERS:
            raise ConfigError(f"{where}.{kind}: unknown object kind; allowed: {', '.join(OBJECT_KINDS)}")
        _OBJECT_BUILDERS[kind](builder, params, f"{where}.{kind}")
    return builder.build()


def parse_objects(value: Any, path: str) -> Primitives:
    """Validate an ``objects`` list (see the module docstring) into primitives.

    Raises
    ------
    ConfigError
        A key, type or value is not allowed; the message names its YAML path under ``path``.
    """
    return _parse_objects(value, path)


# ---------------------------------------------------------------------------------------------
# Extent


def _primitive_extent(p: Primitives) -> tuple[float, float]:
    """``(radius_mm, half_height_mm)`` about the rotation axis of a set of primitives."""
    if len(p) == 0:
        return 0.0, 0.0
    scaled = p.rotation * p.half_size_mm[:, None, :]  # columns: the local half axes in the object frame
    ellipsoid, cylinder, box = (p.kind == k for k in (_ELLIPSOID, _CYLINDER, _BOX))
    # Reach along y (exact per shape).
    reach_y = np.empty(len(p))
    reach_y[ellipsoid] = np.linalg.norm(scaled[ellipsoid, 1, :], axis=1)
    reach_y[cylinder] = np.hypot(scaled[cylinder, 1, 0], scaled[cylinder, 1, 2]) + np.abs(scaled[cylinder, 1, 1])
    reach_y[box] = np.abs(scaled[box, 1, :]).sum(axis=1)
    half_height = float(np.max(np.abs(p.centre_mm[:, 1]) + reach_y))
    # Distance from the axis: the largest of a convex function is at an extreme point.
    radius = np.empty(len(p))
    centre_xz = p.centre_mm[:, [0, 2]]
    flat = scaled[:, [0, 2], :]  # (N, 2, 3): the local half axes projected on the x-z plane
    # Ellipsoids: the centre's distance plus the projected ellipse's major semi-axis (exact when centred).
    radius[ellipsoid] = (np.linalg.norm(centre_xz[ellipsoid], axis=1)
                         + np.linalg.norm(flat[ellipsoid], ord=2, axis=(1, 2)))
    if cylinder.any():
        # Cylinders: both rim circles, sampled and widened by 1/cos(pi/n) so the bound stays an upper one.
        n = 256
        t = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
        rim = np.stack([np.cos(t), np.zeros(n), np.sin(t)])  # (3, n)
        pts = []
        for sign in (-1.0, 1.0):
            u = rim + np.array([[0.0], [sign], [0.0]])
            pts.append(np.einsum("kij,jn->kin", flat[cylinder], u) + centre_xz[cylinder][:, :, None])
        pts = np.concatenate(pts, axis=2)
        radius[cylinder] = np.linalg.norm(pts, axis=1).max(axis=1) / math.cos(math.pi / n)
    if box.any():
        corners = np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1], indexing="ij")).reshape(3, 8).astype(float)
        pts = np.einsum("kij,jn->kin", flat[box], corners) + centre_xz[box][:, :, None]
        radius[box] = np.linalg.norm(pts, axis=1).max(axis=1)
    return float(radius.max()), half_height


def _voxel_extent(volume: np.ndarray, grid: VolumeGrid) -> tuple[float, float]:
    iy, iz, ix = np.nonzero(volume)
    if len(iy) == 0:
        return 0.0, 0.0
    x, y, z = grid.axis_mm("x")[ix], grid.axis_mm("y")[iy], grid.axis_mm("z")[iz]
    half = grid.voxel_size_mm / 2.0
    return float(np.max(np.hypot(x, z)) + half * math.sqrt(2.0)), float(np.max(np.abs(y)) + half)


# ---------------------------------------------------------------------------------------------
# Voxels


def _parse_voxels(value: Any, path: str, base_dir: Path | None) -> tuple[np.ndarray, VolumeGrid]:
    check_keys(value, path, allowed=("file", "voxel_size_mm", "centre_mm", "scale"), required=("file", "voxel_size_mm"))
    name = value["file"]
    if not isinstance(name, str) or not name.lower().endswith((".npy", ".tif", ".tiff")):
        raise ConfigError(f"{path}.file: must be a .npy or .tif file name, got {name!r}")
    file = Path(name)
    if not file.is_absolute() and base_dir is not None:
        file = base_dir / file
    if not file.is_file():
        raise InputError(f"{path}.file: {file}: no such file")
    try:
        if file.suffix.lower() == ".npy":
            volume = np.load(file, allow_pickle=False)
        else:
            import tifffile

            volume = tifffile.imread(file)
    except (ValueError, OSError) as exc:
        raise InputError(f"{path}.file: {file}: cannot be read: {exc}") from None
    if volume.ndim != 3 or not np.issubdtype(volume.dtype, np.number) or np.iscomplexobj(volume):
        raise InputError(f"{path}.file: {file}: must hold a real 3-D array volume[iy, iz, ix], "
                         f"got {volume.dtype} of shape {volume.shape}")
    scale = _number(value, "scale", path, default=1.0)
    volume = (volume.astype(np.float64) * scale).astype(np.float32)
    if not np.all(np.isfinite(volume)):
        raise InputError(f"{path}.file: {file}: has NaN or infinite values")
    n_y, n_z, n_x = volume.shape
    grid = VolumeGrid(n_x, n_y, n_z, _number(value, "voxel_size_mm", path, _POSITIVE),
                      tuple(_vector(value, "centre_mm", path, 3, default=(0, 0, 0))))
    volume.flags.writeable = False
    return volume, grid


# ---------------------------------------------------------------------------------------------
# Entry points


def parse_phantom(mapping: Any, path: str = "phantom", base_dir: str | Path | None = None) -> Phantom:
    """Validate a phantom mapping (see the module docstring).

    Parameters
    ----------
    mapping : mapping
        The parsed YAML.
    path : str
        YAML path prefix of error messages (usually the file name).
    base_dir : path or None
        Folder relative ``voxels.file`` names resolve against (default: the working directory).

    Raises
    ------
    ConfigError
        A key, type or value is not allowed; the message names its YAML path.
    """
    check_keys(mapping, path, allowed=("name", "description", "units", "objects", "voxels"))
    name = check_value(ParamSpec("name", str, None, ""), mapping.get("name", "phantom"), f"{path}.name")
    description = check_value(ParamSpec("description", str, None, ""), mapping.get("description", ""),
                              f"{path}.description")
    if mapping.get("units", "mm") != "mm":
        raise ConfigError(f"{path}.units: must be 'mm', got {mapping['units']!r}")
    if ("objects" in mapping) == ("voxels" in mapping):
        raise ConfigError(f"{path}: give exactly one of objects (analytic primitives) or voxels (an array file)")
    if "objects" in mapping:
        primitives = _parse_objects(mapping["objects"], f"{path}.objects")
        radius, half_height = _primitive_extent(primitives)
        return Phantom(name, description.strip(), primitives, None, None, radius, half_height, path)
    volume, grid = _parse_voxels(mapping["voxels"], f"{path}.voxels", None if base_dir is None else Path(base_dir))
    radius, half_height = _voxel_extent(volume, grid)
    return Phantom(name, description.strip(), None, volume, grid, radius, half_height, path)


def _builtin_dir():
    try:
        return resources.files("ctpipe.phantoms_data")
    except ModuleNotFoundError:
        # An editable install made before phantoms/ was mapped to ctpipe.phantoms_data: the
        # source checkout still has the folder next to the package.
        return Path(__file__).resolve().parents[2] / "phantoms"


def list_phantoms() -> list[str]:
    """Names of the built-in phantoms (``phantoms/*.yaml``), sorted."""
    return sorted(entry.name[: -len(".yaml")] for entry in _builtin_dir().iterdir() if entry.name.endswith(".yaml"))


def load_phantom(name_or_path: str | Path) -> Phantom:
    """Load a phantom by built-in name (``"granular"``) or from a YAML file.

    A string that ends in ``.yaml``/``.yml``, contains a path separator or names an existing
    file is read as a file; anything else must be a built-in name.

    Raises
    ------
    ConfigError
        Unknown built-in name (the message lists the built-in ones), or an invalid file.
    """
    text = str(name_or_path)
    looks_like_file = isinstance(name_or_path, Path) or text.endswith((".yaml", ".yml")) or "/" in text or "\\" in text
    if looks_like_file or Path(text).is_file():
        file = Path(text)
        mapping = load_yaml(file)
        if isinstance(mapping, Mapping) and "name" not in mapping:
            mapping = {"name": file.stem, **mapping}
        return parse_phantom(mapping, path=str(file), base_dir=file.parent)
    builtin = _builtin_dir() / f"{text}.yaml"
    if not builtin.is_file():
        raise ConfigError(f"phantom {text!r}: not a built-in phantom or a file; built-in: {', '.join(list_phantoms())}")
    with resources.as_file(builtin) as file:
        mapping = load_yaml(file)
        if isinstance(mapping, Mapping) and "name" not in mapping:
            mapping = {"name": text, **mapping}
        return parse_phantom(mapping, path=f"{text}.yaml", base_dir=file.parent)
