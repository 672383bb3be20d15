"""``modi --version`` prints the one version string (``modi/_version.py``), which setup.py and CHANGELOG.md share."""
from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

from modi._version import __version__
from modi.cli import build_parser, main

REPO = Path(__file__).resolve().parents[3]


def test_version_prints_the_version(capsys):
    assert main(["--version"]) == 0
    assert capsys.readouterr().out.strip() == f"modi {__version__}"
    assert "--version" in build_parser().format_help()


def test_version_answers_before_torch_is_imported():
    code = "import sys; from modi.cli import main; rc = main(['--version']); print(rc, 'torch' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO, timeout=120,
                         env={**__import__("os").environ, "PYTHONPATH": str(REPO)})
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["modi", __version__, "0", "False"]


def test_changelog_starts_at_0_1_0_and_names_this_version():
    text = (REPO / "CHANGELOG.md").read_text(encoding="utf-8")
    versions = re.findall(r"^## (\S+)", text, flags=re.M)
    assert versions and versions[-1] == "0.1.0" and versions[0] == __version__
    setup = (REPO / "setup.py").read_text(encoding="utf-8")
    assert "version=_version()" in setup  # setup.py reads the same file
