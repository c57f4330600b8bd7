"""Bad input across the whole HTTP surface: schemathesis generates a few thousand requests
from the server's own OpenAPI description, with the key and without, against a real
server process on the fake printer. None may answer 500 or hang, and the server's log
holds no traceback."""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import httpx
import pytest

from tests.support.server import KEY, Server

# Streams never end by themselves: their opening is tested elsewhere.
STREAMS = r".*/(events|xhr_streaming)$"


def schemathesis(server: Server, folder: Path, *options: str) -> subprocess.CompletedProcess[str]:
    # Path parameters that name a printer name the real one, so that requests get past
    # the 404 and into each route's own checks.
    config = folder / "schemathesis.toml"
    config.write_text('[parameters]\n"path.printer" = "demo"\n"path.name" = "demo"\n')
    command = [str(Path(sys.executable).parent / "schemathesis"), "--config-file", str(config)]
    command += ["run", f"{server.url}/openapi.json", "--checks", "not_a_server_error"]
    command += ["--seed", "1", "--request-timeout", "10", "--workers", "1"]
    command += ["--generation-database", "none", "--exclude-path-regex", STREAMS, *options]
    return subprocess.run(command, capture_output=True, text=True, timeout=420, cwd=folder)


@pytest.mark.timeout(480)
@pytest.mark.slow
def test_generated_requests_find_no_server_error_and_no_hang(
    servers: Callable[..., Server], tmp_path: Path
) -> None:
    server = servers({"demo": "fake"})
    keyed = schemathesis(server, tmp_path, "--max-examples", "20", "--header", f"X-Api-Key: {KEY}")
    assert keyed.returncode == 0, keyed.stdout[-4000:]
    assert " passed" in keyed.stdout and "generated" in keyed.stdout
    anonymous = schemathesis(server, tmp_path, "--max-examples", "5")
    assert anonymous.returncode == 0, anonymous.stdout[-4000:]
    # Still answering, at once, and nothing went wrong inside.
    assert httpx.get(f"{server.url}/api/version", headers={"X-Api-Key": KEY}, timeout=5).is_success
    log = server.stderr.read_text()
    assert "Traceback" not in log, log[log.find("Traceback") - 2000 :][:6000]
