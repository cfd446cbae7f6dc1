"""The guide's Python examples (docs/api.md), run as written so that they cannot drift from the
package."""

import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
GUIDE = REPO / "docs" / "api.md"


def python_blocks(text):
    """The bodies of the ```python fences of a Markdown text, in order."""
    return re.findall(r"^```python\n(.*?)^```$", text, flags=re.MULTILINE | re.DOTALL)


def test_the_guide_has_python_examples():
    assert python_blocks(GUIDE.read_text()), f"{GUIDE} has no ```python example"


@pytest.mark.parametrize("index", range(len(python_blocks(GUIDE.read_text()))))
def test_guide_example_runs(index, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    code = python_blocks(GUIDE.read_text())[index]
    exec(compile(code, f"{GUIDE}:python block {index + 1}", "exec"), {"__name__": "__guide__"})
