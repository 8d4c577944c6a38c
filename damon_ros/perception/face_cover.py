"""Whether a box's visible face is whole: a box's face, seen with nothing in front of it,
fills its rectangle in the image, every part of it within a sample spacing or two of a
sample.

The box fits (:mod:`damon_ros.perception.tight_fit`, :mod:`damon_ros.perception.tilted_box`)
take points near a few planes for a box's faces, and the box's shape then stands for what
the camera cannot see. A generated hand (a palm, four fingers side by side and a thumb
standing out of the palm's back beside it) seen from the palm's side puts 92 % and more of
its points on a box's faces: the palm, the fingers (within a finger's radius of the palm's
plane) and the thumb's end. Its front "face" then spans palm, fingers and thumb with empty
image between them, and the box closed at the palm's thickness left the thumb 2-5 cm
outside (19 of the 21 whole one-camera views of seed 2106 not contained). No true box
leaves such gaps: over the whole views of five generated seeds, every box's faces seen at
least `MIN_COSINE` off grazing and `MIN_AREA_PX` large left at most 1.4 % of their image
uncovered, the hands 4.9-12 %.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
from scipy.spatial import cKDTree

from damon_ros.perception.camera import Camera, project

HOLE_SHARE = 0.03
"""A face whose image leaves more than this share uncovered is no box's face. Over the whole
views of seeds 31, 2106, 2207, 2401 and 2412 (one camera and two), true boxes' faces left at
most 0.014 uncovered, the generated hands' 0.049-0.12."""
COVER_SPACINGS = 2.0
"""A pixel of the face's image is covered within this many sample spacings of a sample (the
median distance between neighbouring samples, which includes the tracker's thinning)."""
SPACING_QUERIES = 128
"""The sample spacing is the median over about this many samples (one in every few)."""
MIN_COSINE = 0.1
"""Faces seen more grazingly than this cosine between ray and normal (the median over their
points) are not judged: their samples thin out unevenly along the face."""
MIN_AREA_PX = 200
"""Faces smaller than this in the image (px) are not judged: their corners alone leave a
pixel or two uncovered, 2 % of a face of 100 px."""


def uncovered_share(camera: Camera, points: np.ndarray, corners: np.ndarray) -> float:
    """Share of the face's image (the quadrilateral of its base-frame ``corners``, 4 x 3, in
    order round the face) farther than `COVER_SPACINGS` sample spacings from every
    projected base-frame ``points`` (N x 3) of the face; 0 where there is too little to
    judge (`MIN_AREA_PX`, fewer than 3 points)."""
    if len(points) < 3:
        return 0.0
    uv = project(camera, points)
    outline = project(camera, corners)
    if not (np.isfinite(uv).all() and np.isfinite(outline).all()):
        return 0.0
    some = uv[::max(1, len(uv) // SPACING_QUERIES)]  # the median of a few hundred will do
    spacing = float(np.median(cKDTree(uv).query(some, k=2)[0][:, 1]))
    reach = max(2, math.ceil(COVER_SPACINGS * spacing))
    origin = np.floor(outline.min(axis=0)) - reach - 1
    size = (np.ceil(outline.max(axis=0)) - origin + reach + 2).astype(int)
    face = np.zeros((size[1], size[0]), np.uint8)
    cv2.fillConvexPoly(face, np.round(outline - origin).astype(np.int32), 1)
    area = int(np.count_nonzero(face))
    if area < MIN_AREA_PX:
        return 0.0
    samples = np.zeros_like(face)
    ij = np.round(uv - origin).astype(int)
    inside = (ij >= 0).all(axis=1) & (ij[:, 0] < size[0]) & (ij[:, 1] < size[1])
    samples[ij[inside, 1], ij[inside, 0]] = 1
    disk = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * reach + 1, 2 * reach + 1))
    covered = cv2.dilate(samples, disk)
    return float(np.count_nonzero(face > covered)) / area


def face_corners(local: np.ndarray, axis: int) -> np.ndarray:
    """The rectangle (4 x 3, box-frame, in order round it) that the points ``local`` (N x 3,
    box frame) of one face across ``axis`` span on their median plane."""
    others = [j for j in range(3) if j != axis]
    low, high = local[:, others].min(axis=0), local[:, others].max(axis=0)
    corners = np.empty((4, 3))
    corners[:, axis] = np.median(local[:, axis])
    corners[:, others[0]] = [low[0], high[0], high[0], low[0]]
    corners[:, others[1]] = [low[1], low[1], high[1], high[1]]
    return corners
