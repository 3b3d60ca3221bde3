"""`dempipe bake`'s progress line: what it says while the first frame is slow."""

import time
from types import SimpleNamespace

from dempipe_cli import bake_cmd


def test_slow_first_frame_says_why(monkeypatch, capsys):
    # A first bake on a machine compiles its kernels for a minute or two before the
    # first frame: after SLOW_START seconds the line says so, once.
    monkeypatch.setattr(bake_cmd, "SLOW_START", 0.05)
    p = bake_cmd.Progress(quiet=False)
    time.sleep(0.5)
    p.close()
    err = capsys.readouterr().err
    assert err.count("still on the first frame after") == 1, err
    assert "compiles its simulation kernels" in err


def test_a_prompt_first_frame_or_quiet_says_nothing(monkeypatch, capsys):
    monkeypatch.setattr(bake_cmd, "SLOW_START", 0.2)
    p = bake_cmd.Progress(quiet=False)
    p(0, 10, SimpleNamespace(steps=100, wall_seconds=0.1))     # the first frame, in time
    q = bake_cmd.Progress(quiet=True)
    time.sleep(0.5)
    p.close()
    q.close()
    err = capsys.readouterr().err
    assert "still on the first frame" not in err
    assert "frame 1/10" in err
