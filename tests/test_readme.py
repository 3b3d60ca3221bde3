"""The README's Quick start holds exactly two commands, .ci/run runs both, and its Python
examples run."""

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def quick_start_commands():
    text = (ROOT / "README.md").read_text()
    section = text.split("## Quick start", 1)[1].split("\n## ", 1)[0]
    return [b.strip() for b in re.findall(r"```bash\n(.*?)```", section, re.S)]


def test_quick_start_has_two_commands():
    cmds = quick_start_commands()
    assert len(cmds) == 2 and all("\n" not in c for c in cmds)
    assert "dempipe bake examples/quickstart.toml" in cmds[0]
    assert 'pip install ".[test]"' in cmds[1] and "pytest" in cmds[1]


def test_ci_runs_both_readme_commands():
    """.ci/run holds both commands verbatim (it runs the first in a clean clone with no
    extras, the second in a venv of its own); this fails when README and CI drift."""
    ci = (ROOT / ".ci" / "run").read_text()
    first, second = quick_start_commands()
    assert f"quick_start='{first}'" in ci and f"test_suite='{second}'" in ci
    assert 'bash -c "$quick_start"' in ci and 'bash -c "$test_suite"' in ci
    assert "pip install . " in first and "[" not in first     # no extras
    assert '"$rc" -eq 5' in ci


def test_every_example_is_listed_in_the_readme():
    text = (ROOT / "README.md").read_text()
    for example in [*(ROOT / "examples").glob("*.toml"), *(ROOT / "examples").glob("*.usd*")]:
        assert f"examples/{example.name}" in text


@pytest.mark.slow
def test_readme_python_runs_and_writes_the_quickstart(tmp_path):
    """Each ```python block of the README, run as a user would from a clone (here: in a
    copy of examples/), writes quickstart.usdc with the tray's 196 bodies and 37 frames."""
    import shutil
    import subprocess
    import sys

    from pxr import Usd, UsdGeom

    blocks = re.findall(r"```python\n(.*?)```", (ROOT / "README.md").read_text(), re.S)
    assert len(blocks) >= 2 and "dempipe.bake(" in blocks[0]
    shutil.copytree(ROOT / "examples", tmp_path / "examples")
    for i, code in enumerate(blocks):
        out = tmp_path / "quickstart.usdc"
        out.unlink(missing_ok=True)
        proc = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True,
                              text=True, timeout=900)
        assert proc.returncode == 0, (i, proc.stderr[-3000:])
        stage = Usd.Stage.Open(str(out))
        ids = UsdGeom.PointInstancer(stage.GetPrimAtPath("/World/Bodies")).GetProtoIndicesAttr()
        assert len(ids.Get()) == 196
        assert stage.GetEndTimeCode() - stage.GetStartTimeCode() + 1 == 37
