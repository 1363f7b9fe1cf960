"""The gate: corrected angles only where the projections show them better than the nominal ones.

A refiner's angles can be worse than the scanner's nominal ones (a scale bias of the pair
estimates on a truncated scan, flips on a feature-poor sample, a smooth error a short scan
cannot close), and on a real scan nobody knows the truth. The gate asks the projections
themselves, through the conjugate rays of :mod:`ctpipe.solve.conjugate`, which no reconstruction
can bend to fit.

The correction (``estimate - nominal``, its median removed) is split into three bands
(:func:`~ctpipe.solve.bands.split_bands`): ``fast`` (what the turn's first ``harmonics`` harmonics leave: jitter,
jumps, slips), ``slow-odd`` (odd harmonics: an eccentric table, a scale error) and
``slow-even`` (even harmonics, which conjugate rays see only weakly). Starting from the nominal
angles, bands are added one at a time (forward selection): of the bands not yet added, the one
whose addition lowers the conjugate-ray cost most is added if it lowers it by more than the
standard errors it needs (:class:`~ctpipe.solve.conjugate.ConjugateRayScore`), and the search
stops when none does. Every band must earn its place on its own evidence, so a wrong slow part
cannot ride into the result on a right fast part: on the sweep's scenarios that is what returned
angles worse than the nominal ones when the estimate was judged as a whole or in two bands.

``z`` is what one band tested alone against an exactly known standard error needs (2: a false
gain passes 2.3 % of the time). Each round takes the best of the ``m`` bands it tests, and the
standard error is itself estimated from a few dozen blocks of views, so at ``z`` a band that
changes nothing would pass several times as often. Each round's threshold therefore keeps the
same false-pass rate: Bonferroni's ``alpha / m`` over the bands tested, on Student's t with the
score's degrees of freedom (:func:`needed_z`). On the sweep, bands passed at a plain z of -2.3
to -2.5 with a cost change of 0.4 % made two scenarios worse than their nominal angles.

Views that no pair of conjugate rays reaches (the middle of a short scan) are not seen by the
measure at all, so they keep their nominal angles whatever the bands.

Where the projections cannot tell (no views half a turn apart, a midplane off the detector), the
gate says so and passes the estimate through: there is no evidence either way, and nothing to
base a decision on.

**The refiner's own evidence.** Conjugate rays are one row of the detector: on the small and
sparse scans of the built-in sweep they barely see anything (the whole estimate's z against the
nominal angles lay between -3.1 and +1.7, and estimates tens of degrees off scored -1.0 to
+1.0), so by them alone every correction was refused, right or wrong. Projection matching scores
its angles on views held out of the reference they are compared with
(:func:`~ctpipe.solve.reprojection.held_out_scores`), which a reference built from wrong angles
cannot bend to fit. Where it gives that evidence (``held_out_z``, below ``-z``) and the
conjugate rays' z is below ``-z`` too, the two are combined (Stouffer's sum: two independent
lines of evidence), and where together they show the estimate better than the nominal angles
beyond one band's threshold and the conjugate rays show no band of it worse, the estimate is
returned: whole where the held-out views vouch for it beyond doubt (z at or below minus
``HELD_OUT_DECISIVE_Z``), else less its slow-even band, which the conjugate rays hardly see and the
held-out views, whose reference carries a slow warp too, may not either (a sweep scan returned
whole at held-out z -2.7 was 2.13 -> 2.77 deg RMS, and 1.41 without the band). Held-out
evidence beyond doubt (-6) stands without the conjugate rays' agreement unless they contradict
it (a band shown worse, or the nominal angles shown better) or lean the other way, band by band:
an estimate whose correction is nearly all twice per turn scores near zero by the conjugate rays
however right it is, so its slow-even band comes in where the held-out views show that band
better on its own, and otherwise the rest of the estimate where that alone is decisive (a whole
can be decisive on its other bands while a wrong twice-per-turn warp rides along). Views no
conjugate ray reaches keep their nominal angle on this path too: the held-out views are
interleaved with the reference's, so a slow warp is in both and they do not see it (a 3.7 deg
warp in the middle of a 250 deg sweep scan passed with the rest of its estimate;
``docs/wholescan.md``). Otherwise the bands are selected as above. The conjugate rays' z in this
is that of the estimate less its slow-even band: they see that band only through the spread of
the fan, and with it an estimate 2.8 deg off, nearly all of it slow-even, scored -2.3 on a sweep
scan (the band alone +2.0, the rest -0.1).

**What does not turn.** On a full turn the midplane rows are taken less their mean over the views
(:func:`~ctpipe.solve.conjugate.turning_part`) before anything is scored: a table edge or clamp
under the sample is the same in every view, and its conjugate samples disagree whatever the
angles (correct estimates on two sweep scans, a bead cylinder over a static table edge and a bead
cloud without one, scored +2.4 and -1.8 on the rows as read, -3.0 and -3.5 on their turning
part). A short scan has no such average, and its rows are scored as they are.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np

from ctpipe.errors import InputError
from ctpipe.geometry import Geometry, check_geometry
from ctpipe.model import wrap_deg
from ctpipe.solve.bands import BANDS, split_bands
from ctpipe.solve.conjugate import ConjugateRayScore, conjugate_pairs, conjugate_ray_costs, turning_part
from ctpipe.solve.reprojection import HELD_OUT_DECISIVE_Z

__all__ = ["GateDecision", "gate_angles", "cannot_tell", "needed_z"]


def needed_z(z: float, tests: int, dof: int) -> float:
    """The z a band needs when ``tests`` bands are tried at once on a standard error with ``dof`` degrees of freedom.

    Keeps the one-sided false-pass rate of a single test at ``z`` on an exact standard error,
    ``alpha = P(N(0, 1) < -z)``, for the best of ``tests`` candidates (Bonferroni: ``alpha /
    tests`` each), with ``z`` Student-t distributed; ``needed_z(z, 1, inf) == z``.
    """
    from scipy import stats

    alpha = float(stats.norm.sf(z)) / max(int(tests), 1)
    return float(stats.norm.isf(alpha)) if not dof or not math.isfinite(dof) or dof > 10_000 else \
        float(stats.t.isf(alpha, max(int(dof), 1)))


@dataclass(frozen=True)
class GateDecision:
    """What the gate returned and why.

    Attributes
    ----------
    chosen : str
        ``estimate`` (every band added and every view seen), ``nominal`` (no band), or the bands
        added, e.g. ``fast + slow-odd``; ``nominal`` also when the projections could not be asked
        (``decided`` False, :func:`cannot_tell`).
    angles_deg : ndarray of shape (V,)
        The angles returned, in the estimate's frame.
    decided : bool
        Whether the projections could be asked at all.
    reason : str
        One sentence: why this result (or why no decision).
    bands : tuple of str
        The bands added, in the order they were.
    steps : tuple of dict
        One entry per round of the selection: each remaining band's ``z`` against the angles of
        that round.
    needed : tuple of dict
        One entry per round: the ``z`` below whose negative each band would have been added
        (:func:`needed_z`).
    scores : dict of str to ConjugateRayScore
        ``nominal`` and the returned angles (``returned``), the latter against the former; and
        the whole ``estimate`` against the nominal angles, for the record.
    views_seen : int
        Views reached by at least one pair of conjugate rays; the others keep their nominal angle.
    harmonics : int
        Harmonics of the turn in the slow bands.
    z : float
        Standard errors of gain one band tested alone on an exact standard error needs; each
        round asks more (``needed``).
    estimate_deg : ndarray of shape (V,) or None
        The refiner's angles as they came, in the nominal angles' frame (their median offset
        from them removed).
    held_out_z : float or None
        The refiner's own evidence, where it gave some: how many standard errors better its
        angles predict views held out of the reference than the nominal angles do (negative:
        better). With it the estimate is returned unless the conjugate rays show it, or a band
        of it, worse (``docs/wholescan.md``).
    """

    chosen: str
    angles_deg: np.ndarray
    decided: bool
    reason: str
    bands: tuple[str, ...] = ()
    steps: tuple[dict, ...] = ()
    needed: tuple[dict, ...] = ()
    scores: dict[str, ConjugateRayScore] = field(default_factory=dict)
    views_seen: int = 0
    harmonics: int = 3
    z: float = 2.0
    estimate_deg: np.ndarray | None = field(default=None, repr=False)
    held_out_z: float | None = None

    @property
    def improvement(self) -> float | None:
        """Relative drop of the conjugate-ray cost from the nominal angles to the returned ones (0.12: 12 % lower)."""
        if not self.decided or "returned" not in self.scores:
            return None
        nominal = self.scores["nominal"].cost
        return (nominal - self.scores["returned"].cost) / nominal if nominal > 0 else 0.0

    def to_dict(self) -> dict:
        return {"chosen": self.chosen, "decided": self.decided, "reason": self.reason, "bands": list(self.bands),
                "steps": [dict(step) for step in self.steps],
                "needed": [dict(step) for step in self.needed], "views_seen": self.views_seen,
                "harmonics": self.harmonics, "z": self.z, "improvement": self.improvement,
                "held_out_z": self.held_out_z,
                "scores": {name: score.to_dict() for name, score in self.scores.items()}}


def _frame_offset_deg(nominal: np.ndarray, estimate: np.ndarray) -> float:
    """The estimate's frame against the nominal one: the median of their differences over the views
    with an estimate, taken about the first such view so that it does not split across +-180 deg."""
    difference = wrap_deg(estimate - nominal)
    finite = np.isfinite(difference)
    anchor = float(difference[np.flatnonzero(finite)[0]])
    return float(np.median(wrap_deg(difference[finite] - anchor))) + anchor


def cannot_tell(nominal_deg, estimate_deg, why: str, **fields) -> GateDecision:
    """The gate's answer where the projections cannot be asked: the nominal angles, saying why.

    A correction nothing has checked is not returned as one (on sweep scans where conjugate
    rays could not be asked, pair-only pipelines returned angles tens of degrees off, the
    user none the wiser). ``estimate_deg`` is kept as ``estimate_deg`` (the nominal frame) for
    ``refiner_deg``; ``gate: off`` returns it.
    """
    nominal = np.asarray(nominal_deg, dtype=np.float64)
    estimate = np.asarray(estimate_deg, dtype=np.float64)
    finite = np.isfinite(estimate)
    shift = _frame_offset_deg(nominal, estimate) if finite.any() else 0.0
    return GateDecision("nominal", nominal + shift, False,
                        f"cannot tell whether the correction helped: {why}; the nominal angles are returned",
                        estimate_deg=np.where(finite, estimate - shift, np.nan), **fields)


def gate_angles(rows: np.ndarray, geometry: Geometry, nominal_deg, estimate_deg, *, z: float = 2.0,
                harmonics: int = 3, fit_u0_px: float | None = None, slopes: np.ndarray | None = None,
                fit_tilt_deg: float = 1.0, held_out_z: float | None = None,
                held_out_slow_even_z: float | None = None,
                held_out_without_slow_even_z: float | None = None) -> GateDecision:
    """The nominal angles plus those bands of the correction that the conjugate rays show better.

    Parameters
    ----------
    rows : ndarray of shape (V, cols)
        The midplane rows of the line integrals (:func:`~ctpipe.solve.conjugate.midplane_rows`).
    geometry : Geometry
    nominal_deg, estimate_deg : array_like of shape (V,)
        Degrees, any common offset (the estimate is compared in the nominal frame; whole turns
        between them do not count).
    z : float
        Standard errors of gain a single band on an exact standard error would need; each round
        asks for more, for the bands it tries and the standard error's own uncertainty
        (:func:`needed_z`).
    harmonics : int
        Harmonics of the turn in the slow bands.
    fit_u0_px : float, optional
        Search for the axis column this far either side of ``geometry.u0_px`` (default: 2 % of
        the detector width, at least 3 px), for every candidate.
    slopes : ndarray of shape (V, cols), optional
        The rows' derivatives along the detector rows (``midplane_rows(..., slopes=True)``): with
        them the detector's in-plane tilt is fitted in every comparison, with its reference's
        angles, within ``fit_tilt_deg`` either way (a tilt read as a straight row makes conjugate
        rays disagree in a way a wrong slow band of the angles can partly hide; on a sweep
        scenario with a 0.3 deg tilt, a twice-per-turn band that took the angles from 0.41 to
        0.56 deg RMS passed without it).
    fit_tilt_deg : float
        The largest tilt searched, degrees (used only with ``slopes``).
    held_out_z : float, optional
        The refiner's evidence for its angles against the nominal ones, in standard errors
        (projection matching's held-out views, :class:`~ctpipe.solve.reprojection.HeldOutScore`).
        Below ``-z``, it is combined with the conjugate rays' z of the estimate less its
        slow-even band against the nominal angles (Stouffer: their sum over the square root of
        two; two independent lines of evidence, the one from whole views held out of a
        reference, the other from the midplane's common rays): where the two together pass, and
        the conjugate rays show no band worse than the estimate without it, the whole estimate is
        returned on the views conjugate rays reach (the others keep their nominal angle);
        otherwise the bands are selected as without the evidence. Conjugate rays see
        little on a small or sparse scan (on the built-in sweep the whole estimate's z against the nominal
        angles lay between -3.1 and +1.7, and estimates tens of degrees off scored +1.0 and
        -1.0), so without other evidence nothing passes; views held out of the reference they
        are matched against are that evidence, and they rank the estimate the right way on
        those scans (``docs/wholescan.md``). At or below ``-HELD_OUT_DECISIVE_Z`` (-6) it stands
        without the conjugate rays' agreement where they neither contradict it nor lean the other
        way (a z above 0), band by band: the slow-even band (which they see only through the fan)
        where the held-out views show that band better on its own (``held_out_slow_even_z`` below
        ``-z``), else the rest where that is decisive (``held_out_without_slow_even_z``).
    held_out_slow_even_z, held_out_without_slow_even_z : float, optional
        The refiner's held-out evidence for the slow-even band of its correction: its angles
        against the same less that band, and those against the nominal angles
        (:func:`~ctpipe.solve.reprojection.slow_even_band_scores`). Without them, held-out
        evidence never stands without the conjugate rays' agreement.
    """
    g = check_geometry(geometry)
    nominal = np.asarray(nominal_deg, dtype=np.float64)
    estimate = np.asarray(estimate_deg, dtype=np.float64)
    if nominal.shape != estimate.shape or nominal.ndim != 1 or not np.all(np.isfinite(nominal)):
        raise InputError(f"nominal_deg and estimate_deg: must be finite angles of one shape (V,), got {nominal.shape} "
                         f"and {estimate.shape}")
    if not (z > 0 and math.isfinite(z)) or not (1 <= harmonics <= 32):
        raise InputError(f"z must be > 0 and harmonics 1 to 32, got {z!r} and {harmonics!r}")
    finite = np.isfinite(estimate)
    if not finite.any():
        return cannot_tell(nominal, estimate, "the refiner gave no view an angle", harmonics=harmonics, z=z,
                           held_out_z=held_out_z)
    # The estimate in the nominal frame: its median offset from the nominal angles removed. Views
    # the refiner gave no angle keep their nominal one, and the rest are gated as they are.
    difference = wrap_deg(estimate - nominal)
    shift = _frame_offset_deg(nominal, estimate)
    unestimated = int((~finite).sum())
    if unestimated:
        estimate = np.where(finite, estimate, nominal + shift)
        difference = wrap_deg(estimate - nominal)
    correction = wrap_deg(difference - shift)
    search = max(3.0, 0.02 * g.detector_cols) if fit_u0_px is None else float(fit_u0_px)
    first, second = conjugate_pairs(nominal, g, margin_px=1.0 + search)
    if len(first) == 0:
        return cannot_tell(nominal, estimate, "no two views are half a turn apart with their common ray on the "
                           "detector (a scan must cover 180 deg plus the fan angle)", harmonics=harmonics, z=z,
                           held_out_z=held_out_z)
    if unestimated:
        decision = gate_angles(rows, g, nominal, estimate, z=z, harmonics=harmonics, fit_u0_px=fit_u0_px,
                               slopes=slopes, fit_tilt_deg=fit_tilt_deg, held_out_z=held_out_z,
                               held_out_slow_even_z=held_out_slow_even_z,
                               held_out_without_slow_even_z=held_out_without_slow_even_z)
        return dataclasses.replace(decision, reason=f"{decision.reason}; {unestimated} views the refiner gave no "
                                                    "angle keep their nominal one")
    seen = np.zeros(len(nominal), bool)
    seen[first] = seen[second] = True
    rows, slopes = turning_part(rows, nominal, slopes)
    parts = {name: np.where(seen, part, 0.0) for name, part in split_bands(correction, nominal, harmonics, seen).items()}

    def scored(candidates: dict, reference: str) -> dict[str, ConjugateRayScore]:
        return conjugate_ray_costs(None, g, candidates, reference=reference, fit_u0_px=search, rows=rows,
                                   slopes=slopes, fit_tilt_deg=fit_tilt_deg if slopes is not None else 0.0)

    present = [name for name in BANDS if np.any(parts[name] != 0.0)]
    if held_out_z is not None and held_out_z < -z and present:
        # Views no conjugate ray reaches keep their nominal angle here too: the held-out views are
        # interleaved with the reference's, so a slow warp of the angles is in both and they do not
        # see it. In the middle of a 250 deg sweep scan a 3.7 deg warp passed with the rest of an
        # estimate (held-out z -3.0, conjugate -3.9): 1.35 deg RMS returned against the nominal
        # 1.14, 0.75 with the middle left nominal.
        visible = np.where(seen, correction, 0.0)
        stands = _backward(scored, nominal, visible, present, parts, z, held_out_z, held_out_slow_even_z,
                           held_out_without_slow_even_z)
        if stands is not None:
            reason, step, need, record, kept = stands
            left = [name for name in present if name not in kept]
            chosen = "estimate" if seen.all() and not left else " + ".join(kept)
            angles = (estimate if chosen == "estimate" else
                      nominal + visible - sum((parts[name] for name in left), np.zeros_like(visible)) + shift)
            if not seen.all():
                reason += f"; {int((~seen).sum())} views no pair reaches keep their nominal angle"
            return GateDecision(chosen, angles, True, reason, tuple(kept), (step,), (need,), record,
                                int(seen.sum()), harmonics, z, nominal + correction, held_out_z)
    current, added, steps, needed = nominal, [], [], []
    remaining = list(present)
    while remaining:
        scores = scored({"current": current, **{name: current + parts[name] for name in remaining}}, "current")
        steps.append({name: scores[name].z for name in remaining})
        needed.append({name: needed_z(z, len(remaining), scores[name].dof) for name in remaining})
        # The band furthest past its own threshold (they differ only by their degrees of freedom).
        best = min(remaining, key=lambda name: scores[name].z + needed[-1][name])
        if not scores[best].z < -needed[-1][best]:
            break
        current = current + parts[best]
        added.append(best)
        remaining.remove(best)
    record = scored({"nominal": nominal, "returned": current, "estimate": nominal + correction}, "nominal")
    if not added:
        chosen = "nominal"
        reason = (f"no band of the correction is shown better than the nominal angles by the projections' conjugate rays "
                  f"(best z {min(steps[0].values()):+.1f}; needs z < {-min(needed[0].values()):.1f})" if steps else
                  "the estimate is the nominal angles")
    else:
        chosen = "estimate" if len(added) == len(BANDS) and seen.all() else " + ".join(added)
        reason = (f"conjugate-ray cost {record['returned'].delta / max(record['nominal'].cost, 1e-300):+.1%} against the "
                  f"nominal angles' (z {record['returned'].z:+.1f}) with the {', '.join(added)} band"
                  f"{'s' if len(added) > 1 else ''} of the correction"
                  + ("" if seen.all() else f"; {int((~seen).sum())} views no pair reaches keep their nominal angle"))
    angles = estimate if chosen == "estimate" else current + shift
    if held_out_z is not None and held_out_z < -z:
        reason += (f" (the refiner's held-out views showed its angles better, z {held_out_z:+.1f}, but not together "
                   "with the conjugate rays, or these show a band of them worse)")
    return GateDecision(chosen, angles, True, reason, tuple(added), tuple(steps), tuple(needed), record,
                        int(seen.sum()), harmonics, z, nominal + correction, held_out_z)


def _backward(scored, nominal, correction, present, parts, z, held_out_z, held_out_slow_even_z=None,
              held_out_without_slow_even_z=None):
    """The refiner's held-out evidence with the conjugate rays': the estimate, where the two together show it
    better than the nominal angles and the conjugate rays show no band of it worse nor the nominal angles
    better; or, where the held-out views show it better beyond doubt (``held_out_z`` at or below
    ``-HELD_OUT_DECISIVE_Z``) and the conjugate rays neither contradict it nor lean the other way (their z
    of what is returned at most 0), the estimate with its slow-even band where the held-out views show that
    band better on its own, else without it where that is decisive. Returns ``(reason, steps, needed,
    record, bands kept)`` when it stands, None when not."""
    whole = nominal + correction
    scores = scored({"estimate": whole, "nominal": nominal, **{name: whole - parts[name] for name in present}},
                    "estimate")
    steps = {name: scores[name].z for name in present}
    needed = {name: needed_z(z, len(present), scores[name].dof) for name in present}
    # Removing a band helps beyond its threshold: the band is shown worse. Or the nominal angles
    # are shown better than the whole estimate.
    worse = [name for name in present if scores[name].z < -needed[name]]
    # The conjugate rays' own evidence is taken on what they see: the estimate less its slow-even
    # band, which they see only through the spread of the fan. With it, an estimate 2.8 deg off
    # (nearly all slow-even) scored -2.3 on a sweep scan, its slow-even band alone +2.0, the rest -0.1.
    record = scored({"nominal": nominal, "returned": whole, "visible": whole - parts["slow-even"]}, "nominal")
    conjugate = record.pop("visible")
    record["estimate"] = record["returned"]   # the same angles: scored once
    # Two independent lines of evidence, each a z against the nominal angles: each must show the
    # estimate better on its own (an intersection-union test), and their Stouffer sum beyond the
    # threshold of one band. Their sum alone let a held-out z of -2.9 carry a conjugate z of -1.7 on
    # a trabecular scan whose matched angles had walked (a few views 2 deg off): 2 dB worse.
    combined = (held_out_z + conjugate.z) / math.sqrt(2.0)
    one = needed_z(z, 1, conjugate.dof)
    # The conjugate rays contradict the estimate: a band of it shown worse, or the nominal angles
    # shown better than it, whole or without the slow-even band.
    if worse or record["returned"].z > one or conjugate.z > one:
        return None
    if conjugate.z < -z and combined < -one:
        reason = (f"the refiner's held-out views (z {held_out_z:+.1f}) and the projections' conjugate rays (z "
                  f"{conjugate.z:+.1f}, without the slow-even band they hardly see) together show its angles better "
                  f"than the nominal ones (z {combined:+.1f}), and no band of them worse")
        if "slow-even" not in present or held_out_z <= -HELD_OUT_DECISIVE_Z:
            return reason, steps, needed, record, present
        # Short of held-out evidence beyond doubt, the slow-even band is left out: the conjugate rays' evidence is
        # of the rest, and the held-out views hardly see a slow warp either (it is in the reference they are matched
        # against too). A sweep scan (seed 3201, scenario 0: an electronic board, 222 views, two 2 deg jumps) whose
        # matched angles fixed the jumps and added a twice-per-turn warp of 4 deg passed at held-out z -2.7 and
        # conjugate z -2.2 (-3.4 together): 2.13 -> 2.77 deg RMS returned, 1.41 without the band (which the held-out
        # views, asked, showed better on its own at z -3.1).
        record["returned"] = conjugate
        kept = [name for name in present if name != "slow-even"]
        return (reason + f"; the slow-even band is left out (held-out z {held_out_z:+.1f}, decisive below "
                f"{-HELD_OUT_DECISIVE_Z:.0f})"), steps, needed, record, kept
    if held_out_z > -HELD_OUT_DECISIVE_Z:
        return None
    # Held-out evidence beyond doubt stands without the conjugate rays where they do not contradict
    # it, band by band. They see a twice-per-turn error only through the fan: on a sweep scan whose
    # error was nearly all of that band (0.354 deg RMS; matched 0.149) the held-out views scored the
    # matched angles at z -9.4 and the band alone at -6.6, the conjugate rays at -0.1 without it.
    # A whole can be decisive on its other bands alone: a sweep scan whose matched angles fixed two
    # 2 deg jumps and added a 4 deg twice-per-turn warp scored -5.1 as a whole, the band alone -1.3.
    settled = (f"the refiner's held-out views show its angles better than the nominal ones beyond doubt (z "
               f"{held_out_z:+.1f}, decisive below {-HELD_OUT_DECISIVE_Z:.0f}), and the projections' conjugate "
               f"rays (z {conjugate.z:+.1f} without the slow-even band they hardly see) show no band of them worse")
    # Nor where the conjugate rays, too weak to decide, lean the other way on what is returned:
    # seed-0 sweep scenario 13 (a bead cloud, 63 views, jitter not visible at the grid) had held-out
    # z -8.1 (the slow-even band alone -5.6) while the conjugate rays scored the whole at +1.1 and
    # each band alone at +1.4 to +2.1; its angles came out a little better (0.410 -> 0.383 deg RMS)
    # and its reconstruction 0.41 dB worse against the jitter-free scan's.
    whole_leans_against = record["returned"].z > 0.0
    if "slow-even" not in present:
        return None if whole_leans_against else (settled, steps, needed, record, present)
    if held_out_slow_even_z is not None and held_out_slow_even_z < -z and not whole_leans_against:
        return settled + f"; the slow-even band on its own z {held_out_slow_even_z:+.1f}", steps, needed, record, present
    if (held_out_without_slow_even_z is not None and held_out_without_slow_even_z <= -HELD_OUT_DECISIVE_Z
            and conjugate.z <= 0.0):
        record["returned"] = conjugate
        shown = ("not shown" if held_out_slow_even_z is None else
                 f"not shown better on its own, z {held_out_slow_even_z:+.1f}")
        return (settled + f"; the slow-even band ({shown}) is left out, the rest z "
                f"{held_out_without_slow_even_z:+.1f}"), steps, needed, record, \
            [name for name in present if name != "slow-even"]
    return None
