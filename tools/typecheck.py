"""Type-check the package as ``hdrcap.*`` with mypy; paths in the report are the repository's.

The root folders are installed as subpackages of ``hdrcap`` (``[tool.setuptools] package-dir`` in
pyproject.toml), which mypy cannot follow through the editable install's import hook. This script
lays out the package as it is installed, as symlinks under ``build/typecheck/hdrcap``, runs
``python -m mypy -p hdrcap`` there with the repository's pyproject.toml, and rewrites the paths
mypy prints back to the files in the repository. Extra arguments are passed on to mypy.

Usage: ``python tools/typecheck.py [mypy options]``; exits with mypy's exit status.
"""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = "hdrcap"
TREE = ROOT / "build" / "typecheck"


def package_dirs() -> dict[str, str]:
    """Return the subpackage -> folder map of ``package-dir``, e.g. ``{"pipeline": "pipeline"}``."""
    config = tomllib.loads((ROOT / "pyproject.toml").read_text())
    mapping = config["tool"]["setuptools"]["package-dir"]
    if mapping.get(PACKAGE) != PACKAGE:
        raise SystemExit(f"typecheck: expected package-dir {PACKAGE!r} = {PACKAGE!r} in pyproject.toml")
    subs = {}
    for name, folder in mapping.items():
        if name == PACKAGE:
            continue
        parent, _, sub = name.rpartition(".")
        if parent != PACKAGE:
            raise SystemExit(f"typecheck: cannot lay out package-dir entry {name!r} (only {PACKAGE}.<name>)")
        subs[sub] = folder
    return subs


def lay_out(subs: dict[str, str]) -> Path:
    """Recreate ``build/typecheck/hdrcap`` as symlinks into the repository and return it."""
    package = TREE / PACKAGE
    if package.is_symlink() or package.is_file():
        package.unlink()
    elif package.exists():
        shutil.rmtree(package)
    package.mkdir(parents=True)
    for child in sorted((ROOT / PACKAGE).iterdir()):
        if child.name != "__pycache__" and child.name not in subs:
            (package / child.name).symlink_to(child)
    for sub, folder in subs.items():
        (package / sub).symlink_to(ROOT / folder, target_is_directory=True)
    return package


def main(argv: list[str]) -> int:
    """Lay out the tree, run mypy on it and print its report with repository paths."""
    subs = package_dirs()
    lay_out(subs)
    command = [sys.executable, "-m", "mypy", "--config-file", str(ROOT / "pyproject.toml"), "-p", PACKAGE, *argv]
    proc = subprocess.run(command, cwd=TREE, capture_output=True, text=True)
    # "hdrcap/pipeline/noise.py:12: error: ..." -> "pipeline/noise.py:12: error: ..."
    prefix = re.compile(rf"^{PACKAGE}/({'|'.join(map(re.escape, subs))})/", flags=re.MULTILINE)
    folders = dict(subs)
    sys.stdout.write(prefix.sub(lambda m: f"{folders[m.group(1)]}/", proc.stdout))
    sys.stderr.write(proc.stderr)
    return proc.returncode


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
