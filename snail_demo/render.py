"""Render printed AprilTags into a camera image from a known pose.

Each tag is OpenCV's own 36h11 bitmap with a white quiet zone, warped by the homography of
its plane into an ideal pinhole image (supersampled, then area-averaged, so edges are
anti-aliased), then bent by the camera's lens distortion (every output pixel reads the
ideal image where its undistorted ray lands), blurred and given sensor noise. Pixel
coordinates follow OpenCV: the centre of the top-left pixel is (0, 0).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import cv2
import numpy as np

from snail_client.inputs.camera import Camera
from snail_client.inputs.tagmap import Tag, TagMap
from snail_common.loc.geometry import so3_exp
from snail_common.loc.problem import PoseVectors

CELLS = 8  # a 36h11 marker as OpenCV draws it: black border + 6x6 bits
QUIET = 2  # white cells around the black square (a printed tag's margin)
CELL_PX = 16  # bitmap pixels per cell
SUPERSAMPLE = 3
_UNDISTORT = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-8)


@dataclass(frozen=True)
class Look:
    """How the image looks besides geometry: blur (Gaussian sigma, px), sensor noise
    (sigma, grey levels), background grey and the ink's grey levels."""

    blur_px: float = 0.8
    noise: float = 3.0
    background: int = 110
    black: int = 30
    white: int = 225


@functools.cache
def tag_bitmap(tag_id: int) -> np.ndarray:
    """The tag's bitmap with its quiet zone, float32 in [0, 1] (1 = white)."""
    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11)
    marker = cv2.aruco.generateImageMarker(dictionary, tag_id, CELLS * CELL_PX)
    margin = QUIET * CELL_PX
    padded = cv2.copyMakeBorder(marker, margin, margin, margin, margin, cv2.BORDER_CONSTANT,
                                value=255)
    return padded.astype(np.float32) / 255.0


def _bitmap_to_tag(tag: Tag) -> np.ndarray:
    """Affine map from bitmap pixel coordinates to the tag plane (X, Y, 1): the black
    square's outer edges lie at pixel -0.5 and side - 0.5 of the unpadded marker."""
    side = CELLS * CELL_PX
    margin = QUIET * CELL_PX
    scale = tag.size / side
    # u_marker = u - margin; X = (u_marker + 0.5) * scale - s/2, Y = s/2 - (v_marker + 0.5)*scale
    return np.array([[scale, 0.0, (0.5 - margin) * scale - tag.size / 2],
                     [0.0, -scale, tag.size / 2 - (0.5 - margin) * scale],
                     [0.0, 0.0, 1.0]])


def _ideal(tagmap: TagMap, K: np.ndarray, size: tuple[int, int], pose: PoseVectors,
           background: float) -> np.ndarray:
    """Tags drawn into a pinhole image of ``size`` (float32, 1 = white ink)."""
    width, height = size
    image = np.full((height, width), background, np.float32)
    R = so3_exp(pose.rvec)
    for tag in tagmap.tags.values():
        R_ct = R @ so3_exp(tag.rvec)
        t_ct = R @ tag.tvec + pose.tvec
        bitmap = tag_bitmap(tag.id)
        h, w = bitmap.shape
        plane = _bitmap_to_tag(tag)
        outline_tag = plane @ np.array([[-1.0, w, w, -1.0], [-1.0, -1.0, h, h], [1, 1, 1, 1]])
        depth = R_ct[2, :2] @ outline_tag[:2] + t_ct[2]
        if depth.min() <= 1e-3 or R_ct[2, 2] >= 0:  # (partly) behind, or seen from its back
            continue
        H = K @ np.column_stack([R_ct[:, 0], R_ct[:, 1], t_ct]) @ plane
        outline = cv2.perspectiveTransform(
            np.array([[[-1.0, -1.0], [w, -1.0], [w, h], [-1.0, h]]]), H)[0]
        x0, y0 = np.maximum(np.floor(outline.min(axis=0)).astype(int), 0)
        x1, y1 = np.minimum(np.ceil(outline.max(axis=0)).astype(int) + 1, (width, height))
        if x0 >= x1 or y0 >= y1:
            continue
        H_roi = np.array([[1.0, 0.0, -x0], [0.0, 1.0, -y0], [0.0, 0.0, 1.0]]) @ H
        roi = (int(x1 - x0), int(y1 - y0))
        warped = cv2.warpPerspective(bitmap, H_roi, roi, flags=cv2.INTER_LINEAR)
        cover = cv2.warpPerspective(np.ones_like(bitmap), H_roi, roi, flags=cv2.INTER_LINEAR)
        window = image[y0:y1, x0:x1]
        window[:] = warped + (1 - cover) * window
    return image


@functools.cache
def _distortion_maps(K_bytes: bytes, dist_bytes: bytes, size: tuple[int, int],
                     margin: int) -> tuple[np.ndarray, np.ndarray]:
    """For every output pixel, where its undistorted ray lands in the ideal image (whose
    origin is shifted by ``margin`` pixels)."""
    K = np.frombuffer(K_bytes).reshape(3, 3)
    dist = np.frombuffer(dist_bytes)
    width, height = size
    u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    pix = np.column_stack([u.ravel(), v.ravel()]).reshape(-1, 1, 2)
    ideal = cv2.undistortPoints(pix, K, dist, None, None, K, _UNDISTORT)
    ideal = ideal.reshape(height, width, 2)
    return ((ideal[..., 0] + margin).astype(np.float32),
            (ideal[..., 1] + margin).astype(np.float32))


def render(tagmap: TagMap, camera: Camera, pose: PoseVectors, look: Look = Look(),
           rng: np.random.Generator | None = None) -> np.ndarray:
    """The uint8 grayscale image ``camera`` takes at ``pose`` (world to camera)."""
    if camera.size is None:
        raise ValueError("camera: rendering needs width and height")
    width, height = camera.size
    margin = width // 4 if camera.dist.any() else 0
    s = SUPERSAMPLE
    big = np.array([[s, 0.0, (s - 1) / 2], [0.0, s, (s - 1) / 2], [0.0, 0.0, 1.0]])
    shift = np.array([[1.0, 0.0, margin], [0.0, 1.0, margin], [0.0, 0.0, 1.0]])
    K_big = big @ shift @ camera.K
    size_big = ((width + 2 * margin) * s, (height + 2 * margin) * s)
    bg = (look.background - look.black) / (look.white - look.black)
    ideal = cv2.resize(_ideal(tagmap, K_big, size_big, pose, bg),
                       (width + 2 * margin, height + 2 * margin), interpolation=cv2.INTER_AREA)
    if camera.dist.any():
        map_x, map_y = _distortion_maps(camera.K.tobytes(), camera.dist.tobytes(),
                                        camera.size, margin)
        image = cv2.remap(ideal, map_x, map_y, cv2.INTER_LINEAR,
                          borderMode=cv2.BORDER_CONSTANT, borderValue=float(bg))
    else:
        image = ideal
    image = look.black + image * (look.white - look.black)
    if look.blur_px > 0:
        image = cv2.GaussianBlur(image, (0, 0), look.blur_px)
    if look.noise > 0:
        rng = rng if rng is not None else np.random.default_rng()
        image = image + rng.normal(scale=look.noise, size=image.shape)
    return np.clip(np.rint(image), 0, 255).astype(np.uint8)
