"""A camera for the tests: writes a small PNG to the path given, or to standard output.

``fake_camera.py [PATH] [--fail] [--sleep S] [--text]``: ``--fail`` says why on stderr and
exits 3 (as fswebcam without a device does); ``--text`` writes something that is no image.
"""

from __future__ import annotations

import struct
import sys
import time
import zlib


def png(width: int = 4, height: int = 3) -> bytes:
    def chunk(kind: bytes, data: bytes) -> bytes:
        body = kind + data
        return struct.pack(">I", len(data)) + body + struct.pack(">I", zlib.crc32(body))

    rows = b"".join(b"\x00" + b"\x30\x80\xd0" * width for _ in range(height))
    header = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", header)
        + chunk(b"IDAT", zlib.compress(rows))
        + chunk(b"IEND", b"")
    )


def main(args: list[str]) -> int:
    if "--sleep" in args:
        time.sleep(float(args[args.index("--sleep") + 1]))
    if "--fail" in args:
        sys.stderr.write("Trying source module v4l2...\n/dev/video0: No such device\n")
        return 3
    data = b"not an image\n" if "--text" in args else png()
    paths = [a for a in args if a.endswith(".jpg")]
    if paths:
        with open(paths[0], "wb") as out:
            out.write(data)
    else:
        sys.stdout.buffer.write(data)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
