"""The simulator: phantoms, cone-beam projectors, angle jitter and a noisy detector.

A simulated scan is made the way a real one is: a phantom (:mod:`~ctpipe.sim.phantoms`, built
from the analytic primitives of :mod:`~ctpipe.sim.primitives` or from a voxel volume) is
projected at the true angles, nominal angles plus the jitter of :mod:`~ctpipe.sim.jitter`, by
the exact or the voxel projector of :mod:`~ctpipe.sim.projectors`; :mod:`~ctpipe.sim.acquisition`
turns the line integrals into detector counts with Poisson noise, flats and darks; a sample
holder (:mod:`~ctpipe.sim.holders`) adds parts that turn with the sample and parts that do not.
A scan spec (:mod:`~ctpipe.sim.scan_spec`) says what to acquire and :mod:`~ctpipe.sim.simulator` runs the
chain and writes a scan folder. Reconstruction is in :mod:`ctpipe.recon`, reading and writing
scans in :mod:`ctpipe.io`. ``docs/simulation.md`` has the conventions and figures.
"""

from ctpipe.sim.acquisition import NoiseModel, acquire, beer_lambert, parse_noise
from ctpipe.sim.beam import (ANODES, DETECTOR_RESPONSES, MAX_ENERGY_TERMS, Beam, beam_spectrum, effective_energy_kev,
                             parse_beam, polychromatic_line_integrals)
from ctpipe.sim.detector import (FULL_SCALE_PER_FLAT, MAX_STUCK_FRACTION, DetectorModel, DetectorPattern,
                                 detected_line_integrals, draw_pattern, parse_detector, record, scatter_counts)
from ctpipe.sim.drift import DetectorDrift, Misalignment, parse_misalignment, resample_to_detector
from ctpipe.sim.holders import HOLDER_ORIGINS, Holder, parse_holder
from ctpipe.sim.jitter import JITTER_KINDS, Jitter, nominal_angles_deg, parse_jitter
from ctpipe.sim.materials import (INSTALL_BEAM, MATERIALS, REFERENCE_KEV, Material, beam_libraries_missing,
                                  element_density_g_cm3, mass_attenuation_cm2_g, resolve_material)
from ctpipe.sim.phantoms import ELECTRONIC_MATERIALS, Phantom, list_phantoms, load_phantom, parse_objects, parse_phantom
from ctpipe.sim.primitives import Primitives, voxelise
from ctpipe.sim.projectors import (MAX_SUB_RAYS, MAX_VOXEL_STEPS, VoxelProjector, analytic_work, project_analytic,
                                   voxel_work)
from ctpipe.sim.scan_spec import AngleSpec, ProjectorSpec, ScanSpec, load_scan_spec, parse_scan_spec
from ctpipe.sim.simulator import (SimulatedScan, check_simulation_fits, check_simulation_work, project_phantom,
                                  simulate, simulation_bytes, simulation_work, voxelise_phantom, write_simulated_scan)

__all__ = ["simulate", "SimulatedScan", "write_simulated_scan", "project_phantom", "voxelise_phantom",
           "simulation_bytes", "Phantom", "load_phantom", "parse_phantom", "list_phantoms", "Primitives", "voxelise",
           "project_analytic", "VoxelProjector", "Jitter", "parse_jitter", "nominal_angles_deg", "JITTER_KINDS",
           "NoiseModel", "parse_noise", "acquire", "beer_lambert", "ScanSpec", "AngleSpec", "ProjectorSpec",
           "parse_scan_spec", "load_scan_spec"]
__all__ += ["DetectorModel", "DetectorPattern", "parse_detector", "draw_pattern", "scatter_counts", "record",
            "detected_line_integrals", "MAX_STUCK_FRACTION", "FULL_SCALE_PER_FLAT"]
__all__ += ["Beam", "parse_beam", "beam_spectrum", "effective_energy_kev", "polychromatic_line_integrals", "ANODES",
            "DETECTOR_RESPONSES", "Material", "MATERIALS", "resolve_material", "INSTALL_BEAM", "REFERENCE_KEV",
            "mass_attenuation_cm2_g", "element_density_g_cm3", "beam_libraries_missing"]
__all__ += ["Misalignment", "DetectorDrift", "parse_misalignment", "resample_to_detector"]
__all__ += ["Holder", "parse_holder", "HOLDER_ORIGINS", "parse_objects", "ELECTRONIC_MATERIALS"]
__all__ += ["simulation_work", "check_simulation_work", "check_simulation_fits", "analytic_work", "voxel_work",
            "MAX_SUB_RAYS", "MAX_VOXEL_STEPS", "MAX_ENERGY_TERMS"]
