"""The README stays an operator's first page: short, one line per CLI command, pointing at pages that exist."""

from __future__ import annotations

import argparse
import re
from pathlib import Path

from main import build_parser

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"


def test_the_readme_is_under_6_kb():
    assert README.stat().st_size < 6 * 1024


def test_the_readme_has_a_line_for_every_command():
    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    text = README.read_text(encoding="utf-8")
    missing = [name for name in sub.choices if not re.search(rf"^- `{name}[ `]", text, re.MULTILINE)]
    assert not missing, f"commands without their line in README.md: {missing}"


def test_every_file_the_readme_names_exists():
    text = README.read_text(encoding="utf-8")
    named = set(re.findall(r"`((?:docs|config|tests|bench|scripts)/[\w./-]+\.\w+)`", text))
    assert named, "the README names no files"
    assert not [n for n in sorted(named) if not (ROOT / n).exists()]
