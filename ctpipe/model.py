"""The one-parameter circular-motion model of a turntable scan.

Sign convention
---------------
A turntable rotation of ``+alpha`` from view ``i`` to view ``j`` is estimated as ``+alpha``.
In the frame of :mod:`ctpipe.geometry` (x along detector rows, y down the detector columns,
z from the source to the detector) a point ``X_i`` seen in view ``i`` is seen in view ``j`` at::

    X_j = R(alpha) (X_i - c) + c,   c = (0, 0, source_to_object_mm)
    R(alpha) = [[cos a, 0, -sin a], [0, 1, 0], [sin a, 0, cos a]]

i.e. positive ``alpha`` turns the object counter-clockwise when seen from above (from the
detector's first row looking down the axis): points between the axis and the source move
towards larger columns. The simulator and every estimator use this one definition.

Essential matrix
----------------
With ``X_j = R X_i + t``, ``t = (I - R) c = 2 SOD sin(alpha/2) (cos(alpha/2), 0, sin(alpha/2))``.
ctpipe normalises the translation to its unit direction, so that
``E(alpha) = [t_hat]_x R(alpha) = [[0, -S, 0], [-S, 0, -C], [0, C, 0]]`` with
``C = cos(alpha/2)``, ``S = sin(alpha/2)``. Unlike the unnormalised ``E`` it does not vanish at
``alpha = 0`` (there it is the epipolar geometry of a sideways translation), so residuals stay
comparable across angles. For ``q = (x, y, 1)`` in view ``i`` and ``q' = (x', y', 1)`` in view ``j``::

    q'^T E q = C a - S b,   a = y - y',   b = x' y + x y'

One correspondence fixes ``tan(alpha/2) = a / b``; SOD drops out. See ``docs/model.md``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = [
    "CircularMotion",
    "FailedEstimation",
    "rotation_matrix",
    "essential_matrix",
    "correspondence_terms",
    "angles_from_correspondences",
    "sampson_distance",
    "fit_angle",
    "wrap_deg",
]


@dataclass(frozen=True)
class FailedEstimation:
    """A falsy result that says why an estimation did not produce a model."""

    reason: str

    def __bool__(self) -> bool:
        return False

    def __str__(self) -> str:
        return self.reason


def rotation_matrix(alpha_rad: float) -> np.ndarray:
    """Rotation of a turntable angle ``alpha_rad`` in the source frame, shape (3, 3)."""
    c, s = np.cos(alpha_rad), np.sin(alpha_rad)
    return np.array([[c, 0.0, -s], [0.0, 1.0, 0.0], [s, 0.0, c]])


def essential_matrix(alpha_rad: float) -> np.ndarray:
    """Essential matrix ``E(alpha)`` with unit translation direction, shape (3, 3).

    ``q_j^T E q_i = 0`` for a correspondence in normalised homogeneous coordinates.
    """
    half_c, half_s = np.cos(alpha_rad / 2.0), np.sin(alpha_rad / 2.0)
    return np.array([[0.0, -half_s, 0.0], [-half_s, 0.0, -half_c], [0.0, half_c, 0.0]])


def _split(q_a: np.ndarray, q_b: np.ndarray) -> tuple[np.ndarray, ...]:
    q_a = np.asarray(q_a, dtype=np.float64)
    q_b = np.asarray(q_b, dtype=np.float64)
    return q_a[..., 0], q_a[..., 1], q_b[..., 0], q_b[..., 1]


def correspondence_terms(q_a: np.ndarray, q_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``a = y - y'`` and ``b = x' y + x y'`` of each correspondence, shapes (N,)."""
    x, y, xp, yp = _split(q_a, q_b)
    return y - yp, xp * y + x * yp


def angles_from_correspondences(q_a: np.ndarray, q_b: np.ndarray) -> np.ndarray:
    """Angle fixed by each single correspondence, in radians, shape (N,).

    ``alpha = 2 atan(a / b)`` written as ``atan2(2ab, b^2 - a^2)`` (the double-angle form),
    which lands on the right branch for ``|alpha|`` up to 180 deg and returns 0 for the
    degenerate ``a = b = 0`` (points on the detector row through the principal point).
    """
    a, b = correspondence_terms(q_a, q_b)
    return np.arctan2(2.0 * a * b, b * b - a * a)


def _half_angle(alpha_rad):
    alpha = np.asarray(alpha_rad, dtype=np.float64)
    return np.cos(alpha / 2.0), np.sin(alpha / 2.0)


def sampson_distance(alpha_rad, q_a: np.ndarray, q_b: np.ndarray) -> np.ndarray:
    """Sampson distance of each correspondence to the model ``E(alpha)``.

    ``d = |q'^T E q| / sqrt((Eq)_1^2 + (Eq)_2^2 + (E^T q')_1^2 + (E^T q')_2^2)``, in normalised
    units (multiply by SDD / pixel pitch for pixels). It does not depend on the scale of ``E``.
    ``alpha_rad`` may be scalar or shape (H, 1); the result is (N,) or (H, N).
    """
    x, y, xp, yp = _split(q_a, q_b)
    half_c, half_s = _half_angle(alpha_rad)
    if half_c.ndim == 2 and half_c.shape[1] == 1 and x.ndim == 1:
        # Every hypothesis of a RANSAC round at once: one pass, no (H, N) temporaries, GIL released.
        from ctpipe._shared.sampson import hypotheses_sampson   # numba: not imported with the model

        return hypotheses_sampson(half_c[:, 0], half_s[:, 0], np.ascontiguousarray(x), np.ascontiguousarray(y),
                                   np.ascontiguousarray(xp), np.ascontiguousarray(yp))
    numerator = half_c * (y - yp) - half_s * (xp * y + x * yp)
    # Eq = (-S y, -S x - C, C y), E^T q' = (-S y', C - S x', -C y').
    denominator = (half_s * y) ** 2 + (half_s * x + half_c) ** 2 + (half_s * yp) ** 2 + (half_c - half_s * xp) ** 2
    return np.abs(numerator) / np.sqrt(denominator)


def _sampson_weights(alpha_rad: float, x, y, xp, yp) -> np.ndarray:
    half_c, half_s = np.cos(alpha_rad / 2.0), np.sin(alpha_rad / 2.0)
    denominator = (half_s * y) ** 2 + (half_s * x + half_c) ** 2 + (half_s * yp) ** 2 + (half_c - half_s * xp) ** 2
    return 1.0 / denominator


def fit_angle(
    q_a: np.ndarray,
    q_b: np.ndarray,
    *,
    weights: np.ndarray | None = None,
    objective: str = "sampson",
    iterations: int = 4,
    polish: bool = True,
) -> float | FailedEstimation:
    """Least-squares angle of correspondences, scale-invariant.

    ``objective="tls"`` minimises ``sum (C a - S b)^2`` over unit ``(C, S)``: the smallest
    eigenvector of ``sum [a, -b]^T [a, -b]``, in closed form
    ``alpha = atan2(2 sum ab, sum (b^2 - a^2))``. ``objective="sampson"`` (default) then
    reweights every correspondence by its Sampson denominator at the current angle and
    re-solves (``iterations`` times), then polishes with secant steps on the exact derivative:
    the result is the minimum of the summed squared Sampson distances. Neither is dragged towards ``alpha = 0`` the way an algebraic fit with
    the unnormalised ``E(alpha)`` (zero at 0) is.

    Parameters
    ----------
    q_a, q_b : ndarray of shape (N, 2)
        Normalised coordinates in the first and second view.
    weights : ndarray of shape (N,), optional
        Non-negative per-correspondence weights.
    polish : bool
        Finish the Sampson fit with the secant steps (skip inside loops that refit again).

    Returns
    -------
    float or FailedEstimation
        The angle in radians in (-pi, pi], or a falsy failure when the correspondences carry
        no information (none, or all on the degenerate row).
    """
    x, y, xp, yp = _split(q_a, q_b)
    if x.size == 0:
        return FailedEstimation("no correspondences to fit")
    a = y - yp
    b = xp * y + x * yp
    w = np.ones_like(a) if weights is None else np.asarray(weights, dtype=np.float64)
    ab, bb_aa, energy = (w * a * b).sum(), (w * (b * b - a * a)).sum(), (w * (a * a + b * b)).sum()
    if not energy > 1e-300:
        return FailedEstimation("degenerate correspondences: all lie on the principal row (a = b = 0)")
    alpha = float(np.arctan2(2.0 * ab, bb_aa))
    if objective == "tls":
        return alpha
    if objective != "sampson":
        raise ValueError(f"objective must be 'sampson' or 'tls', got {objective!r}")
    for _ in range(iterations):
        ws = w * _sampson_weights(alpha, x, y, xp, yp)
        alpha = float(np.arctan2(2.0 * (ws * a * b).sum(), (ws * (b * b - a * a)).sum()))
    # Reweighting ignores how the Sampson denominator changes with alpha, so its fixed point is
    # a hair (~1e-6 rad) off the minimum; a few secant steps on the exact derivative land on it.
    step = 1e-7
    for _ in range(3 if polish else 0):
        slope = _sampson_cost_derivative(alpha, w, a, b, x, y, xp, yp)
        curvature = (_sampson_cost_derivative(alpha + step, w, a, b, x, y, xp, yp) - slope) / step
        if not curvature > 0:
            break
        delta = slope / curvature
        alpha -= delta
        if abs(delta) < 1e-13:
            break
    return float(np.arctan2(np.sin(alpha), np.cos(alpha)))


def _sampson_cost_derivative(alpha, w, a, b, x, y, xp, yp) -> float:
    """d/dalpha of sum w (C a - S b)^2 / g(alpha), g the Sampson denominator."""
    c, s = np.cos(alpha / 2.0), np.sin(alpha / 2.0)
    r = c * a - s * b
    dr = -0.5 * (s * a + c * b)
    u, v = s * x + c, c - s * xp
    g = (s * y) ** 2 + u * u + (s * yp) ** 2 + v * v
    dg = s * c * (y * y + yp * yp) + u * (c * x - s) - v * (s + c * xp)
    return float(np.sum(w * (2.0 * r * dr * g - r * r * dg) / (g * g)))


@dataclass(frozen=True)
class CircularMotion:
    """The fitted model: one turntable angle between two views.

    Follows scikit-image's model protocol: :meth:`from_estimate` returns a model or a falsy
    :class:`FailedEstimation`, :meth:`residuals` gives per-correspondence distances.
    """

    angle_rad: float

    @property
    def angle_deg(self) -> float:
        return float(np.rad2deg(self.angle_rad))

    @classmethod
    def from_estimate(cls, q_a: np.ndarray, q_b: np.ndarray, *, weights=None, objective="sampson"):
        """Least-squares model of all given correspondences, see :func:`fit_angle`."""
        alpha = fit_angle(q_a, q_b, weights=weights, objective=objective)
        return alpha if isinstance(alpha, FailedEstimation) else cls(alpha)

    def residuals(self, q_a: np.ndarray, q_b: np.ndarray) -> np.ndarray:
        """Sampson distances of the correspondences, shape (N,), normalised units."""
        return sampson_distance(self.angle_rad, q_a, q_b)

    @property
    def essential_matrix(self) -> np.ndarray:
        return essential_matrix(self.angle_rad)


def wrap_deg(angle_deg):
    """``angle_deg`` wrapped to [-180, 180): the signed turn between two views either way round.

    A pair across the seam of a full turn (view 359 to view 0) turns by one step, not by
    -359 deg; an estimate 359.9 deg from the truth is 0.1 deg off.
    """
    return np.mod(np.asarray(angle_deg, dtype=np.float64) + 180.0, 360.0) - 180.0
