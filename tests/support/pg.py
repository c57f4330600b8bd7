"""A real PostgreSQL for the farm's tests: a throwaway cluster per test session, started
from the installed binaries (Debian's ``postgresql``, which ``.ci/run`` installs), as the
``postgres`` user when the tests run as root (the server refuses to run as root).

Fixtures: ``postgres`` (the cluster: ``restart()``, ``stop()``, ``start()``) and ``farm_db``
(a new database for one test, its URL without the password, which the test process and
the servers it starts find in ``PGPASSWORD``). ``Cut`` is a TCP relay between a node and
the database that the test can cut like a pulled network cable.
"""

from __future__ import annotations

import contextlib
import itertools
import os
import shutil
import socket
import subprocess
import tempfile
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest

__all__ = ["Cut", "Postgres", "farm_db", "needs_postgres", "postgres"]

PASSWORD = "farm-secret"  # the farm role's; nodes take it from PGPASSWORD


def _binaries() -> Path | None:
    found = shutil.which("pg_ctl")
    if found is not None:
        return Path(found).resolve().parent
    versions = sorted(Path("/usr/lib/postgresql").glob("*/bin/pg_ctl"))
    return versions[-1].parent if versions else None


BIN = _binaries()
needs_postgres = pytest.mark.skipif(
    BIN is None, reason="needs PostgreSQL's server (Debian's postgresql; .ci/run installs it)"
)


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


class Postgres:
    """A cluster in a temporary folder, on a free port of 127.0.0.1."""

    def __init__(self, fsync: bool = False) -> None:
        """``fsync``: durable commits, as a production database (the tests go without)."""
        assert BIN is not None
        self.fsync = fsync
        self.root = Path(tempfile.mkdtemp(prefix="farm-pg-"))
        self.data = self.root / "data"
        self.port = _free_port()
        self.as_root = os.geteuid() == 0
        if self.as_root:
            shutil.chown(self.root, "postgres", "postgres")
        self._run("initdb", "-D", str(self.data), "-U", "postgres", "--auth-local=trust",
                  "--auth-host=scram-sha-256", "-E", "UTF8", "--no-sync")  # fmt: skip
        self.start()
        self.sql(f"CREATE ROLE farm LOGIN CREATEDB PASSWORD '{PASSWORD}'")
        self._numbers = itertools.count(1)

    def _run(self, program: str, *args: str, check: bool = True) -> str:
        assert BIN is not None
        command = [str(BIN / program), *args]
        if self.as_root:
            command = ["runuser", "-u", "postgres", "--", *command]
        done = subprocess.run(command, capture_output=True, text=True, timeout=120, cwd="/")
        if check and done.returncode != 0:
            raise RuntimeError(f"{program} failed: {done.stdout}{done.stderr}")
        return done.stdout

    def start(self) -> None:
        options = (
            f"-p {self.port} -k {self.root} -c listen_addresses=127.0.0.1 "
            f"-c fsync={'on' if self.fsync else 'off'} "
            "-c max_connections=400 -c shared_buffers=64MB"
        )
        log = self.root / "server.log"
        self._run("pg_ctl", "-D", str(self.data), "-l", str(log), "-o", options, "-w", "start")

    def ensure_running(self) -> None:
        status = ["pg_ctl", "-D", str(self.data), "status"]
        if "server is running" not in self._run(*status, check=False):
            self.start()

    def stop(self, mode: str = "fast") -> None:
        self._run("pg_ctl", "-D", str(self.data), "-m", mode, "-w", "stop", check=False)

    def restart(self) -> None:
        self.stop()
        self.start()

    def sql(self, statement: str, database: str = "postgres") -> str:
        return self._run(
            "psql", "-h", str(self.root), "-p", str(self.port), "-U", "postgres", "-d", database,
            "-v", "ON_ERROR_STOP=1", "-Atc", statement,
        )  # fmt: skip

    def new_database(self) -> str:
        """A new empty database owned by the farm role; its URL (no password in it)."""
        name = f"farm_{next(self._numbers)}"
        self.sql(f"CREATE DATABASE {name} OWNER farm")
        return f"postgresql://farm@127.0.0.1:{self.port}/{name}"

    def close(self) -> None:
        self.stop("immediate")
        shutil.rmtree(self.root, ignore_errors=True)


@pytest.fixture(scope="session")
def postgres() -> Iterator[Postgres]:
    if BIN is None:
        pytest.skip("needs PostgreSQL's server (Debian's postgresql; .ci/run installs it)")
    cluster = Postgres()
    yield cluster
    cluster.close()


@pytest.fixture
def farm_db(postgres: Postgres, monkeypatch: pytest.MonkeyPatch) -> str:
    """A fresh database for this test; its password in PGPASSWORD (as a node takes it)."""
    postgres.ensure_running()  # a test that stopped it and failed leaves it stopped
    monkeypatch.setenv("PGPASSWORD", PASSWORD)
    return postgres.new_database()


class Cut:
    """A TCP relay to ``port`` that a test can cut: ``cut()`` drops every byte both ways
    and takes no new connection (a pulled cable: no reset, silence), ``mend()`` relays
    again (the old connections stay dead, as after a real outage)."""

    def __init__(self, port: int) -> None:
        self.target = port
        self._listener = socket.create_server(("127.0.0.1", 0))
        self.port = self._listener.getsockname()[1]
        self._cut = threading.Event()
        self._open: list[socket.socket] = []
        self._stopped = False
        threading.Thread(target=self._accept, daemon=True).start()

    def url(self, database_url: str) -> str:
        return database_url.replace(f":{self.target}/", f":{self.port}/")

    def cut(self) -> None:
        self._cut.set()

    def mend(self) -> None:
        # Connections made before the cut are dead (their peer gave up): closed now.
        for sock in self._open:
            with contextlib.suppress(OSError):
                sock.close()
        self._open.clear()
        self._cut.clear()

    def close(self) -> None:
        self._stopped = True
        self._listener.close()
        self.mend()

    def _accept(self) -> None:
        while not self._stopped:
            try:
                client, _ = self._listener.accept()
            except OSError:
                return
            self._open.append(client)
            if self._cut.is_set():
                continue  # accepted, never answered: a connect that hangs
            try:
                server = socket.create_connection(("127.0.0.1", self.target), timeout=5)
            except OSError:
                client.close()
                continue
            self._open.append(server)
            for source, sink in ((client, server), (server, client)):
                threading.Thread(target=self._pipe, args=(source, sink), daemon=True).start()

    def _pipe(self, source: socket.socket, sink: socket.socket) -> None:
        while True:
            try:
                data = source.recv(65536)
            except OSError:
                break
            if not data:
                break
            if self._cut.is_set():
                continue  # swallowed: the cable is out
            try:
                sink.sendall(data)
            except OSError:
                break
        for sock in (source, sink):
            with contextlib.suppress(OSError):
                sock.shutdown(socket.SHUT_RDWR)
