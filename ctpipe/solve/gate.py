"""The gate: corrected angles only where the projections show they are better than the nominal ones.

A refiner's angles can be worse than the scanner's nominal ones (a scale bias of the pair
estimates on a truncated scan, flips on a feature-poor sample, a smooth error a short scan
cannot close), and on a real scan nobody knows the truth. The gate asks the projections
themselves, through the conjugate rays of :mod:`ctpipe.solve.conjugate`, which no reconstruction
can bend to fit. It scores four candidate angle sets against the nominal ones:

- ``estimate``: the refiner's angles;
- ``fast band``: the nominal angles plus the fast part of the correction (``estimate - nominal``
  less its projection on the turn's first ``harmonics`` harmonics: jitter, jumps, slips);
- ``slow band``: the nominal angles plus only the slow part (drift, eccentricity, a scale error);
- ``nominal``, the reference.

A candidate is *shown better* when its conjugate-ray cost is below the nominal angles' by more
than ``z`` standard errors (:class:`~ctpipe.solve.conjugate.ConjugateRayScore`). Of those, the
lowest cost is returned, but the whole estimate is preferred to one of its bands unless the band
is itself shown better than the estimate (the bands are tried to drop a part that is wrong, not
to pick between two that the data cannot tell apart). When none is shown better, the nominal
angles are returned, and said so.

Where the projections cannot tell (no views half a turn apart, a midplane off the detector), the
gate says so and passes the estimate through: there is no evidence either way, and nothing to
base a decision on.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ctpipe.errors import InputError
from ctpipe.geometry import Geometry, check_geometry
from ctpipe.model import wrap_deg
from ctpipe.solve.conjugate import ConjugateRayScore, conjugate_ray_costs

__all__ = ["GateDecision", "split_bands", "gate_angles", "CANDIDATES"]

CANDIDATES = ("estimate", "fast band", "slow band", "nominal")


def split_bands(correction_deg: np.ndarray, nominal_deg: np.ndarray, harmonics: int) -> tuple[np.ndarray, np.ndarray]:
    """``(slow, fast)`` parts of a per-view correction, each shape (V,); ``slow + fast == correction``.

    The slow part is the least-squares fit of ``1, cos(k theta), sin(k theta)`` for ``k`` up to
    ``harmonics``, ``theta`` the nominal angles: on a full turn the turn-periodic errors of low
    order; on a short scan the smooth errors over its range.
    """
    correction = np.asarray(correction_deg, dtype=np.float64)
    theta = np.deg2rad(np.asarray(nominal_deg, dtype=np.float64))
    columns = [np.ones_like(theta)]
    for k in range(1, harmonics + 1):
        columns += [np.cos(k * theta), np.sin(k * theta)]
    basis = np.stack(columns, axis=1)
    coeffs, *_ = np.linalg.lstsq(basis, correction, rcond=None)
    slow = basis @ coeffs
    return slow, correction - slow


@dataclass(frozen=True)
class GateDecision:
    """What the gate returned and why.

    Attributes
    ----------
    chosen : str
        ``estimate``, ``fast band``, ``slow band`` or ``nominal``; ``estimate`` also when the gate
        could not decide (see ``reason``).
    angles_deg : ndarray of shape (V,)
        The angles returned, in the estimate's frame (view 0 at the estimate's).
    decided : bool
        Whether the projections could be asked at all.
    reason : str
        One sentence: why this candidate (or why no decision).
    scores : dict of str to ConjugateRayScore
        Each candidate's conjugate-ray cost and its difference from the nominal angles'.
    harmonics : int
        Harmonics of the turn in the slow band.
    z : float
        Standard errors a candidate must gain over the nominal angles to be returned.
    estimate_deg : ndarray of shape (V,) or None
        The refiner's angles as they came, in the nominal angles' frame (their median offset
        from them removed); None when the gate could not decide.
    """

    chosen: str
    angles_deg: np.ndarray
    decided: bool
    reason: str
    scores: dict[str, ConjugateRayScore] = field(default_factory=dict)
    harmonics: int = 3
    z: float = 2.0
    estimate_deg: np.ndarray | None = field(default=None, repr=False)

    @property
    def improvement(self) -> float | None:
        """Relative drop of the conjugate-ray cost from the nominal angles to the returned ones (0.12: 12 % lower)."""
        if not self.decided or "nominal" not in self.scores:
            return None
        nominal = self.scores["nominal"].cost
        return (nominal - self.scores[self.chosen].cost) / nominal if nominal > 0 else 0.0

    def to_dict(self) -> dict:
        return {"chosen": self.chosen, "decided": self.decided, "reason": self.reason, "harmonics": self.harmonics,
                "z": self.z, "improvement": self.improvement,
                "scores": {name: score.to_dict() for name, score in self.scores.items()}}


def gate_angles(rows: np.ndarray, geometry: Geometry, nominal_deg, estimate_deg, *, z: float = 2.0,
                harmonics: int = 3, fit_u0_px: float | None = None) -> GateDecision:
    """The estimate, one of its bands, or the nominal angles: whichever the conjugate rays show best.

    Parameters
    ----------
    rows : ndarray of shape (V, cols)
        The midplane rows of the line integrals (:func:`~ctpipe.solve.conjugate.midplane_rows`).
    geometry : Geometry
    nominal_deg, estimate_deg : array_like of shape (V,)
        Degrees, any common offset (the estimate is compared in the nominal frame).
    z : float
        Standard errors of gain over the nominal angles a candidate needs.
    harmonics : int
        Harmonics of the turn in the slow band.
    fit_u0_px : float, optional
        Search for the axis column this far either side of ``geometry.u0_px`` (default: 2 % of
        the detector width, at least 3 px), for every candidate.
    """
    g = check_geometry(geometry)
    nominal = np.asarray(nominal_deg, dtype=np.float64)
    estimate = np.asarray(estimate_deg, dtype=np.float64)
    if nominal.shape != estimate.shape or nominal.ndim != 1 or not np.all(np.isfinite(nominal)):
        raise InputError(f"nominal_deg and estimate_deg: must be finite angles of one shape (V,), got {nominal.shape} "
                         f"and {estimate.shape}")
    if not (z > 0 and math.isfinite(z)) or not (0 <= harmonics <= 32):
        raise InputError(f"z must be > 0 and harmonics 0 to 32, got {z!r} and {harmonics!r}")
    # The estimate in the nominal frame: its median offset from the nominal angles removed.
    finite = np.isfinite(estimate)
    if not finite.all():
        return GateDecision("estimate", estimate, False, f"{int((~finite).sum())} views have no estimate; not gated",
                            harmonics=harmonics, z=z)
    # Whole turns between them do not count (a refiner's angles may run past 360 deg, or wrap).
    difference = wrap_deg(estimate - nominal)
    shift = float(np.median(wrap_deg(difference - difference[0]))) + float(difference[0])
    correction = wrap_deg(difference - shift)
    slow, fast = split_bands(correction, nominal, harmonics)
    candidates = {"nominal": nominal, "estimate": nominal + correction, "fast band": nominal + fast,
                  "slow band": nominal + slow}
    search = max(3.0, 0.02 * g.detector_cols) if fit_u0_px is None else float(fit_u0_px)
    try:
        scores = conjugate_ray_costs(None, g, candidates, reference="nominal", fit_u0_px=search, rows=rows)
    except InputError as error:
        return GateDecision("estimate", estimate, False, f"not gated: {error}", harmonics=harmonics, z=z)
    shown = [name for name in ("estimate", "fast band", "slow band") if scores[name].z < -z]
    if not shown:
        est = scores["estimate"]
        return GateDecision("nominal", nominal + shift, True,
                            f"the projections do not show the estimate better than the nominal angles "
                            f"(conjugate-ray cost {est.delta / max(scores['nominal'].cost, 1e-300):+.1%} of the "
                            f"nominal's, z {est.z:+.1f}; needs z < {-z:g})", scores, harmonics, z,
                            candidates["estimate"])
    best = min(shown, key=lambda name: scores[name].cost)
    if best != "estimate" and "estimate" in shown:
        versus = conjugate_ray_costs(None, g, {"estimate": candidates["estimate"], best: candidates[best]},
                                     reference="estimate", fit_u0_px=search, rows=rows)[best]
        if versus.z >= -z:
            best = "estimate"
    score = scores[best]
    reason = (f"conjugate-ray cost {score.delta / max(scores['nominal'].cost, 1e-300):+.1%} against the nominal "
              f"angles' (z {score.z:+.1f})")
    angles = estimate if best == "estimate" else candidates[best] + shift
    return GateDecision(best, angles, True, reason, scores, harmonics, z, candidates["estimate"])
