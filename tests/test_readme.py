"""The README's Quick start holds exactly two commands, and .ci/run runs both."""

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
    for example in (ROOT / "examples").glob("*.toml"):
        assert f"examples/{example.name}" in text
