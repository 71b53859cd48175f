"""Draw the shipped scenes' shape images with Pillow into scenes/images/ (run: python scenes/make_images.py).

Every image is 64 x 64 RGB: white background, shapes in black (or red/blue for the color scenes).
Disks are centred at pixel (32, 32); "cells" refer to the circle_to_torus scene, whose region maps the
64 pixels onto 16 cells of the 32 x 32 grid (4 pixels per cell).
"""
import math
import os
import tempfile
from pathlib import Path

from PIL import Image, ImageChops, ImageDraw

SIZE = 64
C = SIZE / 2  # image centre, in pixel-edge coordinates
BLACK, WHITE, RED, BLUE = (0, 0, 0), (255, 255, 255), (255, 0, 0), (0, 0, 255)
PX_PER_CELL = 4  # circle_to_torus: region [0.25, 0.75]^2 = 16 cells of 32 spans 64 pixels
OUT = Path(__file__).resolve().parent / "images"


def canvas():
    """A white image and its drawing context."""
    img = Image.new("RGB", (SIZE, SIZE), WHITE)
    return img, ImageDraw.Draw(img)


def disk(draw, cx, cy, r, fill):
    """A filled disk of radius r (pixels) centred at (cx, cy), y pointing down as in the image."""
    draw.ellipse((cx - r, cy - r, cx + r - 1, cy + r - 1), fill=fill)


def disk_with_holes(holes, r=28, hole_r=7):
    """A black disk of radius r with white holes of radius hole_r at offsets from the centre."""
    img, draw = canvas()
    disk(draw, C, C, r, BLACK)
    for dx, dy in holes:
        disk(draw, C + dx, C + dy, hole_r, WHITE)
    return img


def star(points=5, outer=30, inner=12):
    """A black star pointing up."""
    img, draw = canvas()
    corners = []
    for k in range(2 * points):
        r = outer if k % 2 == 0 else inner
        a = -math.pi / 2 + k * math.pi / points
        corners.append((C + r * math.cos(a), C + 2 + r * math.sin(a)))
    draw.polygon(corners, fill=BLACK)
    return img


def heart_polygon(scale=1.6, shift=0.0):
    """Corners of the curve x = 16 sin^3 t, y = 13 cos t - 5 cos 2t - 2 cos 3t - cos 4t, upright in the image."""
    pts = []
    for k in range(200):
        t = 2 * math.pi * k / 200
        x = 16 * math.sin(t) ** 3
        y = 13 * math.cos(t) - 5 * math.cos(2 * t) - 2 * math.cos(3 * t) - math.cos(4 * t)
        pts.append((C + shift + scale * x, C + 3 - scale * y))
    return pts


def heart(scale=1.6):
    """A black heart."""
    img, draw = canvas()
    draw.polygon(heart_polygon(scale), fill=BLACK)
    return img


def broken_heart(scale=1.6, gap=5):
    """The heart cut along a zigzag crack, its two pieces pulled apart by gap pixels each way."""
    whole = Image.new("L", (SIZE, SIZE), 0)
    ImageDraw.Draw(whole).polygon(heart_polygon(scale), fill=255)
    crack = [(C + (3 if k % 2 else -3), y) for k, y in enumerate(range(0, SIZE + 8, 8))]
    left = Image.new("L", (SIZE, SIZE), 0)
    ImageDraw.Draw(left).polygon([(0, 0)] + crack + [(0, SIZE + 8)], fill=255)
    right = ImageChops.invert(left)
    img, _ = canvas()
    for side, dx in ((left, -gap), (right, gap)):
        moved = Image.new("L", (SIZE, SIZE), 0)
        moved.paste(ImageChops.multiply(whole, side), (dx, 0))
        img.paste(BLACK, (0, 0, SIZE, SIZE), without_specks(moved))
    return img


def without_specks(mask, keep=20):
    """The mask without its 8-connected pieces of fewer than `keep` pixels (the crack can cut a sliver off
    the heart's tip, which would become a stray blob in the target)."""
    px = mask.load()
    seen, out = set(), Image.new("L", mask.size, 0)
    for start in ((x, y) for y in range(mask.size[1]) for x in range(mask.size[0])):
        if start in seen or px[start] < 128:
            continue
        piece, todo = [], [start]
        seen.add(start)
        while todo:
            x, y = todo.pop()
            piece.append((x, y))
            for nx in (x - 1, x, x + 1):
                for ny in (y - 1, y, y + 1):
                    if 0 <= nx < mask.size[0] and 0 <= ny < mask.size[1] and (nx, ny) not in seen \
                            and px[nx, ny] >= 128:
                        seen.add((nx, ny))
                        todo.append((nx, ny))
        if len(piece) >= keep:
            for p in piece:
                out.putpixel(p, 255)
    return out


def halves(first, second, axis):
    """A disk of radius 28: first color on the left (axis 'x') or top (axis 'y') half, second on the other."""
    img, draw = canvas()
    disk(draw, C, C, 28, second)
    mask = Image.new("L", (SIZE, SIZE), 0)
    half = (0, 0, SIZE // 2 - 1, SIZE - 1) if axis == "x" else (0, 0, SIZE - 1, SIZE // 2 - 1)
    ImageDraw.Draw(mask).rectangle(half, fill=255)
    inside = Image.new("L", (SIZE, SIZE), 0)
    disk(ImageDraw.Draw(inside), C, C, 28, 255)
    img.paste(first, (0, 0), ImageChops.multiply(mask, inside))
    return img


def images():
    """name -> Pillow image of every shipped shape."""
    img_small, draw = canvas()
    disk(draw, C, C, 5 * PX_PER_CELL, BLACK)
    torus, draw = canvas()
    disk(draw, C, C, 5 * PX_PER_CELL, BLACK)
    disk(draw, C, C, 3 * PX_PER_CELL, WHITE)
    return {
        "circle": disk_with_holes([]),
        "circle_small": img_small,
        "torus": torus,
        "genus0": disk_with_holes([]),
        "genus1": disk_with_holes([(0, 0)], hole_r=11),
        "genus2": disk_with_holes([(-13, 0), (13, 0)], hole_r=8),
        "genus4": disk_with_holes([(-12, -12), (12, -12), (-12, 12), (12, 12)], hole_r=7),
        "star": star(),
        "heart": heart(),
        "two_blobs": broken_heart(),
        "color_halves": halves(RED, BLUE, "x"),
        "color_halves_target": halves(RED, BLUE, "y"),
        "color_swap_target": halves(BLUE, RED, "x"),
    }


def save(img, path):
    """Write img as a PNG atomically (a temp file beside path, then renamed over it), readable by all (0644)."""
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as fh:
            img.save(fh, format="PNG", optimize=True)
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def main(out=OUT):
    """Write every image as <out>/<name>.png (default: scenes/images/)."""
    out = Path(out)
    out.mkdir(exist_ok=True)
    for name, img in images().items():
        save(img, out / f"{name}.png")
        print(out / f"{name}.png")


if __name__ == "__main__":
    main()
