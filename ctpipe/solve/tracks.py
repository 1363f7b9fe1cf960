"""Feature tracks: one 3-D point of the object followed through many views.

A pair estimate says that keypoint ``a`` of view ``i`` and keypoint ``b`` of view ``j`` are the
same point (the RANSAC inliers, ``estimate.inlier_mask`` over ``matches[k].index_ab``). Joining
these verified matches over all pairs (seam pairs of a full turn included) by union-find gives
tracks; a track holding two keypoints of one view joins two different points and is dropped.
Bundle adjustment (:mod:`ctpipe.solve.bundle`) then needs a 3-D point per track
(:func:`triangulate_tracks`); with the adjusted angles and points, :func:`extend_tracks` predicts
every point in the views around its track and attaches the keypoint found there, so tracks grow
beyond the pairs that were matched. :func:`static_tracks` finds tracks that do not move the way
any rigid point at their place in the image would (the silhouette of a rotationally symmetric
container, detector defects); they would pull the angles towards zero.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from ctpipe.data import ScanObservations
from ctpipe.errors import InputError
from ctpipe.geometry import Geometry
from ctpipe.solve.camera import pixels_to_rays, project_points

__all__ = ["Tracks", "build_tracks", "triangulate_tracks", "static_tracks", "extend_tracks",
           "descriptor_distances", "verified_match_distances"]


@dataclass(frozen=True, eq=False)
class Tracks:
    """Observations of object points, grouped by track.

    Observations are sorted by track, then by view; a track has at most one observation per view.

    Attributes
    ----------
    track : ndarray of shape (N,), int64
        Track (object point) of each observation, ``0 .. n_tracks - 1``.
    view : ndarray of shape (N,), int64
        View of each observation.
    keypoint : ndarray of shape (N,), int64
        Index into ``features[view]``; -1 for observations that are not keypoints (synthetic).
    xy_px : ndarray of shape (N, 2), float64
        Observed position ``(x=col, y=row)`` in pixels.
    n_tracks, n_views : int
    """

    track: np.ndarray
    view: np.ndarray
    keypoint: np.ndarray
    xy_px: np.ndarray
    n_tracks: int
    n_views: int

    def __post_init__(self) -> None:
        n = len(self.track)
        for name, shape in (("track", (n,)), ("view", (n,)), ("keypoint", (n,)), ("xy_px", (n, 2))):
            if np.shape(getattr(self, name)) != shape:
                raise InputError(f"Tracks.{name}: must have shape {shape}, got {np.shape(getattr(self, name))}")
        if n and (self.track.min() < 0 or self.track.max() >= self.n_tracks):
            raise InputError(f"Tracks.track: must index 0..{self.n_tracks - 1}, got {self.track.min()}..{self.track.max()}")
        if n and (self.view.min() < 0 or self.view.max() >= self.n_views):
            raise InputError(f"Tracks.view: must index views 0..{self.n_views - 1}, got {self.view.min()}..{self.view.max()}")
        for name in ("track", "view", "keypoint", "xy_px"):
            getattr(self, name).flags.writeable = False

    @classmethod
    def from_arrays(cls, track, view, xy_px, *, n_views: int, keypoint=None, min_length: int = 2) -> "Tracks":
        """Tracks from observation arrays in any order (tracks renumbered, short ones dropped).

        Parameters
        ----------
        track, view : array_like of shape (N,), int
        xy_px : array_like of shape (N, 2)
        n_views : int
        keypoint : array_like of shape (N,), int, optional
        min_length : int
            Tracks seen in fewer views are dropped.

        Raises
        ------
        InputError
            A track observed twice in one view, or arrays of different lengths.
        """
        track = np.asarray(track, dtype=np.int64).reshape(-1)
        view = np.asarray(view, dtype=np.int64).reshape(-1)
        xy = np.asarray(xy_px, dtype=np.float64).reshape(-1, 2)
        keypoint = np.full(len(track), -1, np.int64) if keypoint is None else np.asarray(keypoint, np.int64).reshape(-1)
        if not (len(view) == len(xy) == len(keypoint) == len(track)):
            raise InputError(f"Tracks: track, view, xy_px and keypoint must have one row per observation, got "
                             f"{len(track)}, {len(view)}, {len(xy)} and {len(keypoint)}")
        order = np.lexsort((view, track))
        track, view, xy, keypoint = track[order], view[order], xy[order], keypoint[order]
        if np.any((np.diff(track) == 0) & (np.diff(view) == 0)):
            raise InputError("Tracks: a track has two observations in one view")
        _, renumbered = np.unique(track, return_inverse=True)
        lengths = np.bincount(renumbered) if len(track) else np.zeros(0, np.int64)
        keep = lengths[renumbered] >= min_length if len(track) else np.zeros(0, bool)
        _, renumbered = np.unique(renumbered[keep], return_inverse=True)
        return cls(renumbered.astype(np.int64).reshape(-1), view[keep], keypoint[keep], xy[keep],
                   int(renumbered.max() + 1) if keep.any() else 0, int(n_views))

    def __len__(self) -> int:
        return len(self.track)

    @property
    def lengths(self) -> np.ndarray:
        """Views each track is seen in, shape (n_tracks,), int64."""
        return np.bincount(self.track, minlength=self.n_tracks).astype(np.int64)

    def select(self, keep, *, min_length: int = 2) -> "Tracks":
        """The observations where ``keep`` (shape (N,), bool) holds, short tracks dropped."""
        keep = np.asarray(keep, dtype=bool)
        if keep.shape != self.track.shape:
            raise InputError(f"keep: must have one flag per observation {self.track.shape}, got {keep.shape}")
        return Tracks.from_arrays(self.track[keep], self.view[keep], self.xy_px[keep], n_views=self.n_views,
                                  keypoint=self.keypoint[keep], min_length=min_length)

    def select_tracks(self, keep_tracks) -> "Tracks":
        """Only the tracks where ``keep_tracks`` (shape (n_tracks,), bool) holds, renumbered in order."""
        keep_tracks = np.asarray(keep_tracks, dtype=bool)
        if keep_tracks.shape != (self.n_tracks,):
            raise InputError(f"keep_tracks: must have one flag per track ({self.n_tracks},), got {keep_tracks.shape}")
        return self.select(keep_tracks[self.track], min_length=1)

    def summary(self) -> dict:
        """Counts for a report: tracks, observations, median and maximum length."""
        lengths = self.lengths
        return {"tracks": int(self.n_tracks), "observations": int(len(self)),
                "median_track_length": float(np.median(lengths)) if lengths.size else 0.0,
                "max_track_length": int(lengths.max()) if lengths.size else 0}


def verified_match_distances(observations: ScanObservations) -> np.ndarray:
    """Descriptor distances of the verified matches (inliers of successful pairs), shape (M,)."""
    distances = [m.distance[e.inlier_mask] for m, e in zip(observations.matches, observations.estimates) if e]
    return np.concatenate(distances).astype(np.float64) if distances else np.zeros(0)


def build_tracks(observations: ScanObservations, *, min_length: int = 2) -> Tracks:
    """Join the verified matches of all pairs into tracks.

    Every keypoint ``(view, index)`` is a node, every inlier match of a successful pair an edge;
    the connected components are the tracks. A component with two keypoints in one view is a
    conflict (two points chained together by a wrong match) and is dropped whole.

    Parameters
    ----------
    observations : ScanObservations
        Needs ``features`` (one per view); with none (e.g. a refiner given only normalised
        points) there are no tracks.
    min_length : int
        Drop tracks seen in fewer views.

    Returns
    -------
    Tracks
    """
    if not isinstance(min_length, (int, np.integer)) or min_length < 2:
        raise InputError(f"min_length: must be an integer >= 2, got {min_length!r}")
    n_views = observations.n_views
    empty = Tracks.from_arrays([], [], np.zeros((0, 2)), n_views=n_views)
    if len(observations.features) != n_views:
        return empty
    counts = np.array([len(f) for f in observations.features], dtype=np.int64)
    offsets = np.concatenate([[0], np.cumsum(counts)])
    ends_a, ends_b = [], []
    for (i, j), matches, estimate in zip(observations.pairs, observations.matches, observations.estimates):
        if not estimate:
            continue
        index = matches.index_ab[estimate.inlier_mask]
        ends_a.append(offsets[i] + index[:, 0])
        ends_b.append(offsets[j] + index[:, 1])
    if not ends_a or not sum(len(a) for a in ends_a):
        return empty
    a, b = np.concatenate(ends_a), np.concatenate(ends_b)
    n_nodes = int(offsets[-1])
    graph = sp.coo_matrix((np.ones(len(a)), (a, b)), shape=(n_nodes, n_nodes))
    _, labels = connected_components(graph, directed=False)
    nodes = np.unique(np.concatenate([a, b]))
    views = np.searchsorted(offsets, nodes, side="right") - 1
    track = labels[nodes]
    order = np.lexsort((views, track))
    nodes, views, track = nodes[order], views[order], track[order]
    clash = (np.diff(track) == 0) & (np.diff(views) == 0)
    bad = np.zeros(labels.max() + 1, bool)
    bad[track[1:][clash]] = True
    keep = ~bad[track]
    nodes, views, track = nodes[keep], views[keep], track[keep]
    keypoint = nodes - offsets[views]
    xy = np.zeros((len(nodes), 2))
    for v in np.unique(views):
        at = views == v
        xy[at] = observations.features[v].xy[keypoint[at]]
    return Tracks.from_arrays(track, views, xy, n_views=n_views, keypoint=keypoint, min_length=min_length)


def triangulate_tracks(tracks: Tracks, angles_rad, geometry: Geometry, *, tilt_rad: float = 0.0) -> np.ndarray:
    """Linear least-squares 3-D point of every track from its observations and the view angles.

    Each observation ``(x_n, y_n)`` at angle ``theta`` gives two linear equations in ``X``,
    ``(R_0 - x_n R_2) X = x_n SOD`` and ``(R_1 - y_n R_2) X = y_n SOD`` (rows ``R_k`` of
    :func:`ctpipe.model.rotation_matrix`). A tiny ridge towards the rotation axis keeps tracks
    whose depth the views cannot fix (all seen from one angle) finite.

    Parameters
    ----------
    tracks : Tracks
    angles_rad : ndarray of shape (n_views,)
        Observations in views with a NaN angle are ignored.
    geometry : Geometry
    tilt_rad : float

    Returns
    -------
    ndarray of shape (n_tracks, 3)
        Object-frame points in mm.
    """
    angles = np.asarray(angles_rad, dtype=np.float64)
    if angles.shape != (tracks.n_views,):
        raise InputError(f"angles_rad: must have one angle per view ({tracks.n_views},), got {angles.shape}")
    theta = angles[tracks.view]
    ok = np.isfinite(theta)
    rays = pixels_to_rays(tracks.xy_px, geometry, tilt_rad=tilt_rad)
    xn, yn = rays[:, 0], rays[:, 1]
    c, s = np.cos(np.where(ok, theta, 0.0)), np.sin(np.where(ok, theta, 0.0))
    sod = geometry.source_to_object_mm
    rows = np.stack([np.stack([c - xn * s, np.zeros_like(c), -s - xn * c], axis=1),
                     np.stack([-yn * s, np.ones_like(c), -yn * c], axis=1)], axis=1)  # (N, 2, 3)
    rhs = np.stack([xn * sod, yn * sod], axis=1)
    rows = rows * ok[:, None, None]
    rhs = rhs * ok[:, None]
    normal = np.zeros((tracks.n_tracks, 3, 3))
    np.add.at(normal, tracks.track, np.einsum("nki,nkj->nij", rows, rows))
    right = np.zeros((tracks.n_tracks, 3))
    np.add.at(right, tracks.track, np.einsum("nki,nk->ni", rows, rhs))
    ridge = 1e-9 * np.maximum(np.trace(normal, axis1=1, axis2=2), 1e-300)
    normal += ridge[:, None, None] * np.eye(3)
    return np.linalg.solve(normal, right[:, :, None])[:, :, 0]


def _circular_offsets_rad(theta: np.ndarray, reference: np.ndarray) -> np.ndarray:
    return np.angle(np.exp(1j * (theta - reference)))


def static_tracks(tracks: Tracks, angles_rad, geometry: Geometry, *, tilt_rad: float = 0.0,
                  min_motion_px: float = 1.0, static_fraction: float = 0.5) -> np.ndarray:
    """Tracks that stay put in the image where any rigid point would have moved.

    A rigid point at normalised image position ``(x_n, y_n)`` moves vertically by
    ``dy_n = -x_n y_n dtheta`` whatever its depth (it comes closer to the source on one side of
    the axis). For each track a rigid point at its mean image position (on the plane through the
    axis) is turned through the track's views; when that point would move vertically by at least
    ``min_motion_px`` (RMS about its mean) and the track's own vertical motion is less than
    ``static_fraction`` of it, the track is static: a silhouette edge of a rotationally
    symmetric container, a detector defect, a ring.

    Parameters
    ----------
    tracks : Tracks
    angles_rad : ndarray of shape (n_views,)
        Current view angles (the pair graph's are good enough).
    geometry : Geometry
    tilt_rad : float
    min_motion_px : float
        Tracks whose expected motion is smaller cannot be told from rigid ones and are kept.
    static_fraction : float
        A track moving less than this share of the expected motion is static.

    Returns
    -------
    ndarray of shape (n_tracks,), bool
    """
    angles = np.asarray(angles_rad, dtype=np.float64)
    if angles.shape != (tracks.n_views,):
        raise InputError(f"angles_rad: must have one angle per view ({tracks.n_views},), got {angles.shape}")
    if tracks.n_tracks == 0:
        return np.zeros(0, bool)
    counts = np.maximum(tracks.lengths, 1)
    theta = angles[tracks.view]
    finite = np.isfinite(theta)
    theta = np.where(finite, theta, 0.0)
    first = np.zeros(tracks.n_tracks)
    first[tracks.track[::-1]] = theta[::-1]  # the track's first observation (sorted by view)
    offset = _circular_offsets_rad(theta, first[tracks.track])
    reference = first + np.bincount(tracks.track, offset, tracks.n_tracks) / counts
    mean_xy = np.stack([np.bincount(tracks.track, tracks.xy_px[:, k], tracks.n_tracks) for k in (0, 1)], axis=1) / counts[:, None]
    rays = pixels_to_rays(mean_xy, geometry, tilt_rad=tilt_rad)
    sod = geometry.source_to_object_mm
    camera = np.stack([rays[:, 0] * sod, rays[:, 1] * sod, np.zeros(tracks.n_tracks)], axis=1)
    c, s = np.cos(reference), np.sin(reference)
    # Object point X = R(reference)^T (P) for P on the plane through the axis.
    point = np.stack([c * camera[:, 0] + s * camera[:, 2], camera[:, 1], -s * camera[:, 0] + c * camera[:, 2]], axis=1)
    expected_v = project_points(point[tracks.track], theta, geometry, tilt_rad=tilt_rad)[:, 1]

    def rms_about_mean(values):
        mean = np.bincount(tracks.track, values, tracks.n_tracks) / counts
        return np.sqrt(np.bincount(tracks.track, (values - mean[tracks.track]) ** 2, tracks.n_tracks) / counts)

    expected = rms_about_mean(expected_v)
    observed = rms_about_mean(tracks.xy_px[:, 1])
    return (expected >= min_motion_px) & (observed < static_fraction * expected)


def descriptor_distances(a: np.ndarray, b: np.ndarray, norm: str) -> np.ndarray:
    """Row-wise distance between two descriptor arrays in the features' norm.

    Parameters
    ----------
    a, b : ndarray of shape (N, D)
        float32 for ``L2``/``L1``, packed uint8 bits for ``HAMMING``/``HAMMING2``.
    norm : str
        One of :data:`ctpipe.data.DESCRIPTOR_NORMS`.

    Returns
    -------
    ndarray of shape (N,), float64
        As OpenCV's matchers report them (``HAMMING2`` counts differing 2-bit cells).
    """
    if norm == "L2":
        return np.sqrt(np.sum((a.astype(np.float64) - b) ** 2, axis=1))
    if norm == "L1":
        return np.sum(np.abs(a.astype(np.float64) - b), axis=1)
    if norm == "HAMMING":
        return np.unpackbits(np.bitwise_xor(a, b), axis=1).sum(axis=1).astype(np.float64)
    if norm == "HAMMING2":
        x = np.bitwise_xor(a, b)
        cells = (x & 0x55) | ((x >> 1) & 0x55)
        return np.unpackbits(cells, axis=1).sum(axis=1).astype(np.float64)
    raise InputError(f"norm: {norm!r} is not supported. Try one of L2, L1, HAMMING, HAMMING2")


def extend_tracks(tracks: Tracks, features, geometry: Geometry, angles_rad, points_mm, *, tilt_rad: float = 0.0,
                  radius_px: float = 1.5, max_descriptor_distance: float = np.inf, window_views: int = 8,
                  wrap: bool = False, merge: bool = True) -> tuple[Tracks, np.ndarray, dict]:
    """Grow tracks with the keypoints found where their 3-D points project in nearby views.

    For every track and every view within ``window_views`` of one of its observations (and not
    yet in it), the track's point is projected with the current angles and the nearest keypoint
    of that view within ``radius_px`` is looked up; it counts when its descriptor is within
    ``max_descriptor_distance`` of the track's observation in the nearest view.

    * A keypoint of no track is attached (claimed by several tracks: the nearest prediction wins).
    * A keypoint of another track is evidence that both are one point seen in views the matched
      pairs did not bridge. With ``merge``, two tracks are joined when at least two such hits
      link them (in either direction) and the joined track has no two keypoints in one view.

    Parameters
    ----------
    tracks : Tracks
        Observations with keypoint indices (``keypoint >= 0``).
    features : sequence of Features, one per view
    geometry : Geometry
    angles_rad : ndarray of shape (n_views,)
        Views with a NaN angle are not searched.
    points_mm : ndarray of shape (n_tracks, 3)
        Current 3-D point of every track (object frame).
    tilt_rad : float
    radius_px : float
        Largest distance from the prediction, pixels.
    max_descriptor_distance : float
        Largest descriptor distance (in the features' norm) to the reference observation.
    window_views : int
        How far (in views) beyond its observations a track is searched.
    wrap : bool
        Views form a full turn: view ``n_views - 1`` neighbours view 0.
    merge : bool
        Join tracks that turn out to be one point.

    Returns
    -------
    tracks : Tracks
        The extended tracks, renumbered when tracks were merged.
    points_mm : ndarray of shape (n_tracks', 3)
        A start point for every returned track (the longest merged track's).
    stats : dict
        ``attached`` observations and ``merged`` tracks (how many tracks disappeared in merges).
    """
    angles = np.asarray(angles_rad, dtype=np.float64)
    points = np.asarray(points_mm, dtype=np.float64)
    n_views = tracks.n_views
    if len(features) != n_views:
        raise InputError(f"features: must have one Features per view ({n_views}), got {len(features)}")
    if angles.shape != (n_views,):
        raise InputError(f"angles_rad: must have one angle per view ({n_views},), got {angles.shape}")
    if points.shape != (tracks.n_tracks, 3):
        raise InputError(f"points_mm: must have shape ({tracks.n_tracks}, 3), got {points.shape}")
    if np.any(tracks.keypoint < 0):
        raise InputError("tracks: extension needs keypoint indices, got observations with keypoint -1")
    if not (radius_px > 0):
        raise InputError(f"radius_px: must be > 0, got {radius_px!r}")
    nothing = {"attached": 0, "merged": 0}
    if len(tracks) == 0:
        return tracks, points, nothing
    steps = np.arange(-int(window_views), int(window_views) + 1)
    candidate_views = (tracks.view[:, None] + steps[None, :]).ravel()
    candidate_tracks = np.repeat(tracks.track, len(steps))
    if wrap:
        candidate_views = np.mod(candidate_views, n_views)
    else:
        inside = (candidate_views >= 0) & (candidate_views < n_views)
        candidate_views, candidate_tracks = candidate_views[inside], candidate_tracks[inside]
    key = np.unique(candidate_tracks * n_views + candidate_views)
    existing = tracks.track * n_views + tracks.view  # sorted: observations are ordered by track, view
    key = key[~np.isin(key, existing, assume_unique=True)]
    cand_track, cand_view = key // n_views, key % n_views
    ok = np.isfinite(angles[cand_view])
    cand_track, cand_view = cand_track[ok], cand_view[ok]
    if cand_track.size == 0:
        return tracks, points, nothing
    predicted = project_points(points[cand_track], angles[cand_view], geometry, tilt_rad=tilt_rad)
    # The reference observation: the track's observation nearest in view index.
    position = np.searchsorted(existing, cand_track * n_views + cand_view)
    before = np.clip(position - 1, 0, len(existing) - 1)
    after = np.clip(position, 0, len(existing) - 1)
    far = np.iinfo(np.int64).max
    gap_before = np.where(tracks.track[before] == cand_track, np.abs(cand_view - tracks.view[before]), far)
    gap_after = np.where(tracks.track[after] == cand_track, np.abs(tracks.view[after] - cand_view), far)
    reference = np.where(gap_before <= gap_after, before, after)

    # Every keypoint of the scan by one global index.
    counts = np.array([len(f) for f in features], dtype=np.int64)
    offsets = np.concatenate([[0], np.cumsum(counts)])
    owner = np.full(offsets[-1], -1, np.int64)
    owner[offsets[tracks.view] + tracks.keypoint] = tracks.track
    hit_candidate, hit_keypoint, hit_distance = [], [], []
    order = np.argsort(cand_view, kind="stable")
    bounds = np.searchsorted(cand_view[order], np.arange(n_views + 1))
    for v in range(n_views):
        chosen = order[bounds[v]:bounds[v + 1]]
        if chosen.size == 0 or counts[v] == 0:
            continue
        xy = predicted[chosen]
        chosen, xy = chosen[np.all(np.isfinite(xy), axis=1)], xy[np.all(np.isfinite(xy), axis=1)]
        distance, nearest = cKDTree(features[v].xy.astype(np.float64)).query(xy, distance_upper_bound=radius_px)
        hit = np.isfinite(distance)
        hit_candidate.append(chosen[hit])
        hit_keypoint.append(offsets[v] + nearest[hit])
        hit_distance.append(distance[hit])
    if not hit_candidate or not sum(len(h) for h in hit_candidate):
        return tracks, points, nothing
    hit_candidate, hit_keypoint = np.concatenate(hit_candidate), np.concatenate(hit_keypoint)
    hit_distance = np.concatenate(hit_distance)
    descriptors = np.concatenate([f.descriptors for f in features])
    ref = reference[hit_candidate]
    similar = descriptor_distances(descriptors[hit_keypoint], descriptors[offsets[tracks.view[ref]] + tracks.keypoint[ref]],
                                   features[0].norm) <= max_descriptor_distance
    hit_candidate, hit_keypoint, hit_distance = hit_candidate[similar], hit_keypoint[similar], hit_distance[similar]
    hit_track, hit_owner = cand_track[hit_candidate], owner[hit_keypoint]

    # Free keypoints: one keypoint, one track, the nearest prediction wins.
    free = hit_owner < 0
    f_track, f_keypoint, f_distance = hit_track[free], hit_keypoint[free], hit_distance[free]
    order = np.lexsort((f_distance, f_keypoint))
    first = np.ones(order.size, bool)
    first[1:] = np.diff(f_keypoint[order]) != 0
    f_track, f_keypoint = f_track[order[first]], f_keypoint[order[first]]
    f_view = np.searchsorted(offsets, f_keypoint, side="right") - 1
    track = np.concatenate([tracks.track, f_track])
    view = np.concatenate([tracks.view, f_view])
    keypoint = np.concatenate([tracks.keypoint, f_keypoint - offsets[f_view]])

    merged = 0
    if merge and np.any(~free):
        a, b = np.minimum(hit_track[~free], hit_owner[~free]), np.maximum(hit_track[~free], hit_owner[~free])
        link, n_hits = np.unique(a * tracks.n_tracks + b, return_counts=True)
        link = link[n_hits >= 2]
        if link.size:
            graph = sp.coo_matrix((np.ones(link.size), (link // tracks.n_tracks, link % tracks.n_tracks)),
                                  shape=(tracks.n_tracks, tracks.n_tracks))
            _, label = connected_components(graph, directed=False)
            # A joined track may not hold two keypoints of one view: such components stay apart.
            obs_label = label[track]
            o = np.lexsort((view, obs_label))
            clash = (np.diff(obs_label[o]) == 0) & (np.diff(view[o]) == 0)
            bad = np.zeros(tracks.n_tracks, bool)
            bad[obs_label[o][1:][clash]] = True
            label = np.where(bad[label], tracks.n_tracks + np.arange(tracks.n_tracks), label)
            merged = tracks.n_tracks - np.unique(label).size
            track = label[track]
    member_length = tracks.lengths
    xy = np.concatenate([tracks.xy_px, _features_xy(features, offsets, f_keypoint)])
    extended = Tracks.from_arrays(track, view, xy, n_views=n_views, keypoint=keypoint, min_length=1)
    # Map each final track to its longest member's point.
    old_label = np.empty(tracks.n_tracks, np.int64)
    old_label[tracks.track] = track[:len(tracks.track)]
    _, final_index = np.unique(old_label, return_inverse=True)
    best = np.full(extended.n_tracks, -1, np.int64)
    by_length = np.argsort(member_length, kind="stable")
    best[final_index[by_length]] = by_length  # the longest member is written last
    return extended, points[best], {"attached": int(f_track.size), "merged": int(merged)}


def _features_xy(features, offsets: np.ndarray, global_keypoint: np.ndarray) -> np.ndarray:
    """Pixel positions of keypoints given by their index into the scan's concatenated features, shape (N, 2)."""
    if global_keypoint.size == 0:
        return np.zeros((0, 2))
    view = np.searchsorted(offsets, global_keypoint, side="right") - 1
    xy = np.zeros((global_keypoint.size, 2))
    for v in np.unique(view):
        at = view == v
        xy[at] = features[v].xy[global_keypoint[at] - offsets[v]]
    return xy
