"""Epipolar consistency of two cone-beam views against their relative angle: is it a keypoint-free pair angle?

Aichert et al. (IEEE TMI 34:2205, 2015) compare two views through the planes that contain both
sources: by Grangeat's relation, each view gives the derivative of the object's plane integral
over every such plane, so the two must agree at the true relative angle and, the hope is,
disagree away from it, with no features at all. This script measures that on ctpipe's simulator:

- each view's value for a plane through its source with unit normal ``n`` (camera frame,
  normalised detector coordinates ``u, v`` at distance 1) is
  ``(1 + s^2) d/ds R[g / sqrt(1 + u^2 + v^2)](m, s)``, the 2-D Radon transform of the cosine
  weighted line integrals ``g`` along the detector line ``m . (u, v) = s``, with
  ``n ~ (m, -s)``. That is Grangeat's ``dRf/drho`` up to a factor common to both views (the
  derivation: the great circle of directions normal to ``n`` is the detector line seen from the
  source; the homogeneity of the cosine-weighted data turns the derivative along ``n`` into one
  along ``s``). ``--check`` compares it with the analytic value for a solid ball;
- the planes of a pair are those through the baseline ``c - R(alpha)^T c`` (the second source
  in the first view's frame, :mod:`ctpipe.model`), tilted by ``kappa`` from the mid-plane; the
  second view sees the plane's normal turned by ``R(alpha)``;
- the printed figure is the two views' relative disagreement over every plane, for the assumed
  relative angle off the true one by -1 ... +1 deg, and where it is smallest.

The derivative along ``s`` is a Gaussian derivative of ``--sigma-px`` pixels, the same kernel in
both views; the sums along each line are bilinear samples every half pixel.

    python benchmarks/ecc_sensitivity.py [--phantom granular] [--size 256] [--photons 1e5]
                                         [--baselines 3 10 30 90 150] [--check]

Never fails: it prints the figures docs/wholescan.md quotes.
"""

from __future__ import annotations

import argparse

import numpy as np
from scipy.ndimage import map_coordinates

from ctpipe.geometry import Geometry
from ctpipe.model import rotation_matrix
from ctpipe.sim.phantoms import load_phantom, parse_phantom
from ctpipe.sim.simulator import project_phantom

OFFSETS_DEG = (-1.0, -0.3, -0.1, 0.0, 0.1, 0.3, 1.0)


class View:
    """One view's cosine-weighted line integrals and Grangeat's plane derivative from them."""

    def __init__(self, line_integrals: np.ndarray, geometry: Geometry, sigma_px: float) -> None:
        g = geometry
        self.step = g.pixel_pitch_u_mm / g.source_to_detector_mm          # one pixel, normalised
        self.u0, self.v0 = g.u0_px, g.v0_px
        u = (np.arange(g.detector_cols) - g.u0_px) * self.step
        v = (np.arange(g.detector_rows) - g.v0_px) * self.step
        uu, vv = np.meshgrid(u, v)
        self.weighted = line_integrals / np.sqrt(1.0 + uu ** 2 + vv ** 2)
        self.t = np.arange(-1.0, 1.0, self.step / 2)
        sigma = sigma_px * self.step
        self.taus = np.arange(-3 * sigma, 3 * sigma + 1e-12, sigma / 3)
        kernel = -self.taus * np.exp(-0.5 * (self.taus / sigma) ** 2)
        self.kernel = kernel / np.sum(kernel * self.taus)            # sum(kernel * tau) = 1: d/ds

    def plane_derivative(self, normal: np.ndarray) -> float:
        """``dRf/drho`` (up to a common factor) over the plane through the source with this unit normal."""
        c = float(np.hypot(normal[0], normal[1]))
        m = normal[:2] / c
        s = -normal[2] / c
        offsets = s + self.taus[:, None]
        pu = offsets * m[0] - self.t * m[1]
        pv = offsets * m[1] + self.t * m[0]
        sums = map_coordinates(self.weighted, [pv / self.step + self.v0, pu / self.step + self.u0], order=1,
                               cval=0.0).sum(axis=1) * (self.step / 2)
        return (1.0 + s * s) * float(np.sum(self.kernel * sums))


def epipolar_normals(alpha_rad: float, sod_mm: float, kappas_rad: np.ndarray) -> np.ndarray:
    """Unit normals (first view's frame) of the planes through both sources, tilted by ``kappa``."""
    centre = np.array([0.0, 0.0, sod_mm])
    baseline = centre - rotation_matrix(alpha_rad).T @ centre
    up = np.array([0.0, 1.0, 0.0])
    across = np.cross(baseline, up)
    across /= np.linalg.norm(across)
    return np.cos(kappas_rad)[:, None] * up + np.sin(kappas_rad)[:, None] * across


def disagreement(first: View, second: View, alpha_deg: float, sod_mm: float, kappas_rad: np.ndarray) -> float:
    """RMS difference of the two views' plane derivatives over the epipolar planes, relative to the first's."""
    alpha = np.deg2rad(alpha_deg)
    normals = epipolar_normals(alpha, sod_mm, kappas_rad)
    turn = rotation_matrix(alpha)
    a = np.array([first.plane_derivative(n) for n in normals])
    b = np.array([second.plane_derivative(turn @ n) for n in normals])
    return float(np.sqrt(np.mean((a - b) ** 2) / np.mean(a ** 2)))


def check_against_a_ball(geometry: Geometry, sigma_px: float) -> None:
    """Grangeat's derivative from one view of a solid ball against its analytic value ``2 pi mu (n . p)``."""
    centre, radius, mu = np.array([20.0, 10.0, -15.0]), 12.0, 0.05
    ball = parse_phantom({"objects": [{"sphere": {"centre_mm": centre.tolist(), "radius_mm": radius,
                                                  "density_per_mm": mu}}]})
    for theta_deg in (0.0, 60.0):
        view = View(project_phantom(ball, geometry, [theta_deg], supersample=4)[0], geometry, sigma_px)
        camera = rotation_matrix(np.deg2rad(theta_deg)) @ centre + np.array([0.0, 0.0, geometry.source_to_object_mm])
        for kappa_deg in (-5.0, -2.0, 0.0):
            k = np.deg2rad(kappa_deg)
            normal = np.array([0.2 * np.sin(k), np.cos(k), np.sin(k)])
            normal /= np.linalg.norm(normal)
            print(f"ball, view at {theta_deg:4.0f} deg, plane tilted {kappa_deg:+.0f} deg: from the view "
                  f"{view.plane_derivative(normal):+.4f}, analytic {2 * np.pi * mu * float(normal @ camera):+.4f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--phantom", default="granular")
    parser.add_argument("--size", type=int, default=256, help="detector pixels a side (the field of view is fixed)")
    parser.add_argument("--photons", type=float, default=1e5, help="photons per pixel (0: no noise)")
    parser.add_argument("--baselines", type=float, nargs="+", default=[3.0, 10.0, 30.0, 90.0, 150.0])
    parser.add_argument("--sigma-px", type=float, default=1.0)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--check", action="store_true", help="first compare with a ball's analytic plane integrals")
    args = parser.parse_args()
    pitch = 0.8 * 512 / args.size
    geometry = Geometry(150.0, 390.0, args.size, args.size, pitch, pitch)     # the default scan's cone
    if args.check:
        check_against_a_ball(geometry, args.sigma_px)
    phantom = load_phantom(args.phantom)
    rng = np.random.default_rng(args.seed)
    kappas = np.deg2rad(np.linspace(-8.0, 8.0, 161))
    print(f"{args.phantom}, {args.size}^2, {args.photons:g} photons; relative disagreement at the true angle "
          f"plus {', '.join(f'{o:+g}' for o in OFFSETS_DEG)} deg")
    for baseline in args.baselines:
        projections = project_phantom(phantom, geometry, [10.0, 10.0 + baseline], supersample=2, blur_px=0.5)
        if args.photons > 0:
            counts = rng.poisson(args.photons * np.exp(-projections))
            projections = -np.log(np.maximum(counts, 1) / args.photons)
        first, second = (View(p, geometry, args.sigma_px) for p in projections)
        costs = [disagreement(first, second, baseline + o, geometry.source_to_object_mm, kappas) for o in OFFSETS_DEG]
        print(f"baseline {baseline:5.1f} deg: " + " ".join(f"{c:.4f}" for c in costs)
              + f"  smallest at {OFFSETS_DEG[int(np.argmin(costs))]:+g} deg")


if __name__ == "__main__":
    main()
