"""`dempipe wedge`: variants of a bake as tasks on a real Dask cluster on loopback.

Most tests share one LocalCluster of two single-thread worker processes on
127.0.0.1 (dempipe.farm.cluster.connect, as the CLI starts it); one starts a scheduler and
two workers as separate processes and drives the CLI in a real subprocess; one
kills a worker with SIGKILL mid-bake. Scenes are a few balls for a few frames.
Every process a test starts is stopped by it, within a time limit.
"""

import csv
import json
import os
import signal
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("distributed")
pxr = pytest.importorskip("pxr")
from pxr import Usd, UsdGeom  # noqa: E402

from dempipe.errors import SceneError  # noqa: E402
from dempipe.farm.cluster import FarmError, connect, host_warnings, local_sizes  # noqa: E402
from dempipe.farm.wedge import WedgeError, dumps_toml, parse_key, parse_vary, plan, wedge

ROOT = Path(__file__).resolve().parents[2]

SCENE = """
[output]
fps = 24
duration = {duration}

[simulation]
resolution = 3
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
origin = [0.0, 0.0, 0.03]
dims = [2, 1, 1]
spacing = 0.06
rotation = "random"
velocity = [0.2, 0.1, -0.3]

[[colliders]]
type = "plane"
material = "rubber"
"""


def write_scene(folder: Path, duration: float = 0.125, name: str = "tiny.toml") -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / name
    path.write_text(SCENE.format(duration=duration))
    return path


def read_rows(path: Path) -> list[dict]:
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def samples(path) -> tuple[np.ndarray, np.ndarray]:
    """(positions, orientations) of every instance at every frame of a baked stage."""
    stage = Usd.Stage.Open(str(path))
    pi = UsdGeom.PointInstancer(stage.GetPrimAtPath("/World/Bodies"))
    times = range(int(stage.GetStartTimeCode()), int(stage.GetEndTimeCode()) + 1)
    pos = np.array([np.array(pi.GetPositionsAttr().Get(t)) for t in times])
    rot = np.array([[(q.GetReal(), *q.GetImaginary())
                     for q in pi.GetOrientationsAttr().Get(t)] for t in times])
    return pos, rot


@pytest.fixture(scope="module")
def shared(tmp_path_factory):
    """A sphere cache, and the kernels compiled once here (the workers load them)."""
    from dempipe.pipeline.bake import bake
    from dempipe.spheres.cache import SphereCache

    root = tmp_path_factory.mktemp("wedge")
    scene = write_scene(root)
    cache = root / "cache"
    bake(scene, root / "warm.usdc", device="cpu", threads=1, cache=SphereCache(cache))
    return root, cache


@pytest.fixture(scope="module")
def farm(shared):
    with connect(workers=2, threads=1) as f:
        yield f


# ------------------------------------------------------------------ options, no cluster


def test_keys_and_values_parse_as_toml():
    assert parse_key("materials.wood.restitution") == ("materials", "wood", "restitution")
    assert parse_key("bodies[1].count") == parse_key("bodies.1.count") == ("bodies", 1, "count")
    assert parse_vary("simulation.resolution=6,8") == (("simulation", "resolution"), [6, 8])
    key, vals = parse_vary("bodies[0].velocity=[0, 0, 1],[0,0,2]")
    assert vals == [[0, 0, 1], [0, 0, 2]]
    assert parse_vary("simulation.device=cpu,\"cuda\"")[1] == ["cpu", "cuda"]
    for bad, words in [("materials.wood.restitution", "KEY=V1,V2"),
                       ("materials..x=1", "not a key"),
                       ("simulation.resolution=", "comma-separated"),
                       ("simulation.resolution=4,4", "twice")]:
        with pytest.raises(WedgeError) as info:
            parse_vary(bad)
        assert words in str(info.value) and "\n" not in str(info.value)


def test_variant_files_round_trip_every_example():
    import tomllib

    for path in sorted((ROOT / "examples").glob("*.toml")):
        data = tomllib.loads(path.read_text())
        assert tomllib.loads(dumps_toml(data)) == data, path.name


def test_plan_is_a_grid_of_named_variants(tmp_path):
    scene = write_scene(tmp_path)
    keys, variants = plan(scene, tmp_path / "w", seeds=2,
                          vary=["materials.rubber.restitution=0.2,0.6", "bodies[0].count=1,2"])
    assert keys == ["simulation.seed", "materials.rubber.restitution", "bodies[0].count"]
    assert [v.name for v in variants] == [f"v{i:03d}" for i in range(8)]
    assert variants[5].values == {"simulation.seed": 4, "materials.rubber.restitution": 0.2,
                                  "bodies[0].count": 2}
    for bad, words in [
            (dict(vary=["bodies[3].count=1,2"]), "has 1 bodies entries"),
            (dict(vary=["simulation.resolution.x=1,2"]), "is a value, not a table"),
            # a misspelt material would become a new, unused one: every variant the same
            (dict(vary=["materials.rubbr.restitution=0.2,0.6"]),
             "no materials.rubbr (did you mean 'rubber'?"),
            (dict(seeds=2, vary=["simulation.seed=1,2"]), "wedged twice"),
            (dict(), "nothing to wedge")]:
        with pytest.raises(WedgeError) as info:
            plan(scene, tmp_path / "w", **bad)
        assert words in str(info.value), str(info.value)
    broken = tmp_path / "broken.toml"
    broken.write_text(SCENE.format(duration=0.1).replace("density = 900.0", "density = -1"))
    with pytest.raises(SceneError, match="broken.toml: materials.rubber.density"):
        plan(broken, tmp_path / "w", seeds=2)


def test_relative_mesh_paths_become_absolute(tmp_path):
    import trimesh

    (tmp_path / "meshes").mkdir()
    trimesh.creation.box(extents=(0.04, 0.04, 0.04)).export(tmp_path / "meshes" / "box.obj")
    text = SCENE.format(duration=0.1).replace('builtin = "sphere"', 'mesh = "meshes/box.obj"')
    scene = tmp_path / "shot" / "s.toml"
    scene.parent.mkdir()
    scene.write_text(text.replace("meshes/", "../meshes/"))
    _, variants = plan(scene, tmp_path / "elsewhere", seeds=1)
    out = tmp_path / "elsewhere"
    out.mkdir()
    variants[0].scene.write_text(variants[0].text)
    from dempipe.scene.load import load_scene

    loaded = load_scene(variants[0].scene)
    assert loaded.shapes["ball"].mesh_path == (tmp_path / "meshes" / "box.obj").resolve()


def test_host_warnings_name_workers_that_would_fight():
    def f(host, threads, policy="PASSIVE", nthreads=1, cores=8):
        return dict(host=host, cores=cores, numba_threads=threads, wait_policy=policy,
                    nthreads=nthreads, pid=1)

    assert host_warnings({"a": f("n1", 4), "b": f("n1", 4), "c": f("n2", 8, "")}) == []
    out = host_warnings({"a": f("n1", 8, ""), "b": f("n1", 8, ""), "c": f("n2", 2, nthreads=4)})
    assert any("host n1" in w and "16 bake threads" in w and "NUMBA_NUM_THREADS=4" in w
               for w in out), out
    assert any("host n1" in w and "OMP_WAIT_POLICY=PASSIVE" in w for w in out), out
    assert any("worker c runs 4 tasks at once" in w for w in out), out
    assert local_sizes(None, None, 1)[0] == 1
    assert local_sizes(2, None, 8)[0] == 2 and local_sizes(2, 3, 8) == (2, 3)


def test_scheduler_with_local_sizes_is_refused():
    with pytest.raises(FarmError, match="give one or the other"):
        with connect(workers=2, scheduler="tcp://127.0.0.1:1"):
            pass


# ------------------------------------------------------------------ a LocalCluster


def test_local_workers_bake_with_one_thread_and_the_passive_policy(farm):
    def given():
        import numba

        return (numba.config.NUMBA_NUM_THREADS, numba.get_num_threads(),
                os.environ.get("OMP_WAIT_POLICY"))

    got = farm.client.run(given)
    assert len(got) == 2 and set(got.values()) == {(1, 1, "PASSIVE")}, got
    facts = farm.survey()
    assert {f["nthreads"] for f in facts.values()} == {1}
    assert host_warnings(facts) == []
    assert all(a.startswith("tcp://127.0.0.1:") for a in facts)


def test_four_seeds_give_four_different_bakes(farm, shared, tmp_path):
    from dempipe.pipeline.bake import bake
    from dempipe.spheres.cache import SphereCache

    root, cache = shared
    lines = []
    r = wedge(write_scene(tmp_path), tmp_path / "w", seeds=4, farm=farm, device="cpu",
              cache_dir=cache, progress=lines.append)
    rows = read_rows(r.csv)
    assert [row["variant"] for row in rows] == ["v000", "v001", "v002", "v003"]
    assert [int(row["simulation.seed"]) for row in rows] == [3, 4, 5, 6]
    assert all(row["status"] == "ok" and row["threads"] == "1" and row["tries"] == "1"
               for row in rows), rows
    assert {row["worker"] for row in rows} == set(farm.survey())     # both workers baked
    assert all(float(row["wall_s"]) > 0 for row in rows)
    rots = [samples(row["output"])[1] for row in rows]
    for i in range(4):
        for j in range(i):
            assert not np.allclose(rots[i][0], rots[j][0]), (i, j)   # other random turns
    # a line per variant, then the total
    assert sum(line.startswith("[") for line in lines) == 4
    assert lines[-1].startswith("wedge: 4 of 4 ok, 0 failed")
    # the variant's own scene file bakes the same animation bit for bit
    again = bake(tmp_path / "w" / "v002.toml", tmp_path / "again.usdc", device="cpu",
                 threads=1, cache=SphereCache(cache))
    for a, b in zip(samples(again.path), samples(rows[2]["output"])):
        np.testing.assert_array_equal(a, b)


def test_a_vary_grid_writes_its_values(farm, shared, tmp_path):
    import tomllib

    r = wedge(write_scene(tmp_path), tmp_path / "w", farm=farm, device="cpu",
              cache_dir=shared[1],
              vary=["materials.rubber.restitution=0.2,0.6", "simulation.resolution=2,3"])
    rows = read_rows(r.csv)
    got = {(float(row["materials.rubber.restitution"]), int(row["simulation.resolution"]))
           for row in rows}
    assert got == {(0.2, 2), (0.2, 3), (0.6, 2), (0.6, 3)}
    for row in rows:
        assert row["status"] == "ok", row
        data = tomllib.loads(Path(row["scene"]).read_text())
        assert data["materials"]["rubber"]["restitution"] == float(
            row["materials.rubber.restitution"])
        assert data["simulation"]["resolution"] == int(row["simulation.resolution"])
        assert Usd.Stage.Open(row["output"]) is not None
    # dt = "auto" follows the contact stiffness, which follows the sphere size
    steps = {int(row["simulation.resolution"]): int(row["steps"]) for row in rows}
    assert steps[2] != steps[3]


def test_a_bad_variant_fails_its_row_only(farm, shared, tmp_path):
    r = wedge(write_scene(tmp_path), tmp_path / "w", farm=farm, device="cpu",
              cache_dir=shared[1],
              vary=["materials.rubber.restitution=0.3,7", "simulation.dt=\"auto\",0.01"])
    rows = {row["variant"]: row for row in read_rows(r.csv)}
    assert rows["v000"]["status"] == "ok"
    # refused by the scene's validation, before any worker
    assert rows["v002"]["status"].startswith("failed: v002.toml: materials.rubber.restitution")
    assert rows["v003"]["status"].startswith("failed: v003.toml: materials.rubber.restitution")
    # refused by the bake, on a worker
    assert rows["v001"]["status"].startswith("failed: v001.toml: simulation.dt:"), rows["v001"]
    assert rows["v001"]["worker"].startswith("tcp://127.0.0.1:")
    assert all("\n" not in row["status"] for row in rows.values())
    assert [v.name for v in r.failed] == ["v001", "v002", "v003"]


def test_a_second_run_skips_the_done_variants(farm, shared, tmp_path):
    scene, out = write_scene(tmp_path), tmp_path / "w"
    first = wedge(scene, out, seeds=2, farm=farm, device="cpu", cache_dir=shared[1])
    assert len(first.ok) == 2
    stamp = {p.name: p.stat().st_mtime_ns for p in out.glob("v00*.usdc")}
    (out / "v001.usdc").unlink()                          # lost: baked again
    lines = []
    second = wedge(scene, out, seeds=3, farm=farm, device="cpu", cache_dir=shared[1],
                   progress=lines.append)
    assert [v.name for v in second.skipped] == ["v000"]
    assert (out / "v000.usdc").stat().st_mtime_ns == stamp["v000.usdc"]
    assert {row["status"] for row in read_rows(second.csv)} == {"ok"}
    assert any("1 of 3 variants done by an earlier run" in line for line in lines), lines
    # a changed scene is a changed variant: baked again
    scene.write_text(scene.read_text().replace("friction = 0.4", "friction = 0.3"))
    third = wedge(scene, out, seeds=3, farm=farm, device="cpu", cache_dir=shared[1])
    assert third.skipped == [] and len(third.ok) == 3


def test_a_killed_worker_loses_no_variant(farm, shared, tmp_path):
    # a longer bake, so that the kill lands while a worker is baking
    scene = write_scene(tmp_path, duration=1.0)
    out, box = tmp_path / "w", {}

    def run():
        try:
            box["result"] = wedge(scene, out, seeds=4, farm=farm, device="cpu",
                                  cache_dir=shared[1])
        except BaseException as exc:           # seen by the test below
            box["error"] = exc

    def baking(dask_worker):
        return [str(ts.key) for ts in dask_worker.state.executing]

    pids = {a: f["pid"] for a, f in farm.survey().items()}
    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    victim, deadline = None, time.monotonic() + 120
    while victim is None and time.monotonic() < deadline and thread.is_alive():
        busy = {a: keys for a, keys in farm.client.run(baking).items()
                if any("dempipe-wedge" in k for k in keys)}
        if busy:
            victim = sorted(busy)[0]
            os.kill(pids[victim], signal.SIGKILL)
            break
        time.sleep(0.05)
    assert victim is not None, "no worker was seen baking"
    thread.join(timeout=300)
    assert not thread.is_alive() and "error" not in box, box
    rows = read_rows(box["result"].csv)
    assert [row["status"] for row in rows] == ["ok"] * 4, rows
    retried = [row for row in rows if int(row["tries"]) > 1]
    assert len(retried) == 1 and retried[0]["worker"] != victim, rows
    for row in rows:
        assert samples(row["output"])[0].shape[0] == 25          # frames 0..24
    # the retried variant (resumed from its checkpoint folder where the killed try left
    # one) is the bake its scene file gives, bit for bit
    from dempipe.pipeline.bake import bake
    from dempipe.spheres.cache import SphereCache

    again = bake(retried[0]["scene"], tmp_path / "again.usdc", device="cpu", threads=1,
                 cache=SphereCache(shared[1]))
    for a, b in zip(samples(again.path), samples(retried[0]["output"])):
        np.testing.assert_array_equal(a, b)
    farm.client.wait_for_workers(2, timeout=120)                  # the nanny restarted it


# ------------------------------------------------------------------ processes and the CLI


def _stop(procs):
    for p in procs:
        if p.poll() is None:
            try:
                os.killpg(p.pid, signal.SIGTERM)
            except ProcessLookupError:
                pass
    for p in procs:
        try:
            p.wait(timeout=20)
        except subprocess.TimeoutExpired:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait(timeout=20)


def test_scheduler_and_workers_as_processes_run_the_cli(shared, tmp_path):
    env = dict(os.environ, NUMBA_NUM_THREADS="1", OMP_WAIT_POLICY="PASSIVE")
    sched_file = tmp_path / "scheduler.json"
    dask = [sys.executable, "-m", "dask"]
    procs = []
    try:
        procs.append(subprocess.Popen(
            dask + ["scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard",
                    "--scheduler-file", str(sched_file)],
            env=env, start_new_session=True, stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL))
        deadline = time.monotonic() + 120
        while not sched_file.exists() and time.monotonic() < deadline:
            time.sleep(0.1)
        address = json.loads(sched_file.read_text())["address"]
        assert address.startswith("tcp://127.0.0.1:")
        for i in range(2):
            procs.append(subprocess.Popen(
                dask + ["worker", address, "--nthreads", "1", "--host", "127.0.0.1",
                        "--no-dashboard", "--name", f"w{i}"],
                env=env, start_new_session=True, stdout=subprocess.DEVNULL,
                stderr=subprocess.DEVNULL))
        scene = write_scene(tmp_path)
        out = tmp_path / "w"
        proc = subprocess.run(
            [sys.executable, "-m", "dempipe_cli.main", "wedge", str(scene), "-o", str(out),
             "--seeds", "2", "--vary", "materials.rubber.restitution=0.3,7",
             "--scheduler", address, "--device", "cpu", "--cache-dir", str(shared[1])],
            capture_output=True, text=True, env=env, timeout=400)
    finally:
        _stop(procs)
    # two variants baked on the two workers, two refused: exit 1, one error line
    assert proc.returncode == 1, proc.stderr
    err = proc.stderr.strip().splitlines()
    assert err[-1].startswith("error: 2 of 4 variants failed (first, v001: v001.toml: "
                              "materials.rubber.restitution"), err
    assert "Traceback" not in proc.stderr and "warning" not in proc.stderr, proc.stderr
    assert sum(line.startswith("[") for line in err) == 4
    assert any(line.startswith("wedge: 2 of 4 ok, 2 failed") for line in err)
    rows = read_rows(out / "wedge.csv")
    ok = [row for row in rows if row["status"] == "ok"]
    assert [row["variant"] for row in ok] == ["v000", "v002"]
    assert all(row["worker"].startswith("tcp://127.0.0.1:") for row in ok)
    assert all((out / f"{row['variant']}.usdc").is_file() for row in ok)


BLOCKED = textwrap.dedent("""
    import sys

    class NoDask:
        def find_spec(self, name, path=None, target=None):
            if name.split(".")[0] in ("dask", "distributed"):
                raise ModuleNotFoundError(f"No module named {name!r}", name=name)
            return None

    sys.meta_path.insert(0, NoDask())
    from dempipe_cli.main import main
    try:
        main(sys.argv[1:])
    finally:
        print("DASK", sorted(m for m in sys.modules if m.split(".")[0] in
                             ("dask", "distributed")), file=sys.stderr)
""")


def test_without_dask_wedge_says_how_to_install_it_and_bake_never_needs_it(shared, tmp_path):
    scene = write_scene(tmp_path)

    def run(*argv):
        return subprocess.run([sys.executable, "-c", BLOCKED, *argv], capture_output=True,
                              text=True, timeout=300, env=dict(os.environ), cwd=ROOT)

    for argv in (["wedge", str(scene), "-o", str(tmp_path / "w"), "--seeds", "2"],
                 ["report", str(scene), "-o", str(tmp_path / "r"), "--workers", "2",
                  "--no-plots"]):
        p = run(*argv)
        assert p.returncode == 2, p.stderr
        lines = p.stderr.strip().splitlines()
        assert lines[0].startswith("error: ") and 'pip install "dempipe[farm]"' in lines[0]
        assert lines[1:] == ["DASK []"] and "Traceback" not in p.stderr, p.stderr
    assert not (tmp_path / "w" / "wedge.csv").exists()
    p = run("wedge", "--help")
    assert p.returncode == 0 and "--scheduler" in p.stdout
    p = run("bake", str(scene), "-o", str(tmp_path / "b.usdc"), "--quiet", "--threads", "1",
            "--cache-dir", str(shared[1]))
    assert p.returncode == 0 and "DASK []" in p.stderr, p.stderr
    assert (tmp_path / "b.usdc").is_file()


# ------------------------------------------------------------------ report on the farm


def test_report_on_the_farm_measures_what_it_measures_alone(farm, shared, tmp_path):
    from dempipe.spheres.cache import SphereCache
    from dempipe.report.runs import Sweep, run_report

    scene = write_scene(tmp_path)
    sweep = Sweep(resolutions=(2, 3), dt_factors=(1.0,), stiffness_factors=(1.0,),
                  duration=0.125, plots=False, threads=1, device="cpu")
    cache = SphereCache(shared[1])
    lines = []
    farmed = run_report(scene, tmp_path / "farm", sweep, cache=cache, farm=farm,
                        progress=lines.append)
    alone = run_report(scene, tmp_path / "alone", sweep, cache=cache)
    assert sum(line.startswith("run ") for line in lines) == 2
    for a, b in zip(farmed.runs, alone.runs):
        assert (a.label, a.status, a.steps, a.spheres) == (b.label, b.status, b.steps, b.spheres)
        np.testing.assert_array_equal(a.frames.x, b.frames.x)       # the same bake
        assert a.error == b.error or (np.isnan(a.error) and np.isnan(b.error))


def test_a_contact_sheet_shows_each_finished_variant(farm, shared, tmp_path):
    from PIL import Image

    from dempipe.preview import Preview
    from dempipe.farm.wedge import contact_sheet

    root, cache = shared
    r = wedge(write_scene(tmp_path), tmp_path / "w", seeds=2, farm=farm, device="cpu",
              cache_dir=cache)
    path = contact_sheet(r, tile=(320, 180))
    assert path == tmp_path / "w" / "contact_sheet.png"
    sheet = np.asarray(Image.open(path).convert("RGB"), dtype=np.float64)
    assert sheet.shape == (180, 640, 3)               # two tiles side by side
    for k, v in enumerate(r.variants):
        tile = sheet[:, 320 * k:320 * (k + 1)]
        assert tile.std() > 5.0                          # something drawn, not a flat fill
        # the tile is that variant's last frame: compare it with a still of the same bake
        # away from the label strip at the top
        pv = Preview(v.output, size=(320, 180))
        try:
            still = np.asarray(pv.image(), dtype=np.float64)[..., :3]
        finally:
            pv.renderer.release()
        # same picture but for the white tile border and the MSAA of a still
        assert np.abs(tile[40:-4, 4:-4] - still[40:-4, 4:-4]).mean() < 8.0
