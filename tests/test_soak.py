"""Exactly once through the real pty, under noise, in both flow modes (issue 4's proof).

20,066 lines of real slicer output; the fake controller corrupts 2 % of the lines it
receives, garbles 1 % of its replies, drops 1 % of its oks, duplicates 1 %, and sends
spurious resend requests. Its log of executed commands must equal the job.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from repetrel_host.testing.fake_controller import BuiltInFake
from tests.helpers import CONE, executed, hyrel_send, job_commands

NOISE = "corrupt=0.02 garble=0.01 drop_ok=0.01 duplicate_ok=0.01 spurious_resend=0.005"
MARLIN = "flush_on_error=1 drop_duplicates=1 resend_without_ok=1 busy_interval=2"


@pytest.mark.timeout(60)
@pytest.mark.parametrize(
    ("flow", "faults"),
    [
        ("buffered", f"{NOISE} seed=1"),
        ("buffered", f"{NOISE} {MARLIN} seed=2"),
        ("unbuffered", f"{NOISE} seed=3"),
        ("unbuffered", f"{NOISE} {MARLIN} seed=4"),
    ],
)
def test_noisy_link_executes_every_line_exactly_once(
    flow: str, faults: str, tmp_path: Path
) -> None:
    log = tmp_path / "fake.log"
    with BuiltInFake(log, ["--faults", faults]) as fake:
        result = hyrel_send(str(CONE), "--port", fake.port, "--flow", flow, timeout=55)
    assert result.returncode == 0, result.stderr
    assert executed(log) == job_commands(CONE)
    summary = re.search(r"(\d+) resend requests, \d+ lines sent again", result.stdout)
    assert summary is not None and int(summary.group(1)) > 100  # the noise was there
