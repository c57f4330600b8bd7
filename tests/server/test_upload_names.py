"""Uploads keep their names apart (issue 35): letters of any script are kept, and (issue 49)
every character a filesystem holds safely, emoji and combining marks too; two names that
clean or shorten alike stay two files (``-1``, ``-2``... as OctoPrint adds), the same name
replaces, a very long name is taken shortened; and every refusal says why in ``error``, as
OctoPrint's clients read it. A real server over HTTP."""

from __future__ import annotations

import signal
from collections.abc import Callable, Iterator
from pathlib import Path
from urllib.parse import quote

import httpx
import pytest

from tests.support.server import KEY, Server

pytestmark = pytest.mark.timeout(60)


def upload(client: httpx.Client, name: str, text: str) -> str:
    answer = client.post("/api/files/local", files={"file": (name, text.encode())})
    assert answer.status_code == 201, answer.text
    stored: str = answer.json()["files"]["local"]["path"]
    return stored


def content(client: httpx.Client, path: str) -> str:
    answer = client.get(f"/downloads/files/local/{path}")
    assert answer.status_code == 200, answer.text
    return answer.text


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    """One server for the names' cases: each is an upload and a read."""
    started = Server(tmp_path_factory.mktemp("names") / "data", {"demo": "fake"}, "--api-key", KEY)
    yield started.start()
    started.stop(signal.SIGKILL)


def test_names_in_any_script_stay_apart(servers: Callable[..., Server]) -> None:
    with servers({"demo": "fake"}).client() as client:
        japan = upload(client, "日本.gcode", "G1 X1\n")
        china = upload(client, "中国.gcode", "G1 X2\n")
        assert (japan, china) == ("日本.gcode", "中国.gcode")
        assert content(client, japan) == "G1 X1\n" and content(client, china) == "G1 X2\n"


@pytest.mark.parametrize(
    ("given", "stored"),
    [
        ("Wölfe 🐺.gcode", "Wölfe 🐺.gcode"),
        ("👨\u200d👩\u200d👧 family.gcode", "👨\u200d👩\u200d👧 family.gcode"),  # joined emoji
        ("cafe\u0301.gcode", "café.gcode"),  # a combining mark, composed (NFC)
        ("नमस्ते.gcode", "नमस्ते.gcode"),  # marks that compose with nothing stay
        ("#2 [draft] 50%, v1.1 (Ø) it's ok! ~=@^{}.gcode", None),  # punctuation stays
        ("a;b&c$d`e|f.gcode", "a_b_c_d_e_f.gcode"),  # what a shell reads as its own
        ('a"b<c>d?e.gcode', "a_b_c_d_e.gcode"),  # what Windows takes in no name
        ("tab\there\x7f.gcode", "tab_here_.gcode"),  # control characters
        ("evil\u202egcode.exe.gcode", "evil_gcode.exe.gcode"),  # a direction override
    ],
)
def test_a_name_keeps_what_a_filesystem_holds_safely(
    server: Server, given: str, stored: str | None
) -> None:
    # The form written out: httpx would percent-encode a quote or a tab in the name.
    quoted = given.replace('"', '\\"').encode()
    form = b'--xx\r\nContent-Disposition: form-data; name="file"; filename="%s"\r\n\r\n' % quoted
    with server.client() as client:
        answer = client.post(
            "/api/files/local",
            content=form + b"G1 X1\n\r\n--xx--\r\n",
            headers={"Content-Type": "multipart/form-data; boundary=xx"},
        )
        assert answer.status_code == 201, answer.text
        path = answer.json()["files"]["local"]["path"]
        assert path == (stored or given)
        assert content(client, quote(path)) == "G1 X1\n"
        assert path in [f["path"] for f in client.get("/v1/files").json()]
    assert (server.data_dir / "files" / path).read_text() == "G1 X1\n"


def test_names_that_clean_or_shorten_alike_stay_two_files(
    servers: Callable[..., Server],
) -> None:
    long = "p" * 210
    with servers({"demo": "fake"}).client() as client:
        first = upload(client, f"{long}-a.gcode", "G1 X1\n")
        second = upload(client, f"{long}-b.gcode", "G1 X2\n")
        slash = upload(client, "a:b.gcode", "G1 X3\n")
        star = upload(client, "a*b.gcode", "G1 X4\n")
        assert first != second and second == first.replace(".gcode", "-1.gcode")
        assert (slash, star) == ("a_b.gcode", "a_b-1.gcode")
        assert [content(client, p) for p in (first, second, slash, star)] == [
            "G1 X1\n", "G1 X2\n", "G1 X3\n", "G1 X4\n"
        ]  # fmt: skip
        # The same name again replaces its own file, not the other's.
        assert upload(client, "a*b.gcode", "G1 X5\n") == "a_b-1.gcode"
        assert content(client, "a_b-1.gcode") == "G1 X5\n"
        assert content(client, "a_b.gcode") == "G1 X3\n"


@pytest.mark.slow
def test_a_name_of_5000_characters_is_taken_shortened(servers: Callable[..., Server]) -> None:
    with servers({"demo": "fake"}).client() as client:
        stored = upload(client, "ж" * 5000 + ".gcode", "G1 X1\n")
        assert stored.endswith(".gcode") and len(stored.encode()) <= 240
        assert content(client, stored) == "G1 X1\n"


def test_every_refusal_says_why_in_error(servers: Callable[..., Server], tmp_path: Path) -> None:
    server = servers({"demo": "fake"}, "--max-upload-mb", "1")
    with server.client() as client:
        too_big = client.post("/api/files/local", files={"file": ("big.gcode", b"G28\n" * 400_000)})
        assert too_big.status_code == 413
        assert "the upload is over" in too_big.json()["error"]
        # Sent in chunks, without its length: refused as it comes, and says why too.
        head = b'--xx\r\nContent-Disposition: form-data; name="file"; filename="big.gcode"\r\n\r\n'
        chunks = iter([head, *[b"G28\n" * 1000] * 600, b"\r\n--xx--\r\n"])
        streamed = client.post(
            "/api/files/local",
            content=chunks,
            headers={"Content-Type": "multipart/form-data; boundary=xx"},
        )
        assert streamed.status_code == 413
        assert "the upload is over" in streamed.json()["error"]
        no_file = client.post("/v1/printers/demo/jobs", data={"name": "x"})
        assert no_file.status_code == 400
        assert no_file.json()["error"].startswith("bad request: ")
        garbled = client.post(
            "/api/files/local",
            content=b"garbage",
            headers={"Content-Type": "multipart/form-data; boundary=xx"},
        )
        assert garbled.status_code == 400 and garbled.json()["error"]


def test_a_folder_in_any_script_is_made_and_named_in_its_location(
    servers: Callable[..., Server],
) -> None:
    with servers({"demo": "fake"}).client() as client:
        made = client.post("/api/files/local", data={"foldername": "部品", "path": ""})
        assert made.status_code == 201, made.text
        assert made.headers["Location"].endswith("/api/files/local/%E9%83%A8%E5%93%81")
        answer = client.post(
            "/api/files/local", data={"path": "部品"}, files={"file": ("歯車.gcode", b"G28\n")}
        )
        assert answer.status_code == 201, answer.text
        assert content(client, "部品/歯車.gcode") == "G28\n"
