"""Frames of known motion, for writers checked against the poses they were given.

``moved_frames(model)``: three frames of a model's bodies, frame 0 their initial pose,
frames 1 and 2 moved by (0.01 f, -0.02, 0.03 f) m and turned once more each frame by
one fixed rotation (about 0.8 rad), so a writer that drops, reorders or mis-composes a
transform shows.
"""

import numpy as np

from dempipe.sim.frames import Frames


def moved_frames(model, fps: float = 24.0) -> Frames:
    n = model.n_bodies
    x = np.repeat(np.asarray(model.initial_x)[None, :n], 3, axis=0)
    q = np.repeat(np.asarray(model.initial_q)[None, :n], 3, axis=0)
    turn = np.array([np.cos(0.4), 0.3, -0.5, 0.8])
    turn /= np.linalg.norm(turn)
    w1, v1 = turn[0], turn[1:]
    for f in (1, 2):
        x[f] += [0.01 * f, -0.02, 0.03 * f]
        for k in range(n):
            w2, v2 = q[f - 1, k, 0], q[f - 1, k, 1:]
            q[f, k] = [w1 * w2 - v1 @ v2, *(w1 * v2 + w2 * v1 + np.cross(v1, v2))]
    return Frames(np.arange(3), np.arange(3) / fps, x, q, np.zeros((3, n, 3)),
                  np.zeros((3, n, 3)))
