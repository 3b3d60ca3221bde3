"""`dempipe report`: error against run time.

One tiny sweep (two balls, two resolutions, two steps, 0.2 s) runs once through
the CLI for the whole module; the tests read its files. The trends asserted are
the ones that must hold whatever the scene: a finer lattice fits the mesh better,
and a shorter step bounces closer to e². Bad input must fail in one line.
"""

import csv
import math
import re
import struct

import numpy as np
import pytest

from dempipe.spheres import fidelity
from dempipe.report.results import ReportError
from dempipe.report.runs import Sweep, parse_values, run_report
from dempipe.spheres.cache import SphereCache
from dempipe_cli.main import main

SCENE = """
[output]
fps = 24
duration = 2.0

[simulation]
resolution = 4
seed = 3

[materials.rubber]
density = 900.0
restitution = 0.5
friction = 0.4

[shapes.ball]
builtin = "sphere"

[[bodies]]
name = "balls"
shape = "ball"
material = "rubber"
layout = "grid"
origin = [0.0, 0.0, 0.05]
dims = [2, 1, 1]
spacing = 0.06
rotation = "random"
velocity = [0.2, 0.1, 0.0]

[[colliders]]
type = "plane"
material = "rubber"
"""

ARGS = ["--resolutions", "2,4", "--dt-factors", "1,0.25", "--stiffness-factors", "1",
        "--duration", "0.2"]


def tiny_scene(tmp_path_factory, name: str):
    """(folder, SCENE written into it) for a module fixture's report."""
    pytest.importorskip("matplotlib")
    root = tmp_path_factory.mktemp(name)
    scene = root / "tiny.toml"
    scene.write_text(SCENE)
    return root, scene


@pytest.fixture(scope="module")
def report_dir(tmp_path_factory):
    root, scene = tiny_scene(tmp_path_factory, "report")
    out = root / "out"
    main(["report", str(scene), "-o", str(out), "--cache-dir", str(root / "cache"), "-q"]
         + ARGS)
    return out


def rows(report_dir):
    with open(report_dir / "report.csv", newline="") as f:
        return list(csv.DictReader(f))


def run_row(table, res, dt):
    return next(r for r in table if int(r["resolution"]) == res and float(r["dt_factor"]) == dt)


def test_files_written(report_dir):
    names = {p.name for p in report_dir.iterdir()}
    assert {"report.md", "report.csv", "error_vs_time.png", "error_vs_setting.png"} <= names
    assert not [n for n in names if ".tmp-" in n]          # atomic writes leave nothing behind
    for png in ("error_vs_time.png", "error_vs_setting.png"):
        data = (report_dir / png).read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n"
        assert data[12:16] == b"IHDR"
        width, height = struct.unpack(">II", data[16:24])
        assert width > 100 and height > 100
        assert len(data) < 150_000
    md = (report_dir / "report.md").read_text()
    assert "## Recommendation" in md and "## Runs" in md


def test_csv_has_one_row_per_run(report_dir):
    table = rows(report_dir)
    assert len(table) == 4                                   # 2 resolutions x 2 dt factors x 1
    assert {(int(r["resolution"]), float(r["dt_factor"])) for r in table} == \
        {(2, 1.0), (2, 0.25), (4, 1.0), (4, 0.25)}
    ref = [r for r in table if r["reference"] == "1"]
    assert len(ref) == 1 and ref[0]["resolution"] == "4" and float(ref[0]["dt_factor"]) == 0.25
    assert float(ref[0]["error"]) == 0.0
    for r in table:
        assert r["status"] == "ok"
        assert float(r["wall_s"]) > 0 and int(r["steps"]) > 0 and int(r["spheres"]) > 0
        assert float(r["memory_mib"]) > 0


def test_error_falls_as_resolution_rises(report_dir):
    table = rows(report_dir)
    coarse, fine = run_row(table, 2, 1.0), run_row(table, 4, 1.0)
    assert float(coarse["hausdorff"]) > float(fine["hausdorff"])
    assert float(coarse["inertia_err"]) > float(fine["inertia_err"])
    assert int(coarse["spheres"]) < int(fine["spheres"])
    # motion against the reference (r4): the coarse lattice is further off
    assert float(run_row(table, 2, 0.25)["error"]) > float(fine["error"])


def test_bounce_error_falls_as_dt_shrinks(report_dir):
    table = rows(report_dir)
    big, small = run_row(table, 4, 1.0), run_row(table, 4, 0.25)
    assert float(big["dt_s"]) > float(small["dt_s"])
    # the bounce error falls, less than first order: with the contact's onset resolved
    # within the step it is small at every step (measured 0.17% and 0.09% of e²)
    assert float(big["bounce"]) > float(small["bounce"])
    assert float(big["s_per_sim_s"]) < float(small["s_per_sim_s"])   # and it costs more


def write_scene(tmp_path, text):
    p = tmp_path / "scene.toml"
    p.write_text(text)
    return str(p)


def one_line_error(capsys, argv, code=2):
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == code
    err = capsys.readouterr().err.strip()
    assert "Traceback" not in err
    assert len(err.splitlines()) == 1, err
    return err


def test_unknown_scene_key_is_one_line(tmp_path, capsys):
    scene = write_scene(tmp_path, SCENE.replace("resolution = 4", "resolutoin = 4"))
    err = one_line_error(capsys, ["report", scene, "-o", str(tmp_path / "out")])
    assert "simulation.resolutoin" in err and "resolution" in err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("option,value,words", [
    ("--resolutions", "4,x", "'x' is not a number"),
    ("--resolutions", "4.5", "'4.5' is not a number"),
    ("--dt-factors", "1,-0.5", "greater than 0"),
    ("--stiffness-factors", "", "expected comma-separated"),
])
def test_bad_sweep_text_is_one_line(tmp_path, capsys, option, value, words):
    scene = write_scene(tmp_path, SCENE)
    err = one_line_error(capsys, ["report", scene, "-o", str(tmp_path / "out"), option, value])
    assert err.startswith("error: ") and option in err and words in err


def test_missing_matplotlib_is_a_clear_error(tmp_path, monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "matplotlib", None)     # import fails
    with pytest.raises(ReportError, match=r"pip install 'dempipe\[report\]'"):
        run_report(write_scene(tmp_path, SCENE), tmp_path / "out", Sweep())


def test_parse_values():
    assert parse_values("8, 6,12,6", "--resolutions", int) == (6, 8, 12)
    assert parse_values("1,0.5", "--dt-factors") == (0.5, 1.0)


def test_contact_surface_of_a_block_skips_buried_spheres():
    d = 0.01
    one = fidelity.contact_surface(np.zeros((1, 3)), d, n_dirs=64)
    assert len(one) == 64                                   # a lone sphere: all of it
    g = np.stack(np.meshgrid(*[np.arange(3) * d] * 3, indexing="ij"), -1).reshape(-1, 3)
    surf = fidelity.contact_surface(g, d, n_dirs=64)
    centre = g[13]
    assert np.linalg.norm(surf - centre, axis=1).min() > 0.5 * d * (1 - 1e-9) + 0.1 * d


def test_point_mesh_distance_on_a_cube():
    import trimesh

    cube = trimesh.creation.box(extents=(2.0, 2.0, 2.0))
    pts = np.array([[0.0, 0.0, 3.0], [2.0, 2.0, 0.0], [0.0, 0.0, 0.5], [3.0, 3.0, 3.0]])
    want = [2.0, np.sqrt(2.0), 0.5, np.sqrt(12.0)]
    assert fidelity.point_mesh_distance(pts, cube.vertices, cube.faces) == pytest.approx(want)


@pytest.mark.slow
def test_laws_axis_bakes_each_law_at_its_own_step(tmp_path):
    # --laws linear,hertz: every setting once per law, each at its law's automatic
    # step (10 and 12 steps per contact), its bounce measured
    # with its own law; the reference takes the last law; the CSV, the labels and the
    # scene lines name the law. An unknown law is refused naming the choices.
    res = run_report(write_scene(tmp_path, SCENE), tmp_path / "out",
                     Sweep(resolutions=(4,), dt_factors=(1.0,), stiffness_factors=(1.0,),
                           duration=0.2, plots=False, contact_laws=("linear", "hertz")))
    runs = {u.law: u for u in res.runs}
    assert set(runs) == {"linear", "hertz"} and runs["hertz"].reference
    assert runs["hertz"].model.contact_law == "hertz"
    assert runs["linear"].model.contact_law == "linear"
    assert all(u.ok and u.label.endswith(u.law) for u in res.runs)
    assert all(0 <= u.physics["bounce"] < 0.05 for u in res.runs)   # each law's own e²
    table = rows(tmp_path / "out")
    assert sorted(r["contact_law"] for r in table) == ["hertz", "linear"]
    md = (tmp_path / "out" / "report.md").read_text()
    assert "## Contact laws" in md
    from dempipe.report.results import scene_settings
    assert 'contact_law = "linear"' in scene_settings(runs["linear"], 0.02)
    with pytest.raises(ReportError, match="--laws: unknown contact law 'hooke'"):
        run_report(write_scene(tmp_path, SCENE), tmp_path / "out2",
                   Sweep(plots=False, contact_laws=("hooke",)))
    # a stiffness given in the scene's law's units would be read in the other's
    stiff = SCENE.replace("friction = 0.4\n", "friction = 0.4\nstiffness = 2000.0\n")
    assert "stiffness = 2000.0" in stiff
    with pytest.raises(ReportError, match=r"--laws: materials\.rubber .*\"auto\""):
        run_report(write_scene(tmp_path, stiff), tmp_path / "out3",
                   Sweep(plots=False, contact_laws=("linear", "hertz")))


def test_a_horizon_before_any_contact_is_said(tmp_path):
    # two balls a metre up, 0.1 s: they fall 5 cm and touch nothing, so every run's
    # motion matches the reference's free flight and a recommendation means nothing
    # about contacts; report.md and the progress lines say so
    lines = []
    scene = write_scene(tmp_path, SCENE.replace("origin = [0.0, 0.0, 0.05]",
                                                "origin = [0.0, 0.0, 1.0]"))
    res = run_report(scene, tmp_path / "out",
                     Sweep(resolutions=(3, 4), dt_factors=(1.0,), stiffness_factors=(1.0,),
                           duration=0.1, plots=False), progress=lines.append)
    assert res.touched == 0
    assert any(line.startswith("note: no body touched anything") for line in lines)
    md = (tmp_path / "out" / "report.md").read_text()
    assert "**No body touched anything by the horizon" in md
    # the default scene's balls start on the plane: no such note
    res = run_report(write_scene(tmp_path, SCENE), tmp_path / "out2",
                     Sweep(resolutions=(4,), dt_factors=(1.0,), stiffness_factors=(1.0,),
                           duration=0.2, plots=False))
    assert res.touched == 2
    assert "No body touched" not in (tmp_path / "out2" / "report.md").read_text()


@pytest.fixture(scope="module")
def modes_report(tmp_path_factory):
    # --spheres lattice,surface --rolling-tolerance 0.005 on the two balls at 4 across:
    # the reference takes the last mode (surface); both balls roll down the incline
    # through their meshes' inscribed balls, the surface set's closer (measured 0.0014
    # off 5/7 g (sin θ − μ_r cos θ)) than the lattice's (0.0088), whose shell at 4
    # across is coarser
    root, scene = tiny_scene(tmp_path_factory, "modes")
    lines = []
    res = run_report(scene, root / "out",
                     Sweep(resolutions=(4,), dt_factors=(1.0,), stiffness_factors=(1.0,),
                           duration=0.2, sphere_modes=("lattice", "surface"),
                           rolling_tolerance=0.005),
                     cache=SphereCache(root / "cache"), progress=lines.append)
    return res, root / "out", lines


def test_every_mode_has_its_geometry(modes_report):
    # a surface set's geometry is measured too (its envelope's Hausdorff), not only
    # the first mode's: the runs table, the CSV and the geometry table show it
    res, out, _ = modes_report
    runs = {u.mode: u for u in res.runs}
    assert runs["surface"].reference
    for mode in ("lattice", "surface"):
        h = runs[mode].geometry["hausdorff"]
        assert 0 < h < 0.5, (mode, h)
        assert 0 < res.shapes[("ball", 4, mode)].hausdorff < 0.5
    # the cells' volume and inertia (N d³) mean nothing for a shell of overlapping spheres
    assert math.isnan(runs["surface"].geometry["volume"])
    table = {r["sphere_mode"]: r for r in rows(out)}
    assert 0 < float(table["surface"]["hausdorff"]) < 0.5
    md = (out / "report.md").read_text()
    geometry = md.split("## Geometry")[1].split("##")[0]
    assert "| ball | surface | 4 |" in geometry and "| ball | lattice | 4 |" in geometry
    assert (out / "error_vs_setting.png").exists()


def test_the_reference_is_on_the_pareto_front(modes_report, report_dir):
    # error 0: no run beats it in error, so none beats it in both (docs/accuracy.md)
    res, out, _ = modes_report
    assert res.reference.pareto
    for table in (rows(out), rows(report_dir)):
        assert [r["pareto"] for r in table if r["reference"] == "1"] == ["1"]


def test_a_reference_only_it_rolls_is_recommended_with_its_mode(modes_report):
    # only the surface reference meets the rolling tolerance: it is the recommendation
    # (the cheapest run within both tolerances), and its scene lines name its mode
    res, out, _ = modes_report
    runs = {u.mode: u for u in res.runs}
    assert runs["surface"].physics["incline"] <= 0.005 < runs["lattice"].physics["incline"]
    assert res.recommended is res.reference
    md = (out / "report.md").read_text()
    rec = md.split("## Recommendation")[1].split("## Runs")[0]
    assert 'spheres = "surface"' in rec and "resolution = 4" in rec
    assert "r4 dt×1 k×1 lattice" in rec and "incline roll" in rec      # why not it


def test_progress_lines_give_each_runs_time(modes_report):
    # "N steps in T s": T is the run's simulation time, to 3 figures (a fast run
    # printed "0.0 s"), and the run's whole time (sphere sets, kernels) beside it
    res, _, lines = modes_report
    for u in res.runs:
        line = next(s for s in lines if s.startswith("run ") and f" {u.label}:" in s)
        m = re.search(r"steps in ([0-9.e+-]+) s simulating \(([0-9.]+) s in all", line)
        assert m, line
        assert float(m.group(1)) == pytest.approx(u.wall_s, rel=0.01)
        assert float(m.group(2)) >= float(m.group(1)) - 0.05
