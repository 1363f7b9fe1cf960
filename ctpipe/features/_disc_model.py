"""The blurred projected-disc model of the ball finder and its least-squares solver.

A ball of radius ``r`` projects to the chord profile ``sqrt(1 - d^2 / r^2)`` (height 1), cut into
cells of about ``_CELL_PX`` tied to its centre; a Gaussian PSF and the pixel box are integrated
over each cell in closed form, so the model of one disc is separable (``A Wy C Wx^T``) and
exactly symmetric about its centre. :class:`_Window` is the least-squares problem of one window
(a plane, a shared PSF sigma, one or more discs), :func:`_levenberg_marquardt` solves it.
Used by :mod:`ctpipe.features.balls`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ctpipe._shared.jit import FASTMATH, njit

# Cells the disc is sampled on in the model, px (exactly integrated, so only the shape's fidelity
# depends on it, not the centre's symmetry).
_CELL_PX = 0.4
_MAX_CELLS = 96
_CELL_SAMPLES = 4


class _Disc:
    """One disc's cells: edges in units of its radius, and the chord profile (height 1) on them,
    each cell's mean over ``_CELL_SAMPLES^2`` points (so a cell the rim cuts holds its share)."""

    def __init__(self, r0: float):
        # Cells of _CELL_PX up to _MAX_CELLS across: a large disc's rim still falls on cells of a
        # small fraction of its radius, and the cost (cells^2 per pixel row) stays bounded.
        n = min(max(int(math.ceil(2.0 * r0 / _CELL_PX)), 8), _MAX_CELLS)
        self.edges = np.linspace(-1.0, 1.0, n + 1)
        offsets = (np.arange(_CELL_SAMPLES) + 0.5) / _CELL_SAMPLES
        v = (self.edges[:-1, None] + np.diff(self.edges)[:, None] * offsets[None, :]).ravel()
        chord = np.sqrt(np.clip(1.0 - v[:, None] ** 2 - v[None, :] ** 2, 0.0, None))
        self.chord = chord.reshape(n, _CELL_SAMPLES, n, _CELL_SAMPLES).mean(axis=(1, 3))


def _axis(pixels: np.ndarray, centre: float, radius: float, edges: np.ndarray, sigma: float):
    """Gaussian-PSF x pixel-box weights of each disc cell on each pixel along one axis, and their
    derivatives in centre, radius and sigma; each of shape (pixels, cells).

    Cell m spans ``u in [a_m, a_m+1]``, ``a = centre + radius * edges``. A pixel at x sees
    ``int g(x - u) du`` over it, ``g = E(. + 1/2) - E(. - 1/2)`` the PSF (cdf E, pdf n)
    integrated over the pixel box. With ``F(t) = t E(t) + s^2 n(t)`` (``F'' = n``, ``dF/ds = s n``)
    that integral is a double difference of F at the pixel edges and cell edges.
    """
    return tuple(_axis_kernel(float(pixels[0]), len(pixels), centre + radius * edges, edges, sigma))


@njit(cache=True)
def _axis_kernel(first_pixel, n_pixels, a, edges, sigma):
    n_edges = a.shape[0]
    cdf = np.empty((n_pixels + 1, n_edges))
    pdf = np.zeros((n_pixels + 1, n_edges))
    big_f = np.empty((n_pixels + 1, n_edges))
    reach = 0.5 + 8.0 * sigma  # beyond it E is 0 or 1 and n is 0 to double precision
    scale = 1.0 / (math.sqrt(2.0) * sigma)
    norm = 1.0 / (math.sqrt(2.0 * math.pi) * sigma)
    for i in range(n_pixels + 1):
        x = first_pixel - 0.5 + i
        for m in range(n_edges):
            t = x - a[m]
            if t > reach:
                cdf[i, m] = 1.0
                big_f[i, m] = t
            elif t < -reach:
                cdf[i, m] = 0.0
                big_f[i, m] = 0.0
            else:
                z = t * scale
                e = 0.5 * math.erfc(-z)
                n = norm * math.exp(-z * z)
                cdf[i, m] = e
                pdf[i, m] = n
                big_f[i, m] = t * e + sigma * sigma * n
    n_cells = n_edges - 1
    # Weights, then their derivatives in centre, radius and sigma: the x or y half of _disc_products' arguments.
    out = np.empty((4, n_pixels, n_cells))
    for i in range(n_pixels):
        for m in range(n_cells):
            # D(x - a) = F(x - a + 1/2) - F(x - a - 1/2); dD/dt = g; dD/ds = s (n(+) - n(-))
            d0 = big_f[i + 1, m] - big_f[i, m]
            d1 = big_f[i + 1, m + 1] - big_f[i, m + 1]
            g0 = cdf[i + 1, m] - cdf[i, m]
            g1 = cdf[i + 1, m + 1] - cdf[i, m + 1]
            s0 = pdf[i + 1, m] - pdf[i, m]
            s1 = pdf[i + 1, m + 1] - pdf[i, m + 1]
            out[0, i, m] = d0 - d1
            out[1, i, m] = g1 - g0
            out[2, i, m] = g1 * edges[m + 1] - g0 * edges[m]
            out[3, i, m] = sigma * (s0 - s1)
    return out


@njit(fastmath=FASTMATH, cache=True)
def _disc_products(chord, x_weights, y_weights):  # pragma: no cover - numba
    """The model of one disc and its derivatives, each of shape (rows, cols): ``Wy C Wx^T`` and
    ``Wy C Dx^T`` for the three x derivatives, ``Dy C Wx^T`` for the three y derivatives.

    ``x_weights`` is ``(Wx, Dx_centre, Dx_radius, Dx_sigma)`` of shape (4, cols, cells), likewise
    ``y_weights``. A pixel sees only the cells within the PSF's reach (the weights are exactly zero
    beyond it), so each row of these matrices is a short band: the products run over the bands
    (a few cells per pixel for a large disc) rather than through BLAS over every cell, which
    also keeps them single-threaded under the pipeline's own threads.
    """
    cells = chord.shape[0]
    cols, rows = x_weights.shape[1], y_weights.shape[1]
    x_lo, x_hi = _bands(x_weights)
    y_lo, y_hi = _bands(y_weights)
    # t[k, p, j] = sum_m C[p, m] X_k[j, m]; C is symmetric, so C[m, p] runs along memory.
    t = np.zeros((4, cols, cells))
    for j in range(cols):
        for m in range(x_lo[j], x_hi[j]):
            a0, a1, a2, a3 = x_weights[0, j, m], x_weights[1, j, m], x_weights[2, j, m], x_weights[3, j, m]
            for p in range(cells):
                c = chord[m, p]
                t[0, j, p] += c * a0
                t[1, j, p] += c * a1
                t[2, j, p] += c * a2
                t[3, j, p] += c * a3
    tt = np.ascontiguousarray(t.transpose(0, 2, 1))
    out = np.zeros((7, rows, cols))
    # Only the columns the disc reaches (in a window of several balls, a fraction of them).
    j_first, j_last = cols, 0
    for j in range(cols):
        if x_hi[j] > x_lo[j]:
            j_first = min(j_first, j)
            j_last = j + 1
    for i in range(rows):
        for p in range(y_lo[i], y_hi[i]):
            b0, b1, b2, b3 = y_weights[0, i, p], y_weights[1, i, p], y_weights[2, i, p], y_weights[3, i, p]
            for j in range(j_first, j_last):
                t0 = tt[0, p, j]
                out[0, i, j] += b0 * t0
                out[1, i, j] += b0 * tt[1, p, j]
                out[2, i, j] += b0 * tt[2, p, j]
                out[3, i, j] += b0 * tt[3, p, j]
                out[4, i, j] += b1 * t0
                out[5, i, j] += b2 * t0
                out[6, i, j] += b3 * t0
    return out[0], out[1], out[2], out[3], out[4], out[5], out[6]


@njit(cache=True)
def _bands(weights):  # pragma: no cover - numba
    """Per row of ``weights`` (4, rows, cells), the range of cells where any of the four is nonzero."""
    rows, cells = weights.shape[1], weights.shape[2]
    lo = np.zeros(rows, np.int64)
    hi = np.zeros(rows, np.int64)
    for i in range(rows):
        first, last = cells, -1
        for m in range(cells):
            if (weights[0, i, m] != 0.0 or weights[1, i, m] != 0.0 or weights[2, i, m] != 0.0
                    or weights[3, i, m] != 0.0):
                if first == cells:
                    first = m
                last = m
        lo[i] = first if last >= 0 else 0
        hi[i] = last + 1 if last >= 0 else 0
    return lo, hi


@njit(cache=True)
def _window_model(p, x_first, n_x, y_first, n_y, chords, chord_at, edges, edge_at, plane, full):  # pragma: no cover
    """The model (pixels,) of a window at parameters ``p`` (:class:`_Window`'s), its transposed Jacobian written into
    ``full`` (parameters, pixels). One compiled call per evaluation: the Levenberg-Marquardt fits of a 2000^2 view of
    the mixed ball phantom evaluate windows of one to four discs about 650 times, and calling the kernels and stacking
    their arrays disc by disc from Python added to each evaluation's arithmetic (the same values either way).
    """
    sigma = p[3]
    n_pixels = n_y * n_x
    model = np.zeros(n_pixels)
    d_sigma = np.zeros(n_pixels)
    for j in range(chord_at.shape[0] - 1):
        n = edge_at[j + 1] - edge_at[j] - 1
        chord = chords[chord_at[j]:chord_at[j + 1]].reshape((n, n))
        e = edges[edge_at[j]:edge_at[j + 1]]
        cx, cy, r, amp = p[4 + 4 * j], p[5 + 4 * j], p[6 + 4 * j], p[7 + 4 * j]
        unit, w_c, w_r, w_s, c_w, r_w, s_w = _disc_products(chord, _axis_kernel(x_first, n_x, cx + r * e, e, sigma),
                                                            _axis_kernel(y_first, n_y, cy + r * e, e, sigma))
        unit, w_c, w_r, w_s = unit.ravel(), w_c.ravel(), w_r.ravel(), w_s.ravel()
        c_w, r_w, s_w = c_w.ravel(), r_w.ravel(), s_w.ravel()
        for k in range(n_pixels):
            model[k] += amp * unit[k]
            d_sigma[k] += amp * (s_w[k] + w_s[k])
            full[4 + 4 * j, k] = w_c[k] * amp
            full[5 + 4 * j, k] = c_w[k] * amp
            full[6 + 4 * j, k] = (r_w[k] + w_r[k]) * amp
            full[7 + 4 * j, k] = unit[k]
    for k in range(n_pixels):
        full[0, k], full[1, k], full[2, k], full[3, k] = plane[0, k], plane[1, k], plane[2, k], d_sigma[k]
        model[k] += p[0] * plane[0, k] + p[1] * plane[1, k] + p[2] * plane[2, k]
    return model


class _Window:
    """Least-squares problem of one window of the top-hat image: a plane, a shared PSF sigma and
    one or more discs; pixels outside ``keep`` (other balls, not modelled) carry no weight.

    Parameters: ``[b0, bx, by, sigma]`` then ``[cx, cy, r, A]`` per disc.
    """

    def __init__(self, data: np.ndarray, xs: np.ndarray, ys: np.ndarray, keep: np.ndarray, starts: np.ndarray):
        self.keep = keep.ravel()
        self.data = data.ravel()[self.keep]
        self.xs, self.ys = xs, ys
        discs = [_Disc(r0) for r0 in starts[:, 2]]
        # The discs' cells packed for _window_model: chords and cell edges end to end, where each starts.
        self.chords = np.concatenate([d.chord.ravel() for d in discs])
        self.chord_at = np.cumsum([0] + [d.chord.size for d in discs])
        self.edges = np.concatenate([d.edges for d in discs])
        self.edge_at = np.cumsum([0] + [d.edges.size for d in discs])
        self.n_params = 4 + 4 * len(starts)
        self.all_kept = bool(self.keep.all())
        self.plane_full = np.stack([np.ones(len(ys) * len(xs)), np.tile(xs - xs.mean(), len(ys)),
                                    np.repeat(ys - ys.mean(), len(xs))])

    def start_and_bounds(self, starts: np.ndarray, b0: float):
        """Start vector and (lower, upper) bounds: centres within half a radius (+1 px) of the
        start, radii within a factor 1.5, heights >= 0, PSF sigma in [0.05, max(3, r)] px."""
        x0 = [b0, 0.0, 0.0, 0.8]
        lo = [-np.inf, -np.inf, -np.inf, 0.05]
        hi = [np.inf, np.inf, np.inf, max(3.0, float(starts[:, 2].max()))]
        for cx, cy, r0, height in starts[:, :4]:
            reach = 0.5 * r0 + 1.0
            x0 += [cx, cy, r0, max(height, 1e-12)]
            lo += [cx - reach, cy - reach, r0 / 1.5, 0.0]
            hi += [cx + reach, cy + reach, 1.5 * r0, np.inf]
        lo, hi = np.asarray(lo), np.asarray(hi)
        return np.clip(x0, lo, hi), (lo, hi)

    def _evaluate(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Model (pixels,) and Jacobian (pixels, parameters) at ``p``."""
        model, jac_t = self._evaluate_t(p)
        return model, jac_t.T

    def _evaluate_t(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Model (pixels,) and transposed Jacobian (parameters, pixels), C-contiguous, at ``p``."""
        full = np.empty((self.n_params, len(self.ys) * len(self.xs)))
        model = _window_model(np.asarray(p, dtype=np.float64), float(self.xs[0]), len(self.xs), float(self.ys[0]),
                              len(self.ys), self.chords, self.chord_at, self.edges, self.edge_at, self.plane_full, full)
        if self.all_kept:
            return model, full
        return model[self.keep], np.ascontiguousarray(full[:, self.keep])

    def residuals_and_jacobian(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Residuals (pixels,) and the transposed Jacobian (parameters, pixels) at ``p``."""
        model, jac_t = self._evaluate_t(p)
        return model - self.data, jac_t


@dataclass(frozen=True)
class _Solution:
    """What :func:`_levenberg_marquardt` found: ``x``, half the sum of squares ``cost`` and ``status``
    (0: evaluations ran out, 2: the cost stopped falling, 3: the parameters stopped moving)."""

    x: np.ndarray
    cost: float
    status: int


def _levenberg_marquardt(fun, x0: np.ndarray, bounds, *, max_nfev: int, ftol: float = 1e-7,
                         xtol: float = 1e-8) -> _Solution:
    """Bounded Levenberg-Marquardt on ``fun(x) -> (residuals, transposed jacobian)``.

    A window holds 10^4-10^5 pixels and a handful of parameters, so each step solves the damped
    normal equations (parameters x parameters) instead of factoring the Jacobian as
    ``scipy.optimize.least_squares`` does (its SVD of the tall Jacobian cost more than the model).
    Columns are scaled by their norms (``x_scale="jac"``), steps are clipped to the bounds, and
    the stopping rules are scipy's: the cost falls by less than ``ftol`` of itself, or the step is
    below ``xtol (xtol + |x|)``.
    """
    lo, hi = bounds
    x = np.clip(np.asarray(x0, dtype=np.float64), lo, hi)
    r, jac_t = fun(x)
    cost, nfev = 0.5 * float(r @ r), 1
    damping = 1e-3
    while nfev < max_nfev:
        product = jac_t @ jac_t.T
        scale = np.maximum(np.sqrt(np.diag(product)), 1e-12)
        normal, gradient = product / np.outer(scale, scale), (jac_t @ r) / scale
        diagonal = np.diag(normal).copy()
        while nfev < max_nfev:
            step = -np.linalg.solve(normal + damping * np.diag(np.maximum(diagonal, 1e-12)), gradient) / scale
            x_new = np.clip(x + step, lo, hi)
            if np.linalg.norm(x_new - x) < xtol * (xtol + float(np.linalg.norm(x))):
                return _Solution(x, cost, 3)  # at the minimum: no step lowers the cost any more
            r_new, jac_new = fun(x_new)
            nfev += 1
            cost_new = 0.5 * float(r_new @ r_new)
            if np.isfinite(cost_new) and cost_new < cost:
                break
            damping *= 4.0
        else:
            return _Solution(x, cost, 0)
        moved = float(np.linalg.norm(x_new - x))
        fell = cost - cost_new
        x, r, jac_t, cost = x_new, r_new, jac_new, cost_new
        damping = max(damping / 3.0, 1e-9)
        if fell < ftol * cost:
            return _Solution(x, cost, 2)
        if moved < xtol * (xtol + float(np.linalg.norm(x))):
            return _Solution(x, cost, 3)
    return _Solution(x, cost, 0)


def _window_of(seeds: np.ndarray, shape: tuple[int, int]) -> tuple[int, int, int, int]:
    """Pixel ranges ``(x_lo, x_hi, y_lo, y_hi)`` covering ``1.3 r + 4`` px around every seed."""
    half = 1.3 * seeds[:, 2] + 4.0
    x_lo, x_hi = int(math.floor(np.min(seeds[:, 0] - half))), int(math.ceil(np.max(seeds[:, 0] + half))) + 1
    y_lo, y_hi = int(math.floor(np.min(seeds[:, 1] - half))), int(math.ceil(np.max(seeds[:, 1] + half))) + 1
    return max(x_lo, 0), min(x_hi, shape[1]), max(y_lo, 0), min(y_hi, shape[0])


def _render(balls: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """The model image of fitted balls (rows ``(cx, cy, r, A, psf_sigma)``), without background."""
    image = np.zeros(shape)
    for cx, cy, r, height, sigma in balls.reshape(-1, 5):
        x_lo, x_hi, y_lo, y_hi = _window_of(np.array([[cx, cy, r + 3.0 * sigma]]), shape)
        if x_lo >= x_hi or y_lo >= y_hi:
            continue
        disc = _Disc(r)
        wx = _axis(np.arange(x_lo, x_hi, dtype=np.float64), cx, r, disc.edges, sigma)[0]
        wy = _axis(np.arange(y_lo, y_hi, dtype=np.float64), cy, r, disc.edges, sigma)[0]
        image[y_lo:y_hi, x_lo:x_hi] += height * (wy @ disc.chord @ wx.T)
    return image
