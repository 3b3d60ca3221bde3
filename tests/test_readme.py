"""The README's Quick start holds exactly two commands, and .ci/run runs the second."""

import re
from pathlib import Path

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


def test_ci_runs_the_readme_test_command():
    ci = (ROOT / ".ci" / "run").read_text()
    assert quick_start_commands()[1] in ci
    assert '"$rc" -eq 5' in ci


def test_every_example_is_listed_in_the_readme():
    text = (ROOT / "README.md").read_text()
    for example in [*(ROOT / "examples").glob("*.toml"), *(ROOT / "examples").glob("*.usd*")]:
        assert f"examples/{example.name}" in text
