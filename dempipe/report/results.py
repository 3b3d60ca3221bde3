"""What a report measured: one bake of the sweep (:class:`Run`), the whole result
(:class:`ReportResult`), and what the tables and plots derive from them."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

from dempipe.errors import DempipeError
from dempipe.pipeline.checkpoint import atomic_write


class ReportError(DempipeError):
    """A report's settings are unusable (bad sweep values, missing plotting extra)."""


#: The default horizon of the per-body motion error: this long after the median
#: body's first contact. Before any contact every run agrees (free flight is exact);
#: long after it, contacts have amplified every difference (chaos), whatever the
#: accuracy. A few frames of contact in between is where accuracy shows.
HORIZON_AFTER_CONTACT = 0.1


@dataclass
class Run:
    """One baked combination and everything measured about it (one CSV row)."""

    resolution: int
    dt_factor: float
    stiffness_factor: float
    reference: bool = False
    status: str = "ok"
    diameter: float = math.nan
    dt: float = math.nan
    steps: int = 0
    spheres: int = 0
    wall_s: float = math.nan
    memory_bytes: int = 0
    sphere_build_cold_s: float = math.nan
    sphere_build_cached_s: float = math.nan
    geometry: dict = field(default_factory=dict)      # worst shape: volume, inertia, hausdorff
    motion: dict = field(default_factory=dict)
    physics: dict = field(default_factory=dict)
    error: float = math.nan
    pareto: bool = False
    frames: object = None
    model: object = None
    pile: object = None
    mode: str | None = None          # sphere-set mode of the sweep's mode axis (None: none)
    law: str | None = None           # contact law of the sweep's law axis (None: none)
    envelope: dict = field(default_factory=dict)   # worst shape: hausdorff_d, bump_d

    @property
    def model_frames(self) -> int:
        """Frames stepped (the first is the initial state)."""
        return self.frames.n_frames - 1 if self.frames is not None else 0

    @property
    def label(self) -> str:
        mode = f" {self.mode}" if self.mode else ""
        law = f" {self.law}" if self.law else ""
        return (f"r{self.resolution} dt×{self.dt_factor:g} k×{self.stiffness_factor:g}"
                f"{mode}{law}")

    @property
    def ok(self) -> bool:
        return self.status == "ok"

    @property
    def s_per_step(self) -> float:
        return self.wall_s / self.steps if self.steps else math.nan

    @property
    def sim_seconds(self) -> float:
        return self.frames.times[-1] if self.frames is not None else math.nan

    @property
    def s_per_sim_s(self) -> float:
        return self.wall_s / self.sim_seconds if self.sim_seconds else math.nan


@dataclass
class ReportResult:
    """What run_report measured and wrote."""

    runs: list
    reference: Run
    recommended: Run | None
    #: (shape name, resolution, sphere-set mode of the sweep's axis or None) ->
    #: spheres.fidelity.GeometryError
    shapes: dict
    files: list
    wall_s: float
    scene: str
    material: str
    pile: bool
    duration: float
    horizon: float
    tolerance: float
    bodies: int
    target_overlap: float = 0.02
    #: bodies of the reference that touched something by the horizon (0: the motion
    #: errors measured free flight only, which every run gets right)
    touched: int = -1
    rolling_tolerance: float | None = None
    stage: str | None = None    # the USD stage's file name when it was given as the scene


def seconds(x: float) -> str:
    """A time in seconds to three figures (0.0436, 4.06, 42.8; 136 and up whole): a
    fixed one decimal showed a small scene's 0.04 s run as "0.0"."""
    if x is None or not math.isfinite(x):
        return "—"
    return f"{x:.0f}" if abs(x) >= 100 else f"{x:.3g}"


def within_tolerances(u: Run, tolerance: float, rolling_tolerance: float | None) -> bool:
    """Whether run ``u`` may be recommended: measured, its error within ``tolerance``
    and, when given, its incline rolling error within ``rolling_tolerance`` (an incline
    that could not be measured, NaN, passes: it says nothing against it)."""
    if not (u.ok and u.error <= tolerance):
        return False
    return rolling_tolerance is None or not u.physics.get("incline", math.nan) > rolling_tolerance


def scene_settings(u: Run, target_overlap: float) -> list:
    """The scene-file lines that bake run ``u``'s setting."""
    lines = [f"resolution = {u.resolution}"]
    if u.mode:
        lines.append(f'spheres = "{u.mode}"')
    if u.law:
        lines.append(f'contact_law = "{u.law}"')
    if u.dt_factor != 1.0:
        per_frame = u.steps // max(u.model_frames, 1)
        lines.append(f"dt = {u.dt:.6g}   # {per_frame} steps per frame")
    if u.stiffness_factor != 1.0:
        lines.append(f"stiffness_target_overlap = {target_overlap / u.stiffness_factor ** 0.5:.4g}"
                     f"   # auto stiffness ×{u.stiffness_factor:g}; a material's own "
                     "stiffness: multiply it")
    return lines


def chaos_floor(r: ReportResult):
    """The run that differs from the reference only by the next larger dt factor, or None."""
    ref = r.reference
    same = [u for u in r.runs if u.ok and not u.reference and u.resolution == ref.resolution
            and u.stiffness_factor == ref.stiffness_factor and u.dt_factor > ref.dt_factor]
    return min(same, key=lambda u: u.dt_factor) if same else None


def write_atomically(path: Path, data: bytes) -> Path:
    """``data`` into ``path`` whole or not at all (pipeline.checkpoint.atomic_write:
    a temporary file beside it, fsync, rename); a ReportError naming the path when
    the OS refuses."""
    try:
        atomic_write(path, lambda fh: fh.write(data))
    except OSError as exc:
        raise ReportError(f"{path}: cannot write ({exc.strerror or exc})") from None
    return path
