"""Preview images as slicers embed them: made by Pillow (a test dependency, whose QOI
encoder uses every QOI operation), written as PrusaSlicer writes them (78 base64
characters a line)."""

from __future__ import annotations

import base64
import io

from PIL import Image


def picture(width: int, height: int) -> Image.Image:
    """Gradients, flat runs and repeats: every QOI operation has pixels to encode."""
    image = Image.new("RGBA", (width, height))
    for y in range(height):
        for x in range(width):
            if y < height // 3:
                image.putpixel((x, y), (x * 255 // width, y * 3 % 256, 90, 255))
            elif y < 2 * height // 3:
                image.putpixel((x, y), (200, 30, 30, 255) if x < width // 2 else (5, 5, 5, 128))
            else:
                image.putpixel((x, y), ((x * 7) % 256, (x * 13 + y) % 256, (y * 5) % 256, 255))
    return image


def encoded(image: Image.Image, kind: str) -> bytes:
    out = io.BytesIO()
    (image.convert("RGB") if kind == "JPEG" else image).save(out, kind)
    return out.getvalue()


def block(data: bytes, width: int, height: int, tag: str = "thumbnail") -> str:
    text = base64.b64encode(data).decode()
    lines = [f"; {text[i : i + 78]}" for i in range(0, len(text), 78)]
    return "\n".join(
        [";", f"; {tag} begin {width}x{height} {len(text)}", *lines, f"; {tag} end", ";", ""]
    )
