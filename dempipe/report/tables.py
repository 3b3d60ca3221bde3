"""The report's tables: report.csv (one row per run) and report.md (what was run,
the recommendation, and the tables a reader compares the runs in).

    text = format_markdown(result)      # a ReportResult of report.run_report
    text = write_csv(result.runs)

Text only: report.run_report writes the files (atomically). Relative errors are
shown as percentages (two significant figures below 10 %), a dash where a figure
could not be measured. docs/accuracy.md explains every column.
"""

from __future__ import annotations

import csv
import io
import math
from pathlib import Path

from dempipe.report import accuracy as acc
from dempipe.report.results import (
    HORIZON_AFTER_CONTACT,
    ReportResult,
    Run,
    chaos_floor,
    scene_settings,
    seconds,
    within_tolerances,
)
from dempipe.spheres import fidelity

CSV_COLUMNS = (
    "label", "resolution", "dt_factor", "stiffness_factor", "reference", "status",
    "diameter_m", "dt_s", "steps", "spheres", "wall_s", "s_per_step", "s_per_sim_s",
    "memory_mib", "sphere_build_cold_s", "sphere_build_cached_s",
    "volume_err", "inertia_err", "hausdorff", "position_h", "orientation_h_deg",
    "position_end", "orientation_end_deg", "pile_height", "pile_com", "pile_spread",
    "settle_s", "at_rest", "bounce", "rolling", "incline", "spin_L", "spin_energy", "error",
    "pareto",
    "sphere_mode", "envelope_hausdorff_d", "envelope_bump_d", "contact_law")


def csv_row(u: Run) -> dict:
    g, mo, ph = u.geometry, u.motion, u.physics
    return dict(
        label=u.label, resolution=u.resolution, dt_factor=u.dt_factor,
        stiffness_factor=u.stiffness_factor, reference=int(u.reference), status=u.status,
        diameter_m=u.diameter, dt_s=u.dt, steps=u.steps, spheres=u.spheres, wall_s=u.wall_s,
        s_per_step=u.s_per_step, s_per_sim_s=u.s_per_sim_s,
        memory_mib=u.memory_bytes / 2 ** 20, sphere_build_cold_s=u.sphere_build_cold_s,
        sphere_build_cached_s=u.sphere_build_cached_s,
        volume_err=g.get("volume", math.nan), inertia_err=g.get("inertia", math.nan),
        hausdorff=g.get("hausdorff", math.nan),
        **{k: mo.get(k, math.nan) for k in ("position_h", "orientation_h_deg", "position_end",
                                            "orientation_end_deg", "pile_height", "pile_com",
                                            "pile_spread", "settle_s", "at_rest")},
        **{k: ph.get(k, math.nan) for k in ("bounce", "rolling", "incline", "spin_L",
                                           "spin_energy")},
        error=u.error, pareto=int(u.pareto), sphere_mode=u.mode or "",
        envelope_hausdorff_d=u.envelope.get("hausdorff_d", math.nan),
        envelope_bump_d=u.envelope.get("bump_d", math.nan), contact_law=u.law or "")


def write_csv(runs) -> str:
    """The runs as CSV text, one row per run (columns: CSV_COLUMNS)."""
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=CSV_COLUMNS, lineterminator="\n")
    w.writeheader()
    for u in runs:
        row = csv_row(u)
        w.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in row.items()})
    return buf.getvalue()


def _pct(x) -> str:
    return "—" if x is None or not math.isfinite(x) else f"{100 * x:.2g}%" if abs(x) < 0.1 \
        else f"{100 * x:.0f}%"


def _num(x, fmt=".3g") -> str:
    return "—" if x is None or not math.isfinite(x) else format(x, fmt)


def format_markdown(r: ReportResult) -> str:
    """report.md: what was run, the recommendation, and the tables."""
    ref = r.reference
    ok = [u for u in r.runs if u.ok]
    L = [f"# dempipe report: {Path(r.scene).name}", ""]
    L.append(f"{len(r.runs)} runs of {r.bodies} bodies, {r.duration:g} s simulated each, "
             f"{r.wall_s:.0f} s in all. Reference: **{ref.label}** ({ref.spheres:,} spheres, "
             f"dt {ref.dt:.3g} s). Motion errors are against the reference; geometry errors "
             f"against each shape's mesh; physical errors against closed forms "
             f"(material `{r.material}`). Lengths are in body sizes (the mesh's longest "
             f"extent). How to read this: docs/accuracy.md.")
    L.append("")
    L.append(f"**Error** (the headline, plotted against run time): the RMS over bodies of "
             f"|x − x_ref| in body sizes at the horizon t = {r.horizon:.3g} s, "
             f"{HORIZON_AFTER_CONTACT:g} s after the median body's first contact unless "
             f"--horizon says otherwise: late enough for contacts to have acted, early "
             f"enough that chaos has not yet amplified every difference.")
    L.append("")
    L.append("## Recommendation")
    L.append("")
    if r.touched == 0:
        L.append(f"**No body touched anything by the horizon t = {r.horizon:.3g} s**: the "
                 "motion errors below measure free flight, which every run gets right, so "
                 "this recommendation says nothing about contacts. Lengthen --duration, or "
                 "set --horizon after the first contacts.")
        L.append("")
    rolls = ("" if r.rolling_tolerance is None else
             f" and incline rolling error within {r.rolling_tolerance:g}")
    others = [u for u in ok if not u.reference]
    closest = min(others, key=lambda u: u.error, default=None)
    why_not = ("" if closest is None else
               f"; the closest is {closest.label} (error {_num(closest.error)}"
               + ("" if r.rolling_tolerance is None else
                  f", incline roll {_pct(closest.physics.get('incline', math.nan))}") + ")")
    if r.recommended is not None:
        u = r.recommended
        if u is not ref:
            L.append(f"Cheapest run with error within the tolerance {r.tolerance:g}{rolls}: "
                     f"**{u.label}** (error {_num(u.error)}, {seconds(u.wall_s)} s, "
                     f"{_num(ref.wall_s / u.wall_s, '.1f')}× faster than the reference). ")
        elif any(within_tolerances(o, r.tolerance, r.rolling_tolerance) for o in others):
            L.append(f"Cheapest run with error within the tolerance {r.tolerance:g}{rolls}: "
                     f"the reference **{u.label}** ({seconds(u.wall_s)} s): keep its "
                     "setting. ")
        else:
            # the reference (error 0) is the only run within the tolerances, so by the
            # rule it is the recommendation; its scene lines name its mode, law, dt and
            # stiffness, which may not be the scene's
            incline = ("" if r.rolling_tolerance is None else
                       f" and incline roll {_pct(u.physics.get('incline', math.nan))}")
            L.append(f"No run other than the reference stays within the tolerance "
                     f"{r.tolerance:g}{rolls}{why_not}. The reference, with error 0"
                     f"{incline}, does: **{u.label}** ({seconds(u.wall_s)} s) is the "
                     "recommendation. Bake with its setting, or loosen the tolerances, or "
                     "widen the sweep. ")
        L[-1] += ("In the scene file:" if r.stage is None else
                  "dempipe's settings for a stage go in a small TOML beside it that names "
                  "it (docs/usd-input.md), baked with `dempipe bake SETTINGS.toml -o OUT`:")
        L.append("")
        L.append("```toml")
        if r.stage is not None:
            L += ["[usd]", f'stage = "{r.stage}"', ""]
        L.append("[simulation]")
        L += scene_settings(u, r.target_overlap)
        L.append("```")
    else:
        # only a rolling tolerance leaves no recommendation: not even the reference rolls
        L.append(f"No run stays within the tolerance {r.tolerance:g}{rolls}, not even the "
                 f"reference {ref.label} (incline roll "
                 f"{_pct(ref.physics.get('incline', math.nan))}){why_not}. Loosen "
                 "--rolling-tolerance, or sweep finer resolutions or --spheres surface.")
    L.append("")
    L.append("## Runs")
    L.append("")
    L.append("| run | spheres | dt [s] | steps | wall [s] | s/step | s per sim. s | memory "
             "[MiB] | hausdorff | pos. @h | orient. @h [°] | bounce e² | incline roll | "
             "error | Pareto |")
    L.append("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|:-:|")
    for u in r.runs:
        if not u.ok:
            L.append(f"| {u.label} | {u.spheres:,} | {_num(u.dt)} | | | | | | | | | | | "
                     f"{u.status} | |")
            continue
        name = f"**{u.label}** (ref.)" if u.reference else u.label
        L.append(f"| {name} | {u.spheres:,} | {_num(u.dt)} | {u.steps:,} | "
                 f"{seconds(u.wall_s)} | {_num(u.s_per_step, '.2e')} | "
                 f"{seconds(u.s_per_sim_s)} | {_num(u.memory_bytes / 2 ** 20, '.1f')} | "
                 f"{_pct(u.geometry.get('hausdorff', math.nan))} | {_num(u.motion['position_h'])} | "
                 f"{_num(u.motion['orientation_h_deg'], '.1f')} | {_pct(u.physics['bounce'])} | "
                 f"{_pct(u.physics.get('incline', math.nan))} | "
                 f"{_num(u.error)} | {'●' if u.pareto else ''} |")
    L.append("")
    L.append(f"pos. @h, orient. @h: per-body RMS at the horizon t = {r.horizon:g} s. s/step "
             "and s per sim. s are wall time of the simulation alone (kernels already "
             "compiled). Incline roll: a ball of the run's resolution and sphere-set mode "
             f"rolling down a {acc.INCLINE_DEGREES:g}° slope, its acceleration against "
             "5/7 g sin θ (docs/accuracy.md); what the sphere set does to round bodies.")
    L.append("")
    L.append(f"## {'Pile statistics' if r.pile else 'Bodies'} at the last frame "
             f"(t = {r.duration:g} s)")
    L.append("")
    L.append("| run | height [m] | spread [m] | at rest | settled at [s] | Δheight | ΔCOM | "
             "Δspread | Δsettle [s] | pos. @end | orient. @end [°] |")
    L.append("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for u in ok:
        p, mo = u.pile, u.motion
        L.append(f"| {u.label} | {p.height:.4f} | {p.spread:.4f} | {p.at_rest:.0%} | "
                 f"{_num(p.settle_s, '.2f')} | {_num(mo['pile_height'])} | "
                 f"{_num(mo['pile_com'])} | {_num(mo['pile_spread'])} | "
                 f"{_num(mo['settle_s'], '.2f')} | {_num(mo['position_end'])} | "
                 f"{_num(mo['orientation_end_deg'], '.0f')} |")
    L.append("")
    L.append(f"Height: {acc.HEIGHT_PERCENTILE:g}th percentile of the centres of mass; spread: "
             "RMS horizontal distance from the centre of mass; at rest: moving less than "
             f"{acc.REST_FRACTION_PER_FRAME:.0%} of its size per frame; settled: from when "
             f"{acc.SETTLED_FRACTION:.0%} stay at rest (— : not within the run). Δ: against "
             "the reference, lengths in body sizes.")
    floor = chaos_floor(r)
    if r.pile and floor is not None:
        mo = floor.motion
        L.append(f"**Chaos floor**: {floor.label} differs from the reference only in dt, and "
                 f"its pile differs by Δheight {_num(mo['pile_height'])}, ΔCOM "
                 f"{_num(mo['pile_com'])}, Δspread {_num(mo['pile_spread'])}. Two equally "
                 "valid bakes of a pile differ this much; smaller differences are not a loss "
                 "of accuracy.")
    L.append("")
    L.append("## Geometry: sphere sets against their meshes")
    L.append("")
    modes = list(dict.fromkeys(u.mode for u in r.runs))      # the sweep's order
    by_mode = modes != [None]
    L.append("| shape |" + (" mode |" if by_mode else "") + " resolution | spheres | volume | "
             "inertia | hausdorff | mesh→spheres | spheres→mesh | build cold [s] | "
             "build cached [s] |")
    L.append("|---|" + ("---|" if by_mode else "") + "---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    build = {(u.resolution, u.mode): (u.sphere_build_cold_s, u.sphere_build_cached_s)
             for u in r.runs}
    order = sorted(r.shapes.items(), key=lambda kv: (kv[0][0], kv[0][1],
                                                     modes.index(kv[0][2])
                                                     if kv[0][2] in modes else 0))
    for (name, res, mode), g in order:
        cold, cached = build.get((res, mode), (math.nan, math.nan))
        L.append(f"| {name} |" + (f" {mode} |" if by_mode else "")
                 + f" {res} | {g.spheres} | {_pct(g.volume)} | {_pct(g.inertia)} | "
                 f"{_pct(g.hausdorff)} | {_pct(g.mesh_to_spheres)} | {_pct(g.spheres_to_mesh)} "
                 f"| {_num(cold, '.3f')} | {_num(cached, '.3f')} |")
    L.append("")
    L.append("Volume and inertia: the lattice cells (cubes of side d) against the exact mesh "
             "(the bodies' mass properties come from the mesh itself). Hausdorff: the largest "
             f"distance between the mesh surface ({fidelity.MESH_SAMPLES} area-weighted samples) and "
             "the spheres' contact surface (the part another sphere can touch; "
             f"{fidelity.SPHERE_DIRECTIONS} directions per sphere), either way, in shape sizes. "
             "A surface set (overlapping spheres, no lattice cells) shows its envelope's "
             "Hausdorff (docs/spheres.md, \"Surface mode\"), in shape sizes too; its cells' "
             "volume and inertia would count the overlaps, and are left out (—). "
             "Build times are for all shapes of the scene at that resolution and mode "
             "(cold: no cache).")
    L.append("")
    if any(u.mode for u in r.runs):
        L.append("## Sphere-set modes")
        L.append("")
        L.append("| run | spheres | Hausdorff [d] | bump [d] | incline roll | error | wall [s] |")
        L.append("|---|---:|---:|---:|---:|---:|---:|")
        for u in ok:
            e = u.envelope
            L.append(f"| {u.label} | {u.spheres:,} | {_num(e.get('hausdorff_d', math.nan))} | "
                     f"{_num(e.get('bump_d', math.nan))} | "
                     f"{_pct(u.physics.get('incline', math.nan))} | {_pct(u.error)} | "
                     f"{seconds(u.wall_s)} |")
        L.append("")
        L.append("Hausdorff and bump: the worst shape's spheres' envelope against its mesh "
                 "(docs/spheres.md, \"Surface mode\"), in sphere diameters.")
        L.append("")
    if any(u.law for u in r.runs):
        L.append("## Contact laws")
        L.append("")
        L.append("| run | dt [s] | steps | bounce: error of e² | error | wall [s] |")
        L.append("|---|---:|---:|---:|---:|---:|")
        for u in ok:
            L.append(f"| {u.label} | {_num(u.dt, '.3g')} | {u.steps:,} | "
                     f"{_pct(u.physics.get('bounce', math.nan))} | {_pct(u.error)} | "
                     f"{seconds(u.wall_s)} |")
        L.append("")
        L.append("Each law at its own automatic step (docs/physics.md, \"Contact laws\"): "
                 "for the same error, the cheaper is the one with the smaller wall time. "
                 "The motion error is against the reference, which takes the last law "
                 "given; a law's own stiffness is in its own units (Hertz: N/m^1.5). "
                 "Under either law a contact between two bodies is one patch: each sphere "
                 "pair takes 1/n_eff of the law's constants, n_eff = (Σδ)²/Σδ² over the "
                 "patch, so a face landing flat rebounds with the asked e (docs/physics.md, "
                 "\"Contact patches\", with its limits).")
        L.append("")
    L.append("## Physics: closed forms against dt")
    L.append("")
    L.append("| run | dt factor | bounce: mean abs. error of e² | rolling 5/7 v0 | |L| drift | "
             "energy drift (free spin) |")
    L.append("|---|---:|---:|---:|---:|---:|")
    for u in ok:
        ph = u.physics
        L.append(f"| {u.label} | {u.dt_factor:g} | {_pct(ph['bounce'])} | "
                 f"{_num(ph['rolling'], '.2g')} | {_num(ph['spin_L'], '.1e')} | "
                 f"{_num(ph['spin_energy'], '.1e')} |")
    L.append("")
    L.append(f"Bounce: {acc.BOUNCE_PHASES} balls of one sphere diameter dropped "
             f"{acc.BOUNCE_HEIGHT:g} diameters, impacts spread over a step; the ball's "
             "contact is resolved in as many steps as the pile's stiffest contact. Rolling: a "
             "ball launched sliding; the larger of the end-speed and travel errors. Spin: the "
             "smallest shape tumbling torque-free for 0.2 s at the run's dt.")
    L.append("")
    return "\n".join(L)
