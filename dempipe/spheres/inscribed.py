"""Inscribed balls and rings: how a sphere set meets a wall as smoothly as its mesh.

A surface set's shell spheres sit at depth r = d/2 under the mesh, a spacing h apart
(spheres/surface.py). Against a plane, the set's envelope dips between them: where the
body's lowest point falls between two centres, neither sphere reaches the plane as
deep as the surface would, by up to κ ρ²/2 (κ the curvature of the offset surface,
ρ ≤ h the distance to the nearest centre). A ball rolling across those dips rides
over a polygon of corners of radius r: past √(g R) it hops from sphere to sphere and
each landing loses what the restitution takes. A lattice set's envelope is terraced,
a few tenths of d deep, and its spheres stick out of the mesh as much: a lattice
ball is a polyhedron that does not roll at all.

So each shell sphere also carries its osculating torus inside the mesh: a circle of
radius a about an axis, swept by a tube of radius b, touching the surface where the
sphere does with the surface's two curvatures there (b = r + 1/κ2, a + b = r + 1/κ1,
κ1 ≥ κ2 the principal curvatures of the offset surface, fitted to the sphere's shell
neighbours), the tube held inside the shell (a shrinking-ball test) and to
RHO_MAX_SHARE of the shape's smallest extent (inscribed_tori). On a ball it is the
ball; on a cylinder's side the cross-section, or near a cap the ring about the axis
through the sphere. A wall contact takes the torus's overlap at its point lowest
towards the wall (kernels/contacts.py inscribed_wall), never more than the row's reach
beyond the sphere's own (REACH d), which keeps a torus far from the contact out of it.
Edge and corner spheres (a fit across an edge is no surface), interior and thin-part
spheres keep their own sphere.

A lattice set takes the tori its mesh's shell would have at the same d, held inside
the mesh itself, each given to the lattice sphere outermost where it was fitted, with
a reach that spans the terraces; on a solid of revolution each is swept about the
body's axis instead where that ring stays inside (a cone's side); its sharp circular
edges (rims: a cylinder's, a chess piece's base) are rings of tube 0 held by the
lattice spheres nearest them (two closer than d, a chess piece's plinth, one band: a
ring swept along its axis); and a lattice sphere that sticks out of the mesh meets
walls as a ball a little inside its depth (lattice_tori). So with the default sphere
sets too a ball, a cylinder, a cone, a torus and a pawn on its side roll on walls at
their closed forms. docs/physics.md, "Round bodies on walls".
"""

from __future__ import annotations

import hashlib

import numpy as np

from dempipe.spheres.sphere_set import repaired_mesh

#: Shell spheres: centres within this share of r of depth r under the mesh.
SHELL_TOLERANCE = 0.02
#: Neighbours (the sphere itself included) each shell sphere's quadric is fitted to.
FIT_NEIGHBOURS = 32
#: A torus's tube radius is at most this share of the shape's smallest extent (its
#: bounding box's, body frame): a ball's own radius, a box's half side.
RHO_MAX_SHARE = 0.5
#: A fit whose RMS residual exceeds this [d], or whose tangent plane leans more than
#: this [rad] from the closest point's normal, spans an edge: no torus.
FIT_RESIDUAL = 0.01
FIT_TILT = 0.2
#: The offset surface of a faceted mesh is faceted: a torus's tube may reach this
#: far [d] past its neighbouring centres (a wall contact never takes more than REACH
#: beyond the sphere's own).
SHRINK_SLACK = 0.05
#: How much deeper [d] than its own sphere a shell sphere's torus may touch a wall
#: (contacts.inscribed_wall): above the dips of a surface set's envelope on a round
#: body (at most h² / (2 (R − r)) for shell spacing h, 0.013 d on a ball 8 spheres
#: across) and the facets of its mesh. A lattice sphere's reach adds its shape's
#: terraces (lattice_tori).
REACH = 0.05


#: Columns of a sphere's row (inscribed_tori): the vector from the sphere's centre to
#: the torus's centre (3), its axis (3), the direction from its centre to the tube's
#: centre under the sphere (3), the circle's radius a, the tube's radius b, how much
#: deeper than the sphere's own its wall contact may be [m], a band's height H [m]: a
#: rim's ring (b = 0) swept H along its axis, a band between two rims closer than d (a
#: chess piece's plinth), 0 elsewhere; and 1 where the sphere meets no wall, its
#: neighbours reaching every wall first (wall_cover), 0 elsewhere.
COLUMNS = 14
#: The column that leaves a sphere out of wall contacts (wall_cover).
COVERED = 13
def all_own(rows, diameter: float) -> bool:
    """Whether every row of ``rows`` (COLUMNS) is its sphere's own ball, radius d/2 at
    its centre: no torus, nothing a wall contact needs the table for (the contact
    kernels are compiled without contacts.inscribed_wall); column COVERED may still
    leave spheres out of walls."""
    return not (np.any(rows[:, 0:3] != 0.0) or np.any(rows[:, 10] != 0.5 * diameter))


#: A circle larger than this many times the shape's largest extent is a straight line
#: to the contact: the sphere takes a ball instead.
CIRCLE_MAX_SHARE = 4.0


#: Tori computed in this process, by their inputs: a shape built into a model again (a
#: wedge's variants, a bake resumed in the same process, a test's scenes) costs nothing.
MEMO_SIZE = 32
_MEMO: dict = {}
#: The fit's version, in the disk cache's keys: a change to what the functions below
#: compute changes it, and old entries are never read.
TORI_VERSION = 11


def wall_tori(centers, diameter: float, vertices, faces, *, surface: bool,
              cache=None) -> np.ndarray:
    """What each sphere of a set meets walls through: inscribed_tori for a surface set's
    ``centers``, with the spheres its neighbours cover left out (wall_cover), lattice_tori
    for a lattice's (body frame [m]); read-only, remembered
    for the process by the bytes of every input (MEMO_SIZE sets) and, with ``cache`` (a
    spheres.cache.SphereCache), on disk beside the sphere sets: a scene built again
    (`dempipe check` after a bake) fits nothing and loads no numba."""
    c = np.ascontiguousarray(np.asarray(centers, dtype=np.float64).reshape(-1, 3))
    v = np.ascontiguousarray(vertices, dtype=np.float64)
    f = np.ascontiguousarray(faces, dtype=np.int64)
    h = hashlib.sha256(f"inscribed tori {TORI_VERSION}".encode())
    for a in (c, v, f):
        h.update(str(a.shape).encode())
        h.update(a.tobytes())
    h.update(np.asarray([diameter], dtype=np.float64).tobytes())
    h.update(b"surface" if surface else b"lattice")
    key = h.hexdigest()
    rows = _MEMO.get(key)
    if rows is None and cache is not None:
        got = cache.get_arrays(key)
        if got is not None and got.get("rows", np.zeros(0)).shape == (c.shape[0], COLUMNS):
            rows = got["rows"].astype(np.float64)
    if rows is None:
        rows = (inscribed_tori if surface else lattice_tori)(c, diameter, v, f)
        if surface:
            rows[:, COVERED] = wall_cover(c, rows, diameter, v, f)
        if cache is not None:
            cache.put_arrays(key, {"rows": rows})
    if key not in _MEMO:
        rows.setflags(write=False)
        if len(_MEMO) >= MEMO_SIZE:
            _MEMO.pop(next(iter(_MEMO)))
        _MEMO[key] = rows
    return rows


def inscribed_tori(centers, diameter: float, vertices, faces, *,
                   curved_only: bool = False) -> np.ndarray:
    """(N, COLUMNS) per sphere of ``centers`` (body frame [m], the set's order): its
    osculating torus, the torus inside the mesh that touches the surface where the
    sphere does with the surface's two curvatures there: a circle of radius a about an
    axis, swept by a tube (a ball) of radius b. A ball's spheres get the ball (a = 0),
    a cylinder's side spheres its cross-section (a = 0, b = R) or, near a cap, the
    ring of radius R − b through them; a flat face's a ball held clear of its edges.
    Where the sphere is its own (not on the shell, on an edge, a thin part), the row
    is (0, ..., 0, b = d/2, REACH d). Body frame, [m]. ``curved_only``: flat parts
    (their larger radius beyond CIRCLE_MAX_SHARE of the largest extent) get nothing
    either (lattice_tori)."""
    # scipy and the numba mesh queries load here, when a surface set is built into a model
    from scipy.spatial import cKDTree

    from dempipe.spheres.surface import MeshQueries

    c = np.asarray(centers, dtype=np.float64).reshape(-1, 3)
    r = 0.5 * float(diameter)
    out = np.zeros((c.shape[0], COLUMNS))
    out[:, 10] = r
    out[:, 11] = REACH * float(diameter)
    v = np.asarray(vertices, dtype=np.float64)
    if c.shape[0] < FIT_NEIGHBOURS or v.shape[0] == 0:
        return out
    dist, q = MeshQueries(v, faces, 2.0 * diameter).closest(c)
    shell = np.flatnonzero(np.abs(dist - r) <= SHELL_TOLERANCE * r)
    if shell.size < FIT_NEIGHBOURS:
        return out
    cs = c[shell]
    n = (q[shell] - cs) / dist[shell, None]           # outward, from the closest point
    _, nb = cKDTree(cs).query(cs, k=FIT_NEIGHBOURS)
    rel = cs[nb] - cs[:, None, :]                     # (M, K, 3)
    # a tangent frame per sphere
    pick = np.where(np.abs(n[:, 0:1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    e1 = np.cross(n, pick)
    e1 /= np.linalg.norm(e1, axis=1)[:, None]
    e2 = np.cross(n, e1)
    u = np.einsum("mkj,mj->mk", rel, e1)
    w = np.einsum("mkj,mj->mk", rel, e2)
    z = -np.einsum("mkj,mj->mk", rel, n)              # depth under the tangent plane
    # z = α u + β w + (A u² + 2 B u w + C w²) / 2, least squares per sphere
    basis = np.stack([u, w, 0.5 * u * u, u * w, 0.5 * w * w], axis=2)   # (M, K, 5)
    ata = np.einsum("mki,mkj->mij", basis, basis)
    atz = np.einsum("mki,mk->mi", basis, z)
    scale = np.einsum("mii->m", ata)[:, None, None] * 1e-12
    coef = np.linalg.solve(ata + scale * np.eye(5)[None], atz[..., None])[..., 0]
    alpha, beta, A, B, C = coef.T
    # a quadric fitted across an edge (a cylinder's rim, a box's edges) is no surface:
    # those spheres keep their own ball
    resid = z - np.einsum("mki,mi->mk", basis, coef)
    smooth = (np.sqrt(np.mean(resid * resid, axis=1)) <= FIT_RESIDUAL * diameter) & (
        alpha * alpha + beta * beta <= FIT_TILT * FIT_TILT)
    # principal curvatures of the offset surface, k1 ≥ k2, and k1's direction
    half = np.sqrt(0.25 * (A - C) ** 2 + B * B)
    k1 = 0.5 * (A + C) + half
    k2 = 0.5 * (A + C) - half
    phi = 0.5 * np.arctan2(2.0 * B, A - C)
    normal = n + alpha[:, None] * e1 + beta[:, None] * e2
    normal /= np.linalg.norm(normal, axis=1)[:, None]
    d1 = np.cos(phi)[:, None] * e1 + np.sin(phi)[:, None] * e2
    d1 -= np.einsum("mj,mj->m", d1, normal)[:, None] * normal
    d1 /= np.linalg.norm(d1, axis=1)[:, None]
    extent = v.max(axis=0) - v.min(axis=0)

    def radius(k):                                    # r + 1/k of the mesh, inf if k ≤ 0
        with np.errstate(divide="ignore"):
            return np.where(k > 0.0, r + 1.0 / np.where(k > 0.0, k, 1.0), np.inf)

    # the tube: the surface's smaller radius, inside the shell (the shrinking-ball bound:
    # a face's sphere near an edge is held to the edge's distance, which the fit over a
    # flat face cannot see), at most RHO_MAX_SHARE of the smallest extent
    b = np.minimum(radius(k2), RHO_MAX_SHARE * float(extent.min()))
    b = np.minimum(b, r + _shrinking_ball(cs, -normal, SHRINK_SLACK * diameter))
    # the circle: the surface's larger radius R1 = a + b along d1
    r1 = radius(k1)
    b = np.minimum(b, r1)
    ring = np.isfinite(r1) & (r1 <= CIRCLE_MAX_SHARE * float(extent.max())) & (r1 - b > 1e-9 * r)
    a = np.where(ring, r1 - b, 0.0)
    centre = -(np.where(ring, r1, b) - r)[:, None] * normal     # inward: the circle's centre
    grow = smooth & ((b > r * (1.0 + 1e-9)) | ring)
    if curved_only:
        grow &= np.isfinite(r1) & (r1 <= CIRCLE_MAX_SHARE * float(extent.max()))
    rows = shell[grow]
    out[rows, 0:3] = centre[grow]
    out[rows, 3:6] = np.where(ring[grow, None], np.cross(normal[grow], d1[grow]), 0.0)
    out[rows, 6:9] = np.where(ring[grow, None], normal[grow], 0.0)
    out[rows, 9] = a[grow]
    out[rows, 10] = b[grow]
    return out


#: wall_cover: the spacing [d] of the spheres it tries to keep; a sphere is left out
#: where those within twice that reach every wall within WALL_TOLERANCE [d] of as deep
#: as it does, in each of WALL_DIRECTIONS directions over the sphere and the rings of
#: directions WALL_CONE round the direction of its closest point of the mesh.
WALL_SPACING = 0.6
WALL_TOLERANCE = 0.002
WALL_DIRECTIONS = 256
#: wall_cover's second order: a kept sphere stands in only for neighbours whose normals
#: lie within this angle [rad] of its own (its facet).
WALL_FACET = np.radians(40.0)
#: wall_cover: the spheres within this gap [d] of a wall's deepest touch it at rest.
REST_GAP = 0.01
#: Tilts [rad] of the rings of directions round each sphere's normal wall_cover tests.
WALL_CONE = np.radians([2.0, 4.0, 6.0, 9.0, 13.0, 18.0, 25.0])
#: Pairs × directions wall_cover evaluates at once (memory: 8 bytes each, twice).
WALL_BLOCK = 2_000_000 // WALL_DIRECTIONS


def wall_cover(centers, rows, diameter: float, vertices, faces) -> np.ndarray:
    """(N,) 1.0 for each sphere of a surface set (``centers`` body frame [m], ``rows``
    their inscribed_tori, the mesh's ``vertices`` and ``faces``) that never meets a wall
    first, 0.0 for the rest.

    A shell 0.3 d apart is as fine as rolling between bodies needs, but a wall sees
    only its envelope, which sparser spheres and their tori follow as well where the
    surface is flat or gently curved: a face standing on the floor would otherwise
    test every sphere under it at every step. Each sphere reaches a wall lying in
    direction u as far as its contact does (contacts.inscribed_wall): its torus's
    support t·u + a |u × axis| + b, at most its own sphere's c·u + r plus its reach.

    Spheres are kept greedily WALL_SPACING d apart. Another is left out where, in
    each direction tested, a kept sphere within 2 WALL_SPACING d reaches within
    WALL_TOLERANCE d of as far: WALL_DIRECTIONS over the sphere and, where its reach
    peaks, towards the mesh's closest point (its normal, an edge's bisector) and
    WALL_CONE rings round it. The ones that fall short get another round: kept among
    themselves WALL_SPACING d apart, the rest tested again against every kept one,
    until none is open. So the envelope walls meet moves by at most about the
    tolerance (0.004-0.005 d in 4,000 random directions: tests/sim/test_inscribed.py),
    and a finite wall (a box's face) still finds a sphere at least every 2
    WALL_SPACING d, finer than a lattice's d. Where neighbours fall short the spheres
    stay: corners, the polygon of a round edge a fit gives no torus (a chess piece's
    foot at 6 across), a small ball's tori past their reach.

    The greedy choice is made in two orders, and the one fewer of whose spheres touch
    a resting face (within REST_GAP d of a wall along each of the mesh's face normals,
    weighted by area) is returned: the set's order, which closes the most on flat
    faces and balls; and the outermost first, each kept sphere standing in only for
    neighbours whose normals lie within WALL_FACET of its own, which keeps the outer
    polygon of a foot rather than its middle (a rook's at 6 across: 9 of the 27
    spheres under its foot, not 17)."""
    from scipy.spatial import cKDTree

    from dempipe.spheres.surface import MeshQueries

    c = np.asarray(centers, dtype=np.float64).reshape(-1, 3)
    d = float(diameter)
    n = c.shape[0]
    out = np.zeros(n)
    if n < 2:
        return out
    tree = cKDTree(c)
    # each sphere's normal: towards its closest point of the mesh
    gap, q = MeshQueries(np.asarray(vertices, dtype=np.float64), faces, 2.0 * d).closest(c)
    normal = np.where(np.isfinite(gap)[:, None], q - c, 0.0)
    size = np.linalg.norm(normal, axis=1)
    normal = np.where(size[:, None] > 0.0, normal / np.where(size > 0.0, size, 1.0)[:, None],
                      [[0.0, 0.0, 1.0]])
    k = np.arange(WALL_DIRECTIONS) + 0.5
    z = 1.0 - 2.0 * k / WALL_DIRECTIONS
    turn = np.pi * (1.0 + np.sqrt(5.0)) * k
    spiral = np.column_stack([np.sqrt(1.0 - z * z) * np.cos(turn),
                              np.sqrt(1.0 - z * z) * np.sin(turn), z])
    tol = WALL_TOLERANCE * d

    def reach(i, u):                                    # rows i along directions u (.., 3)
        au = np.einsum("...j,...kj->...k", rows[i, 3:6], u)
        return np.minimum(
            np.einsum("...j,...kj->...k", c[i] + rows[i, 0:3], u)
            + rows[i, 9, None] * np.sqrt(np.clip(1.0 - au * au, 0.0, None))
            + rows[i, 10, None],
            np.einsum("...j,...kj->...k", c[i], u) + 0.5 * d + rows[i, 11, None])

    def cone(m):                                        # (len(m), L, 3) round normal[m]
        nm = normal[m]
        pick = np.where(np.abs(nm[:, 0:1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
        e1 = np.cross(nm, pick)
        e1 /= np.linalg.norm(e1, axis=1)[:, None]
        e2 = np.cross(nm, e1)
        out = [nm]
        for tilt in WALL_CONE:
            for phi in np.linspace(0.0, 2.0 * np.pi, 8, endpoint=False):
                out.append(np.cos(tilt) * nm + np.sin(tilt) * (
                    np.cos(phi) * e1 + np.sin(phi) * e2))
        return np.stack(out, axis=1)

    def covered(pairs):
        """The candidates (column 0) that their pairs' kept spheres (column 1) reach
        every wall for, within the tolerance; pairs sorted by candidate."""
        done = np.zeros(0, dtype=np.int64)
        if pairs.shape[0] == 0:
            return done
        # in blocks of candidates, each with all its pairs: memory ~ pairs × directions
        start = np.flatnonzero(np.r_[True, pairs[1:, 0] != pairs[:-1, 0]])
        bounds = np.r_[start, pairs.shape[0]]
        step = max(1, int(WALL_BLOCK // max(1, pairs.shape[0] // max(1, start.size))))
        for b0 in range(0, start.size, step):
            part = pairs[bounds[b0]:bounds[min(b0 + step, start.size)]]
            first = start[b0:b0 + step] - bounds[b0]
            who = part[first, 0]
            group = np.repeat(np.arange(who.size), np.diff(np.r_[first, part.shape[0]]))
            ok = np.ones(who.size, dtype=bool)
            for u in (spiral[None], cone(who)):
                best = np.maximum.reduceat(
                    reach(part[:, 1], u[group] if u.shape[0] > 1 else u), first, axis=0)
                ok &= np.all(best >= reach(who, u) - tol, axis=1)
            done = np.concatenate([done, who[ok]])
        return done

    pairs = tree.query_pairs(2.0 * WALL_SPACING * d, output_type="ndarray")
    pairs = np.concatenate([pairs, pairs[:, ::-1]])
    pairs = pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))]
    near_of = tree.query_ball_point(c, WALL_SPACING * d)

    def cover(order, facet):
        """Rounds until no sphere is open: the open ones kept greedily in ``order``
        WALL_SPACING d apart (a kept one closing only its neighbours whose normals lie
        within ``facet`` [rad] of its own; None: all of them), then each other open
        one left out where the kept cover it."""
        out = np.zeros(n)
        kept = np.zeros(n, dtype=bool)
        open_ = np.ones(n, dtype=bool)
        while open_.any():
            near = ~open_
            for i in order[open_[order]]:
                if not near[i]:
                    kept[i] = True
                    j = np.asarray(near_of[i], dtype=np.int64)
                    if facet is not None:
                        j = j[normal[j] @ normal[i] >= np.cos(facet)]
                    near[j] = True
            open_ &= ~kept
            gone = covered(pairs[open_[pairs[:, 0]] & kept[pairs[:, 1]]])
            out[gone] = 1.0
            open_[gone] = False
        return out

    # the directions a body rests on a wall: its faces' outward normals, in bins of
    # about a degree, with their area, where that is at least d² (a face that carries
    # more than a sphere or two; a curved part touches a wall at one point anyway)
    fv = np.asarray(vertices, dtype=np.float64)[np.asarray(faces, dtype=np.int64)]
    fn = np.cross(fv[:, 1] - fv[:, 0], fv[:, 2] - fv[:, 0])
    area = np.linalg.norm(fn, axis=1)
    face_u, where = np.unique(np.round(fn[area > 0.0] / area[area > 0.0, None] * 50.0),
                              axis=0, return_inverse=True)
    face_w = 0.5 * np.bincount(where.ravel(), weights=area[area > 0.0],
                               minlength=face_u.shape[0])
    face_u = face_u[face_w >= d * d] / np.linalg.norm(face_u[face_w >= d * d], axis=1)[:, None]
    face_w = face_w[face_w >= d * d]

    def resting(out):
        """The spheres a wall meets within REST_GAP d of the deepest, summed over the
        faces' directions weighted by their area: what a face resting on a wall carries."""
        live = np.flatnonzero(out == 0.0)
        step = max(1, WALL_BLOCK * WALL_DIRECTIONS // max(1, live.size))
        total = 0.0
        for b0 in range(0, face_u.shape[0], step):
            r = reach(live, face_u[None, b0:b0 + step])           # (live, directions)
            total += float(face_w[b0:b0 + step]
                           @ np.count_nonzero(r >= r.max(axis=0) - REST_GAP * d, axis=0))
        return total

    plain = cover(np.arange(n), None)
    outer = cover(np.argsort(-np.linalg.norm(c, axis=1), kind="stable"), WALL_FACET)
    return outer if resting(outer) < resting(plain) else plain


def _shrinking_ball(points, inward, tau) -> np.ndarray:
    """Per point p_i with inward unit normal m_i: the radius ρ of the largest ball
    tangent at p_i (centre p_i + ρ m_i) that holds no other point deeper than ``tau``
    inside it (surface.shrinking_ball)."""
    from dempipe.spheres.surface import shrinking_ball

    out = np.empty(points.shape[0])
    shrinking_ball(np.ascontiguousarray(points, dtype=np.float64),
                   np.ascontiguousarray(inward, dtype=np.float64), float(tau), out)
    return out


#: Points round a ring's circle at which lattice_tori tests that its tube stays inside,
#: and by how much [d] it may come nearer the surface there than at the sphere.
RING_CHECKS = 32
RING_SLACK = 0.02
#: A lattice set takes tori only where at least this share of its mesh's surface is
#: curved (a fit follows it): a coarse set's odd fit (one on a king's crown at 6 spheres
#: across the pawn) would change how its body meets walls for nothing. Flat faces take
#: none: where a lattice is flush with one it is already flat, and balls tangent at a
#: shell's scattered points would press a face landing flat off centre.
MIN_ROUND_SHARE = 0.1
#: A lattice sphere less than this share of r short of depth r under the mesh is flush
#: (an icosphere of 4 subdivisions comes 0.2 % short of its radius).
OWN_SLACK = 0.02
#: Such a sphere meets walls as the ball of its depth less this [d]: inside the tori
#: and rims where the body is round, so that it takes none of their load as the line
#: of contact passes it (tangent, each pass's dashpot took 4 % a second of a rolling
#: frustum's speed); where no torus or rim is, the body rests this much deeper.
OWN_INSET = 0.05
#: The spacing [d] of the shell lattice_tori fits a lattice's tori to: dense enough that
#: a fit of FIT_NEIGHBOURS spans a smooth patch of a piece 6 spheres across. Its own
#: constant, not the surface mode's default: a lattice's cache key ignores the surface
#: options, so what it holds must not follow them.
LATTICE_FIT_SPACING = 0.3


def lattice_tori(centers, diameter: float, vertices, faces) -> np.ndarray:
    """(N, COLUMNS) per sphere of a lattice set's ``centers`` (body frame [m]): the mesh's
    inscribed tori (inscribed_tori, fitted to the surface-following shell the mesh would
    have at this d, spheres/surface.py), each given to the sphere that is outermost under
    the surface where it was fitted, so that a lattice set meets a wall through its mesh's
    curvature too: a ball rolls as a ball however coarse its lattice's terraces.

    A lattice's envelope lies up to its terraces' depth G under the mesh, not REACH d, so
    a sphere's torus may touch up to G + REACH d deeper than the sphere (column 11): G is
    the largest distance from a point of the mesh where it is round to the envelope. A
    torus is inside the mesh, so its overlap is never more than the mesh's own; a ring
    whose tube leaves the mesh somewhere round its circle (fitted on a surface that is not
    one of revolution about its axis: a knight's mane) is only its tube's ball at the
    sphere, which the shrinking-ball test holds inside.

    On a solid of revolution (revolution_axis) a torus is swept about the body's axis
    through the same tube wherever that ring stays inside the mesh: a cone's side, whose
    own fit leans with the side and left only its tube's ball, over which the body
    rolled from ball to ball. A shape with tori also gets its rims (rims, _rim_rows): a
    cylinder or a pawn tipped onto the edge of its base rolls on the edge's circle.

    On a shape with tori, every other sphere whose centre is less than r deep (more than
    OWN_SLACK r short) meets walls as the ball of its depth less OWN_INSET d (a = 0), so
    that none sticks out of the mesh either (a cylinder's rim) nor takes load from the
    tori; the rest are their own (inscribed_tori's rows for those). A shape with no
    round surface a fit can follow at this d (the quickstart's pieces at 6 across) has
    no tori nor rims and is left as it is."""
    from dempipe.spheres.surface import MeshQueries

    c = np.asarray(centers, dtype=np.float64).reshape(-1, 3)
    d = float(diameter)
    r = 0.5 * d
    out = np.zeros((c.shape[0], COLUMNS))
    out[:, 10] = r
    out[:, 11] = REACH * d
    mesh = repaired_mesh(np.asarray(vertices, dtype=np.float64), faces)
    if c.shape[0] == 0 or len(mesh.faces) == 0:
        return out
    rows = _round_rows(c, d, mesh, out)
    if rows.size == 0:
        return out
    rims = _rim_rows(c, d, mesh, out, rows)
    # a lattice sphere whose centre is nearer the surface than r sticks out of the mesh
    # (a cylinder's rim): against a wall it is the ball of its depth, never more than
    # the mesh, or a body rolling on its tori would ride on what its lattice adds
    own = np.ones(c.shape[0], dtype=bool)
    own[rows] = False
    own[rims] = False
    depth, _ = MeshQueries(np.asarray(mesh.vertices, dtype=np.float64), mesh.faces,
                           d).closest(c[own])
    out[np.flatnonzero(own), 10] = np.where(depth < (1.0 - OWN_SLACK) * r,
                                            np.maximum(depth - OWN_INSET * d, 0.0), r)
    return out


def _round_rows(c, d, mesh, out) -> np.ndarray:
    """lattice_tori's round surfaces: writes the tori of the lattice spheres ``c`` that
    are outermost under them into ``out``; returns those rows."""
    from scipy.spatial import cKDTree

    from dempipe.mesh.winding import inside_mask
    from dempipe.spheres.surface import METRIC_SPACING, grid_samples, surface_centers

    r = 0.5 * d
    sc = surface_centers(mesh, d, LATTICE_FIT_SPACING)
    shell = sc.centers[:sc.shell]
    t = inscribed_tori(shell, d, mesh.vertices, mesh.faces, curved_only=True)
    grown = np.any(t[:, 0:3] != 0.0, axis=1)
    if not grown.any():
        return np.zeros(0, dtype=np.int64)
    # the surface where it is round, each point's outermost sphere and its gap
    pts, _ = grid_samples(mesh.vertices, mesh.faces, METRIC_SPACING * d)
    _, fit = cKDTree(shell).query(pts)
    if np.count_nonzero(grown[fit]) < MIN_ROUND_SHARE * pts.shape[0]:
        return np.zeros(0, dtype=np.int64)
    pts, fit = pts[grown[fit]], fit[grown[fit]]
    gap, owner = cKDTree(c).query(pts)
    gap -= r
    # each owner takes the torus fitted nearest the point where it is closest to the mesh
    order = np.lexsort((gap, owner))
    first = np.ones(order.size, dtype=bool)
    first[1:] = owner[order[1:]] != owner[order[:-1]]
    rows = owner[order[first]]
    k = fit[order[first]]
    # only the tori given to a sphere are held inside the mesh (a few of the shell's)
    used, k = np.unique(k, return_inverse=True)
    t = _inside_mesh(shell[used], t[used], mesh, d, inside_mask)
    axis = revolution_axis(mesh)
    if axis is not None:
        # on a solid of revolution, the ring about its axis through the same tube
        # wherever that ring is whole (a cone's side, which the fit's own ring, about
        # the side's line, leaves: the body rolled over the tube's balls)
        about = _inside_mesh(shell[used], _about_axis(shell[used], t, *axis), mesh, d,
                             inside_mask)
        swap = about[:, 9] > 0.0
        t[swap] = about[swap]
    kept = np.any(t[k, 0:3] != 0.0, axis=1)
    rows, k = rows[kept], k[kept]
    out[rows, 0:3] = shell[used][k] + t[k, 0:3] - c[rows]
    out[rows, 3:11] = t[k, 3:11]
    out[rows, 11] = max(0.0, float(gap.max())) + REACH * d
    return rows


#: A mesh edge whose faces turn by more than this [rad], outwards, is sharp: a chain
#: of them round a circle is a rim (a cylinder's, a chess piece's base).
RIM_ANGLE = np.radians(30.0)
#: A chain is a rim where its vertices lie within this share of its radius of one
#: circle, at least RIM_MIN_EDGES of them, with no gap round it wider than RIM_GAP
#: [rad]: a whole polygonised circle (a box's edges, a notched crown are none).
RIM_RESIDUAL = 0.01
RIM_MIN_EDGES = 12
RIM_GAP = np.radians(30.0)
#: Points per d of rim at which rim rings find the lattice spheres that hold them.
RIM_SAMPLES = 10


def rims(mesh) -> list:
    """The mesh's rims: chains of sharp convex edges (RIM_ANGLE) round a whole circle
    (RIM_RESIDUAL, RIM_MIN_EDGES, RIM_GAP), each as (centre (3,), axis (3,), radius):
    the circle inscribed in its polygon, so that it lies on the mesh (body frame [m])."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    sharp = (np.asarray(mesh.face_adjacency_angles) > RIM_ANGLE) & np.asarray(
        mesh.face_adjacency_convex, dtype=bool)
    edges = np.asarray(mesh.face_adjacency_edges)[sharp]
    if edges.shape[0] < RIM_MIN_EDGES:
        return []
    verts = np.asarray(mesh.vertices, dtype=np.float64)
    n = verts.shape[0]
    graph = coo_matrix((np.ones(edges.shape[0]), (edges[:, 0], edges[:, 1])), shape=(n, n))
    _, label = connected_components(graph, directed=False)
    # the chains, each its edges (a rock has thousands of short ones: one sort, no scan)
    order = np.argsort(label[edges[:, 0]], kind="stable")
    cut = np.flatnonzero(np.diff(label[edges[order, 0]])) + 1
    found = []
    for part in np.split(order, cut):
        chain = edges[part]
        if chain.shape[0] < RIM_MIN_EDGES:
            continue
        p = verts[np.unique(chain)]
        centre = p.mean(axis=0)
        _, _, vt = np.linalg.svd(p - centre, full_matrices=False)
        axis, e1, e2 = vt[2], vt[0], vt[1]
        u = (p - centre) @ e1
        w = (p - centre) @ e2
        # the circle through them: u² + w² + D u + E w + F = 0, least squares
        sol = np.linalg.lstsq(np.column_stack([u, w, np.ones_like(u)]), -(u * u + w * w),
                              rcond=None)[0]
        cu, cw = -0.5 * sol[0], -0.5 * sol[1]
        radius2 = cu * cu + cw * cw - sol[2]
        if radius2 <= 0.0:
            continue
        radius = float(np.sqrt(radius2))
        off = np.hypot(u - cu, w - cw) - radius
        height = (p - centre) @ axis
        if max(np.abs(off).max(), np.abs(height).max()) > RIM_RESIDUAL * radius:
            continue
        turn = np.sort(np.arctan2(w - cw, u - cu))
        if np.diff(np.append(turn, turn[0] + 2.0 * np.pi)).max() > RIM_GAP:
            continue
        centre = centre + cu * e1 + cw * e2
        mid = 0.5 * (verts[chain[:, 0]] + verts[chain[:, 1]]) - centre
        inner = float(np.sqrt(np.min(np.sum(mid * mid, axis=1) - (mid @ axis) ** 2)))
        found.append((centre, axis, inner))
    return found


def _rim_rows(c, d, mesh, out, taken) -> np.ndarray:
    """lattice_tori's rims (rims): each rim's ring (a circle, tube 0) goes to the lattice
    spheres nearest it round its circle that hold no torus (``taken``) and are no
    farther from it than the tori's terraces (their reach less REACH d: so the model's
    largest reach, by which every sphere marks its walls, is the tori's), with a reach
    of their largest gap to it; written into ``out``, those rows returned. Two rims of
    one circle closer than d along their axis (a chess piece's plinth, a coin's edge)
    are one band (_bands), which the spheres along both hold: a piece on its side rests
    on the upper edge, tipped onto its foot on the lower. The largest rims choose
    first. A body tipped onto a rim (a piece on its side, a coin on its edge) rolls on
    its circle, not on the lattice's corners there."""
    from scipy.spatial import cKDTree

    found = _bands(sorted(rims(mesh), key=lambda rim: -rim[2]), d)
    if not found:
        return np.zeros(0, dtype=np.int64)
    r = 0.5 * d
    limit = float(out[taken, 11].max()) - REACH * d
    free = np.ones(c.shape[0], dtype=bool)
    free[taken] = False
    tree = cKDTree(c)
    k = min(8, c.shape[0])
    given = []
    for centre, axis, radius, height in found:
        m = max(RIM_MIN_EDGES, int(np.ceil(2.0 * np.pi * radius * RIM_SAMPLES / d)))
        phi = np.linspace(0.0, 2.0 * np.pi, m, endpoint=False)
        e1 = np.cross(axis, [1.0, 0.0, 0.0] if abs(axis[0]) < 0.9 else [0.0, 1.0, 0.0])
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(axis, e1)
        ring = radius * (np.cos(phi)[:, None] * e1 + np.sin(phi)[:, None] * e2)
        pts = centre + ring
        if height > 0.0:
            pts = np.concatenate([pts, pts + height * axis])
        dist, near = tree.query(pts, k=k)
        dist, near = dist.reshape(len(pts), k), near.reshape(len(pts), k)
        usable = free[near] & (dist - r <= limit)
        pick = np.argmax(usable, axis=1)            # the nearest free one near enough
        ok = usable[np.arange(len(pts)), pick]
        if not ok.any():
            continue
        rows = near[np.arange(len(pts)), pick][ok]
        gap = dist[np.arange(len(pts)), pick][ok] - r
        reach = max(0.0, float(gap.max())) + REACH * d
        rows = np.unique(rows)
        rows = rows[np.any(c[rows] != centre, axis=1)]    # (a zero row is the sphere's own)
        rel = c[rows] - centre
        radial = rel - np.outer(rel @ axis, axis)
        size = np.linalg.norm(radial, axis=1)
        radial = np.where(size[:, None] > 1e-12 * d, radial / np.maximum(size, 1e-300)[:, None],
                          e1)
        out[rows, 0:3] = centre - c[rows]
        out[rows, 3:6] = axis
        out[rows, 6:9] = radial
        out[rows, 9] = radius
        out[rows, 10] = 0.0
        out[rows, 11] = reach
        out[rows, 12] = height
        free[rows] = False
        given.append(rows)
    return np.concatenate(given) if given else np.zeros(0, dtype=np.int64)


def _bands(found, d) -> list:
    """``found`` rims (centre, axis, radius) as (centre, axis, radius, height): two of
    one circle (the same radius and axis line, RIM_RESIDUAL) less than d apart along
    it are one band from the first, its axis turned towards the second, ``height``
    their distance; any other rim is a band of height 0. Order kept."""
    used = [False] * len(found)
    out = []
    for i, (ci, ai, ri) in enumerate(found):
        if used[i]:
            continue
        height, axis = 0.0, ai
        for j in range(i + 1, len(found)):
            cj, aj, rj = found[j]
            if used[j] or abs(rj - ri) > RIM_RESIDUAL * ri or abs(ai @ aj) < 1.0 - 1e-6:
                continue
            off = cj - ci
            along = float(off @ ai)
            if 0.0 < abs(along) < d and np.linalg.norm(off - along * ai) <= RIM_RESIDUAL * ri:
                height, axis = abs(along), ai * np.sign(along)
                used[j] = True
                break
        out.append((ci, axis, ri, height))
    return out


#: Two principal moments of inertia within this share of the largest are equal: the
#: third's axis may be one of revolution (revolution_axis).
REVOLUTION_MOMENTS = 1e-4


def revolution_axis(mesh):
    """(point, unit axis) of the mesh's axis of symmetry if two of its principal
    moments are equal and the third is not (a cylinder, a cone, a chess piece, a
    ring: REVOLUTION_MOMENTS), else None (body frame [m]). Equal moments do not make a
    solid of revolution (a square prism has them): callers keep only the rings about
    it that stay inside the mesh all round (_inside_mesh)."""
    moments, vectors = np.linalg.eigh(np.asarray(mesh.moment_inertia, dtype=np.float64))
    tol = REVOLUTION_MOMENTS * float(np.abs(moments).max())
    if moments[2] - moments[0] <= tol:
        return None                              # a ball, a cube: every axis alike
    if moments[1] - moments[0] <= tol:
        return np.asarray(mesh.center_mass, dtype=np.float64), vectors[:, 2]
    if moments[2] - moments[1] <= tol:
        return np.asarray(mesh.center_mass, dtype=np.float64), vectors[:, 0]
    return None


def _about_axis(shell, t, point, axis) -> np.ndarray:
    """``t`` (the rows of ``shell`` after _inside_mesh) with each torus's tube, where it
    is under its sphere, swept about ``axis`` through ``point`` instead: a ring of
    revolution touching the surface where the fit did, or a ball where the tube's
    centre is on the axis."""
    t = t.copy()
    idx = np.flatnonzero(np.any(t[:, 0:3] != 0.0, axis=1))
    tube = shell[idx] + t[idx, 0:3] + t[idx, 9, None] * t[idx, 6:9]
    rel = tube - point
    centre = point + np.outer(rel @ axis, axis)
    radial = tube - centre
    a = np.linalg.norm(radial, axis=1)
    ring = a > 1e-6 * t[idx, 10]
    t[idx, 0:3] = np.where(ring[:, None], centre, tube) - shell[idx]
    t[idx, 3:6] = np.where(ring[:, None], axis, 0.0)
    t[idx, 6:9] = np.where(ring[:, None], radial / np.where(ring, a, 1.0)[:, None], 0.0)
    t[idx, 9] = np.where(ring, a, 0.0)
    return t


def _inside_mesh(shell, t, mesh, diameter, inside_mask) -> np.ndarray:
    """``t`` (inscribed_tori's rows for ``shell``) held inside the mesh itself, each still
    touching it where it was fitted. The shrinking-ball test holds a tube within
    SHRINK_SLACK d of the shell only, so near a cap a cylinder's tube pokes a few
    hundredths of d through it, which a lattice's reach would let through, and a body
    would rock on those tori. So each tube's radius becomes at most its centre's
    distance from the mesh (all round a ring's circle), its circle moved out by what it
    lost (a ring's radius grows, a ball's centre moves towards the surface), so that it
    touches where the sphere's fit did. A ring is kept where its tube then stays that far
    inside all round its circle (within RING_SLACK d: a surface of revolution about its
    axis), else it becomes its tube's ball at the sphere; a torus whose tube's centre is
    outside the mesh is dropped."""
    from dempipe.spheres.surface import MeshQueries

    t = t.copy()
    idx = np.flatnonzero(np.any(t[:, 0:3] != 0.0, axis=1))
    if idx.size == 0:
        return t
    ring = t[idx, 9] > 0.0
    normal = -t[idx, 0:3] / np.linalg.norm(t[idx, 0:3], axis=1)[:, None]
    normal = np.where(ring[:, None], t[idx, 6:9], normal)         # outward at the sphere
    axis = t[idx, 3:6]
    side = np.cross(axis, normal)
    phi = np.linspace(0.0, 2.0 * np.pi, RING_CHECKS, endpoint=False)
    queries = MeshQueries(np.asarray(mesh.vertices, dtype=np.float64), mesh.faces,
                          float(t[idx, 10].max()) + diameter)

    def gaps(o, a):                     # each tube centre's depth under the surface
        tube = o[:, None, :] + a[:, None, None] * (
            np.cos(phi)[None, :, None] * normal[:, None, :]
            + np.sin(phi)[None, :, None] * side[:, None, :])
        # a ball's points are all its centre: one query
        pick = np.where(ring[:, None], True, np.arange(RING_CHECKS)[None, :] == 0)
        flat = tube[pick]
        g, _ = queries.closest(flat)
        out = np.empty(tube.shape[:2])
        out[pick] = np.where(inside_mask(mesh, flat), g, -np.inf)
        return np.where(ring[:, None], out, out[:, 0:1])

    o = shell[idx] + t[idx, 0:3]
    a = t[idx, 9]
    b0 = t[idx, 10]
    g = gaps(o, a)
    b = np.minimum(b0, np.where(ring, g.min(axis=1), g[:, 0]))
    lost = np.where(np.isfinite(b), b0 - b, 0.0)
    a = np.where(ring, a + lost, 0.0)
    o = np.where(ring[:, None], o, o + lost[:, None] * normal)
    g = gaps(o, a)
    whole = ring & (g.min(axis=1) >= b - RING_SLACK * diameter)
    o = np.where((ring & ~whole)[:, None], o + a[:, None] * normal, o)
    b = np.minimum(b, np.where(whole, g.min(axis=1), g[:, 0]))
    t[idx, 0:3] = o - shell[idx]
    t[idx, 3:6] = np.where(whole[:, None], axis, 0.0)
    t[idx, 6:9] = np.where(whole[:, None], normal, 0.0)
    t[idx, 9] = np.where(whole, a, 0.0)
    t[idx, 10] = b
    out = idx[~np.isfinite(b) | (b <= 0.0)]
    t[out, 0:10] = 0.0
    t[out, 10] = 0.5 * diameter
    return t
