"""The report's plots: error against run time, and error against each setting.

    files = plot_report(result, Path("report/"))   # error_vs_time.png, error_vs_setting.png

matplotlib is optional (the `report` extra) and imported only here, when a plot is
drawn; ``require_matplotlib`` says so up front, before any run is baked.
"""

from __future__ import annotations

import io
import math
from pathlib import Path

from dempipe.report.results import ReportError, ReportResult, write_atomically


def require_matplotlib():
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        raise ReportError("the report's plots need matplotlib: pip install 'dempipe[report]' "
                          "(or pass --no-plots)") from None


def _save(fig, path: Path) -> Path:
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    FigureCanvasAgg(fig)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100)
    return write_atomically(path, buf.getvalue())


def _log_axes(ax, xticks=None) -> None:
    """Log-log axes labelled 1, 2, 5, 10, ... in plain numbers."""
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    ax.set_xscale("log")
    ax.set_yscale("log")
    for axis, lim in ((ax.xaxis, ax.get_xlim()), (ax.yaxis, ax.get_ylim())):
        narrow = math.log10(max(lim) / min(lim)) < 3.0
        axis.set_major_locator(LogLocator(base=10.0, subs=(1.0, 2.0, 5.0) if narrow else (1.0,)))
        axis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
        axis.set_minor_formatter(NullFormatter())
    if xticks:
        ax.set_xticks(xticks)
    ax.grid(True, which="both", alpha=0.3)


def plot_report(r: ReportResult, out: Path) -> list:
    """error_vs_time.png and error_vs_setting.png; returns their paths.

    The reference (error 0 by definition) has no place on a log axis: its run time
    is the dotted line.
    """
    from matplotlib.figure import Figure

    ok = [u for u in r.runs if u.ok and not u.reference and math.isfinite(u.error)
          and u.error > 0]
    res_lo, res_hi = min(u.resolution for u in r.runs), max(u.resolution for u in r.runs)
    fig = Figure(figsize=(6.4, 4.4))
    ax = fig.add_subplot()
    for i, k in enumerate(sorted({u.stiffness_factor for u in r.runs})):
        pts = [u for u in ok if u.stiffness_factor == k]
        if pts:
            ax.scatter([u.wall_s for u in pts], [u.error for u in pts], marker="os^Dv<>p"[i % 8],
                       c=[u.resolution for u in pts], cmap="viridis", vmin=res_lo, vmax=res_hi,
                       label=f"stiffness ×{k:g}", edgecolors="k", linewidths=0.5, zorder=3)
    front = sorted((u for u in ok if u.pareto), key=lambda u: u.wall_s)
    if front:
        ax.plot([u.wall_s for u in front], [u.error for u in front], "o-", color="C3", lw=1.0,
                ms=11, mfc="none", label="Pareto front", zorder=2)
    for u in ok:
        ax.annotate(f"r{u.resolution} dt×{u.dt_factor:g}", (u.wall_s, u.error), fontsize=6,
                    xytext=(4, 3), textcoords="offset points")
    if r.recommended is not None and r.recommended.error > 0:    # the reference: its line
        u = r.recommended
        ax.scatter([u.wall_s], [u.error], marker="*", s=160, c="C3", zorder=4,
                   label="recommended")
    ax.axhline(r.tolerance, color="0.4", ls="--", lw=0.8, label=f"tolerance {r.tolerance:g}")
    ax.axvline(r.reference.wall_s, color="0.4", ls=":", lw=0.8,
               label=f"reference ({r.reference.label}"
               + (", recommended)" if r.recommended is r.reference else ")"))
    _log_axes(ax)
    ax.set_xlabel("run time [s] (simulation, wall clock)")
    ax.set_ylabel(f"error [body sizes] at t = {r.horizon:.3g} s")
    ax.set_title(f"{Path(r.scene).name}: error against run time (colour: resolution "
                 f"{res_lo}–{res_hi})", fontsize=9)
    ax.legend(fontsize=6, loc="best")
    fig.tight_layout()
    files = [_save(fig, out / "error_vs_time.png")]

    fig = Figure(figsize=(9.6, 3.9))
    a1, a2 = fig.add_subplot(1, 2, 1), fig.add_subplot(1, 2, 2)
    ress = sorted({res for (_, res, _) in r.shapes})
    for name, mode in dict.fromkeys((n, m) for (n, _, m) in r.shapes):
        row = [res for res in ress if (name, res, mode) in r.shapes]
        a1.plot(row, [r.shapes[(name, res, mode)].hausdorff for res in row], "o-", lw=0.8,
                ms=3, alpha=0.7, label=f"{name}{f' {mode}' if mode else ''}: Hausdorff")
    k1 = [u for u in ok if u.stiffness_factor == 1.0]
    for f in sorted({u.dt_factor for u in k1}, reverse=True):
        row = sorted((u for u in k1 if u.dt_factor == f), key=lambda u: u.resolution)
        a1.plot([u.resolution for u in row], [u.error for u in row], "ks-", lw=1.4, ms=5,
                alpha=1.0 if f == max(u.dt_factor for u in k1) else 0.5,
                label=f"motion, dt×{f:g}")
    _log_axes(a1, ress)
    a1.set_xlabel("resolution (spheres across the smallest shape)")
    a1.set_ylabel("error (shape sizes; motion: body sizes)")
    a1.legend(fontsize=6)
    physics = {}
    for u in r.runs:
        if u.ok and u.stiffness_factor == 1.0:
            physics.setdefault(u.dt_factor, u.physics)
    dts = sorted(physics)
    a2.plot(dts, [physics[f]["bounce"] for f in dts], "o-", color="C1",
            label="bounce: error of e²")
    a2.plot(dts, [physics[f]["rolling"] for f in dts], "v-", color="C2",
            label="rolling: 5/7 v0 and travel")
    for res in sorted({u.resolution for u in k1}):
        row = sorted((u for u in k1 if u.resolution == res), key=lambda u: u.dt_factor)
        a2.plot([u.dt_factor for u in row], [u.error for u in row], "s--", ms=5, lw=1.0,
                color=_viridis((res - res_lo) / max(res_hi - res_lo, 1)),
                label=f"motion, r{res}")
    _log_axes(a2, dts)
    a2.set_xlabel("dt factor (1: the scene's own dt)")
    a2.legend(fontsize=6)
    fig.suptitle(f"{Path(r.scene).name}: error against resolution (stiffness ×1) and dt "
                 f"(the reference r{r.reference.resolution} dt×{r.reference.dt_factor:g} "
                 "has motion error 0)", fontsize=9)
    fig.tight_layout()
    files.append(_save(fig, out / "error_vs_setting.png"))
    return files


def _viridis(x: float):
    from matplotlib import colormaps

    return colormaps["viridis"](x)
