"""Submap matching (thesis 6.1): keypoints and suitability of single submaps (6.1.1),
pairing and prioritisation of submap pairs (eq. 6.1-6.4), and the pairwise matching
pipeline (6.1.2): 3D descriptors, correspondences, Hough voting into hypotheses,
RANSAC with the two-point gravity-aligned solver (eq. 6.5-6.7), plausibility checks,
ICP restricted to x, y, z and yaw, and a covariance from the ICP residual. The
variants of 8.1.2 are :class:`MatchMode`: 6D (3-point RANSAC and 6D ICP, 10 deg / 1 deg
roll-pitch thresholds) and 4D+6D (the 4D alignment, refined by a 6D ICP).

Keypoints (:class:`KeypointSelection`) are the thesis's obstacle points (6.1.1), or
points of salient local geometry: a surface variation (Pauly et al. 2002: the smallest
eigenvalue of the neighbourhood's scatter over their sum) above a threshold that
persists at twice the neighbourhood (Rusu et al. 2008's persistence over scales), so that
rough ground, ridges and crater rims can be matched where no obstacle was classified
(the lesson of 9.3), or both.

Choices where the thesis used PCL:

- Descriptors (:class:`Descriptor`) are Open3D's FPFH (Rusu et al. 2009) on the full
  cloud, taken at the cloud point nearest each keypoint and scaled to unit L2 norm; the
  thesis used PCL's CSHOT, which no maintained Python library offers. FPFH describes the
  same spherical neighbourhood (radius ``descriptor_radius_m``) by histograms of normal
  angles. Normals are oriented to +z, which both gravity-aligned submaps share. Or, ours,
  spin images about the gravity axis (:mod:`slam.spin_images`): yaw-invariant as the 4D
  matching needs, without normals or reference frames.
- Voting (:class:`Voting`, ``slam/voting.py``): the thesis's Hough3D (Tombari and Di
  Stefano 2010, as PCL's ``Hough3DGrouping``) with SHOT's local reference frames
  (Tombari et al. 2010: the eigenvectors of the distance-weighted neighbourhood scatter,
  signs towards the majority of neighbours), run in both directions (6.1.2, the asymmetry
  of translation and rotation); or, ours, a sweep over yaw that votes in the 4D space of
  gravity-aligned transformations and needs no reference frames, over the yaws the
  plausibility checks can accept and optionally (``MatcherParams.sweep_within_prior``)
  only for the translations they can accept.
- The plausibility checks bound the yaw as well as the translation (ours; the thesis
  bounds the translation): both against the graph's relative sigmas and the match's own
  combined, the match's yaw sigma being its translation sigma over the lever of its
  matched points.
- Optionally (``MatcherParams.icp_from_prior``, ours) a second ICP starts at the graph's
  prediction of the pair, and the match keeps whichever ICP ends at the lower truncated
  cost: on smooth ground the best hypothesis can lie in another basin of nearly the same
  cost, 0.1-0.6 m from the truth, where the graph's prediction lies in the right one.

Only numpy, scipy and open3d (``slam`` stays free of simulator code).
"""

from __future__ import annotations

import heapq
import math
import time
from dataclasses import dataclass, field
from enum import StrEnum

import numpy as np
from scipy.spatial import cKDTree

from slam.lie import gravity_aligned, roll_pitch, wrap_angle, yaw_of
from slam.registration import IcpResult, Photometric, horizontal_radius, icp, intensity_gradients, off_line_count, ransac
from slam.spin_images import vertical_spin_images
from slam.submap import Submap, voxel_filter
from slam.voting import hough3d, yaw_sweep

SubmapKey = tuple[str, int]  # (robot, submap index)
PairKey = tuple[SubmapKey, SubmapKey]  # sorted


class MatcherException(ValueError):
    """Bad parameters or input to the matcher."""


class MatchMode(StrEnum):
    """Dimensionality of initial alignment and refinement (thesis 6.1.2, 8.1.2)."""

    FOUR_D = "4d"  # 2-point gravity-aligned RANSAC and x, y, z, yaw ICP
    SIX_D = "6d"  # 3-point SVD RANSAC and 6D ICP, roll/pitch checked afterwards
    FOUR_SIX_D = "4d+6d"  # 2-point gravity-aligned RANSAC and 4D ICP, then 6D ICP, roll/pitch checked afterwards


class KeypointSelection(StrEnum):
    """Which points of a submap become keypoints (6.1.1; 9.3 for the geometry)."""

    OBSTACLES = "obstacles"  # the obstacle classification's points (thesis)
    GEOMETRY = "geometry"  # points whose surface variation reaches min_surface_variation
    BOTH = "both"


class Descriptor(StrEnum):
    """The keypoints' 3D descriptors (6.1.2 feature generation)."""

    FPFH = "fpfh"  # Open3D's FPFH, a stand-in for the thesis's CSHOT
    SPIN = "spin"  # ours: spin images about the gravity axis (slam/spin_images.py), yaw-invariant


class Voting(StrEnum):
    """How correspondences are clustered into hypotheses (6.1.2; ``slam/voting.py``)."""

    HOUGH3D = "hough3d"  # the thesis: Hough3D with SHOT local reference frames, both directions
    YAW_SWEEP = "yaw_sweep"  # ours: every yaw of a grid, translation votes, no reference frames


class MatchPoints(StrEnum):
    """Which of a submap's points the ICP refinement aligns (6.1.2)."""

    ALL = "all"  # the whole cloud, out to the mapping range (SubmapParams.max_depth_error_m)
    # only the points within the obstacle classification's range (Submap.classified): stereo depth error
    # grows with z^2 (eq. 5.2c), and so does the depth bias of a stereo calibration error, which distorts
    # two robots' far points differently (docs/matching.md, "Calibration bias and the ICP's points")
    CLASSIFIED = "classified"


@dataclass(frozen=True)
class MatcherParams:
    mode: MatchMode = MatchMode.FOUR_D
    # suitability and keypoints (6.1.1)
    keypoints: KeypointSelection = KeypointSelection.OBSTACLES  # as the thesis; geometry and both measured in docs/matching.md
    min_points: int = 1000
    min_selected_points: int = 100  # thesis: 100 obstacle points; here of the keypoint selection
    saliency_radius_m: float = 0.2  # neighbourhood of the surface variation (geometry keypoints)
    min_surface_variation: float = 0.03  # lambda_min / sum(lambda) of that neighbourhood; a plane has 0, isotropic scatter 1/3
    # ... and it must persist at twice the radius (Rusu et al. 2008): stereo noise on flat ground at 3-4 m reaches 0.03 at
    # 0.2 m but averages out at 0.4 m, rock flanks stay salient (docs/matching.md, "Mapping range")
    min_surface_variation_wide: float = 0.02
    # salient keypoints (not obstacle ones) thinned to the most salient per cell of this size: in the realistic world
    # stereo noise leaves much of the ground weakly salient, thousands of keypoints per submap unthinned (docs/matching.md)
    salient_spacing_m: float = 0.2
    keypoint_resolution_m: float = 0.1
    min_known_fraction: float = 0.5  # of the voxels in the descriptor sphere (thesis 0.8; see docs/matching.md)
    line_distance_m: float = 0.5
    min_off_line_keypoints: int = 10
    # pairing (eq. 6.1-6.4)
    min_overlap_m2: float = 2.0
    alpha: float = 0.125
    stereo_error_m: float = 0.12  # right side of eq. 6.3 (thesis: LRU at 4 m); see docs/matching.md
    # features and correspondences
    descriptor: Descriptor = Descriptor.FPFH
    descriptor_radius_m: float = 0.4
    # > 0: the descriptors on the cloud voxel-filtered at this size (normals averaged per voxel). FPFH takes at most
    # 100 neighbours within descriptor_radius_m; on the submaps' 5 cm clouds they reach about 0.17 m, on a 0.1 m
    # thinning about 0.4 m (docs/matching.md, "Descriptors on a thinned cloud")
    descriptor_resolution_m: float = 0.0
    # spin images (descriptor spin): spin_bins distances from the vertical axis in [0, spin_radius_m] by spin_bins heights
    # in [-spin_height_m, spin_height_m]; on Etna's submaps the true partner of a keypoint was among its 3 nearest
    # descriptors for 22 % of the keypoints, against 6-10 % with FPFH (docs/matching.md, "Spin images about the gravity axis")
    spin_radius_m: float = 0.8
    spin_height_m: float = 0.5
    spin_bins: int = 10
    normal_radius_m: float = 0.2  # thesis r = 0.2 m for normals, frames and descriptors
    nearest: int = 3  # most similar features per keypoint, both directions
    # L2 between unit descriptors over its range [0, sqrt 2] (thesis 0.5 for CSHOT); at 0.25 it drops almost no right
    # correspondence of FPFH or spin images (docs/matching.md, "The distance threshold for spin images")
    max_descriptor_distance: float = 0.25
    # voting and RANSAC
    voting: Voting = Voting.HOUGH3D
    hough_bin_m: float = 0.3
    hough_min_votes: int = 5
    max_clusters: int = 8  # per voting direction, largest first
    # the yaw sweep's grid: half a step over a 5 m lever is 9 cm, a third of a bin
    hough_yaw_step_rad: float = math.radians(2.0)
    # ours: the yaw sweep votes only for translations the 2-sigma check can accept (as it sweeps only such yaws), so
    # that peaks the check would reject do not take the places of max_clusters; measured in docs/matching.md
    # ("Voting inside the plausible translations")
    sweep_within_prior: bool = False
    ransac_iterations: int = 100
    ransac_inlier_m: float = 0.2
    # distinct keypoints on each side supporting a hypothesis: the correct closures of the Etna and rock field runs and
    # replays had 12-593, a wrong one 0.58 m off had 7 (docs/matching.md, "Voting without reference frames")
    min_inliers: int = 10
    min_off_line_inliers: int = 3  # matched keypoints off the RANSAC line, in each submap
    max_roll_pitch_initial_rad: float = math.radians(10.0)  # 6D RANSAC only (8.1.2)
    max_roll_pitch_final_rad: float = math.radians(1.0)  # 6D and 4D+6D ICP (8.1.2)
    sigma_bound: float = 2.0  # hypotheses must lie within this many sigmas of the graph (its relative sigmas and theirs combined)
    # a match's own translation sigma in that check, at least: half RANSAC's inlier distance (the ICP residual
    # understates a closure's error: 7-18 cm errors at 4-8 cm RMSE on the rock field and Etna, docs/matching.md)
    hypothesis_sigma_m: float = 0.1
    sigma_scale: float = 1.0  # multiplies the graph's relative sigmas (eq. 6.1-6.4 and the checks)
    # refinement and acceptance
    icp_max_distance_m: float = 0.25
    icp_outlier_m: float = 0.05  # truncation of the ICP's point-to-plane residuals (slam/registration.py icp)
    icp_iterations: int = 40
    icp_point_resolution_m: float = 0.1  # source cloud subsampling for the ICP
    icp_points: MatchPoints = MatchPoints.ALL
    # ours: > 0 adds the points' intensities to the ICP, a coloured ICP (Park, Zhou and Koltun 2017) held to 4D: an
    # intensity residual of 1 (the submap's median intensity) weighs as a point-to-plane residual of this many metres.
    # The ground's relief barely holds x, y and yaw, its texture does (docs/matching.md, "A coloured ICP"); 0: the
    # thesis's geometric ICP
    icp_intensity_scale_m: float = 0.0
    # ours: a second ICP started at the graph's prediction of the pair; the match keeps whichever ends at the lower
    # truncated cost. On smooth ground the hypotheses are ambiguous at 0.1-0.6 m, and the ICP's cost near the truth
    # is no lower than at a wrong hypothesis's end (docs/matching.md, "A second ICP from the graph's prediction")
    icp_from_prior: bool = False
    max_icp_rmse_m: float = 0.1
    min_icp_pairs: int = 300
    roll_pitch_sigma_rad: float = math.radians(0.5)  # 4D ICP: the filter's roll/pitch uncertainty of the origins
    # memory: the submaps matched last whose CloudGeometry a PairQueue keeps; the others' is rebuilt when paired again
    geometry_held: int = 8
    seed: int = 0

    def __post_init__(self):
        try:
            object.__setattr__(self, "mode", MatchMode(self.mode))
        except ValueError:
            raise MatcherException(f"mode must be one of {[m.value for m in MatchMode]}, got {self.mode!r}") from None
        try:
            object.__setattr__(self, "descriptor", Descriptor(self.descriptor))
        except ValueError:
            raise MatcherException(f"descriptor must be one of {[d.value for d in Descriptor]}, got {self.descriptor!r}") from None
        if self.spin_bins < 2:
            raise MatcherException(f"spin_bins must be at least 2, got {self.spin_bins}")
        try:
            object.__setattr__(self, "keypoints", KeypointSelection(self.keypoints))
        except ValueError:
            raise MatcherException(f"keypoints must be one of {[k.value for k in KeypointSelection]}, got {self.keypoints!r}") from None
        try:
            object.__setattr__(self, "voting", Voting(self.voting))
        except ValueError:
            raise MatcherException(f"voting must be one of {[v.value for v in Voting]}, got {self.voting!r}") from None
        try:
            object.__setattr__(self, "icp_points", MatchPoints(self.icp_points))
        except ValueError:
            raise MatcherException(f"icp_points must be one of {[k.value for k in MatchPoints]}, got {self.icp_points!r}") from None
        bad = [
            f"{k}={v}" for k, v in vars(self).items() if isinstance(v, int | float) and not isinstance(v, bool) and (not math.isfinite(v) or v < 0)
        ]
        if bad:
            raise MatcherException(f"matcher parameters must be finite and >= 0: {', '.join(bad)}")
        if self.geometry_held < 2:
            raise MatcherException(f"geometry_held must be at least 2 (the two submaps of a pair), got {self.geometry_held}")
        if self.hough_bin_m <= 0 or not 0 < self.hough_yaw_step_rad <= math.pi:
            raise MatcherException(f"hough_bin_m must be > 0 and hough_yaw_step_rad in (0, pi], got {self.hough_bin_m}, {self.hough_yaw_step_rad}")

    @property
    def ransac_dof(self) -> int:
        """Degrees of freedom of the initial alignment."""
        return 6 if self.mode is MatchMode.SIX_D else 4

    @property
    def dof(self) -> int:
        """Degrees of freedom of the final refinement (and of the match's covariance)."""
        return 4 if self.mode is MatchMode.FOUR_D else 6


# ----------------------------------------------------------------------------- single submaps


@dataclass(frozen=True)
class CloudGeometry:
    """A submap's full cloud as matching uses it (6.1.2): float64 points, their normals
    (+z-oriented) and KD-tree. Most of a prepared submap's memory (56 bytes a point with
    the tree's index, and its nodes, against 12 for the submap's float32 points), so :class:`PairQueue` holds it only
    for the submaps matched last and rebuilds it, the same values, when a submap is
    paired again."""

    cloud: np.ndarray  # (k, 3)
    normals: np.ndarray  # (k, 3)
    tree: cKDTree


@dataclass
class Keypoints:
    """What the pairing thread precomputes per submap (6.1.1); features are added by the
    matching thread when the submap is first in a pair (6.1.2)."""

    key: SubmapKey
    frame_index: int
    points: np.ndarray  # (n, 3) keypoints in the submap frame
    selected_xyz: np.ndarray  # (m, 3) the selected points through the voxel filter, before the known-space filter (bounding boxes)
    source: np.ndarray  # (k, 3) float32: the submap's full point cloud, the submap's own array (not copied)
    classified: np.ndarray  # (k,) the cloud's points within the obstacle classification's range
    descriptors: np.ndarray | None = None  # (n, 33) unit FPFH or (n, spin_bins^2) unit spin images
    frames: np.ndarray | None = None  # (n, 3, 3) local reference frames, rows x, y, z
    geometry: CloudGeometry | None = None  # built by cloud_geometry when matched, released by PairQueue.hold_geometry
    intensity: np.ndarray | None = None  # (k,) uint8: the intensities of source, the submap's own array (coloured ICP)
    intensity_gradients: np.ndarray | None = None  # (k, 3) of the coloured ICP, held and released with geometry


def surface_variation(cloud: np.ndarray, radius: float) -> np.ndarray:
    """Surface variation (Pauly et al. 2002) of each point: the smallest eigenvalue of
    the scatter of its neighbours within ``radius`` over the sum of all three; 0 on a
    plane, larger on ridges, rims, rough ground and rocks, at most 1/3."""
    import open3d as o3d

    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(cloud))
    pcd.estimate_covariances(o3d.geometry.KDTreeSearchParamRadius(radius=radius))
    ev = np.linalg.eigvalsh(np.asarray(pcd.covariances))
    return ev[:, 0] / np.maximum(ev.sum(axis=1), 1e-12)


_SELECTED = {KeypointSelection.OBSTACLES: "obstacle", KeypointSelection.GEOMETRY: "salient", KeypointSelection.BOTH: "obstacle or salient"}


def prepare(submap: Submap, params: MatcherParams) -> Keypoints | str:
    """Suitability check and keypoints of one submap (6.1.1), or the reason it is
    unsuitable: at least ``min_points`` points and ``min_selected_points`` selected
    points. The selection (``params.keypoints``): obstacle points (the thesis), filtered at
    ``keypoint_resolution_m``, or the voxel centroids of :func:`salient_keypoints` (with
    or without the obstacle voxels, counted in voxels). Keypoints are dropped where less
    than ``min_known_fraction`` of the voxels in the descriptor sphere are known; at
    least ``min_off_line_keypoints`` of them must lie farther than ``line_distance_m``
    (xy) from a RANSAC line through them."""
    pts = np.asarray(submap.points, dtype=float)
    if len(pts) < params.min_points:
        return "too few points"
    obstacle = np.asarray(submap.obstacle, dtype=bool)
    if params.keypoints is KeypointSelection.OBSTACLES:
        n = int(obstacle.sum())
        kp = voxel_filter(pts[obstacle], np.ones(n, bool), np.zeros(n), params.keypoint_resolution_m)[0] if n >= params.min_selected_points else None
    else:
        kp = salient_keypoints(pts, obstacle if params.keypoints is KeypointSelection.BOTH else np.zeros(len(pts), bool), params)
    if kp is None:
        return f"too few {_SELECTED[params.keypoints]} points"
    known = submap.voxels.known_fraction(kp, params.descriptor_radius_m)
    points = kp[known >= params.min_known_fraction]
    rng = np.random.default_rng([params.seed, submap.index, len(points)])
    if off_line_count(points, params.line_distance_m, 100, rng) < params.min_off_line_keypoints:
        return "keypoints line-like"
    return Keypoints(submap.key, submap.frame_index, points, kp, submap.points, np.asarray(submap.classified, dtype=bool), intensity=submap.intensity)


def salient_keypoints(pts: np.ndarray, obstacle: np.ndarray, params: MatcherParams) -> np.ndarray | None:
    """Keypoints from the geometry of the whole cloud (the lesson of thesis 9.3), on the
    cloud's ``keypoint_resolution_m`` voxel centroids: every voxel holding an ``obstacle``
    point, and voxels whose :func:`surface_variation` reaches ``min_surface_variation``
    within ``saliency_radius_m`` and ``min_surface_variation_wide`` within twice that
    (persistence over scales, as Rusu et al. 2008 keep features), thinned to the most
    salient (at the wide radius) per ``salient_spacing_m`` cell; None with fewer than
    ``min_selected_points`` such voxels. Surface variation on the voxel centroids rather
    than on every point: a tenth of the time, the same closures (docs/matching.md)."""
    cen, cen_obstacle, _ = voxel_filter(pts, obstacle, np.zeros(len(pts)), params.keypoint_resolution_m)
    wide = surface_variation(cen, 2 * params.saliency_radius_m)
    salient = ~cen_obstacle & (wide >= params.min_surface_variation_wide)
    salient[salient] = surface_variation(cen, params.saliency_radius_m)[salient] >= params.min_surface_variation
    if int(cen_obstacle.sum() + salient.sum()) < params.min_selected_points:
        return None
    idx = np.flatnonzero(salient)
    order = idx[np.argsort(-wide[idx], kind="stable")]
    _, first = np.unique(np.floor(cen[order] / params.salient_spacing_m).astype(np.int64), axis=0, return_index=True)
    keep = cen_obstacle.copy()
    keep[order[first]] = True
    return cen[keep]


def _lrf(cloud: np.ndarray, tree: cKDTree, centers: np.ndarray, radius: float) -> np.ndarray:
    """SHOT local reference frames (Tombari et al. 2010) at ``centers``: rows x, y, z."""
    frames = np.tile(np.eye(3), (len(centers), 1, 1))
    for i, (c, nb) in enumerate(zip(centers, tree.query_ball_point(centers, radius))):
        if len(nb) < 5:
            continue
        d = cloud[nb] - c
        w = radius - np.linalg.norm(d, axis=1)
        M = (d * w[:, None]).T @ d / max(w.sum(), 1e-12)
        vec = np.linalg.eigh(M)[1]
        x, z = vec[:, 2], vec[:, 0]
        if np.sum(d @ x >= 0) < len(d) / 2:
            x = -x
        if np.sum(d @ z >= 0) < len(d) / 2:
            z = -z
        frames[i] = np.stack([x, np.cross(z, x), z])
    return frames


def cloud_geometry(kp: Keypoints, params: MatcherParams) -> CloudGeometry:
    """``kp.geometry``, built first if it was never built or was released: normals from
    the neighbours within ``normal_radius_m`` (at most 40), oriented to +z."""
    if kp.geometry is None:
        import open3d as o3d  # here, not at the top: it takes about a second, and the scenario schema imports MatcherParams

        cloud = np.asarray(kp.source, dtype=float)
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(cloud))
        pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=params.normal_radius_m, max_nn=40))
        pcd.orient_normals_to_align_with_direction(np.array([0.0, 0.0, 1.0]))
        kp.geometry = CloudGeometry(cloud, np.array(pcd.normals), cKDTree(cloud))
    return kp.geometry


def compute_features(kp: Keypoints, params: MatcherParams) -> None:
    """Descriptors (``params.descriptor``) and (Hough3D voting) local reference frames of
    the keypoints (6.1.2 feature generation; computed once per submap, when first
    needed), on the cloud's :func:`cloud_geometry`, or with ``descriptor_resolution_m``
    on its voxel centroids: FPFH at the cloud point nearest each keypoint, or spin
    images about the vertical through the keypoint (:mod:`slam.spin_images`)."""
    if kp.descriptors is not None:
        return
    import open3d as o3d

    g = cloud_geometry(kp, params)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(g.cloud))
    pcd.normals = o3d.utility.Vector3dVector(g.normals)
    tree = g.tree
    if params.descriptor_resolution_m > 0:
        pcd = pcd.voxel_down_sample(params.descriptor_resolution_m)
        pcd.normalize_normals()
        tree = cKDTree(np.asarray(pcd.points))
    if params.descriptor is Descriptor.SPIN:
        kp.descriptors = vertical_spin_images(np.asarray(pcd.points), tree, kp.points, params.spin_radius_m, params.spin_bins, params.spin_height_m)
    else:
        _, nearest = tree.query(kp.points)
        search = o3d.geometry.KDTreeSearchParamHybrid(radius=params.descriptor_radius_m, max_nn=100)
        # only at the keypoints' cloud points (the same values as over the whole cloud, a fraction of the time)
        at, back = np.unique(nearest, return_inverse=True)
        desc = np.asarray(o3d.pipelines.registration.compute_fpfh_feature(pcd, search, at.tolist()).data).T[back]
        kp.descriptors = desc / np.maximum(np.linalg.norm(desc, axis=1, keepdims=True), 1e-12)
    if params.voting is Voting.HOUGH3D:
        kp.frames = _lrf(g.cloud, g.tree, kp.points, params.descriptor_radius_m)


def correspondences(a: Keypoints, b: Keypoints, params: MatcherParams) -> np.ndarray:
    """(n, 2) keypoint index pairs (a, b): the ``nearest`` most similar descriptors of
    each keypoint in the other submap, both directions, duplicates removed, L2 distance
    (scaled to [0, 1]) at most ``max_descriptor_distance`` (6.1.2)."""
    k = min(params.nearest, len(a.points), len(b.points))
    if k == 0:
        return np.zeros((0, 2), int)
    pairs = []
    for src, dst, flip in ((a, b, False), (b, a, True)):
        dist, idx = cKDTree(dst.descriptors).query(src.descriptors, k=k)
        dist, idx = dist.reshape(len(src.points), k), idx.reshape(len(src.points), k)
        ok = dist / math.sqrt(2) <= params.max_descriptor_distance
        i = np.repeat(np.arange(len(src.points)), k)[ok.ravel()]
        j = idx.ravel()[ok.ravel()]
        pairs.append(np.column_stack([j, i] if flip else [i, j]))
    return np.unique(np.vstack(pairs), axis=0)


# ----------------------------------------------------------------------------- pairwise matching


@dataclass(frozen=True)
class Prior:
    """The graph's current estimate of ``T_a_b`` and its relative standard deviations
    ``sigma_xyz`` (m, in ``a``'s frame) and ``sigma_yaw`` (rad; None: yaw unchecked) for
    the 2-sigma plausibility checks (6.1.2)."""

    T_a_b: np.ndarray
    sigma_xyz: np.ndarray
    sigma_yaw: float | None = None


@dataclass
class MatchResult:
    """Outcome of one pairwise attempt: ``T_a_b`` and its 6x6 covariance ([rotation,
    translation], right perturbation) on success, else the reason; stage wall times."""

    a: SubmapKey
    b: SubmapKey
    T_a_b: np.ndarray | None = None
    cov: np.ndarray | None = None
    reason: str = ""
    inliers: int = 0
    hypotheses: int = 0
    correspondences: int = 0
    icp: IcpResult | None = None
    start: str = ""  # where the kept ICP started: "hypothesis", or "prior" (MatcherParams.icp_from_prior)
    timings: dict[str, float] = field(default_factory=dict)

    @property
    def success(self) -> bool:
        return self.T_a_b is not None

    @property
    def reached_icp(self) -> bool:
        """Whether a hypothesis passed the checks and the ICP ran on it, whatever its outcome
        (6.1.2): the attempts the thesis's ICP time applies to (8.4)."""
        return "icp" in self.timings


def _within(T: np.ndarray, prior: Prior | None, bound: float, sigma_xyz: np.ndarray | float, sigma_yaw: float) -> bool:
    """The plausibility check of 6.1.2: ``T``'s translation within ``bound`` sigmas of the graph's. Both are
    estimates, so the sigma of their difference is that of the graph and that of ``T`` (``sigma_xyz``) combined;
    the graph's alone rejects correct closures whenever it is more certain than the match. Ours: the yaw too
    (``sigma_yaw``, T's), where the prior has a yaw sigma; a translation check alone let hypotheses 10-34 deg off
    through on Etna (docs/matching.md, "Voting without reference frames")."""
    if prior is None:
        return True
    if prior.sigma_yaw is not None and abs(wrap_angle(yaw_of(T[:3, :3]) - yaw_of(prior.T_a_b[:3, :3]))) > _yaw_bound(prior, bound, sigma_yaw):
        return False
    return bool(np.all(np.abs(T[:3, 3] - prior.T_a_b[:3, 3]) <= _translation_bound(prior, bound, sigma_xyz)))


_MIN_LEVER_M = 0.5  # the shortest lever a translation sigma is turned into a yaw sigma over


def _yaw_sigma(sigma_m: float, lever_m: float) -> float:
    """A translation sigma turned into a yaw sigma over ``lever_m`` (at least ``_MIN_LEVER_M``)."""
    return sigma_m / max(lever_m, _MIN_LEVER_M)


def _translation_bound(prior: Prior, bound: float, sigma_xyz: np.ndarray | float) -> np.ndarray:
    """The largest offset per axis from ``prior``'s translation the plausibility check accepts (a match's sigmas
    ``sigma_xyz``)."""
    return bound * np.hypot(prior.sigma_xyz, sigma_xyz)


def _yaw_bound(prior: Prior, bound: float, sigma_yaw: float) -> float:
    """The largest yaw offset from ``prior`` the plausibility check accepts (a match's yaw sigma ``sigma_yaw``)."""
    return bound * math.hypot(prior.sigma_yaw, sigma_yaw)


def _clusters(a: Keypoints, b: Keypoints, corr: np.ndarray, params: MatcherParams, prior: Prior | None) -> list[np.ndarray]:
    """The voting of 6.1.2 (``params.voting``): clusters of indices into ``corr``. The yaw sweep covers only the
    yaws the plausibility checks can accept (``prior``'s yaw sigma and the hypothesis's at the shortest lever), and
    with ``params.sweep_within_prior`` only the translations they can accept, widened by a vote bin (a cluster's
    neighbourhood; RANSAC refits its translation)."""
    if params.voting is Voting.YAW_SWEEP:
        window = t_window = None
        if prior is not None and prior.sigma_yaw is not None:  # the yaws _within can accept, at the shortest lever
            window = (yaw_of(prior.T_a_b[:3, :3]), _yaw_bound(prior, params.sigma_bound, _yaw_sigma(params.hypothesis_sigma_m, 0.0)))
        if prior is not None and params.sweep_within_prior:  # the translations _within can accept, a bin wider
            t_window = (prior.T_a_b[:3, 3], _translation_bound(prior, params.sigma_bound, params.hypothesis_sigma_m) + params.hough_bin_m)
        grid = (params.hough_bin_m, params.hough_yaw_step_rad, params.hough_min_votes, params.max_clusters)
        return yaw_sweep(a.points, b.points, corr, *grid, window, t_window)
    votes = (params.hough_bin_m, params.hough_min_votes, params.max_clusters)
    return hough3d(a.points, a.frames, b.points, b.frames, corr, *votes) + hough3d(b.points, b.frames, a.points, a.frames, corr[:, ::-1], *votes)


def _icp_points(kp: Keypoints, params: MatcherParams) -> np.ndarray | slice:
    """Index of the points of the cloud the ICP aligns (``params.icp_points``); the
    whole cloud as a slice, so that it is not copied."""
    return kp.classified if params.icp_points is MatchPoints.CLASSIFIED else slice(None)


def _normalised_intensity(kp: Keypoints) -> np.ndarray:
    """The cloud's intensities over the submap's median: the robots' exposures differ, and
    so do one robot's from submap to submap (auto-exposure)."""
    if kp.intensity is None:
        raise MatcherException(f"submap {kp.key} has no intensities: the coloured ICP needs them (Keypoints from prepare)")
    c = np.asarray(kp.intensity, dtype=float)
    return c / max(float(np.median(c)), 1.0)


def _photometric(a: Keypoints, b_intensity: np.ndarray, params: MatcherParams) -> Photometric:
    """The coloured ICP's intensity term (``params.icp_intensity_scale_m``) for submap a's
    ICP points and the source's voxel intensities; a's gradients computed over its whole
    cloud once, kept and released with its geometry (:meth:`PairQueue.hold_geometry`)."""
    g = cloud_geometry(a, params)
    c = _normalised_intensity(a)
    if a.intensity_gradients is None:
        a.intensity_gradients = intensity_gradients(g.cloud, g.normals, c, g.tree)
    m = _icp_points(a, params)
    return Photometric(c[m], a.intensity_gradients[m], b_intensity, params.icp_intensity_scale_m)


def _refine(
    source: np.ndarray, a: Keypoints, T0: np.ndarray, dof: int, params: MatcherParams, photometric: Photometric | None = None
) -> IcpResult | None:
    m = _icp_points(a, params)
    g = cloud_geometry(a, params)
    tree = g.tree if params.icp_points is MatchPoints.ALL else None
    return icp(
        source,
        g.cloud[m],
        g.normals[m],
        T0,
        dof,
        params.icp_max_distance_m,
        params.icp_iterations,
        min_pairs=params.min_icp_pairs,
        tree=tree,
        outlier_m=params.icp_outlier_m,
        photometric=photometric,
    )


def _refine_best(
    source: np.ndarray, a: Keypoints, starts: dict[str, np.ndarray], dof: int, params: MatcherParams, photometric: Photometric | None = None
) -> tuple[IcpResult | None, str]:
    """The ICP from each of ``starts`` (named); the result with the lowest truncated cost per point
    (``IcpResult.cost``: the same source and target, so comparable) and its start's name, the first on ties; None
    and "" where every ICP had too little overlap."""
    fits = [(fit, name) for name, T0 in starts.items() if (fit := _refine(source, a, T0, dof, params, photometric)) is not None]
    return min(fits, key=lambda f: f[0].cost) if fits else (None, "")


def match_pair(a: Keypoints, b: Keypoints, params: MatcherParams, prior: Prior | None = None) -> MatchResult:
    """Thesis 6.1.2 for one pair: ``T_a_b`` mapping points of ``b`` into ``a``."""
    res = MatchResult(a.key, b.key)
    rng = np.random.default_rng([params.seed, *(ord(c) for c in a.key[0]), a.key[1], *(ord(c) for c in b.key[0]), b.key[1]])
    t0 = time.perf_counter()
    compute_features(a, params)
    compute_features(b, params)
    t1 = time.perf_counter()
    corr = correspondences(a, b, params)
    res.correspondences = len(corr)
    t2 = time.perf_counter()
    clusters = _clusters(a, b, corr, params, prior)
    t3 = time.perf_counter()
    res.timings.update(features=t1 - t0, correspondences=t2 - t1, hough=t3 - t2)
    best = None
    seen: set[tuple] = set()
    for members in clusters:
        key = tuple(np.sort(members))
        if key in seen:
            continue
        seen.add(key)
        pa, pb = a.points[corr[members, 0]], b.points[corr[members, 1]]
        found = ransac(pa, pb, params.ransac_dof, params.ransac_inlier_m, params.ransac_iterations, rng, ids=corr[members])
        if found is None:
            continue
        ia, ib = np.unique(corr[members[found.inliers], 0]), np.unique(corr[members[found.inliers], 1])
        support = min(len(ia), len(ib))
        T = found.T_a_b
        if support < params.min_inliers:
            continue
        if params.ransac_dof == 6 and max(map(abs, roll_pitch(T[:3, :3]))) > params.max_roll_pitch_initial_rad:
            continue
        sigma_yaw = _yaw_sigma(params.hypothesis_sigma_m, horizontal_radius(a.points[ia]))  # over the matched points' lever
        if not _within(T, prior, params.sigma_bound, params.hypothesis_sigma_m, sigma_yaw):
            continue
        off_line = min(off_line_count(a.points[ia], params.line_distance_m, 50, rng), off_line_count(b.points[ib], params.line_distance_m, 50, rng))
        if off_line < params.min_off_line_inliers:
            continue
        res.hypotheses += 1
        if best is None or support > best[1]:
            best = (T, support)
    t4 = time.perf_counter()
    res.timings["ransac"] = t4 - t3
    if best is None:
        res.reason = "no hypothesis"
        return res
    res.inliers = best[1]
    if a.geometry is None:  # released since a's features were computed (PairQueue.hold_geometry)
        cloud_geometry(a, params)
        res.timings["geometry"] = time.perf_counter() - t4
    t5 = time.perf_counter()
    cloud_b = np.asarray(b.source[_icp_points(b, params)], dtype=float)
    coloured = params.icp_intensity_scale_m > 0
    intensity_b = _normalised_intensity(b)[_icp_points(b, params)] if coloured else np.zeros(len(cloud_b))
    source, _, source_intensity = voxel_filter(cloud_b, np.zeros(len(cloud_b), bool), intensity_b, params.icp_point_resolution_m)
    photometric = _photometric(a, source_intensity, params) if coloured else None
    starts = {"hypothesis": best[0]}
    if params.icp_from_prior and prior is not None:  # 4D: the prediction's yaw and translation, as a hypothesis's
        starts["prior"] = prior.T_a_b if params.ransac_dof == 6 else gravity_aligned(prior.T_a_b)
    fit, res.start = _refine_best(source, a, starts, params.ransac_dof, params, photometric)
    if fit is not None and params.mode is MatchMode.FOUR_SIX_D:  # 8.1.2's 4D+6D: the 4D result refined in 6D
        fit = _refine(source, a, fit.T_a_b, 6, params, photometric)
    res.timings["icp"] = time.perf_counter() - t5
    res.icp = fit
    if fit is None:
        res.reason = "icp: too little overlap"
        return res
    T = fit.T_a_b
    if fit.rmse_m > params.max_icp_rmse_m:
        res.reason = "icp: residual too large"
    elif params.dof == 6 and max(map(abs, roll_pitch(T[:3, :3]))) > params.max_roll_pitch_final_rad:
        res.reason = "roll/pitch"
    else:
        cov = match_covariance(fit, params)
        sigma_t = np.maximum(np.sqrt(np.diag(cov)[3:]), params.hypothesis_sigma_m)
        if _within(T, prior, params.sigma_bound, sigma_t, _yaw_sigma(float(sigma_t.max()), fit.overlap_radius_m)):
            res.T_a_b, res.cov = T, cov
        else:
            res.reason = "outside 2 sigma"
    return res


def match_covariance(fit: IcpResult, params: MatcherParams) -> np.ndarray:
    """6x6 covariance ([rotation, translation]) of a match from its ICP residual (6.1.2:
    approximated from the point-to-point RMSE of the final alignment): the RMSE as the
    standard deviation of each translation axis, the RMSE over the overlap's horizontal
    radius for yaw; roll and pitch from ``roll_pitch_sigma_rad`` (4D: fixed at zero by
    construction, so only the origins' own roll/pitch errors remain) or as yaw (6D)."""
    s_t = max(fit.rmse_m, 1e-3)
    s_yaw = _yaw_sigma(s_t, fit.overlap_radius_m)
    s_rp = params.roll_pitch_sigma_rad if params.dof == 4 else s_yaw
    return np.diag(np.square([s_rp, s_rp, s_yaw, s_t, s_t, s_t]))


# ----------------------------------------------------------------------------- pairing


@dataclass(frozen=True)
class Candidate:
    """A queued pair (6.1.1) with its overlap (eq. 6.2), relative sigmas and score (eq. 6.4)."""

    pair: PairKey
    overlap_m2: float
    sigma_xyz: np.ndarray
    score: float
    sigma_yaw: float | None = None  # rad, relative yaw (ours: the checks bound the yaw too)


def pair_key(a: SubmapKey, b: SubmapKey) -> PairKey:
    return (a, b) if a <= b else (b, a)


def _box(kp: Keypoints, S: np.ndarray) -> np.ndarray:
    xy = kp.selected_xyz @ S[:3, :3].T[:, :2] + S[:2, 3]
    return np.concatenate([xy.min(axis=0), xy.max(axis=0)])


def evaluate_pair(ka: Keypoints, kb: Keypoints, S_a: np.ndarray, S_b: np.ndarray, cov_ab: np.ndarray, params: MatcherParams) -> Candidate | str:
    """Eq. 6.1-6.4 for two submaps with origins ``S_a``, ``S_b`` in the map and the 6x6
    covariance of ``S_a^-1 S_b`` (right perturbation); the candidate or why not."""
    if ka.key[0] == kb.key[0] and abs(ka.key[1] - kb.key[1]) == 1:
        return "consecutive"
    R = S_b[:3, :3]
    cov_t = params.sigma_scale**2 * cov_ab[3:, 3:]
    sigma = np.sqrt(np.maximum(np.diag(R @ cov_t @ R.T), 0.0))  # in the map frame
    ba, bb = _box(ka, S_a), _box(kb, S_b)
    overlap = np.minimum(ba[2:], bb[2:]) - np.maximum(ba[:2], bb[:2]) + 2 * sigma[:2]  # eq. 6.1
    if np.any(overlap <= 0) or overlap[0] * overlap[1] <= params.min_overlap_m2:  # eq. 6.2
        return "no overlap"
    if sigma.mean() < params.stereo_error_m:  # eq. 6.3
        return "already certain"
    area = float(overlap[0] * overlap[1])
    R_a = S_a[:3, :3]
    return Candidate(
        pair_key(ka.key, kb.key),
        area,
        np.sqrt(np.maximum(np.diag(R_a.T @ R @ cov_t @ R.T @ R_a), 0.0)),
        params.alpha * area + float(sigma.sum()),
        params.sigma_scale * math.sqrt(max(cov_ab[2, 2], 0.0)),
    )


class PairQueue:
    """The pairing thread's state (6.1.1, fig. 6.1): prepared submaps, pairs attempted by
    any robot of the team, and the priority queue of candidates (eq. 6.4, highest
    first). The queue is rebuilt from the latest graph estimate by :meth:`refresh`.
    Every prepared submap stays pairable for the whole run, but only the
    ``geometry_held`` matched last keep their :class:`CloudGeometry` (:meth:`hold_geometry`)."""

    def __init__(self, params: MatcherParams):
        self.params = params
        self.prepared: dict[SubmapKey, Keypoints] = {}
        self.unsuitable: dict[SubmapKey, str] = {}
        self.attempted: set[PairKey] = set()
        self.rejected: dict[str, int] = {}
        self._heap: list[tuple[float, PairKey, Candidate]] = []
        self._held: dict[SubmapKey, None] = {}  # submaps with a CloudGeometry, matched last at the end

    def add(self, submap: Submap) -> Keypoints | str:
        if submap.key in self.prepared or submap.key in self.unsuitable:
            return self.prepared.get(submap.key) or self.unsuitable[submap.key]
        kp = prepare(submap, self.params)
        if isinstance(kp, str):
            self.unsuitable[submap.key] = kp
        else:
            self.prepared[submap.key] = kp
        return kp

    def mark_attempted(self, pair: PairKey) -> None:
        self.attempted.add(pair)

    def hold_geometry(self, pair: PairKey) -> None:
        """After matching ``pair``: its two submaps are the latest matched; release the
        geometry of those beyond the ``geometry_held`` latest."""
        for key in pair:
            self._held.pop(key, None)
            self._held[key] = None
        while len(self._held) > self.params.geometry_held:
            oldest = next(iter(self._held))
            del self._held[oldest]
            self.prepared[oldest].geometry = None
            self.prepared[oldest].intensity_gradients = None

    def open_pairs(self) -> list[PairKey]:
        keys = sorted(self.prepared)
        return [(a, b) for i, a in enumerate(keys) for b in keys[i + 1 :] if (a, b) not in self.attempted]

    def refresh(self, origins: dict[SubmapKey, np.ndarray], covariances: dict[PairKey, np.ndarray]) -> None:
        """Rebuild the queue from the graph's origins and relative covariances."""
        self._heap = []
        self.rejected = {}
        for pair in self.open_pairs():
            a, b = pair
            if a not in origins or b not in origins or pair not in covariances:
                continue
            cand = evaluate_pair(self.prepared[a], self.prepared[b], origins[a], origins[b], covariances[pair], self.params)
            if isinstance(cand, str):
                self.rejected[cand] = self.rejected.get(cand, 0) + 1
            else:
                heapq.heappush(self._heap, (-cand.score, pair, cand))

    def candidates(self) -> list[Candidate]:
        """The queued candidates not yet attempted, best first."""
        return [c for _, pair, c in sorted(self._heap) if pair not in self.attempted]

    def pop(self) -> Candidate | None:
        while self._heap:
            _, pair, cand = heapq.heappop(self._heap)
            if pair not in self.attempted:
                return cand
        return None

    def __len__(self) -> int:
        return sum(1 for _, pair, _ in self._heap if pair not in self.attempted)


__all__ = [
    "Candidate",
    "CloudGeometry",
    "KeypointSelection",
    "Keypoints",
    "MatchMode",
    "MatchResult",
    "MatcherException",
    "MatcherParams",
    "PairQueue",
    "Prior",
    "Voting",
    "cloud_geometry",
    "compute_features",
    "correspondences",
    "evaluate_pair",
    "match_pair",
    "pair_key",
    "prepare",
    "salient_keypoints",
    "surface_variation",
]
