"""Preview cameras: presets that frame a box, view/projection matrices, projecting points.

Matrices here use the column-vector convention (``clip = P @ V @ [p, 1]``); the GL code
uploads them transposed. Pixel coordinates are (x right, y down) from the top-left corner
of the picture, as in the PNG.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: Camera presets: direction from the target to the eye in a Z-up stage, and screen up.
#: three-quarter: from the front right, 28° above the ground (Blender's front is -Y).
PRESETS = {
    "three-quarter": ((math.cos(math.radians(28)) * math.cos(math.radians(-55)),
                       math.cos(math.radians(28)) * math.sin(math.radians(-55)),
                       math.sin(math.radians(28))), (0.0, 0.0, 1.0)),
    "front": ((0.0, -1.0, 0.0), (0.0, 0.0, 1.0)),
    "top": ((0.0, 0.0, 1.0), (0.0, 1.0, 0.0)),
}


def to_stage(v, up_axis: str) -> np.ndarray:
    """A Z-up direction in the stage's axes ((x, y, z) → (x, z, -y) for Y-up)."""
    x, y, z = v
    return np.array((x, z, -y) if up_axis == "Y" else (x, y, z), dtype=np.float64)


@dataclass
class Camera:
    """A perspective pinhole camera looking from ``eye`` at ``target``."""

    eye: np.ndarray
    target: np.ndarray
    up: np.ndarray
    fov_y: float          # vertical field of view [degrees]
    width: int
    height: int
    near: float
    far: float

    def view(self) -> np.ndarray:
        f = self.target - self.eye
        f = f / np.linalg.norm(f)
        r = np.cross(f, self.up)
        r = r / np.linalg.norm(r)
        u = np.cross(r, f)
        m = np.eye(4)
        m[0, :3], m[1, :3], m[2, :3] = r, u, -f
        m[:3, 3] = -m[:3, :3] @ self.eye
        return m

    def projection(self) -> np.ndarray:
        t = 1.0 / math.tan(math.radians(self.fov_y) / 2)
        a = self.width / self.height
        n, f = self.near, self.far
        return np.array([[t / a, 0, 0, 0], [0, t, 0, 0],
                         [0, 0, (f + n) / (n - f), 2 * f * n / (n - f)], [0, 0, -1, 0]])

    def view_projection(self) -> np.ndarray:
        return self.projection() @ self.view()

    def project(self, points) -> np.ndarray:
        """World points (N, 3) → pixel coordinates (N, 2), x right and y down."""
        p = np.atleast_2d(np.asarray(points, dtype=np.float64))
        clip = np.c_[p, np.ones(len(p))] @ self.view_projection().T
        ndc = clip[:, :2] / clip[:, 3:4]
        return np.c_[(ndc[:, 0] + 1) / 2 * self.width, (1 - ndc[:, 1]) / 2 * self.height]


def frame_box(preset: str, lo, hi, up_axis: str, width: int, height: int,
              scene_radius: float | None = None, fov_y: float = 35.0) -> Camera:
    """A ``preset`` camera whose picture holds the box [lo, hi] with a small margin.

    The distance is the least at which every corner of the box is inside both the
    vertical and the horizontal field of view; near and far enclose a sphere of
    ``scene_radius`` (default: the box's) about the box's centre.
    """
    if preset not in PRESETS:
        raise ValueError(f"unknown camera {preset!r} (known: {', '.join(PRESETS)})")
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    size = max(float(np.linalg.norm(hi - lo)), 1e-6)
    lo, hi = lo - 0.02 * size, hi + 0.02 * size      # a flat box still has some room
    centre = (lo + hi) / 2
    direction, screen_up = (to_stage(v, up_axis) for v in PRESETS[preset])
    fwd = -direction / np.linalg.norm(direction)
    right = np.cross(fwd, screen_up)
    right /= np.linalg.norm(right)
    up = np.cross(right, fwd)
    tan_v = math.tan(math.radians(fov_y) / 2)
    tan_h = tan_v * width / height
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                        for z in (lo[2], hi[2])]) - centre
    along, across_r, across_u = corners @ fwd, corners @ right, corners @ up
    # corner inside the frustum: |across| <= tan * (distance + along)
    dist = float(np.max(np.maximum(np.abs(across_r) / tan_h, np.abs(across_u) / tan_v) - along))
    dist = max(dist * 1.08, 1e-3)
    radius = max(scene_radius or 0.0, size / 2)
    near = max(dist - 1.5 * radius, dist * 0.01)
    far = dist + 3.0 * radius
    return Camera(centre - fwd * dist, centre, up, fov_y, width, height, near, far)
