"""Submaps of one robot: a point cloud with obstacle flags and a log-odds voxel grid, partitioning, exchange format
(thesis 5.1.2, 5.1.3, 5.2.1).

Pure module: numpy (numba for the per-voxel sums), on top of ``slam.stereo`` (back-projection, far cut of eq. 5.2c) and ``slam.voxels``
(the voxel grid, eq. 5.5-5.9). Depth images with the filter's camera poses in, finished submaps out.

A submap (5.1.2) is a gravity-aligned origin that coincides with one local frame of the reference filter
(a new submap switches the filter's frame) and two representations in that frame:

- a point cloud at ``point_resolution_m`` (5 cm) with a binary obstacle flag and an intensity per point,
  built with the thesis's two-stage voxel-grid filter (PCL ``VoxelGrid``: the centroid of the points in
  each non-empty voxel, obstacle if any of them is): each image's points are filtered, then merged into
  the submap's cloud and filtered again. The merge here is exact: the cloud keeps, per voxel, the sums
  and the count of every raw point that fell into it (``VoxelSums``), so a cloud point is the centroid of
  all raw points of its voxel, identical to one filter over all images at once. PCL filtering the cloud
  itself would count an old centroid as one point (a running average favouring recent images); the
  voxels and the flags are the same either way. Each point also carries a ``classified`` flag (ours, not
  the thesis's): whether any of its raw points lay within the obstacle classification's range
  (``slam.obstacles.classified_pixels``, 2.4 m for the 320x240 LRU), which is shorter than the cloud's far
  cut (4.0 m); beyond it a point's obstacle flag is unknown rather than "traversable", which a map user
  (navigation, the map scores of ``sim/evaluation/map_quality.py``) must tell apart.
- a log-odds voxel grid at ``voxel_resolution_m`` (10 cm, ``slam.voxels.VoxelGrid``), one beam-model
  update per image with rays from the camera origin.

A new submap starts (5.1.3) when the filter's position standard deviation reaches ``max_position_std_m``
(thesis 0.1 m) or the distance driven since the submap began reaches ``max_distance_m`` (thesis 3.5 or 7 m).
Finished submaps are immutable and are what robots exchange (5.2.1), in the format of ``Submap.to_bytes``.

Ray end points and cost
-----------------------
The voxel grid gets rays to the image's 5 cm centroids (stage one of the point filter), not to every
pixel: with the default resolutions each 10 cm voxel is the union of 2x2x2 cells of 5 cm (both grids are
aligned with the submap origin), so the occupied voxels are exactly those of the raw points, and the rays
differ from raw rays by under 5 cm at their ends (with other resolutions, by under one point cell).
Measured (2-core machine, 2026-11-22) on one 320x240 image of ground and boxes from 1.3 m, tilted 25 deg
down, far cut at 2.54 m (f b = 30.5 px m): 27,840 valid pixels, 1,326 centroids; ``VoxelGrid.integrate``
0.10 s with a ray per pixel, 0.0032 s with the centroids (0.0034 s with its ``discretize=True``).
``SubmapBuilder.integrate`` takes 7.1-7.5 ms per image over a 50-image, 5 m drive (``drive_submap`` in
``tests/test_submap.py``, command there, second pass; 2026-12-05, the same before and after the numba
kernels below); the thesis measured 10 ms on average (8.4).

Size (thesis 8.4: 700 KB on average in LRU Experiment #2): that drive's submap has 19,692 points and
20,020 voxels and encodes to 31.5 KB (149 KB without zlib, of which the voxel grid is 5.8 KB; measured
2026-12-03 with the 4.0 m far cut; the classified flags cost 20 bytes of it, every point being classified
there). The thesis's cameras saw farther (higher resolution, so a farther far cut) and its points carry
RGB; here the far cut of a 320x240 camera keeps the ground up to about 4 m ahead, and points carry one
intensity byte.
"""

from __future__ import annotations

import math
import numbers
import struct
import zlib
from dataclasses import dataclass
from enum import StrEnum
from functools import cached_property

import numba
import numpy as np

from slam.stereo import StereoCalibration, cut_far_points, depth_to_points_at
from slam.voxels import VoxelException, VoxelGrid

_BITS = 21  # per axis in a packed voxel key: +-2^20 voxels, +-52 km at 5 cm
_OFFSET = 1 << (_BITS - 1)


class SubmapException(ValueError):
    """Bad input to submap building, filtering or decoding."""


class PartitionReason(StrEnum):
    """Why a new submap starts (thesis 5.1.3)."""

    POSITION_STD = "position_std"
    DISTANCE = "distance"


# --------------------------------------------------------------------------- voxel-grid filter


@dataclass(frozen=True)
class VoxelSums:
    """Per-voxel sums of a point set on the grid ``floor(p / resolution)``: the exact, mergeable form of the
    PCL voxel-grid filter (thesis 5.1.2). ``keys`` are sorted packed voxel indices; ``tag`` is the tag of
    each voxel's first contributing point (in input order; ``merged`` puts ``self`` first)."""

    resolution: float
    keys: np.ndarray  # (n,) int64, sorted, unique
    xyz: np.ndarray  # (n, 3) float64 sums of positions
    count: np.ndarray  # (n,) int64 raw points per voxel
    obstacle: np.ndarray  # (n,) bool, any point an obstacle
    intensity: np.ndarray  # (n,) float64 sums of intensities
    tag: np.ndarray  # (n,) int64
    classified: np.ndarray  # (n,) bool, any point within the obstacle classification's range

    @classmethod
    def empty(cls, resolution: float) -> VoxelSums:
        e = np.empty
        return cls(resolution, e(0, np.int64), e((0, 3)), e(0, np.int64), e(0, bool), e(0), e(0, np.int64), e(0, bool))

    @classmethod
    def of_points(
        cls,
        points: np.ndarray,
        obstacle: np.ndarray,
        intensity: np.ndarray,
        resolution: float,
        tag: np.ndarray | int = 0,
        classified: np.ndarray | bool = False,
    ) -> VoxelSums:
        """Sums of finite ``points`` (n, 3) with their flags and intensities; ``tag`` and
        ``classified`` per point or one for all."""
        p = np.asarray(points, dtype=float)
        if p.ndim != 2 or p.shape[1] != 3:
            raise SubmapException(f"points must have shape (n, 3), got {p.shape}")
        n = len(p)
        obs = np.asarray(obstacle)
        inten = np.asarray(intensity)
        if obs.shape != (n,) or inten.shape != (n,):
            raise SubmapException(f"obstacle and intensity must have shape ({n},), got {obs.shape} and {inten.shape}")
        if not np.all(np.isfinite(p)):
            raise SubmapException("points must be finite")
        if not (np.isfinite(resolution) and resolution > 0):
            raise SubmapException(f"resolution must be a positive number of metres, got {resolution!r}")
        idx = np.floor(p / resolution).astype(np.int64)
        if n and (idx.min() < -_OFFSET or idx.max() >= _OFFSET):
            raise SubmapException(f"points lie outside the +-{_OFFSET} voxels per axis of a packed key at {resolution} m")
        u = idx + _OFFSET
        keys = (u[:, 0] << (2 * _BITS)) | (u[:, 1] << _BITS) | u[:, 2]
        tags = np.broadcast_to(np.asarray(tag, dtype=np.int64), (n,))
        known = np.asarray(classified, dtype=bool)
        if known.ndim and known.shape != (n,):
            raise SubmapException(f"classified must be one flag or have shape ({n},), got {known.shape}")
        known = np.broadcast_to(known, (n,))
        return cls._reduce(resolution, keys, p, np.ones(n, np.int64), obs.astype(bool), inten.astype(float), tags, known)

    @classmethod
    def _reduce(cls, resolution, keys, xyz, count, obstacle, intensity, tag, classified) -> VoxelSums:
        """Sum rows with equal keys in input order; the first row of each key gives its tag."""
        order = np.argsort(keys, kind="stable")
        fields = _segment_sums(
            keys,
            order,
            np.ascontiguousarray(xyz, dtype=np.float64).reshape(-1, 3),
            np.asarray(count, np.int64),
            np.asarray(obstacle, np.bool_),
            np.asarray(intensity, np.float64),
            np.asarray(tag, np.int64),
            np.asarray(classified, np.bool_),
        )
        return cls(resolution, *fields)

    def merged(self, other: VoxelSums) -> VoxelSums:
        """The sums of both point sets: exactly ``of_points`` of their union (the same float
        sums, ``self`` first), in one pass over the two sorted key lists."""
        if self.resolution != other.resolution:
            raise SubmapException(f"resolutions differ: {self.resolution} and {other.resolution}")
        fields = ("keys", "xyz", "count", "obstacle", "intensity", "tag", "classified")
        return VoxelSums(self.resolution, *_merge_sums(*(getattr(self, f) for f in fields), *(getattr(other, f) for f in fields)))

    @staticmethod
    def union(parts: list[VoxelSums]) -> VoxelSums:
        """The sums of all point sets at once (one reduction; first contributors in list order)."""
        if not parts:
            raise SubmapException("union needs at least one VoxelSums")
        if len({p.resolution for p in parts}) > 1:
            raise SubmapException(f"resolutions differ: {sorted({p.resolution for p in parts})}")

        def cat(name):
            return np.concatenate([getattr(p, name) for p in parts])

        fields = ("keys", "xyz", "count", "obstacle", "intensity", "tag", "classified")
        return VoxelSums._reduce(parts[0].resolution, *(cat(f) for f in fields))

    def __len__(self) -> int:
        return len(self.keys)

    def centroids(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """One point per voxel in key order: (centroids (n, 3) float64, obstacle (n,) bool, mean intensity (n,) float64)."""
        return self.xyz / self.count[:, None], self.obstacle.copy(), self.intensity / self.count


@numba.njit(cache=True, nogil=True)
def _zero_sums(m):
    """Fields of ``m`` voxels' sums (``VoxelSums`` order), zero (keys and tags unset)."""
    keys, tag = np.empty(m, np.int64), np.empty(m, np.int64)
    return keys, np.zeros((m, 3)), np.zeros(m, np.int64), np.zeros(m, np.bool_), np.zeros(m), tag, np.zeros(m, np.bool_)


@numba.njit(cache=True, nogil=True)
def _segment_sums(keys, order, xyz, count, obstacle, intensity, tag, classified):
    """Per-key sums of rows visited in ``order`` (a stable sort of ``keys``): what
    ``np.unique`` with one ``np.bincount`` per field gives, the same float additions in the
    same order, in one pass."""
    n = len(order)
    m = 0
    for i in range(n):
        if i == 0 or keys[order[i]] != keys[order[i - 1]]:
            m += 1
    out_keys, out_xyz, out_count, out_obstacle, out_intensity, out_tag, out_classified = _zero_sums(m)
    j = -1
    for i in range(n):
        r = order[i]
        if i == 0 or keys[r] != keys[order[i - 1]]:
            j += 1
            out_keys[j] = keys[r]
            out_tag[j] = tag[r]
        out_xyz[j, 0] += xyz[r, 0]
        out_xyz[j, 1] += xyz[r, 1]
        out_xyz[j, 2] += xyz[r, 2]
        out_count[j] += count[r]
        out_obstacle[j] |= obstacle[r]
        out_intensity[j] += intensity[r]
        out_classified[j] |= classified[r]
    return out_keys, out_xyz, out_count, out_obstacle, out_intensity, out_tag, out_classified


@numba.njit(cache=True, nogil=True)
def _merge_sums(ka, xa, ca, oa, ia, ta, cla, kb, xb, cb, ob, ib, tb, clb):
    """Two reduced sums (sorted unique keys) merged: rows of equal keys added, ``a``'s tag kept."""
    na, nb = len(ka), len(kb)
    m = na + nb
    i = j = 0
    while i < na and j < nb:
        if ka[i] == kb[j]:
            m -= 1
            i += 1
            j += 1
        elif ka[i] < kb[j]:
            i += 1
        else:
            j += 1
    keys, xyz, count, obstacle, intensity, tag, classified = _zero_sums(m)
    i = j = 0
    for k in range(m):
        take_a = j >= nb or (i < na and ka[i] <= kb[j])
        take_b = i >= na or (j < nb and kb[j] <= ka[i])
        if take_a and take_b:
            keys[k] = ka[i]
            for d in range(3):
                xyz[k, d] = xa[i, d] + xb[j, d]
            count[k] = ca[i] + cb[j]
            obstacle[k] = oa[i] or ob[j]
            intensity[k] = ia[i] + ib[j]
            tag[k] = ta[i]
            classified[k] = cla[i] or clb[j]
            i += 1
            j += 1
        elif take_a:
            keys[k] = ka[i]
            for d in range(3):
                xyz[k, d] = xa[i, d]
            count[k], obstacle[k], intensity[k], tag[k], classified[k] = ca[i], oa[i], ia[i], ta[i], cla[i]
            i += 1
        else:
            keys[k] = kb[j]
            for d in range(3):
                xyz[k, d] = xb[j, d]
            count[k], obstacle[k], intensity[k], tag[k], classified[k] = cb[j], ob[j], ib[j], tb[j], clb[j]
            j += 1
    return keys, xyz, count, obstacle, intensity, tag, classified


def voxel_filter(points: np.ndarray, obstacle: np.ndarray, intensity: np.ndarray, resolution: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """PCL voxel-grid filter (thesis 5.1.2): one point per non-empty voxel of ``floor(p / resolution)``, the
    centroid of its points, obstacle if any of them is, their mean intensity. Sorted by voxel index
    (x, then y, then z). Returns (points (m, 3) float64, obstacle (m,) bool, intensity (m,) float64)."""
    return VoxelSums.of_points(points, obstacle, intensity, resolution).centroids()


# --------------------------------------------------------------------------- parameters


def _positive(v) -> bool:
    return isinstance(v, numbers.Real) and not isinstance(v, bool) and math.isfinite(v) and v > 0


@dataclass(frozen=True)
class SubmapParams:
    """Submap generation and partitioning (thesis 5.1.2, 5.1.3). Defaults after the thesis or the scenario's."""

    point_resolution_m: float = 0.05  # point cloud voxel filter (5.1.2)
    voxel_resolution_m: float = 0.1  # log-odds voxel grid (5.1.2)
    max_depth_error_m: float = 0.15  # far cut: points with Δp_z (eq. 5.2c) above this are dropped
    # Δp of eq. 5.2c for the far cut: the disparity error stereo really has, not the thesis's 0.5 px (which the obstacle
    # thresholds keep). 0.2 px is the 1-sigma SGBM error measured on Etna in the realistic world (docs/matching.md,
    # "Mapping range"); with max_depth_error_m 0.15 m the 320x240 LRU maps to 4.0 m (0.5 px: 2.5 m), as the thesis's 2.5-5 m.
    pixel_error: float = 0.2
    max_position_std_m: float = 0.15  # new submap at this filter position std (5.1.3: 0.1 m)
    max_distance_m: float = 5.0  # new submap after this distance driven in it (5.1.3: 3.5 or 7 m)
    voxel_max_range_m: float | None = None  # rays longer than this only clear free space, up to this range

    def __post_init__(self):
        positive = ("point_resolution_m", "voxel_resolution_m", "max_depth_error_m", "pixel_error", "max_position_std_m", "max_distance_m")
        optional = ("voxel_max_range_m",) if self.voxel_max_range_m is not None else ()
        bad = [f"{k}={getattr(self, k)!r}" for k in positive + optional if not _positive(getattr(self, k))]
        if bad:
            raise SubmapException(f"SubmapParams must be positive finite numbers (voxel_max_range_m may be None): {', '.join(bad)}")


# --------------------------------------------------------------------------- finished submaps

_MAGIC = b"MSMP"
_VERSION = 2
_FLAG_ZLIB = 1
# magic, version, flags, coordinate bytes, robot name length, index, frame index, t_start, t_end, distance, images, points, anchor
_HEADER = struct.Struct("<4sHBBHiidddII3d")
_LENGTH = struct.Struct("<I")
QUANTUM_M = 0.001  # point coordinates are sent in millimetres: error at most 0.5 mm per axis (plus float32 rounding)


def _read_only(a: np.ndarray) -> np.ndarray:
    a = np.array(a, copy=True)
    a.flags.writeable = False
    return a


@dataclass(frozen=True, eq=False)
class Submap:
    """A finished (or snapshot of the active) submap (thesis 5.1.2): everything in its origin's frame, which is
    the filter's local frame ``frame_index`` at the submap's start (gravity-aligned).

    Arrays are read-only copies. ``voxels`` must not be modified (``VoxelGrid`` has no read-only mode);
    merging it into another grid only reads it.
    """

    robot: str
    index: int  # per robot, from 0
    frame_index: int  # the filter's local frame this submap's origin coincides with
    t_start: float
    t_end: float
    points: np.ndarray  # (n, 3) float32
    obstacle: np.ndarray  # (n,) bool
    classified: np.ndarray  # (n,) bool: within the obstacle classification's range (every obstacle point is)
    intensity: np.ndarray  # (n,) uint8
    voxels: VoxelGrid
    images: int  # depth images integrated
    distance_m: float  # distance driven in the submap

    def __post_init__(self):
        points = np.asarray(self.points, dtype=np.float32)
        n = len(points)
        if points.ndim != 2 or points.shape[1] != 3 or not np.all(np.isfinite(points)):
            raise SubmapException(f"points must be finite with shape (n, 3), got {points.shape}")
        shapes = [np.shape(a) for a in (self.obstacle, self.classified, self.intensity)]
        if any(shape != (n,) for shape in shapes):
            raise SubmapException(f"obstacle, classified and intensity must have shape ({n},), got {', '.join(map(str, shapes))}")
        obstacle, classified = np.asarray(self.obstacle, dtype=bool), np.asarray(self.classified, dtype=bool)
        if np.any(obstacle & ~classified):
            raise SubmapException(f"{int(np.sum(obstacle & ~classified))} obstacle points are not classified")
        intensity = np.asarray(self.intensity)
        if intensity.dtype != np.uint8:
            intensity = np.clip(np.rint(intensity), 0, 255).astype(np.uint8)
        if not isinstance(self.voxels, VoxelGrid):
            raise SubmapException(f"voxels must be a VoxelGrid, got {type(self.voxels).__name__}")
        if not (self.t_end >= self.t_start and self.images >= 0 and self.distance_m >= 0):
            raise SubmapException(
                f"need t_end >= t_start, images >= 0, distance_m >= 0; got {self.t_start}, {self.t_end}, {self.images}, {self.distance_m}"
            )
        object.__setattr__(self, "points", _read_only(points))
        object.__setattr__(self, "obstacle", _read_only(obstacle))
        object.__setattr__(self, "classified", _read_only(classified))
        object.__setattr__(self, "intensity", _read_only(intensity))

    @property
    def key(self) -> tuple[str, int]:
        return self.robot, self.index

    def __repr__(self) -> str:
        return (
            f"Submap({self.robot!r}, index={self.index}, frame={self.frame_index}, t={self.t_start:.2f}..{self.t_end:.2f}, "
            f"points={len(self.points)}, voxels={len(self.voxels)}, images={self.images}, distance={self.distance_m:.2f} m)"
        )

    def to_bytes(self, compress: bool = True) -> bytes:
        """Versioned encoding for the exchange between robots (thesis 5.2.1).

        Little-endian: a 74-byte header (magic ``MSMP``, version, flags, coordinate width 2 or 4, robot name
        length, index, frame index, t_start, t_end, distance, images, point count n, float64 anchor), the
        robot name (UTF-8), then ``u32 length + body``: the coordinates as mm offsets from the anchor, int16
        (int32 when an axis spans more than +-32.767 m), column by column, each column delta-coded along the
        point order (modulo 2^16 or 2^32; -30 % after zlib on the synthetic drive), the obstacle flags and
        then the classified flags bit-packed (``np.packbits``), the intensities (uint8); the body is a zlib
        stream when ``compress`` (flag bit 0). Last ``u32 length + VoxelGrid.to_bytes()`` (already
        compressed). Points come back within 0.5 mm per axis (plus float32 rounding), flags and intensities
        exactly, voxel states exactly. Version 2 added the classified flags.
        """
        p = self.points.astype(np.float64)
        anchor = (p.min(axis=0) + p.max(axis=0)) / 2 if len(p) else np.zeros(3)
        q = np.rint((p - anchor) / QUANTUM_M)
        width = 2 if not len(q) or np.abs(q).max() <= np.iinfo(np.int16).max else 4
        if width == 4 and np.abs(q).max() > np.iinfo(np.int32).max:
            raise SubmapException("submap points span more than +-2147 km around their centre")
        deltas = np.diff(q.T.astype(np.int64), axis=1, prepend=0)  # along the key order: small, compresses well
        coords = np.ascontiguousarray(deltas.astype(np.dtype(f"<i{width}")))  # wraps modulo 2^16 (2^32); decoding wraps back
        body = coords.tobytes() + np.packbits(self.obstacle).tobytes() + np.packbits(self.classified).tobytes() + self.intensity.tobytes()
        if compress:
            body = zlib.compress(body, 6)
        name = self.robot.encode("utf-8")
        voxels = self.voxels.to_bytes()
        header = _HEADER.pack(
            _MAGIC, _VERSION, _FLAG_ZLIB if compress else 0, width, len(name), self.index, self.frame_index,
            self.t_start, self.t_end, self.distance_m, self.images, len(p), *anchor,
        )  # fmt: skip
        return b"".join([header, name, _LENGTH.pack(len(body)), body, _LENGTH.pack(len(voxels)), voxels])

    @classmethod
    def from_bytes(cls, data: bytes) -> Submap:
        """Decode ``to_bytes``; raises ``SubmapException`` on anything else."""
        data = bytes(data)
        if len(data) < _HEADER.size:
            raise SubmapException(f"submap data too short for its header: {len(data)} bytes, need {_HEADER.size}")
        magic, version, flags, width, name_len, index, frame_index, t_start, t_end, distance, images, n, *anchor = _HEADER.unpack_from(data)
        if magic != _MAGIC:
            raise SubmapException(f"not submap data: magic {magic!r}, expected {_MAGIC!r}")
        if version != _VERSION:
            raise SubmapException(f"submap data version {version} is not supported (this reader knows {_VERSION})")
        if width not in (2, 4) or flags & ~_FLAG_ZLIB:
            raise SubmapException(f"submap data is corrupt: coordinate width {width} (2 or 4) or unknown flags {flags:#x}")
        pos = _HEADER.size + name_len
        try:
            robot = data[_HEADER.size : pos].decode("utf-8")
        except UnicodeDecodeError as exc:
            raise SubmapException(f"submap robot name is not UTF-8: {exc}") from exc
        if pos > len(data) or not robot:
            raise SubmapException(f"submap data is corrupt: robot name of {name_len} bytes")
        body, pos = _chunk(data, pos, "point data")
        voxel_bytes, pos = _chunk(data, pos, "voxel data")
        if pos != len(data):
            raise SubmapException(f"submap data has {len(data) - pos} trailing bytes")
        if flags & _FLAG_ZLIB:
            try:
                body = zlib.decompress(body)
            except zlib.error as exc:
                raise SubmapException(f"submap point data is corrupt: {exc}") from exc
        n_flags = (n + 7) // 8
        if len(body) != 3 * n * width + 2 * n_flags + n:
            raise SubmapException(f"submap point data has {len(body)} bytes, {n} points need {3 * n * width + 2 * n_flags + n}")
        deltas = np.frombuffer(body, dtype=np.dtype(f"<i{width}"), count=3 * n).reshape(3, n)
        q = np.cumsum(deltas, axis=1, dtype=np.int64).astype(np.dtype(f"<i{width}")).T
        obstacle, classified = (
            np.unpackbits(np.frombuffer(body, np.uint8, n_flags, 3 * n * width + k * n_flags), count=n).astype(bool) for k in (0, 1)
        )
        intensity = np.frombuffer(body, np.uint8, n, 3 * n * width + 2 * n_flags)
        try:
            voxels = VoxelGrid.from_bytes(voxel_bytes)
        except VoxelException as exc:
            raise SubmapException(f"submap voxel grid: {exc}") from exc
        points = q * QUANTUM_M + np.asarray(anchor)
        return cls(robot, index, frame_index, t_start, t_end, points, obstacle, classified, intensity, voxels, images, distance)

    @cached_property
    def size_bytes(self) -> int:
        """Length of ``to_bytes()`` (compressed), what a submap costs on the network."""
        return len(self.to_bytes())


def _chunk(data: bytes, pos: int, what: str) -> tuple[bytes, int]:
    if pos + _LENGTH.size > len(data):
        raise SubmapException(f"submap data truncated before the {what} length")
    (length,) = _LENGTH.unpack_from(data, pos)
    pos += _LENGTH.size
    if pos + length > len(data):
        raise SubmapException(f"submap data truncated: {what} needs {length} bytes, {len(data) - pos} left")
    return data[pos : pos + length], pos + length


# --------------------------------------------------------------------------- building


@dataclass
class _Active:
    index: int
    frame_index: int
    t_start: float | None
    cloud: VoxelSums
    voxels: VoxelGrid
    t_last: float | None = None
    images: int = 0
    distance_m: float = 0.0


class SubmapBuilder:
    """The active submap of one robot (thesis 5.1.2, 5.1.3): integrates depth images, says when to partition,
    and freezes it into a ``Submap`` when the next one starts.

    The first submap coincides with the filter's local frame ``frame_index`` (0: the start frame); its
    ``t_start`` is the first image's time unless given.
    """

    def __init__(self, robot: str, params: SubmapParams, calibration: StereoCalibration, frame_index: int = 0, t_start: float | None = None):
        if not isinstance(robot, str) or not robot:
            raise SubmapException(f"robot must be a non-empty name, got {robot!r}")
        self.robot = robot
        self.params = params
        self.calibration = calibration
        self._active = self._new(0, frame_index, t_start)

    def _new(self, index: int, frame_index: int, t_start: float | None) -> _Active:
        return _Active(index, frame_index, t_start, VoxelSums.empty(self.params.point_resolution_m), VoxelGrid(self.params.voxel_resolution_m))

    @property
    def index(self) -> int:
        return self._active.index

    @property
    def frame_index(self) -> int:
        return self._active.frame_index

    @property
    def images(self) -> int:
        return self._active.images

    def integrate(
        self, depth: np.ndarray, T_submap_cam: np.ndarray, obstacle: np.ndarray, intensity: np.ndarray, t: float, *, classified: np.ndarray
    ) -> None:
        """Add one z-depth image (H, W) of the left camera, seen from ``T_submap_cam`` (4x4, the camera in the
        active submap's frame), with its per-pixel obstacle flags and intensities (thesis 5.1.2), and the
        pixels the obstacle classification read (``slam.obstacles.Classification.pixel_classified``).

        Invalid (NaN, inf, <= 0) and far pixels (eq. 5.2c above ``max_depth_error_m``) are dropped; the rest
        are voxel-filtered at ``point_resolution_m`` and merged into the cloud, and the voxel grid gets one
        update with rays from the camera origin to those centroids.
        """
        depth = np.asarray(depth)
        c = self.calibration
        if depth.shape != (c.height, c.width):
            raise SubmapException(f"depth must be a ({c.height}, {c.width}) image as the calibration says, got shape {depth.shape}")
        obstacle, intensity, classified = np.asarray(obstacle), np.asarray(intensity), np.asarray(classified)
        if obstacle.shape != depth.shape or intensity.shape != depth.shape or classified.shape != depth.shape:
            raise SubmapException(
                f"obstacle, intensity and classified must have the depth's shape {depth.shape}, "
                f"got {obstacle.shape}, {intensity.shape} and {classified.shape}"
            )
        if np.any(obstacle.astype(bool) & ~classified.astype(bool)):
            raise SubmapException("obstacle pixels must be classified pixels")
        T = np.asarray(T_submap_cam, dtype=float)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise SubmapException(f"T_submap_cam must be a finite 4x4 matrix, got shape {T.shape}")
        if not math.isfinite(t):
            raise SubmapException(f"t must be finite, got {t!r}")
        p = self.params
        cut = cut_far_points(depth, self.calibration, p.max_depth_error_m, p.pixel_error)
        with np.errstate(invalid="ignore"):
            valid = np.isfinite(cut) & (cut > 0)
        points = depth_to_points_at(cut, valid, self.calibration).astype(float) @ T[:3, :3].T + T[:3, 3]
        image = VoxelSums.of_points(points, obstacle[valid], intensity[valid], p.point_resolution_m, classified=classified[valid])
        a = self._active
        a.cloud = a.cloud.merged(image)
        a.voxels.integrate(image.centroids()[0], T[:3, 3], max_range=p.voxel_max_range_m)
        a.images += 1
        a.t_last = t if a.t_last is None else max(a.t_last, t)
        if a.t_start is None:
            a.t_start = t

    def should_partition(self, position_std_m: float, distance_m: float) -> PartitionReason | None:
        """Why a new submap must start now (thesis 5.1.3), or None: the filter's position standard deviation has
        reached ``max_position_std_m``, or the distance driven since the submap began (= in the filter's current
        frame) has reached ``max_distance_m`` (std checked first). ``distance_m`` is recorded as the submap's
        ``distance_m``."""
        for name, v in (("position_std_m", position_std_m), ("distance_m", distance_m)):
            if not (math.isfinite(v) and v >= 0):
                raise SubmapException(f"{name} must be a finite non-negative number, got {v!r}")
        self._active.distance_m = float(distance_m)
        if position_std_m >= self.params.max_position_std_m:
            return PartitionReason.POSITION_STD
        if distance_m >= self.params.max_distance_m:
            return PartitionReason.DISTANCE
        return None

    def _snapshot(self, t_end: float, voxels: VoxelGrid) -> Submap:
        a = self._active
        points, obstacle, intensity = a.cloud.centroids()
        t_start = t_end if a.t_start is None else a.t_start
        flags = (obstacle, a.cloud.classified, intensity)
        return Submap(self.robot, a.index, a.frame_index, t_start, max(t_end, t_start), points, *flags, voxels, a.images, a.distance_m)

    def current(self) -> Submap:
        """A snapshot of the active submap (copies), e.g. for the robot's own global map (thesis 5.2.2); its
        ``t_end`` is the latest image's time (both times 0 before the first image if no ``t_start`` was given)."""
        a = self._active
        t_end = a.t_last if a.t_last is not None else a.t_start if a.t_start is not None else 0.0
        return self._snapshot(t_end, a.voxels.copy())

    def finish(self, t: float, next_frame_index: int) -> Submap:
        """Freeze the active submap at time ``t`` and start an empty one, ``index + 1``, coinciding with the filter's
        new local frame ``next_frame_index`` (the caller switches the filter's frame at the same time)."""
        if next_frame_index <= self._active.frame_index:
            raise SubmapException(f"next_frame_index must exceed the active submap's frame {self._active.frame_index}, got {next_frame_index}")
        a = self._active
        if a.t_start is not None and t < a.t_start:
            raise SubmapException(f"t = {t} is before the submap's start {a.t_start}")
        submap = self._snapshot(t, a.voxels)
        self._active = self._new(a.index + 1, next_frame_index, t)
        return submap
