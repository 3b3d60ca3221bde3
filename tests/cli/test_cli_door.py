"""Command-line values checked at the door: numbers that are not finite or are absurd,
report sweeps that cannot be what they say, a --scheduler address where no Dask
scheduler listens. Real `dempipe` processes; nothing simulates."""

import os
import socket
import subprocess
import sys
import threading
import time

import pytest

SCENE = """
[output]
fps = 24
duration = 0.2

[simulation]
resolution = 2

[shapes.ball]
builtin = "sphere"
diameter = 0.1

[[bodies]]
name = "ball"
shape = "ball"
position = [0.0, 0.0, 0.2]

[[colliders]]
type = "plane"
point = [0.0, 0.0, 0.0]
normal = [0.0, 0.0, 1.0]
"""


def dempipe(tmp_path, *args, timeout=120):
    env = dict(os.environ, DEMPIPE_CACHE_DIR=str(tmp_path / "cache"))
    t0 = time.monotonic()
    r = subprocess.run([sys.executable, "-m", "dempipe_cli.main", *map(str, args)],
                       cwd=tmp_path, capture_output=True, text=True, env=env, timeout=timeout)
    return r.returncode, r.stderr, time.monotonic() - t0


@pytest.mark.parametrize("args, option", [
    (("bake", "s.toml", "-o", "o.usda", "--sphere-diameter", "nan"), "--sphere-diameter"),
    (("bake", "s.toml", "-o", "o.usda", "--sphere-diameter", "1e300"), "--sphere-diameter"),
    (("bake", "s.toml", "-o", "o.usda", "--checkpoint-every", "inf"), "--checkpoint-every"),
    (("bake", "s.toml", "-o", "o.usda", "--chunk-frames", "99999999"), "--chunk-frames"),
    (("report", "s.toml", "-o", "rep", "--duration", "nan"), "--duration"),
    (("report", "s.toml", "-o", "rep", "--tolerance", "-inf"), "--tolerance"),
    (("spheres", "sphere", "--diameter", "nan"), "--diameter"),
])
def test_numbers_that_are_not_finite_or_absurd_are_usage_errors(tmp_path, args, option):
    (tmp_path / "s.toml").write_text(SCENE)
    code, err, _ = dempipe(tmp_path, *args)
    assert code == 2 and option in err and "internal error" not in err, err
    assert not (tmp_path / "o.usda").exists() and not (tmp_path / "rep").exists()


def test_report_duration_beyond_reason_is_one_line_before_any_bake(tmp_path):
    (tmp_path / "s.toml").write_text(SCENE)
    code, err, took = dempipe(tmp_path, "report", "s.toml", "-o", "rep", "--duration", "1e9",
                              "--no-plots")
    assert code == 2 and "--duration" in err and "frames" in err, err
    assert len(err.strip().splitlines()) == 1 and "MemoryError" not in err and took < 60


def test_report_dt_factors_above_one_on_auto_dt_are_refused(tmp_path):
    # the auto step is the largest stable one: dt x2 would be the dt x1 run relabelled
    (tmp_path / "s.toml").write_text(SCENE)
    code, err, _ = dempipe(tmp_path, "report", "s.toml", "-o", "rep", "--dt-factors", "1,2,4",
                           "--no-plots")
    assert code == 2 and "--dt-factors" in err and "2, 4" in err, err
    assert len(err.strip().splitlines()) == 1


def _server(reply: bytes | None):
    """A TCP server on loopback that says ``reply`` to each connection (None: nothing)."""
    srv = socket.socket()
    srv.bind(("127.0.0.1", 0))
    srv.listen(8)
    conns = []

    def serve():
        while True:
            try:
                c, _ = srv.accept()
            except OSError:
                return
            conns.append(c)
            if reply is not None:
                c.sendall(reply)

    threading.Thread(target=serve, daemon=True).start()
    return srv, conns


@pytest.mark.parametrize("reply", [None, b"SSH-2.0-OpenSSH_9.6\r\n",
                                   b"HTTP/1.1 400 Bad Request\r\n\r\n"])
def test_scheduler_address_where_no_dask_listens_is_refused_in_seconds(tmp_path, reply):
    pytest.importorskip("distributed")
    srv, conns = _server(reply)
    try:
        (tmp_path / "s.toml").write_text(SCENE)
        port = srv.getsockname()[1]
        code, err, took = dempipe(tmp_path, "wedge", "s.toml", "-o", "w", "--seeds", "2",
                                  "--scheduler", f"tcp://127.0.0.1:{port}", timeout=120)
        assert code == 2 and "not" in err and "Dask scheduler" in err, err
        assert "MemoryError" not in err and len(err.strip().splitlines()) == 1, err
        assert took < 30
    finally:
        srv.close()
        for c in conns:
            c.close()


def test_a_real_scheduler_passes_the_probe():
    pytest.importorskip("distributed")
    import asyncio

    from distributed import Scheduler

    from dempipe.farm.cluster import probe_scheduler

    async def main():
        s = await Scheduler(host="127.0.0.1", port=0, dashboard_address=None)
        try:
            await asyncio.get_running_loop().run_in_executor(None, probe_scheduler, s.address)
        finally:
            await s.close()

    asyncio.run(main())


@pytest.mark.parametrize("option, value", [("--stiffness-factors", "1,1e300"),
                                           ("--dt-factors", "1e-300,1"),
                                           ("--resolutions", "4,1000000000")])
def test_report_sweep_values_beyond_reason_are_one_line(tmp_path, option, value):
    (tmp_path / "s.toml").write_text(SCENE)
    code, err, _ = dempipe(tmp_path, "report", "s.toml", "-o", "rep", option, value,
                           "--no-plots")
    assert code == 2 and option in err and "out of range" in err, err
    assert len(err.strip().splitlines()) == 1 and not (tmp_path / "rep").exists()
