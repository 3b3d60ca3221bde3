"""A bake's work folder at the door: one bake per output (an OS lock), checkpoints
verified before a resume runs anything, --report and -o that would overwrite the
scene, names too long, and the leftovers of killed bakes cleared.

Every process here is a real `dempipe`; the checkpoints are left by real signals.
"""

import json
import os
import shutil
import signal
import subprocess
import time
from pathlib import Path

import pytest

pytest.importorskip("pxr")

from dempipe.pipeline.bake import partial_path  # noqa: E402
from dempipe.pipeline.lock import work_dir  # noqa: E402
from processes import assert_same_samples, dempipe, frames_done, run, wait_for  # noqa: E402
from test_faults import write_scene  # noqa: E402


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    d = tmp_path_factory.mktemp("ref")
    cache = d / "cache"
    scene = write_scene(d)
    out = d / "ref.usda"
    code, _, err = run("bake", scene, "-o", out, "--device", "cpu", "-q", cache=cache)
    assert code == 0, err
    return scene, out, cache


@pytest.fixture(scope="module")
def stopped(reference, tmp_path_factory):
    """A bake stopped by SIGTERM after its checkpoint at frame 8 or later: its work
    folder and partial file, to copy and damage."""
    scene, _, cache = reference
    d = tmp_path_factory.mktemp("stopped")
    out = d / "o.usda"
    p = dempipe("bake", scene, "-o", out, "--device", "cpu", "--chunk-frames", "4", "-q",
                cache=cache)
    wait_for(lambda: frames_done(out) >= 8, p)
    p.send_signal(signal.SIGTERM)
    _, err = p.communicate(timeout=120)
    assert p.returncode == 128 + signal.SIGTERM, err
    assert (work_dir(out) / "lock").exists()        # the lock file stays; its lock does not
    return out


def _copy(stopped, tmp_path) -> Path:
    out = tmp_path / stopped.name
    shutil.copytree(work_dir(stopped), work_dir(out))
    shutil.copy(partial_path(stopped), partial_path(out))
    return out


def test_second_bake_to_the_same_output_is_refused(reference, tmp_path):
    # The first bake runs on to its file; the second is refused at once, naming the
    # first's process, before loading anything. (The scene at 8 s, so that the first
    # is still running when the second starts: at 1 s it had finished by then.)
    _, _, cache = reference
    scene = write_scene(tmp_path, duration=8.0)
    out = tmp_path / "o.usda"
    first = dempipe("bake", scene, "-o", out, "--device", "cpu", "--chunk-frames", "2", "-q",
                    cache=cache)
    wait_for(lambda: frames_done(out) >= 2, first)
    t0 = time.monotonic()
    code, _, err = run("bake", scene, "-o", out, "--device", "cpu", "-q", cache=cache)
    assert code == 2 and time.monotonic() - t0 < 30
    assert "another bake to this output is running" in err and str(first.pid) in err, err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err
    _, err = first.communicate(timeout=300)
    assert first.returncode == 0, err
    assert out.exists() and not work_dir(out).exists()


@pytest.mark.parametrize("which", ["output", "scene"])
def test_report_over_the_output_or_scene_is_refused(reference, tmp_path, which):
    scene, _, cache = reference
    own = tmp_path / "scene.toml"
    shutil.copy(scene, own)
    out = tmp_path / "o.usda"
    out.write_text("#usda 1.0\n")
    target = out if which == "output" else own
    before = target.read_bytes()
    code, _, err = run("bake", own, "-o", out, "--report", target, "-q", cache=cache)
    assert code == 2 and f"is the {which}" in err or "is the scene file" in err, err
    assert target.read_bytes() == before


def test_output_equal_to_the_scene_or_too_long_fails_before_work(reference, tmp_path):
    scene, _, cache = reference
    stage = tmp_path / "shot.usda"
    stage.write_text("#usda 1.0\n")
    code, _, err = run("bake", stage, "-o", stage, cache=cache, timeout=60)
    assert code == 2 and "is the scene file" in err, err
    assert stage.read_text() == "#usda 1.0\n"
    long = tmp_path / ("x" * 245 + ".usda")
    t0 = time.monotonic()
    code, _, err = run("bake", scene, "-o", long, cache=cache, timeout=120)
    assert code == 2 and "too long" in err and "internal error" not in err, err
    assert time.monotonic() - t0 < 30
    assert list(tmp_path.iterdir()) == [stage]


DAMAGE = {
    "zero-byte state": lambda d: _state(d).write_bytes(b""),
    "truncated state": lambda d: _state(d).write_bytes(_state(d).read_bytes()[:100]),
    "random state": lambda d: _state(d).write_bytes(os.urandom(_state(d).stat().st_size)),
    "missing chunk": lambda d: (d / "chunk-000000.npz").unlink(),
    "truncated chunk": lambda d: (d / "chunk-000001.npz").write_bytes(
        (d / "chunk-000001.npz").read_bytes()[:-10]),
    "meta not json": lambda d: (d / "meta.json").write_text("{"),
    "meta altered": lambda d: (d / "meta.json").write_text(
        json.dumps({**json.loads((d / "meta.json").read_text()), "chunks": [["x"]]})),
}


def _state(d: Path) -> Path:
    return next(d.glob("state-*.npz"))


@pytest.mark.parametrize("damage", list(DAMAGE))
def test_damaged_checkpoint_is_one_line_before_any_work(reference, stopped, tmp_path, damage):
    scene, _, cache = reference
    out = _copy(stopped, tmp_path)
    DAMAGE[damage](work_dir(out))
    t0 = time.monotonic()
    code, _, err = run("bake", scene, "-o", out, "--device", "cpu", "--resume", "-q",
                       cache=cache, timeout=120)
    assert code == 2, err
    assert "checkpoint" in err and "without --resume" in err, err
    assert len(err.strip().splitlines()) == 1 and "internal error" not in err, err
    assert time.monotonic() - t0 < 30


def test_resume_clears_a_killed_write_and_the_stale_partial(reference, stopped, tmp_path):
    # What a SIGKILL inside the final write leaves (.NAME.tmp-PID.EXT) and the partial
    # file of the stop are gone once the resumed bake has written the whole file.
    scene, ref, cache = reference
    out = _copy(stopped, tmp_path)
    stale = [tmp_path / ".o.tmp-999999.usda", tmp_path / ".o.partial.tmp-999998.usda"]
    for p in stale:
        p.write_text("half")
    code, _, err = run("bake", scene, "-o", out, "--device", "cpu", "--chunk-frames", "4",
                       "--resume", "-q", cache=cache)
    assert code == 0, err
    assert_same_samples(ref, out)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["o.usda"]


def _mount_tmpfs(folder: Path, size: str) -> bool:
    folder.mkdir(exist_ok=True)
    return subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(folder)],
                          capture_output=True).returncode == 0


def test_full_disk_at_a_checkpoint_keeps_the_last_one(reference, tmp_path):
    # A real full file system (a small tmpfs): the bake stops with one line naming the
    # file and the OS's reason; the last whole checkpoint is kept, and --resume on a
    # disk with room goes on from it to the uninterrupted bake's file.
    scene, ref, cache = reference
    disk = tmp_path / "disk"
    if not _mount_tmpfs(disk, "96k"):
        pytest.skip("cannot mount a tmpfs here (not root?)")
    try:
        out = disk / "o.usda"
        code, _, err = run("bake", scene, "-o", out, "--device", "cpu", "--chunk-frames", "1",
                           "-q", cache=cache)
        assert code == 2, err
        assert "No space left on device" in err and "pxr" not in err, err
        assert "--resume" in err and len(err.strip().splitlines()) == 1, err
        done = frames_done(out)
        assert done > 0 and f"checkpoint at frame {done}" in err, err
        subprocess.run(["mount", "-o", "remount,size=16m", str(disk)], check=True)
        code, _, err = run("bake", scene, "-o", out, "--device", "cpu", "--chunk-frames", "1",
                           "--resume", "-q", cache=cache)
        assert code == 0, err
        assert_same_samples(ref, out)
    finally:
        subprocess.run(["umount", "-l", str(disk)])


def test_full_disk_at_the_usd_write_is_the_os_reason(reference, tmp_path):
    # The frames fit (one chunk and a State: about 90 KiB) but the 250 KiB .usda does
    # not: one line saying the disk is full, no pxr C++ text, the frames kept; --resume
    # with room writes them without simulating again.
    scene, ref, cache = reference
    disk = tmp_path / "disk"
    if not _mount_tmpfs(disk, "160k"):
        pytest.skip("cannot mount a tmpfs here (not root?)")
    try:
        out = disk / "o.usda"
        code, _, err = run("bake", scene, "-o", out, "--device", "cpu", "-q", cache=cache)
        assert code == 2, err
        assert "No space left on device" in err and "pxrInternal" not in err, err
        assert "--resume" in err and len(err.strip().splitlines()) == 1, err
        assert [p.name for p in disk.iterdir()] == [work_dir(out).name]   # no temporary
        subprocess.run(["mount", "-o", "remount,size=16m", str(disk)], check=True)
        rep = tmp_path / "r.json"
        code, _, err = run("bake", scene, "-o", out, "--device", "cpu", "--resume", "--report",
                           rep, "-q", cache=cache)
        assert code == 0, err
        assert json.loads(rep.read_text())["resumed_from_frame"] == 25
        assert_same_samples(ref, out)
    finally:
        subprocess.run(["umount", "-l", str(disk)])


def test_simulation_settings_from_a_caller_are_checked(reference, tmp_path):
    # bake(simulation=...) is what the command line's --sphere-diameter reaches
    from dempipe.errors import SceneError
    from dempipe.pipeline.bake import bake

    scene, _, cache = reference
    for v in (float("nan"), -1.0, 1e300):
        with pytest.raises(SceneError, match="simulation.sphere_diameter"):
            bake(scene, tmp_path / "o.usda", simulation={"sphere_diameter": v})
    assert list(tmp_path.iterdir()) == []


def test_sigkill_inside_the_final_write_leaves_nothing_after_resume(reference, tmp_path):
    # A real SIGKILL the moment the USD write's temporary file appears (pxr's own
    # temporary beside it): the next bake to that output, here --resume, removes both
    # and writes the file from the kept frames without simulating again.
    _, _, cache = reference
    scene = write_scene(tmp_path, duration=4.0)        # a 1 MB .usda: a write to land in
    out = tmp_path / "o.usda"
    p = dempipe("bake", scene, "-o", out, "--device", "cpu", "-q", cache=cache)
    hit = None
    while p.poll() is None:
        hit = [q.name for q in tmp_path.iterdir() if q.name.startswith(".o.tmp-")]
        if hit:
            p.send_signal(signal.SIGKILL)
            break
        time.sleep(0.0005)
    p.communicate(timeout=60)
    if not hit:
        pytest.skip("the write ended before the kill could land in it on this machine")
    assert p.returncode == -signal.SIGKILL
    rep = tmp_path / "r.json"
    code, _, err = run("bake", scene, "-o", out, "--device", "cpu", "--resume", "--report",
                       rep, "-q", cache=cache)
    assert code == 0, err
    assert json.loads(rep.read_text())["resumed_from_frame"] == 97     # 4 s at 24 fps
    assert sorted(q.name for q in tmp_path.iterdir()) == ["o.usda", "r.json", "scene.toml"]
