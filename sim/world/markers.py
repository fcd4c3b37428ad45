"""AprilTag 36h11 markers as textured MJCF geoms (robots' mast markers, the lander's tag).

The marker images come from OpenCV's own generator (``cv2.aruco.generateImageMarker``
with ``DICT_APRILTAG_36h11``), so what is rendered is exactly what ``cv2.aruco``
detects (thesis 6.2.1). A marker is a thin box whose +z face carries the tag; the
tag's printed size ``size_m`` is the edge of its black square (8 of the 10 cells of
the texture; the outer cell is a white quiet zone), the convention of
``cv2.aruco``/PnP. ``MarkerSpec`` gives the marker frame: origin at the centre of the
printed face, z out of it (the box geom sits half its thickness behind).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import mujoco
import numpy as np
from dm_control import mjcf

TAG_FAMILY = cv2.aruco.DICT_APRILTAG_36h11
TAG_CELLS = 8  # 6x6 data cells plus the black border
QUIET_CELLS = 1  # white cells around the black border
MARKER_THICKNESS_M = 0.004
MARKER_MATERIAL_PREFIX = "apriltag_"  # a marker geom's material: the prefix and its tag id


@dataclass(frozen=True)
class MarkerSpec:
    """Where a marker sits: on which body, with which id and printed size."""

    name: str  # geom name inside its MJCF model
    tag_id: int
    size_m: float  # edge of the black square
    pos: tuple[float, float, float]  # in the parent body frame
    quat: tuple[float, float, float, float]  # (w, x, y, z), face normal = geom z


def tag_dictionary() -> cv2.aruco.Dictionary:
    return cv2.aruco.getPredefinedDictionary(TAG_FAMILY)


def apriltag_image(tag_id: int, px_per_cell: int = 16) -> np.ndarray:
    """Grey tag image with its quiet zone, (10 * px_per_cell) pixels square."""
    dictionary = tag_dictionary()
    if not 0 <= tag_id < dictionary.bytesList.shape[0]:
        raise ValueError(f"tag id {tag_id} is outside AprilTag 36h11 (0..{dictionary.bytesList.shape[0] - 1})")
    core = cv2.aruco.generateImageMarker(dictionary, tag_id, TAG_CELLS * px_per_cell, borderBits=1)
    pad = QUIET_CELLS * px_per_cell
    return cv2.copyMakeBorder(core, pad, pad, pad, pad, cv2.BORDER_CONSTANT, value=255)


def _png_asset(image: np.ndarray) -> mjcf.Asset:
    ok, png = cv2.imencode(".png", cv2.cvtColor(image, cv2.COLOR_GRAY2RGB))
    if not ok:
        raise RuntimeError("PNG encoding of a marker texture failed")
    return mjcf.Asset(png.tobytes(), ".png")


def add_marker(body: mjcf.Element, spec: MarkerSpec) -> mjcf.Element:
    """Add the textured marker geom to ``body`` (visual only: no contacts, no mass)."""
    root = body.root
    texture_name = f"{MARKER_MATERIAL_PREFIX}{spec.tag_id}"
    if root.asset.find("texture", texture_name) is None:
        root.asset.add("texture", name=texture_name, type="2d", file=_png_asset(apriltag_image(spec.tag_id)))
        root.asset.add("material", name=texture_name, texture=texture_name, specular=0.0, shininess=0.0)
    half = spec.size_m * (TAG_CELLS + 2 * QUIET_CELLS) / TAG_CELLS / 2
    normal = np.zeros(3)
    mujoco.mju_rotVecQuat(normal, np.array([0.0, 0.0, 1.0]), np.asarray(spec.quat, float))
    return body.add(
        "geom",
        name=spec.name,
        type="box",
        size=[half, half, MARKER_THICKNESS_M / 2],
        pos=list(np.asarray(spec.pos) - normal * MARKER_THICKNESS_M / 2),
        quat=list(spec.quat),
        material=texture_name,
        contype=0,
        conaffinity=0,
        mass=0,
        group=1,
    )
