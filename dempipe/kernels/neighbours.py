"""Verlet neighbour lists: the contact search of stages 2-3, done once per many steps.

The paper builds the grid and searches the 27 neighbour cells at every step. Both
targets instead keep, for each sphere, the list of spheres of other bodies closer
than (1 + SKIN) d when the list was built, and walk only that list at each step.
The lists are rebuilt (grid, counting sort, 27-cell search) at the first step of
each ``step`` call and whenever some sphere has moved SKIN/2 d or more since the
last build. Between rebuilds no pair outside the lists can touch: each of its two
spheres has moved less than SKIN/2 d, so their distance is still above d.

The grid of the rebuild has cells of edge (1 + SKIN) d (``cell_size``), not d: its 27
cells must hold every sphere within the list's reach, (1 + SKIN) d.

A list is kept in its partners' sphere-index order. The force on a sphere is the
sum over the list of the partners that touch it (a listed pair farther apart than d
adds nothing), in that order, then the walls: so the forces, and the frames, do not
depend on SKIN, on when the lists were rebuilt, on the grid's layout or on how the
steps were split into calls. CPU and CUDA sum in the same order.

This module holds the constants both targets share; it imports no numba.
"""

#: Verlet skin [diameters]: a list holds the partners within (1 + SKIN) d; rebuilt
#: when a sphere has moved SKIN/2 d. Larger: longer lists walked every step, fewer
#: rebuilds. Measured: docs/performance.md, "Throughput".
SKIN = 0.2

#: Entries per sphere a backend allocates to start with. A rebuild that finds a
#: longer list (a sphere deep in others, a dense pile of small bodies) makes the
#: backend grow the lists and carry on from that step (the CPU returns before the
#: step's contacts; on CUDA nothing of the State changes from that step on and the
#: host relaunches the remaining steps): contacts are never dropped.
NEIGHBOURS = 16


def cell_size(diameter: float) -> float:
    """Edge of the rebuild grid's cells [m]: the lists' reach, (1 + SKIN) d, so the 27
    cells round a sphere hold every partner a list may need."""
    return (1.0 + SKIN) * diameter
