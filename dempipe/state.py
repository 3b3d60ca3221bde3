"""State: where the bodies ARE. Mutable; the simulator advances it in place."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class State:
    """Body state at one instant (dynamic bodies first, then static pseudo-bodies).

    body_x : (B, 3) float64, centre of mass, world frame [m]
    body_q : (B, 4) float64, orientation (w, x, y, z), body to world
    body_P : (B, 3) float64, linear momentum, world frame [kg m/s]
    body_L : (B, 3) float64, angular momentum about the centre of mass, world frame [kg m²/s]
    time : simulated time [s]
    step : steps taken since frame 0
    """

    body_x: np.ndarray
    body_q: np.ndarray
    body_P: np.ndarray
    body_L: np.ndarray
    time: float = 0.0
    step: int = 0

    def copy(self) -> "State":
        return State(self.body_x.copy(), self.body_q.copy(), self.body_P.copy(),
                     self.body_L.copy(), self.time, self.step)
