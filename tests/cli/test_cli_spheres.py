"""`dempipe spheres` and `dempipe cache` through click's CliRunner and a real process."""

import json
import subprocess
import sys
import textwrap

import numpy as np
import pytest
import trimesh
from click.testing import CliRunner

from dempipe_cli.main import app, main

pytest.importorskip("dempipe.mesh.shapes")


@pytest.fixture(autouse=True)
def _cache_env(monkeypatch, tmp_path):
    monkeypatch.setenv("DEMPIPE_CACHE_DIR", str(tmp_path / "cache"))


def run(*args):
    result = CliRunner().invoke(app, list(args), catch_exceptions=False)
    return result


def run_main(capsys, *args):
    """The console entry point (errors -> one line + exit code)."""
    with pytest.raises(SystemExit) as exc:
        main(list(args))
        raise SystemExit(0)
    out = capsys.readouterr()
    return exc.value.code, out.out, out.err


def test_list_shapes():
    result = run("spheres", "--list-shapes")
    assert result.exit_code == 0
    names = [line.split()[0] for line in result.stdout.splitlines()]
    for name in ("pawn", "rook", "bishop", "queen", "king", "torus", "box", "sphere"):
        assert name in names


def test_json_output_and_cache_hit(tmp_path):
    args = ["spheres", "pawn", "torus", "--resolution", "12", "--json"]
    first = json.loads(run(*args).stdout)
    second = json.loads(run(*args).stdout)
    assert [r["name"] for r in first] == ["pawn", "torus"]
    assert [r["cache"] for r in first] == ["miss", "miss"]
    assert [r["cache"] for r in second] == ["hit", "hit"]
    for r in first:
        assert r["count"] > 10
        assert abs(r["volume_error_percent"]) < 15 and 0 <= r["inertia_error_percent"] < 15
        assert r["build_seconds"] >= 0 and r["diameter"] > 0
    assert first[0]["count"] == second[0]["count"]
    assert len(list((tmp_path / "cache").glob("*.npz"))) == 2


def test_text_output_and_no_cache(tmp_path):
    result = run("spheres", "box", "--diameter", "0.01", "--no-cache")
    assert result.exit_code == 0
    # the default box is 0.04 m: 4 x 4 x 4 cells, an exact tiling
    assert "box: 64 spheres" in result.stdout and "volume error +0.00%" in result.stdout
    assert "cache off" in result.stdout
    assert not (tmp_path / "cache").exists()


def test_npz_output(tmp_path):
    out = tmp_path / "pawn.npz"
    result = run("spheres", "pawn", "-r", "10", "-o", str(out), "--cache-dir", str(tmp_path / "c2"))
    assert result.exit_code == 0, result.output
    with np.load(out, allow_pickle=False) as z:
        assert set(z.files) == {"centers", "diameter", "com", "volume", "inertia", "mesh_sha256"}
        assert z["centers"].dtype == np.float32 and z["centers"].shape[1] == 3
        assert z["inertia"].shape == (3, 3) and z["com"].shape == (3,)
        from dempipe.mesh.shapes import build_shape, mesh_digest

        pawn = build_shape("pawn")
        assert float(z["volume"]) == pytest.approx(pawn.volume, rel=1e-12)
        assert str(z["mesh_sha256"]) == mesh_digest(pawn)
        # body frame: sphere COM near the origin (within one diameter)
        assert np.all(np.abs(z["centers"].mean(axis=0)) < float(z["diameter"]))
    assert len(list((tmp_path / "c2").glob("*.npz"))) == 1
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []


def test_usda_output_is_valid_usd(tmp_path):
    from pxr import Usd, UsdGeom, UsdValidation

    out = tmp_path / "spheres_{name}.usda"
    result = run("spheres", "pawn", "torus", "-r", "8", "-o", str(out))
    assert result.exit_code == 0, result.output
    for name in ("pawn", "torus"):
        stage = Usd.Stage.Open(str(tmp_path / f"spheres_{name}.usda"))
        assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.z
        assert UsdGeom.GetStageMetersPerUnit(stage) == 1.0
        root = stage.GetDefaultPrim()
        assert root and root.GetName() == name
        mesh = UsdGeom.Mesh(root.GetChild("mesh"))
        points = UsdGeom.Points(root.GetChild("spheres"))
        assert mesh and points
        n = len(points.GetPointsAttr().Get())
        widths = np.array(points.GetWidthsAttr().Get())
        assert len(widths) == n > 0 and np.allclose(widths, widths[0])
        ctx = UsdValidation.ValidationContext(
            UsdValidation.ValidationRegistry().GetOrLoadAllValidators())
        errors = [e for e in ctx.Validate(stage)
                  if e.GetType() == UsdValidation.ValidationErrorType.Error]
        assert errors == [], [e.GetMessage() for e in errors]


def test_mesh_file_input_with_scale(tmp_path):
    path = tmp_path / "brick.stl"
    trimesh.creation.box(extents=[4, 3, 2]).export(path)
    result = run("spheres", str(path), "--scale", "0.01", "--diameter", "0.01", "--json", "--no-cache")
    assert result.exit_code == 0, result.output
    (row,) = json.loads(result.stdout)
    assert row["name"] == "brick" and row["count"] == 24
    assert row["volume"] == pytest.approx(24e-6, rel=1e-9)


def test_cache_info_and_clear(tmp_path):
    run("spheres", "pawn", "-r", "6")
    info = run("cache", "info")
    assert info.exit_code == 0
    assert str(tmp_path / "cache") in info.stdout and "entries:  1" in info.stdout
    data = json.loads(run("cache", "info", "--json").stdout)
    assert data["entries"] == 1 and data["bytes"] > 0
    cleared = run("cache", "clear")
    assert cleared.exit_code == 0 and "removed 1 entry" in cleared.stdout
    assert json.loads(run("cache", "info", "--json").stdout)["entries"] == 0


@pytest.mark.parametrize("args, expect", [
    (["spheres", "pwn", "-r", "8"], "pwn: no such mesh file and no built-in shape"),
    (["spheres", "shpere", "-r", "8"], "; did you mean 'sphere'?"),
    (["spheres", "missing.obj", "-r", "8"], "missing.obj: no such mesh file"),
    (["spheres", "pawn", "--diameter", "-1"], "diameter must be a positive finite"),
    (["spheres", "pawn", "--resolution", "0"], "resolution must be a positive number"),
])
def test_library_errors_are_one_line(capsys, args, expect):
    code, out, err = run_main(capsys, *args)
    assert code != 0
    assert expect in err
    assert len(err.strip().splitlines()) == 1
    assert "Traceback" not in out + err


@pytest.mark.parametrize("args, expect", [
    (["spheres", "pawn"], "exactly one of --diameter and --resolution"),
    (["spheres", "pawn", "-d", "0.01", "-r", "5"], "exactly one of --diameter and --resolution"),
    (["spheres", "pawn", "torus", "-r", "5", "-o", "x.npz"], "must contain {name}"),
    (["spheres", "pawn", "-r", "5", "-o", "x.obj"], "use a .npz, .usda"),
    (["spheres", "-r", "5"], "at least one mesh"),
    (["spheres", "pawn", "-r", "5", "--scale", "0"], "positive"),
])
def test_usage_errors(capsys, args, expect):
    code, out, err = run_main(capsys, *args)
    assert code == 2
    assert expect in err and "Traceback" not in out + err


def test_unusable_cache_dir_is_an_error(capsys, tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    code, out, err = run_main(capsys, "spheres", "pawn", "-r", "5", "--cache-dir", str(blocker / "c"))
    assert code != 0 and "not writable" in err and len(err.strip().splitlines()) == 1


def test_real_process_and_no_pxr_or_cuda_import(tmp_path):
    # the console entry point in a fresh interpreter; pxr and numba.cuda stay unimported
    code = textwrap.dedent("""
        import sys
        from dempipe_cli.main import main
        try:
            main(["spheres", "pawn", "-r", "8", "--json", "-o", sys.argv[1]])
        except SystemExit as e:
            assert not e.code, e.code
        print("MODULES", "pxr" in sys.modules, "numba.cuda" in sys.modules, file=sys.stderr)
    """)
    proc = subprocess.run([sys.executable, "-c", code, str(tmp_path / "p.npz")],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout)[0]["name"] == "pawn"
    assert "MODULES False False" in proc.stderr
    proc = subprocess.run([sys.executable, "-m", "dempipe_cli.main", "spheres", "nope", "-r", "8"],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode != 0
    assert proc.stderr.strip().splitlines() == [proc.stderr.strip()]
    assert "Traceback" not in proc.stderr


def test_an_open_mesh_has_no_volume_error_to_show(tmp_path):
    # a box with one face missing encloses no volume: its mass properties come from its
    # spheres, and comparing them with themselves printed "+0.00%"
    box = trimesh.creation.box(extents=(0.1, 0.1, 0.1))
    open_box = trimesh.Trimesh(box.vertices, box.faces[:-2], process=False)
    path = tmp_path / "open.obj"
    open_box.export(path)
    result = run("spheres", str(path), "-r", "4", "--json")
    row = json.loads(result.stdout)[0]
    assert row["volume_error_percent"] is None and row["inertia_error_percent"] is None
    text = run("spheres", str(path), "-r", "4").stdout
    assert "errors n/a (an open mesh: mass from the spheres)" in text
    closed = tmp_path / "box.obj"
    box.export(closed)
    assert json.loads(run("spheres", str(closed), "-r", "4", "--json").stdout)[0][
        "volume_error_percent"] == pytest.approx(0.0, abs=1e-9)


def test_surface_sets_report_no_cell_errors(tmp_path):
    # A surface set is a shell of overlapping spheres: N d^3 against the mesh volume
    # (+250 % for a ball) says nothing of the body, whose mass comes from the mesh.
    rows = json.loads(run("spheres", "sphere", "-r", "6", "--mode", "both", "--no-errors",
                          "--json").stdout)
    lattice, surface = rows
    assert (lattice["mode"], surface["mode"]) == ("lattice", "surface")
    assert abs(lattice["volume_error_percent"]) < 40
    assert surface["volume_error_percent"] is None and surface["inertia_error_percent"] is None
    # most of a ball's shell meets walls through its inscribed ball, and so do the
    # lattice's outermost spheres, through the mesh's (spheres.inscribed)
    assert surface["inscribed"] > 0.5 * surface["count"]
    assert 0.2 * lattice["count"] < lattice["inscribed"] < lattice["count"]
    text = run("spheres", "sphere", "-r", "6", "--mode", "both", "--no-errors").stdout
    lat_line, surf_line = text.splitlines()
    assert f"{surface['inscribed']} meet walls through inscribed balls" in surf_line
    assert f"{lattice['inscribed']} meet walls through inscribed balls" in lat_line
    assert "on the surface" in lat_line and "volume error" in lat_line
    assert "mass and inertia from the mesh" in surf_line and "volume error" not in surf_line


def test_round_shapes_are_called_round_on_a_lattice():
    # The same measure as `dempipe check`'s round-lattice warning: the share of the
    # mesh's area off the lattice's axes (a ball 99 %, a box 0).
    rows = {r["name"]: r for r in json.loads(run("spheres", "sphere", "box", "-r", "6",
                                                 "--no-errors", "--json").stdout)}
    assert rows["sphere"]["off_axis_share"] == pytest.approx(0.99, abs=0.01)
    assert rows["box"]["off_axis_share"] == 0.0
    ball, box = run("spheres", "sphere", "box", "-r", "6", "--no-errors").stdout.splitlines()
    assert "99% of the surface off the lattice's axes" in ball and "--mode surface" in ball
    assert "off the lattice's axes" not in box
    # with its mesh's balls the lattice ball rolls on walls (6 across: a fit follows
    # it); at 3 across none does, and it is called terraced
    assert "it rolls on walls through its mesh's balls and rings" in ball
    coarse = run("spheres", "sphere", "-r", "3", "--no-errors").stdout
    assert "terraced, it rolls badly; a finer resolution" in coarse


def test_a_lattice_pawn_reports_the_spheres_on_its_rims():
    # at 12 to its height the pawn's head is fitted, and its base's and collar's sharp
    # circular edges are rims (spheres.inscribed.rims) held by lattice spheres; a ball
    # has no rim
    row = json.loads(run("spheres", "pawn", "-r", "12", "--no-errors", "--json").stdout)[0]
    assert 0 < row["rims"] < row["inscribed"] < row["count"]
    line = run("spheres", "pawn", "-r", "12", "--no-errors").stdout
    assert f"{row['inscribed']} meet walls through inscribed balls or rings " \
           f"({row['rims']} on rims)" in line
    ball = json.loads(run("spheres", "sphere", "-r", "6", "--no-errors", "--json").stdout)[0]
    assert ball["rims"] == 0
