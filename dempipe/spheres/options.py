"""How a sphere set is built: its mode, the surface mode's spacing and the inside test's
threshold. Every option is part of the sphere-set cache key."""

from __future__ import annotations

from dataclasses import asdict, dataclass

from dempipe.errors import ShapeError

#: Bumped whenever the surface mode's output for the same input could change (its
#: cache keys change; the lattice's do not): 2, thin-part rays no longer hit a face
#: they run along; 3, a thin part's medial centre only where it sticks out by less
#: than the offset leaves uncovered (not at the acute edges of thick parts); 4, an
#: offset centre is inside by the parity of a ray's crossings; 5, by the winding
#: number (overlapping parts, meshes with holes).
SURFACE_BUILDER = 5

#: Default spacing of the surface mode's shell centres, as a fraction of the diameter
#: d. Chosen from the measured bump height (docs/spheres.md, "Surface mode"): at 0.3 d
#: the envelope of a flat face or a round one dips at most ~0.03 d between neighbours.
#: Here rather than in spheres.surface, so that `dempipe check` does not import numba.
DEFAULT_SPACING = 0.3
#: The spacings a surface set may have, as fractions of d (BuildOptions, the scene key
#: surface_spacing, `dempipe spheres --spacing`): below 0.05 a set has hundreds of
#: spheres per d² of surface; 1 is the lattice's pitch.
SPACING_RANGE = (0.05, 1.0)
#: The sphere-set modes: "lattice" (solid voxelization, Harada et al.) and "surface"
#: (centres on the inward offset of the surface, so round bodies roll).
MODES = ("lattice", "surface")
#: What a scene may name: a mode, or "auto": per shape, "surface" where most of the
#: mesh is curved or slanted to the lattice (fidelity.ROUND_SHARE: it would not roll
#: on a lattice), else "lattice" (spheres.fidelity.auto_mode).
SCENE_MODES = MODES + ("auto",)
#: The mode a scene gets when it names none (docs/spheres.md, "Surface mode": why).
DEFAULT_MODE = "lattice"


@dataclass(frozen=True)
class BuildOptions:
    """Options of the sphere-set builder (all part of the cache key).

    winding_threshold: a lattice cell is kept when ``|winding number|`` at its centre
        exceeds this (0.5: the generalized winding number's natural inside test).
    mode: "lattice" (solid voxelization: the cells inside the mesh) or "surface"
        (centres on the inward offset of the surface at d/2, dempipe.spheres.surface).
    spacing: surface mode only: spacing of the shell's centres as a fraction of the
        diameter, in [0.05, 1].
    """

    winding_threshold: float = 0.5
    mode: str = DEFAULT_MODE
    spacing: float = DEFAULT_SPACING

    def __post_init__(self):
        t = self.winding_threshold
        if not (isinstance(t, (int, float)) and 0.0 < float(t) < 1.0):
            raise ShapeError(f"winding_threshold must be between 0 and 1, got {t!r}")
        if self.mode not in MODES:
            raise ShapeError(f"sphere mode must be one of {', '.join(MODES)}, got {self.mode!r}")
        h = self.spacing
        lo, hi = SPACING_RANGE
        if isinstance(h, bool) or not isinstance(h, (int, float)) or not lo <= float(h) <= hi:
            raise ShapeError(f"surface spacing must be a fraction of the diameter in "
                             f"[{lo:g}, {hi:g}], got {h!r}")

    def key_text(self) -> str:
        items = asdict(self)
        if self.mode == "lattice":
            # the lattice ignores the surface options: its keys stay those of before
            items = {k: v for k, v in items.items() if k not in ("mode", "spacing")}
        else:
            items["surface_builder"] = SURFACE_BUILDER
        return repr(sorted((k, repr(v)) for k, v in items.items()))


DEFAULT_OPTIONS = BuildOptions()
