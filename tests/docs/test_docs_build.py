"""The documentation: the mkdocs site builds without a warning, the README stays short and
starts with its example early, and every relative link in the README and docs/ resolves."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
README = ROOT / "README.md"
DOCS = ROOT / "docs"

README_MAX_LINES = 200
EXAMPLE_WITHIN_LINES = 100

_LINK = re.compile(r"(?<!!)\[[^\]]*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")
_FENCE = re.compile(r"^\s*(```|~~~)")


def _prose_lines(path: Path) -> list[tuple[int, str]]:
    """``(line number, text)`` of the lines outside fenced code blocks."""
    out, fenced = [], False
    for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), start=1):
        if _FENCE.match(line):
            fenced = not fenced
            continue
        if not fenced:
            out.append((number, line))
    return out


def _relative_links(path: Path) -> list[tuple[int, str]]:
    """``(line number, target)`` of the Markdown links in ``path`` that point at files:
    not web addresses, not mail, not anchors on the same page."""
    links = []
    for number, line in _prose_lines(path):
        for target in _LINK.findall(re.sub(r"`[^`]*`", "", line)):
            if re.match(r"^[a-z][a-z0-9+.-]*:", target, re.IGNORECASE) or target.startswith("#"):
                continue
            links.append((number, target))
    return links


def _markdown_files() -> list[Path]:
    return [README, *sorted(DOCS.rglob("*.md"))]


@pytest.mark.slow
def test_mkdocs_builds_strictly_without_warnings(tmp_path: Path) -> None:
    pytest.importorskip("mkdocs")
    pytest.importorskip("mkdocstrings_handlers.python")
    site = tmp_path / "site"
    proc = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--config-file",
         str(ROOT / "mkdocs.yml"), "--site-dir", str(site)],
        cwd=ROOT, capture_output=True, text=True, timeout=300,
    )
    log = proc.stdout + proc.stderr
    warnings = [line for line in log.splitlines() if "WARNING" in line or "ERROR" in line]
    assert proc.returncode == 0 and not warnings, f"mkdocs build --strict failed:\n{log[-4000:]}"
    assert (site / "index.html").is_file()
    api = (site / "api" / "tracker" / "index.html").read_text(encoding="utf-8")
    # the docstrings were rendered
    assert 'id="evtrack.tracking.tracker.Tracker.push_events"' in api
    assert ":class:`" not in api and ":meth:`" not in api  # Sphinx roles shown as code


def test_readme_is_short_and_shows_python_early() -> None:
    lines = README.read_text(encoding="utf-8").splitlines()
    assert len(lines) <= README_MAX_LINES, (
        f"README.md has {len(lines)} lines (at most {README_MAX_LINES}): move detail to docs/")
    first = next((i for i, line in enumerate(lines, start=1)
                  if line.strip().startswith("```python")), None)
    assert first is not None, "README.md has no ```python example"
    assert first <= EXAMPLE_WITHIN_LINES, (
        f"README.md's first ```python block starts on line {first} (at most "
        f"{EXAMPLE_WITHIN_LINES})")


def test_readme_quick_start_is_what_ci_runs() -> None:
    ci = (ROOT / ".ci" / "run").read_text(encoding="utf-8")
    test_command = "./scripts/install.sh && .venv/bin/python -m pytest -q"
    assert test_command in ci
    readme = README.read_text(encoding="utf-8")
    assert test_command in readme
    assert "./scripts/install.sh && .venv/bin/evtrack demo --overwrite" in readme


@pytest.mark.parametrize("path", _markdown_files(), ids=lambda p: str(p.relative_to(ROOT)))
def test_relative_links_point_to_existing_files(path: Path) -> None:
    missing = []
    for number, target in _relative_links(path):
        file_part = target.split("#", 1)[0]
        if file_part and not (path.parent / file_part).exists():
            missing.append(f"line {number}: {target}")
    assert not missing, f"{path.relative_to(ROOT)} links to files that do not exist: {missing}"


def test_link_finder_sees_links_and_skips_code(tmp_path: Path) -> None:
    page = tmp_path / "page.md"
    page.write_text(
        "[a](a.md) and [b](sub/b.md#part), ![img](pic.png), [web](https://x.org), [top](#top)\n"
        "`[not](code.md)`\n```\n[fenced](fenced.md)\n```\n[c](c.md \"title\")\n",
        encoding="utf-8")
    assert _relative_links(page) == [(1, "a.md"), (1, "sub/b.md#part"), (6, "c.md")]
