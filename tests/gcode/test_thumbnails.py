"""The slicers' embedded previews: found by the analysis pass, read back from the file as
images (PNG and JPEG as they were, QOI made PNG), and served at ``/v1/files/PATH/thumbnail``.
The images are made by Pillow (a test dependency), whose QOI encoder uses every QOI
operation; the blocks are written as PrusaSlicer writes them (78 base64 characters a line)."""

from __future__ import annotations

import base64
import io
from collections.abc import Callable
from pathlib import Path

import pytest
from PIL import Image

from repetrel_host.gcode.analysis import FileSummary, analyse
from repetrel_host.gcode.thumbnails import Thumbnail, ThumbnailError, read
from tests.support.helpers import CONE
from tests.support.images import block, encoded, picture
from tests.support.server import Server


@pytest.fixture
def images() -> dict[str, tuple[Image.Image, bytes]]:
    small, medium, large = picture(16, 16), picture(40, 30), picture(300, 200)
    return {
        "PNG": (small, encoded(small, "PNG")),
        "JPG": (medium, encoded(medium, "JPEG")),
        "QOI": (large, encoded(large, "QOI")),
    }


def sliced(folder: Path, images: dict[str, tuple[Image.Image, bytes]], newline: str = "\n") -> Path:
    """The cone as PrusaSlicer wrote it, with three thumbnails after its first comments."""
    lines = CONE.read_text().splitlines(keepends=True)
    blocks = block(images["PNG"][1], 16, 16)
    blocks += block(images["JPG"][1], 40, 30, "thumbnail_JPG")
    blocks += block(images["QOI"][1], 300, 200, "thumbnail_QOI")
    text = "".join(lines[:2]) + blocks + "".join(lines[2:])
    path = folder / "cone-with-thumbnails.gcode"
    path.write_bytes(text.replace("\n", newline).encode())
    return path


@pytest.mark.parametrize("newline", ["\n", "\r\n"], ids=["lf", "crlf"])
def test_the_analysis_finds_each_thumbnail_and_reads_it_back(
    tmp_path: Path, images: dict[str, tuple[Image.Image, bytes]], newline: str
) -> None:
    path = sliced(tmp_path, images, newline)
    summary = analyse(path).summary
    assert summary is not None
    found = [(t.format, t.width, t.height) for t in summary.thumbnails]
    assert found == [("PNG", 16, 16), ("JPG", 40, 30), ("QOI", 300, 200)]
    assert summary.layers == analyse(CONE).summary.layers  # type: ignore[union-attr]
    png, jpg, qoi = summary.thumbnails
    assert read(path, png) == (images["PNG"][1], "image/png")
    assert read(path, jpg) == (images["JPG"][1], "image/jpeg")
    made, media_type = read(path, qoi)
    assert media_type == "image/png"
    shown = Image.open(io.BytesIO(made))
    assert shown.size == (300, 200) and shown.tobytes() == images["QOI"][0].tobytes()
    assert summary.largest_thumbnail() == qoi
    # Kept and read back as the server's cache does.
    assert FileSummary.from_dict(summary.as_dict()) == summary
    assert summary.as_json()["thumbnails"][2] == {"format": "QOI", "width": 300, "height": 200}


def test_a_damaged_block_is_an_error_not_an_image(
    tmp_path: Path, images: dict[str, tuple[Image.Image, bytes]]
) -> None:
    path = sliced(tmp_path, images)
    png, jpg, _ = analyse(path).summary.thumbnails  # type: ignore[union-attr]
    text = bytearray(path.read_bytes())
    text[png.start + 10 : png.start + 12] = b"!!"  # not base64
    text[jpg.start + 2 : jpg.start + 6] = base64.b64encode(b"GIF")  # not a JPEG
    path.write_bytes(bytes(text))
    for thumbnail in (png, jpg):
        with pytest.raises(ThumbnailError):
            read(path, thumbnail)
    cut = tmp_path / "cut.gcode"  # a QOI image whose last pixels are missing
    cut.write_text("G28\n" + block(images["QOI"][1][:5000], 300, 200, "thumbnail_QOI"))
    (qoi,) = analyse(cut).summary.thumbnails  # type: ignore[union-attr]
    with pytest.raises(ThumbnailError, match="ends before its last pixel"):
        read(cut, qoi)
    with pytest.raises(ThumbnailError):
        read(path, Thumbnail("PNG", 1, 1, 100, 100))  # an empty block


@pytest.mark.timeout(60)
@pytest.mark.slow
def test_the_server_lists_and_serves_the_largest_thumbnail(
    tmp_path: Path, images: dict[str, tuple[Image.Image, bytes]], servers: Callable[..., Server]
) -> None:
    server = servers({"demo": "fake"})
    path = sliced(tmp_path, images)
    with server.client() as client:
        sent = client.post(
            "/api/files/local",
            data={"path": "parts"},
            files={"file": ("cone thumb.gcode", path.read_bytes())},
        )
        assert sent.status_code == 201, sent.text
        client.post("/api/files/local", files={"file": ("plain.gcode", b"G28\nG1 X1\n")})
        listed = {f["path"]: f for f in client.get("/v1/files").json()}
        entry = listed["parts/cone thumb.gcode"]
        assert entry["thumbnail"] == "/v1/files/parts/cone%20thumb.gcode/thumbnail"
        assert [t["format"] for t in entry["analysis"]["thumbnails"]] == ["PNG", "JPG", "QOI"]
        image = client.get(entry["thumbnail"])
        assert image.status_code == 200 and image.headers["content-type"] == "image/png"
        shown = Image.open(io.BytesIO(image.content))
        assert shown.size == (300, 200) and shown.tobytes() == images["QOI"][0].tobytes()
        assert listed["plain.gcode"]["thumbnail"] is None
        none = client.get("/v1/files/plain.gcode/thumbnail")
        assert none.status_code == 404 and "no thumbnail" in none.json()["error"]
        assert client.get("/v1/files/nothing.gcode/thumbnail").status_code == 404
    with server.client(key=None) as anonymous:
        assert anonymous.get(entry["thumbnail"]).status_code == 403
