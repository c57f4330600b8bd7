"""The soak benchmark runs (on a small input; the figures live in the closing notes)."""

import subprocess
import sys
from pathlib import Path

import pytest

SOAK = Path(__file__).parent.parent / "bench" / "soak.py"


@pytest.mark.timeout(120)
def test_soak_bench_runs_and_reports_exactly_once() -> None:
    result = subprocess.run(
        [sys.executable, str(SOAK), "--lines", "3000", "--flow", "buffered"],
        capture_output=True,
        text=True,
        timeout=110,
    )
    assert result.returncode == 0, result.stderr
    assert "exactly once" in result.stdout
    assert "stall/ok" in result.stdout
