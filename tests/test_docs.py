"""The generated results tables are current, and the README keeps to its size."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_results_tables_match_the_result_files():
    """README.md's and docs/benchmarks.md's tables are what benchmarks/summary.py makes of
    benchmarks/results/ (run ``python benchmarks/summary.py`` after a benchmark)."""
    run = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "summary.py"), "--check"], cwd=ROOT,
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stdout + run.stderr


def test_readme_is_short():
    assert len((ROOT / "README.md").read_text().splitlines()) <= 300
