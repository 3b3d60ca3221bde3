"""State: where the bodies ARE. Mutable; the simulator advances it in place."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Contacts each sphere remembers for static friction (its tangential springs).
#: Equal spheres on lattices touch at most ~6 spheres of other bodies plus 3
#: walls in a corner; a contact beyond the slots gets no spring (only the
#: viscous part of friction) until a slot frees up.
CONTACT_SLOTS = 12


@dataclass
class State:
    """Body state at one instant (dynamic bodies first, then static pseudo-bodies).

    body_x : (B, 3) float64, centre of mass, world frame [m]
    body_q : (B, 4) float64, orientation (w, x, y, z), body to world
    body_P : (B, 3) float64, linear momentum, world frame [kg m/s]
    body_L : (B, 3) float64, angular momentum about the centre of mass, world frame [kg m²/s]
    time : simulated time [s]
    step : steps taken since frame 0
    contact_partner : (S, CONTACT_SLOTS) int32, per sphere the contacts it
        remembers: 2 (p + 1) + (step parity when last touched), p the other
        sphere's index or n_spheres + wall index; 0 is an empty slot
    contact_spring : (S, CONTACT_SLOTS, 3) float64, tangential spring stretch of
        each remembered contact, world frame [m] (Cundall-Strack history)
    Both are None until a backend that needs them (friction) allocates them.
    body_rest : (B,) int32, steps each body has been at rest (sleeping); a body is
        asleep when it reaches Model.sleep_steps. None until a backend allocates it.
    bond_broken : (N,) int32, 1 for each glue bond (sim/glue.py) that has broken, for
        good; None in a scene without glue
    bond_shear : (P,) x 3 float64, each bonded sphere pair's shear stretch, world
        frame [m] (physics.glue_force); None without glue
    """

    body_x: np.ndarray
    body_q: np.ndarray
    body_P: np.ndarray
    body_L: np.ndarray
    time: float = 0.0
    step: int = 0
    contact_partner: np.ndarray | None = None
    contact_spring: np.ndarray | None = None
    body_rest: np.ndarray | None = None
    bond_broken: np.ndarray | None = None
    bond_shear: np.ndarray | None = None

    def copy(self) -> "State":
        return State(self.body_x.copy(), self.body_q.copy(), self.body_P.copy(),
                     self.body_L.copy(), self.time, self.step,
                     None if self.contact_partner is None else self.contact_partner.copy(),
                     None if self.contact_spring is None else self.contact_spring.copy(),
                     None if self.body_rest is None else self.body_rest.copy(),
                     None if self.bond_broken is None else self.bond_broken.copy(),
                     None if self.bond_shear is None else self.bond_shear.copy())

    def ensure_rest(self, n_bodies: int) -> None:
        """Allocate rest counts (every body awake, not yet at rest)."""
        if self.body_rest is None or self.body_rest.shape[0] != n_bodies:
            self.body_rest = np.zeros(n_bodies, dtype=np.int32)

    def asleep(self, sleep_steps: int) -> np.ndarray:
        """(B,) bool, which bodies sleep now."""
        if self.body_rest is None or sleep_steps <= 0:
            return np.zeros(self.body_x.shape[0], dtype=bool)
        return self.body_rest >= sleep_steps

    def ensure_contacts(self, n_spheres: int) -> None:
        """Allocate empty contact histories (every contact starts unstretched)."""
        if self.contact_partner is None or self.contact_partner.shape[0] != n_spheres:
            self.contact_partner = np.zeros((n_spheres, CONTACT_SLOTS), dtype=np.int32)
            self.contact_spring = np.zeros((n_spheres, CONTACT_SLOTS, 3))
