"""Draw the shipped scenes' shape images with Pillow into scenes/images/ (run: python scenes/make_images.py).

Every image is 64 x 64 RGB: white background, shapes in black (or red/blue for the color scenes).
Disks are centred at pixel (32, 32); "cells" refer to the circle_to_torus scene, whose region maps the
64 pixels onto 16 cells of the 32 x 32 grid (4 pixels per cell).

scenes/images/pairs/ holds the shape pairs of `mls-mpm bench quality` (mls_mpm/bench/quality.py lists them and
what each tests): <pair>_initial.png and <pair>_target.png, black shapes (one pair in red and blue), every
shape at least 6% of the image, its thin parts (rings, strokes) 6 pixels thick or more (a crescent's tips aside).
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


def shape(*parts):
    """A black shape on white: parts are (kind, args, fill) with kind "disk" (cx, cy, r), "rect" (x0, y0, x1, y1,
    corners included), "poly" (corner list) or "mask" (a test of a pixel's centre x, y); a white fill cuts a hole.
    Drawn in order."""
    img, draw = canvas()
    for kind, args, fill in parts:
        if kind == "disk":
            disk(draw, *args, fill)
        elif kind == "rect":
            draw.rectangle(args, fill=fill)
        elif kind == "mask":
            for y in range(SIZE):
                for x in range(SIZE):
                    if args(x + 0.5, y + 0.5):
                        img.putpixel((x, y), fill)
        else:
            draw.polygon(args, fill=fill)
    return img


def ring(cx, cy, outer, inner):
    """The parts of an annulus (a disk with a concentric hole)."""
    return ("disk", (cx, cy, outer), BLACK), ("disk", (cx, cy, inner), WHITE)


def square(cx, cy, side, fill=BLACK):
    """The part of an axis-aligned square of `side` pixels centred at (cx, cy)."""
    x0, y0 = int(cx - side / 2), int(cy - side / 2)
    return "rect", (x0, y0, x0 + side - 1, y0 + side - 1), fill


def arc_stroke(cx, cy, r, width, start, end):
    """The part of a stroke `width` pixels thick along the circle of radius r about (cx, cy), from angle start
    counter-clockwise to end (degrees, 0 pointing right, 90 up), with round ends: a pixel is in it when its
    centre is."""
    sweep = (end - start) % 360
    ends = [(cx + r * math.cos(math.radians(a)), cy - r * math.sin(math.radians(a))) for a in (start, end)]

    def inside(x, y):
        angle = math.degrees(math.atan2(cy - y, x - cx))
        on_arc = abs(math.hypot(x - cx, y - cy) - r) <= width / 2 and (angle - start) % 360 <= sweep
        return on_arc or any(math.hypot(x - ex, y - ey) <= width / 2 for ex, ey in ends)

    return "mask", inside, BLACK


def two_colors(body, first, second, axis):
    """The body (a black-on-white image) painted first on its left (axis "x") or top (axis "y") half, second on
    the other half."""
    mask = ImageChops.invert(body.convert("L"))
    img, _ = canvas()
    img.paste(second, (0, 0), mask)
    half = Image.new("L", (SIZE, SIZE), 0)
    ImageDraw.Draw(half).rectangle((0, 0, SIZE // 2 - 1, SIZE - 1) if axis == "x" else (0, 0, SIZE - 1, SIZE // 2 - 1),
                                   fill=255)
    img.paste(first, (0, 0), ImageChops.multiply(mask, half))
    return img


def pairs():
    """pair name -> (initial image, target image): the suite of `mls-mpm bench quality`. Areas are in pixels of
    the 4096; a pair that does not test an area ratio keeps its two areas within about 10%."""
    disk24 = shape(("disk", (C, C, 24), BLACK))  # 1810 px, 44%
    disk22 = shape(("disk", (C, C, 22), BLACK))  # 1520 px
    disk20 = shape(("disk", (C, C, 20), BLACK))  # 1256 px
    disk16 = shape(("disk", (C, C, 16), BLACK))  # 804 px
    A = ([(8, 58), (32, 6), (56, 58), (45, 58), (32, 29), (19, 58)], [(25, 44), (39, 44), (41, 50), (23, 50)])
    return {
        # area ratio 1/3 and 3
        "shrink_disk": (shape(("disk", (C, C, 28), BLACK)), disk16),  # 2463 -> 804 px
        "grow_square": (shape(square(C, C, 26)), shape(square(C, C, 45))),  # 676 -> 2025 px
        # off-centre targets
        "corner_disk": (disk16, shape(("disk", (46, 18, 16), BLACK))),  # the top-right corner
        "side_crescent": (shape(("disk", (C, C, 17), BLACK)),  # to a crescent on the left, 12 px at its widest
                          shape(("disk", (26, C, 24), BLACK), ("disk", (38, C, 18), WHITE))),
        # thin parts (6 pixels)
        "thin_ring": (shape(("disk", (C, C, 17), BLACK)), shape(*ring(C, C, 28, 22))),
        "letter_L_thin": (shape(square(C, C, 24)), shape(("rect", (10, 8, 15, 55), BLACK),
                                                        ("rect", (10, 50, 55, 55), BLACK))),
        # holes appearing and closing
        "hole_opens": (disk24, shape(*ring(C, C, 28, 14))),
        "hole_closes": (shape(*ring(C, C, 28, 14)), disk24),
        # one body into several, several into one
        "split_two": (disk20, shape(("disk", (17, C, 14), BLACK), ("disk", (47, C, 14), BLACK))),
        "split_three": (disk22, shape(("disk", (C, 15, 12), BLACK), ("disk", (15, 46, 12), BLACK),
                                      ("disk", (49, 46, 12), BLACK))),
        # separate bodies each keep their own centre of mass (the controls are internal forces), so they can only
        # merge by growing towards each other: the ellipse's halves have the disks' centroids (4 a / 3 pi = 11.25)
        "merge_two": (shape(("disk", (C - 11.25, C, 9), BLACK), ("disk", (C + 11.25, C, 9), BLACK)),
                      shape(("mask", lambda x, y: ((x - C) / 26.5) ** 2 + ((y - C) / 6.1) ** 2 <= 1.0, BLACK))),
        # glyphs drawn as polygons and strokes
        "letter_T": (shape(square(C, C, 34)), shape(("rect", (6, 6, 57, 17), BLACK),
                                                    ("rect", (26, 6, 37, 57), BLACK))),
        "letter_C": (disk20, shape(arc_stroke(C, C, 20, 12, 45, 315))),
        "letter_S": (shape(square(C, C, 30)), shape(arc_stroke(C, 20, 11.5, 9, 20, 270),
                                                     arc_stroke(C, 43, 11.5, 9, 200, 90))),
        "letter_A": (shape(("disk", (C, C, 19), BLACK)), shape(("poly", A[0], BLACK), ("poly", A[1], BLACK))),
        # colours: a red-and-blue body whose colours have to trade places
        "color_bar_to_disk": (two_colors(shape(("rect", (6, 20, 57, 43), BLACK)), RED, BLUE, "x"),
                              two_colors(shape(("disk", (C, C, 20), BLACK)), BLUE, RED, "x")),
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
    """Write every image as <out>/<name>.png (default: scenes/images/) and every pair as
    <out>/pairs/<pair>_initial.png and <out>/pairs/<pair>_target.png."""
    out = Path(out)
    out.mkdir(exist_ok=True)
    for name, img in images().items():
        save(img, out / f"{name}.png")
        print(out / f"{name}.png")
    (out / "pairs").mkdir(exist_ok=True)
    for name, (initial, target) in pairs().items():
        for role, img in (("initial", initial), ("target", target)):
            save(img, out / "pairs" / f"{name}_{role}.png")
            print(out / "pairs" / f"{name}_{role}.png")


if __name__ == "__main__":
    main()
