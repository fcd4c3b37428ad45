"""Geometric building blocks of submap matching (thesis 6.1.2): the two-point
gravity-aligned solver (eq. 6.5-6.7), least-squares 4D and 6D alignment of point
pairs, RANSAC over correspondences, the RANSAC line test of the suitability checks
(6.1.1), and point-to-plane ICP restricted to x, y, z and yaw (or full 6D), with a
coloured ICP's intensity rows as an option (ours).

Transforms map points of submap ``b`` into submap ``a``: ``p_a = R p_b + t``, i.e.
``T_a_b`` with ``s_b = s_a (+) T_a_b`` as the graph's ``c`` factor expects. Both
submap origins are gravity-aligned, so a 4D transform is a rotation about z.

Written here rather than taken from Open3D: Open3D's RANSAC and ICP estimate full
6D transforms and cannot hold roll and pitch at zero, which is the point of 6.1.2;
the 6D variants use the same code with all six degrees of freedom, so the 4D/6D
comparison of 8.1.2 differs only in the constraint. Only numpy, scipy and slam/lie.py.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from slam.lie import rot_z, se3, so3_exp

Z = np.array([0.0, 0.0, 1.0])


class RegistrationException(ValueError):
    """Degenerate input to a solver."""


def two_point_4d(p: np.ndarray, q: np.ndarray, p_b: np.ndarray, q_b: np.ndarray) -> np.ndarray | None:
    """Eq. 6.5-6.7: the gravity-aligned transform ``T_a_b`` that maps the pair
    ``(p_b, q_b)`` of submap b onto ``(p, q)`` of submap a. ``R_i`` has the horizontal
    part of ``q_i - p_i``, its cross product with z, and z as columns; ``R = R_0 R_1^T``,
    ``t = p̄_0 - R p̄_1``. None when either pair is (nearly) vertical."""
    frames = []
    for a, b in ((p, q), (p_b, q_b)):
        d = b - a
        d = d - (d @ Z) * Z
        n = np.linalg.norm(d)
        if n < 1e-6:
            return None
        d = d / n
        frames.append(np.column_stack([d, np.cross(d, Z), Z]))
    R = frames[0] @ frames[1].T
    return se3(R, (p + q) / 2 - R @ ((p_b + q_b) / 2))


def fit_4d(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Least-squares ``T_a_b`` with rotation about z only, for paired points (n >= 2):
    the 2D Procrustes yaw of the horizontal parts, translation from the centroids."""
    ca, cb = a.mean(axis=0), b.mean(axis=0)
    da, db = a - ca, b - cb
    s = float(np.sum(db[:, 0] * da[:, 1] - db[:, 1] * da[:, 0]))
    c = float(np.sum(db[:, 0] * da[:, 0] + db[:, 1] * da[:, 1]))
    if abs(s) + abs(c) < 1e-12:
        raise RegistrationException("points have no horizontal extent: yaw undetermined")
    R = rot_z(math.atan2(s, c))
    return se3(R, ca - R @ cb)


def fit_6d(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Least-squares rigid ``T_a_b`` for paired points (n >= 3, not collinear), by SVD
    (Umeyama 1991, without scale)."""
    ca, cb = a.mean(axis=0), b.mean(axis=0)
    H = (b - cb).T @ (a - ca)
    U, S, Vt = np.linalg.svd(H)
    if S[1] < 1e-9 * max(S[0], 1e-12):
        raise RegistrationException("points are collinear: rotation undetermined")
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    return se3(R, ca - R @ cb)


@dataclass(frozen=True)
class RansacResult:
    T_a_b: np.ndarray
    inliers: np.ndarray  # indices into the correspondences


def ransac(
    a: np.ndarray,
    b: np.ndarray,
    dof: int,
    inlier_m: float,
    iterations: int,
    rng: np.random.Generator,
    ids: np.ndarray | None = None,
    min_spread_m: float = 0.3,
) -> RansacResult | None:
    """RANSAC over paired points ``a[i] <-> b[i]``: minimal samples of 2 points with
    :func:`two_point_4d` (``dof=4``) or 3 points with :func:`fit_6d` (``dof=6``), sample
    points at least ``min_spread_m`` apart in both sets; the hypothesis with the most
    support (first found on ties), refitted by least squares on its inliers (distance
    below ``inlier_m``). With ``ids`` (n, 2), the keypoint indices behind each pair,
    support counts distinct keypoints (the smaller of the two sides), so that a clump of
    many-to-one correspondences cannot outvote a spread-out set. None with fewer pairs
    than a sample."""
    k = 2 if dof == 4 else 3
    n = len(a)
    if n < k:
        return None

    def support(inl: np.ndarray) -> int:
        if ids is None:
            return len(inl)
        return min(len(np.unique(ids[inl, 0])), len(np.unique(ids[inl, 1])))

    def spread(pts: np.ndarray) -> bool:
        return all(np.linalg.norm(pts[i] - pts[j]) >= min_spread_m for i in range(k) for j in range(i + 1, k))

    best: np.ndarray | None = None
    best_support = -1
    for _ in range(iterations):
        idx = rng.choice(n, size=k, replace=False)
        if not (spread(a[idx]) and spread(b[idx])):
            continue
        try:
            T = two_point_4d(a[idx[0]], a[idx[1]], b[idx[0]], b[idx[1]]) if dof == 4 else fit_6d(a[idx], b[idx])
        except RegistrationException:
            continue
        if T is None:
            continue
        inl = np.flatnonzero(np.linalg.norm(b @ T[:3, :3].T + T[:3, 3] - a, axis=1) < inlier_m)
        s = support(inl)
        if s > best_support:
            best, best_support = inl, s
    if best is None or len(best) < k:
        return None
    try:
        T = fit_4d(a[best], b[best]) if dof == 4 else fit_6d(a[best], b[best])
    except RegistrationException:
        return None
    inl = np.flatnonzero(np.linalg.norm(b @ T[:3, :3].T + T[:3, 3] - a, axis=1) < inlier_m)
    return RansacResult(T, inl if support(inl) >= best_support else best)


def off_line_count(points: np.ndarray, distance_m: float, iterations: int, rng: np.random.Generator) -> int:
    """Thesis 6.1.1: fit a 3D line to ``points`` by RANSAC (the line with the most points
    within ``distance_m``) and count the points farther than ``distance_m`` from it in
    the xy-plane."""
    n = len(points)
    if n < 2:
        return 0
    best_line, best_in = None, -1
    for _ in range(iterations):
        i, j = rng.choice(n, size=2, replace=False)
        d = points[j] - points[i]
        norm = np.linalg.norm(d)
        if norm < 1e-9:
            continue
        d = d / norm
        r = points - points[i]
        dist = np.linalg.norm(r - np.outer(r @ d, d), axis=1)
        inl = int(np.sum(dist <= distance_m))
        if inl > best_in:
            best_line, best_in = (points[i], d), inl
    if best_line is None:
        return 0
    o, d = best_line
    dxy = d[:2]
    r = (points - o)[:, :2]
    if np.linalg.norm(dxy) < 1e-9:  # a vertical line: xy distance to its foot
        dist = np.linalg.norm(r, axis=1)
    else:
        u = dxy / np.linalg.norm(dxy)
        dist = np.abs(r[:, 0] * u[1] - r[:, 1] * u[0])
    return int(np.sum(dist > distance_m))


@dataclass(frozen=True)
class IcpResult:
    T_a_b: np.ndarray
    rmse_m: float  # point-to-point RMS distance of the final correspondences
    pairs: int
    overlap_radius_m: float  # RMS horizontal distance of the paired points from their centroid
    iterations: int
    converged: bool
    cost: float  # the truncated cost at T_a_b over the source's points (icp), per point: comparable between starts


def _increment(delta: np.ndarray, dof: int) -> np.ndarray:
    """The left increment ``Exp(delta)`` of the ICP: ``delta = (dx, dy, dz, dyaw)`` for
    ``dof=4``, ``(dx, dy, dz, wx, wy, wz)`` for ``dof=6``."""
    return se3(rot_z(delta[3]) if dof == 4 else so3_exp(delta[3:]), delta[:3])


@dataclass(frozen=True)
class Photometric:
    """The intensity term of a coloured ICP (Park, Zhou and Koltun 2017, "Colored point
    cloud registration revisited"): per target point its intensity and its gradient in its
    tangent plane (:func:`intensity_gradients`), per source point its intensity; the
    residual of a pair is ``C_p + d_p . (x - p) - C_x``, ``scale_m`` metres per unit of
    intensity, so that it is truncated and weighted as a point-to-plane residual."""

    target_intensity: np.ndarray  # (k,)
    target_gradients: np.ndarray  # (k, 3), orthogonal to the target normals
    source_intensity: np.ndarray  # (m,)
    scale_m: float


def intensity_gradients(points: np.ndarray, normals: np.ndarray, intensity: np.ndarray, tree: cKDTree, neighbours: int = 16) -> np.ndarray:
    """Per point the gradient of ``intensity`` in its tangent plane (Park et al. 2017,
    eq. 10): least squares over its ``neighbours`` nearest points projected into the plane,
    ``C_q - C_p = d . (q' - p)``, with ``d`` orthogonal to the normal."""
    k = min(neighbours, len(points))
    _, nb = tree.query(points, k=k)
    helper = np.where(np.abs(normals[:, 2:3]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
    e1 = np.cross(normals, helper)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(normals, e1)
    d = points[nb] - points[:, None, :]  # (n, k, 3)
    u, v = np.einsum("nkj,nj->nk", d, e1), np.einsum("nkj,nj->nk", d, e2)
    dc = intensity[nb] - intensity[:, None]
    a11, a12, a22 = np.sum(u * u, axis=1), np.sum(u * v, axis=1), np.sum(v * v, axis=1)
    b1, b2 = np.sum(u * dc, axis=1), np.sum(v * dc, axis=1)
    det = a11 * a22 - a12 * a12
    ok = det > 1e-12
    det = np.where(ok, det, 1.0)
    g1, g2 = np.where(ok, (a22 * b1 - a12 * b2) / det, 0.0), np.where(ok, (a11 * b2 - a12 * b1) / det, 0.0)
    return g1[:, None] * e1 + g2[:, None] * e2


_HALVINGS = 6  # of a Gauss-Newton step that does not lower the ICP's cost, before the ICP stops


def icp(
    source: np.ndarray,
    target: np.ndarray,
    target_normals: np.ndarray,
    T0: np.ndarray,
    dof: int = 4,
    max_distance_m: float = 0.3,
    iterations: int = 30,
    tolerance: float = 1e-4,
    min_pairs: int = 50,
    tree: cKDTree | None = None,
    outlier_m: float = 0.05,
    photometric: Photometric | None = None,
) -> IcpResult | None:
    """Point-to-plane ICP of ``source`` (submap b) onto ``target`` (submap a, with unit
    normals) from ``T0`` (thesis 6.1.2: refinement on the full clouds). ``dof=4``
    optimises x, y, z and yaw only, the increment applied as ``T <- Exp(delta) T`` with
    ``delta = (dx, dy, dz, dyaw)``, so roll and pitch of ``T0`` are never changed (zero
    for a 4D hypothesis); ``dof=6`` adds roll and pitch.

    The cost is a truncated least squares over *every* source point: ``min(|r|, c)^2``
    with ``r`` its point-to-plane residual to the nearest target point within
    ``max_distance_m`` and ``c = outlier_m``; a point without such a neighbour costs
    ``c^2`` too. A point that leaves the overlap costs as much as an outlier, so the ICP
    cannot lower its cost by sliding the clouds apart, and a point with a large residual
    pulls no more than one outside. Gauss-Newton steps on the inliers (weights 1 inside
    ``c``, 0 outside) are taken only where they lower this cost, halved up to
    ``_HALVINGS`` times otherwise (the thesis adapted PCL's Levenberg-Marquardt ICP, which
    likewise rejects steps that raise its cost); the ICP stops (converged) when none does
    or the cost falls by less than ``tolerance`` relatively. A plain ICP on these ground-dominated
    clouds, whose cost is nearly flat in x, y and yaw, wanders: started at the true
    transform it ended more than 0.3 m or 3 deg off on most overlapping revisits
    (docs/matching.md, "The ICP's cost"). With ``photometric`` each pair adds its
    intensity residual as a second row (:class:`Photometric`), truncated and costed alike;
    the RMSE, pairs and overlap are the geometric rows'. None with fewer than ``min_pairs``
    pairs."""
    tree = cKDTree(target) if tree is None else tree
    cap = outlier_m**2

    def evaluate(T: np.ndarray):
        x = source @ T[:3, :3].T + T[:3, 3]
        dist, idx = tree.query(x, distance_upper_bound=max_distance_m)
        ok = np.isfinite(dist)
        x, p, n = x[ok], target[idx[ok]], target_normals[idx[ok]]
        r = np.einsum("ij,ij->i", x - p, n)
        cost = float(np.sum(np.minimum(r * r, cap)) + cap * np.count_nonzero(~ok))
        rows = (x, n, r)  # each row: its point, its residual's gradient over the point, its residual
        if photometric is not None:  # the intensity residuals, in metres, as further rows
            g = photometric.scale_m * photometric.target_gradients[idx[ok]]
            rc = photometric.scale_m * (photometric.target_intensity[idx[ok]] - photometric.source_intensity[ok]) + np.einsum("ij,ij->i", x - p, g)
            cost += float(np.sum(np.minimum(rc * rc, cap)) + cap * np.count_nonzero(~ok))
            rows = (np.vstack([x, x]), np.vstack([n, g]), np.concatenate([r, rc]))
        return cost, x, p, rows

    T = np.array(T0, dtype=float)
    cost, x, p, (xr, n, r) = evaluate(T)
    converged = False
    done = 0
    for it in range(1, iterations + 1):
        done = it
        if len(x) < min_pairs:
            return None
        inl = np.abs(r) < outlier_m
        # d(R x + t)/d[t, w] for a left increment: t -> I, w -> -[x]_x
        J = np.column_stack([n[inl], np.cross(xr[inl], n[inl])])  # [n, x × n]: the rotation columns about x, y, z
        J = J[:, [0, 1, 2, 5]] if dof == 4 else J
        try:
            delta = -np.linalg.solve(J.T @ J + 1e-9 * np.eye(J.shape[1]), J.T @ r[inl])
        except np.linalg.LinAlgError:
            return None
        for _ in range(_HALVINGS):
            T_new = _increment(delta, dof) @ T
            new = evaluate(T_new)
            if new[0] < cost:
                break
            delta = delta / 2
        else:
            converged = True
            break
        decrease = (cost - new[0]) / max(cost, 1e-300)
        T, (cost, x, p, (xr, n, r)) = T_new, new
        if decrease < tolerance:
            converged = True
            break
    if len(x) < min_pairs:
        return None
    rmse = float(np.sqrt(np.mean(np.sum((x - p) ** 2, axis=1))))
    return IcpResult(T, rmse, len(x), horizontal_radius(x), done, converged, cost / len(source))


def horizontal_radius(points: np.ndarray) -> float:
    """RMS horizontal distance of ``points`` from their centroid: the lever over which a
    translation error becomes a yaw error."""
    return float(np.sqrt(np.mean(np.sum((points[:, :2] - points[:, :2].mean(axis=0)) ** 2, axis=1))))
