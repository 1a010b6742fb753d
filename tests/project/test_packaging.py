"""The distribution installs one import name, ``hdrcap``, and nothing else at the top level."""

from __future__ import annotations

import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
OLD_NAMES = ("acquire", "pipeline", "planner", "mock_camera")


@pytest.mark.slow
def test_wheel_holds_only_hdrcap(tmp_path):
    """Build the wheel from the checkout: its top level is ``hdrcap`` and its dist-info only."""
    proc = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "--quiet", "-w", str(tmp_path), str(ROOT)],
        capture_output=True,
        text=True,
        cwd=tmp_path,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    (wheel,) = tmp_path.glob("hdrcap-*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    top = {n.split("/", 1)[0] for n in names}
    assert {t for t in top if not t.endswith(".dist-info")} == {"hdrcap"}
    for sub in OLD_NAMES:
        assert f"hdrcap/{sub}/__init__.py" in names
    assert "hdrcap/py.typed" in names
    assert any(n.endswith(".dist-info/licenses/LICENSE") for n in names)


def test_old_top_level_names_are_not_importable():
    """In the test environment the four folders exist only inside ``hdrcap``."""
    code = f"import importlib.util as u, sys; print([n for n in {OLD_NAMES!r} if u.find_spec(n) is not None])"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd="/")
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"


def test_version_has_one_source():
    """The version lives in hdrcap/__init__.py only; the installed metadata agrees with it."""
    from importlib.metadata import version

    import hdrcap

    assert version("hdrcap") == hdrcap.__version__
    assert "version =" not in (ROOT / "pyproject.toml").read_text().split("[project]", 1)[1].split("[", 1)[0]


def test_readme_is_a_front_page():
    """README stays the user's front page: at most 160 lines, exactly two set-up commands, every
    command of the CLI in its table."""
    import re

    from hdrcap.cli import cli

    text = (ROOT / "README.md").read_text(encoding="utf-8")
    assert len(text.splitlines()) <= 160
    setup = text.split("## Set-up on a fresh machine", 1)[1].split("```sh", 1)[1].split("```", 1)[0]
    assert [line.split()[:2] for line in setup.strip().splitlines()] == [["make", "demo"], ["make", "test"]]
    listed = set(re.findall(r"^\| `hdrcap ([a-z-]+)", text, re.M))
    assert set(cli.commands) <= listed, set(cli.commands) - listed
