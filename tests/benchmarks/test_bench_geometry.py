"""benchmarks/bench_geometry.py --smoke runs (a second or two) and finds the same values as the previous search."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

SCRIPT = Path(__file__).resolve().parents[2] / "benchmarks" / "bench_geometry.py"


def test_smoke_run_reports_identical_values() -> None:
    proc = subprocess.run(
        [sys.executable, str(SCRIPT), "--smoke"], capture_output=True, text=True, timeout=120, check=False
    )
    assert proc.returncode == 0, proc.stderr
    assert "| cdist-exact |" in proc.stdout
    assert "| DCP-v2's DGCNN, 2 x 32 points |" in proc.stdout and proc.stdout.count("| yes |") == 4, proc.stdout
    assert proc.stdout.rstrip().endswith("| 0 of 512 | 0.0e+00 |"), proc.stdout  # B=2, N=64, k=4
