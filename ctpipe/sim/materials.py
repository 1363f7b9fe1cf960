"""Materials for a polychromatic beam: names users write, their composition and attenuation.

A phantom object or a beam filter names a material either by a built-in name (case-insensitive,
:data:`MATERIALS`; aliases such as ``aluminum``, ``Al``, ``acrylic`` resolve to the same entry)
or by a chemical formula that ``xraydb`` parses (``Ca5(PO4)3OH``, ``SiO2``), which then needs a
density. The mass attenuation coefficient ``mu/rho(E)`` (cm^2/g, total cross-section with
coherent scattering) comes from ``xraydb`` (Elam, Ravel and Sieber's tables): for a formula
through :func:`xraydb.material_mu`, for a mixture given by mass fractions as
``sum_i w_i mu/rho_i(E)`` (the mixture rule).

``xraydb`` is an optional dependency (``pip install 'ctpipe[beam]'``): the built-in table also
stores ``mu/rho`` at :data:`REFERENCE_KEV` so that a phantom naming built-in materials loads
and scans monochromatically without it; a test checks those numbers against ``xraydb``.
"""

from __future__ import annotations

import functools
import importlib.util
from dataclasses import dataclass

import numpy as np

from ctpipe.errors import ConfigError

__all__ = ["Material", "MATERIALS", "REFERENCE_KEV", "INSTALL_BEAM", "resolve_material",
           "mass_attenuation_cm2_g", "element_density_g_cm3", "beam_libraries_missing"]

#: The pip command that installs the polychromatic beam's libraries (spekpy and xraydb).
INSTALL_BEAM = "pip install 'ctpipe[beam]'"

#: Energy (keV) at which a material object without ``density_per_mm`` gets its monochromatic
#: attenuation, and at which objects without a material count as water.
REFERENCE_KEV = 60.0


@dataclass(frozen=True)
class Material:
    """A material: what it is made of and its usual density.

    Attributes
    ----------
    name : str
        The canonical name (a built-in name, or the formula as written).
    formula : str
        Chemical formula for ``xraydb`` ("" for a mixture given by ``mass_fractions``).
    mass_fractions : tuple of (str, float)
        Element symbol and mass fraction (summing to 1) of a mixture; empty for a formula.
    density_g_cm3 : float or None
        Usual density; None for a formula (the phantom must give it).
    mu_rho_reference_cm2_g : float or None
        ``mu/rho`` at :data:`REFERENCE_KEV` (built-in entries only).
    """

    name: str
    formula: str = ""
    mass_fractions: tuple = ()
    density_g_cm3: float | None = None
    mu_rho_reference_cm2_g: float | None = None


_BONE = (("H", 0.034), ("C", 0.155), ("N", 0.042), ("O", 0.435), ("Na", 0.001), ("Mg", 0.002), ("P", 0.103),
         ("S", 0.003), ("Ca", 0.225))  # ICRU 44 cortical bone
_STEEL = (("Fe", 0.695), ("Cr", 0.19), ("Ni", 0.095), ("Mn", 0.02))  # stainless 304
_AIR = (("N", 0.755), ("O", 0.232), ("Ar", 0.013))  # dry air at sea level

#: Built-in materials by canonical name. ``mu_rho_reference_cm2_g`` is xraydb 4.5's value at 60 keV.
MATERIALS: dict[str, Material] = {m.name: m for m in (
    Material("water", "H2O", (), 1.0, 0.20587),
    Material("pmma", "C5H8O2", (), 1.18, 0.19238),
    Material("aluminium", "Al", (), 2.70, 0.27781),
    Material("titanium", "Ti", (), 4.506, 0.76604),
    Material("iron", "Fe", (), 7.874, 1.20493),
    Material("steel", "", _STEEL, 8.0, 1.18534),
    Material("copper", "Cu", (), 8.96, 1.59258),
    Material("tungsten", "W", (), 19.25, 3.71262),
    Material("hydroxyapatite", "Ca5(PO4)3OH", (), 3.16, 0.40671),
    Material("bone", "", _BONE, 1.92, 0.31483),
    Material("air", "", _AIR, 0.001205, 0.18750),
)}

_ALIASES = {"h2o": "water", "acrylic": "pmma", "perspex": "pmma", "plexiglas": "pmma", "aluminum": "aluminium",
            "al": "aluminium", "ti": "titanium", "fe": "iron", "stainless steel": "steel", "cu": "copper",
            "w": "tungsten", "ha": "hydroxyapatite", "cortical bone": "bone"}


def beam_libraries_missing() -> list[str]:
    """Names of the polychromatic beam's libraries (spekpy, xraydb) that are not installed."""
    return [name for name in ("spekpy", "xraydb") if importlib.util.find_spec(name) is None]


def resolve_material(text, path: str) -> Material:
    """The :class:`Material` a name or formula means.

    Raises
    ------
    ConfigError
        Not a string, or neither a built-in name nor a formula xraydb parses (the message lists
        the built-in names); a formula while xraydb is not installed.
    """
    names = ", ".join(MATERIALS)
    if not isinstance(text, str) or not text.strip():
        raise ConfigError(f"{path}: must be a material name ({names}) or a chemical formula, got {text!r}")
    key = text.strip().lower()
    key = _ALIASES.get(key, key)
    if key in MATERIALS:
        return MATERIALS[key]
    if importlib.util.find_spec("xraydb") is None:
        raise ConfigError(f"{path}: {text!r} is not a built-in material ({names}); a chemical formula needs xraydb, "
                          f"which is not installed: {INSTALL_BEAM}")
    from xraydb.chemparser import chemparse

    try:
        chemparse(text.strip())
    except (ValueError, TypeError, KeyError):
        raise ConfigError(f"{path}: unknown material {text!r}; give one of {names} or a chemical formula such "
                          f"as Ca5(PO4)3OH") from None
    return Material(text.strip(), text.strip())


@functools.lru_cache(maxsize=256)
def _mass_attenuation(material: Material, energies_kev: tuple) -> np.ndarray:
    import xraydb

    energies_ev = np.asarray(energies_kev, dtype=np.float64) * 1e3
    if material.formula:
        mu = xraydb.material_mu(material.formula, energies_ev, density=1.0)
    else:
        mu = sum(w * np.asarray(xraydb.mu_elam(element, energies_ev), dtype=np.float64)
                 for element, w in material.mass_fractions)
    mu = np.atleast_1d(np.asarray(mu, dtype=np.float64))
    mu.flags.writeable = False
    return mu


def mass_attenuation_cm2_g(material: Material, energies_kev) -> np.ndarray:
    """``mu/rho`` (cm^2/g) of ``material`` at ``energies_kev``, float64 of the energies' shape (1-D).

    Cached per material and energy set, so a scan looks each table up once.
    """
    energies = tuple(float(e) for e in np.atleast_1d(np.asarray(energies_kev, dtype=np.float64)))
    return _mass_attenuation(material, energies)


def element_density_g_cm3(symbol: str) -> float | None:
    """The density (g/cm^3) of the pure element ``symbol`` from xraydb, or None if it is not an element symbol."""
    import xraydb

    try:
        return float(xraydb.atomic_density(symbol))
    except (ValueError, KeyError, TypeError):
        return None
