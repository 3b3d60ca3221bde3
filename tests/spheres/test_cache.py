"""The sphere-set disk cache: hits, misses, corruption, location."""

import os
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
import trimesh

import dempipe.spheres.sphere_set as spheres
from dempipe.spheres.cache import FORMAT_VERSION, SphereCache, default_cache_dir
from dempipe.errors import CacheError
from dempipe.spheres.options import BuildOptions
from dempipe.spheres.sphere_set import build_sphere_set, build_sphere_set_with_info


@pytest.fixture(autouse=True)
def _cache_env(monkeypatch, tmp_path):
    monkeypatch.setenv("DEMPIPE_CACHE_DIR", str(tmp_path / "env-cache"))


@pytest.fixture
def torus():
    return trimesh.creation.torus(major_radius=0.02, minor_radius=0.008)


def _same(a, b):
    # a hit returns the stored arrays bit for bit
    return (np.array_equal(a.centers, b.centers) and a.diameter == b.diameter
            and a.volume == b.volume and np.array_equal(a.com, b.com)
            and np.array_equal(a.inertia, b.inertia) and a.mesh_sha256 == b.mesh_sha256
            and a.key == b.key and a.notes == b.notes)


def test_second_build_is_a_hit_with_the_same_arrays(tmp_path, torus):
    cache = SphereCache(tmp_path / "c")
    a, info_a = build_sphere_set_with_info(torus, 0.003, cache=cache)
    b, info_b = build_sphere_set_with_info(torus, 0.003, cache=cache)
    assert (info_a.cache, info_b.cache) == ("miss", "hit")
    assert _same(a, b) and a is not b
    assert not b.centers.flags.writeable
    assert cache.info()["entries"] == 1


def test_changes_that_miss(tmp_path, torus, monkeypatch):
    cache = SphereCache(tmp_path / "c")
    _, first = build_sphere_set_with_info(torus, 0.003, cache=cache)
    assert first.cache == "miss"
    scaled = torus.copy()
    scaled.apply_scale(1.5)
    cases = [
        (torus, 0.0031, {}),                                                  # diameter
        (scaled, 0.003, {}),                                                  # scale
        (torus, 0.003, {"options": BuildOptions(winding_threshold=0.45)}),    # options
    ]
    keys = {first.key}
    for mesh, d, kw in cases:
        _, info = build_sphere_set_with_info(mesh, d, cache=cache, **kw)
        assert info.cache == "miss"
        keys.add(info.key)
    monkeypatch.setattr(spheres, "BUILDER_VERSION", spheres.BUILDER_VERSION + 1)
    _, info = build_sphere_set_with_info(torus, 0.003, cache=cache)
    assert info.cache == "miss"
    keys.add(info.key)
    assert len(keys) == 5


def test_what_does_not_miss(tmp_path, torus):
    cache = SphereCache(tmp_path / "c")
    build_sphere_set(torus, 0.003, cache=cache)
    # a copy of the mesh, another name, a fresh cache object on the same folder: all hits
    _, info = build_sphere_set_with_info(torus.copy(), 0.003, name="other", cache=SphereCache(tmp_path / "c"))
    assert info.cache == "hit"


@pytest.mark.parametrize("damage", ["truncate", "garbage", "empty", "bad_checksum", "old_format", "wrong_key"])
def test_corrupt_entry_is_detected_warned_and_rebuilt(tmp_path, torus, damage):
    cache = SphereCache(tmp_path / "c")
    good, info = build_sphere_set_with_info(torus, 0.003, cache=cache)
    path = cache.path_for(info.key)
    raw = path.read_bytes()
    if damage == "truncate":
        path.write_bytes(raw[: len(raw) // 2])
    elif damage == "garbage":
        path.write_bytes(os.urandom(len(raw)))
    elif damage == "empty":
        path.write_bytes(b"")
    else:
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
        if damage == "bad_checksum":
            c = data["centers"].copy()
            c[0, 0] += 1e-3  # plausible but wrong data
            data["centers"] = c
        elif damage == "old_format":
            data["format_version"] = np.asarray(FORMAT_VERSION + 99)
        else:
            data["key"] = np.asarray("0" * 64)
        with open(path, "wb") as f:
            np.savez(f, **data)
    with pytest.warns(UserWarning, match=r"sphere cache: entry .*\.npz was corrupt \(.+\); rebuilt"):
        again, info2 = build_sphere_set_with_info(torus, 0.003, cache=cache)
    assert info2.cache == "miss"
    assert _same(good, again)  # correct data, not the damaged one
    # and the rebuilt entry is good again: a silent hit
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        _, info3 = build_sphere_set_with_info(torus, 0.003, cache=cache)
    assert info3.cache == "hit"


def test_no_pickle_and_no_temp_files_left(tmp_path, torus):
    cache = SphereCache(tmp_path / "c")
    build_sphere_set(torus, 0.003, cache=cache)
    files = list((tmp_path / "c").iterdir())
    assert len(files) == 1 and files[0].suffix == ".npz"
    with np.load(files[0], allow_pickle=False) as z:  # loads without pickle
        assert {"centers", "key", "checksum", "format_version"} <= set(z.files)


def test_info_and_clear(tmp_path, torus):
    cache = SphereCache(tmp_path / "c")
    assert cache.info() == {"location": str(tmp_path / "c"), "entries": 0, "bytes": 0}
    build_sphere_set(torus, 0.003, cache=cache)
    build_sphere_set(torus, 0.004, cache=cache)
    info = cache.info()
    assert info["entries"] == 2 and info["bytes"] > 0
    assert cache.clear() == 2
    assert cache.info()["entries"] == 0
    assert cache.clear() == 0


def test_dempipe_cache_dir_respected(tmp_path, torus):
    assert default_cache_dir() == tmp_path / "env-cache"
    cache = SphereCache()
    assert cache.root == tmp_path / "env-cache"
    build_sphere_set(torus, 0.003, cache=cache)
    assert len(list((tmp_path / "env-cache").glob("*.npz"))) == 1


@pytest.mark.skipif(sys.platform in ("win32", "darwin"), reason="Linux folder layout")
def test_default_cache_dir_linux(monkeypatch, tmp_path):
    monkeypatch.delenv("DEMPIPE_CACHE_DIR")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert default_cache_dir() == tmp_path / "xdg" / "dempipe"
    monkeypatch.delenv("XDG_CACHE_HOME")
    assert default_cache_dir() == Path.home() / ".cache" / "dempipe"


def test_unwritable_folder_warns_once_and_continues(tmp_path, torus):
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    cache = SphereCache(blocker / "cache")  # cannot be created: its parent is a file
    with pytest.warns(UserWarning, match="not writable") as record:
        s1, i1 = build_sphere_set_with_info(torus, 0.003, cache=cache)
        s2, i2 = build_sphere_set_with_info(torus, 0.003, cache=cache)
    assert len([w for w in record if "not writable" in str(w.message)]) == 1
    assert i1.cache == i2.cache == "off"
    assert s1.count == s2.count > 0


def test_unwritable_folder_strict_raises(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    with pytest.raises(CacheError, match="not writable"):
        SphereCache(blocker / "cache", strict=True)


def test_notes_survive_the_cache(tmp_path):
    # a mesh with a hole: the warning is given again on a hit
    ico = trimesh.creation.icosphere(subdivisions=3, radius=0.02)
    holey = trimesh.Trimesh(ico.vertices, ico.faces[1:], process=False)
    cache = SphereCache(tmp_path / "c")
    with pytest.warns(UserWarning, match="not watertight"):
        a = build_sphere_set(holey, 0.004, cache=cache, name="h")
    with pytest.warns(UserWarning, match="h2: mesh is not watertight"):
        b, info = build_sphere_set_with_info(holey, 0.004, cache=cache, name="h2")
    assert info.cache == "hit" and b.notes == a.notes == ("not_watertight",)
