"""The ``tabletop`` layout: a round table with a tea set and snacks in a 6 x 6 m room, seen from a
closed ring of views (every preset was tuned on it)."""

from __future__ import annotations

import math

import numpy as np

from ...cameras import Camera, look_at
from .model import (
    TABLE_HEIGHT,
    Builder,
    DemoScene,
    Draws,
    Material,
    Query,
    add_regions,
    add_walls,
    frame_z,
    normalize,
    rot_z,
)

# (level, name, caption, parent's name); ids are assigned in this order, unique across levels.
_REGIONS = (
    (2, "room", "the room around the table", None),
    (1, "floor", "the wooden floor", "room"),
    (1, "wall", "the striped wall in the background", "room"),
    (1, "table", "a round table with a checkered tablecloth", "room"),
    (0, "tabletop", "the top of the table", "table"),
    (0, "table base", "the base of the table", "table"),
    (2, "tea set", "a tea set", None),
    (1, "teapot", "a white teapot with blue stripes", "tea set"),
    (0, "teapot body", "the body of the teapot", "teapot"),
    (0, "teapot lid", "the lid of the teapot", "teapot"),
    (0, "teapot spout", "the spout of the teapot", "teapot"),
    (0, "teapot handle", "the handle of the teapot", "teapot"),
    (1, "red mug", "a red mug", "tea set"),
    (1, "blue mug", "a blue mug with a white handle", "tea set"),
    (0, "blue mug body", "the body of the blue mug", "blue mug"),
    (0, "blue mug handle", "the handle of the blue mug", "blue mug"),
    (2, "snacks", "snacks on the table", None),
    (1, "bag of cookies", "a bag of cookies", "snacks"),
    (0, "bag", "the paper bag", "bag of cookies"),
    (0, "cookies in the bag", "the cookies in the bag", "bag of cookies"),
    (1, "loose cookies", "loose cookies", "snacks"),
    (1, "plate of fruit", "a plate of fruit", "snacks"),
    (0, "plate", "the plate", "plate of fruit"),
    (0, "apple", "a red apple", "plate of fruit"),
    (0, "orange", "an orange", "plate of fruit"),
    (0, "banana", "a banana", "plate of fruit"),
)
# (query, type, the names of the regions it refers to), by level: group, object, part.
_QUERIES = (
    ("tea set", "simple", ("tea set",)),
    ("snacks", "simple", ("snacks",)),
    ("teapot", "simple", ("teapot",)),
    ("mug", "simple", ("red mug", "blue mug")),
    ("red mug", "compound", ("red mug",)),
    ("blue mug", "compound", ("blue mug",)),
    ("table", "simple", ("table",)),
    ("floor", "simple", ("floor",)),
    ("bag of cookies", "compound", ("bag of cookies",)),
    ("loose cookies", "compound", ("loose cookies",)),
    ("plate of fruit", "compound", ("plate of fruit",)),
    ("lid of the teapot", "compound", ("teapot lid",)),
    ("spout of the teapot", "compound", ("teapot spout",)),
    ("handle of the teapot", "compound", ("teapot handle",)),
    ("handle of the blue mug", "compound", ("blue mug handle",)),
    ("plate", "simple", ("plate",)),
    ("apple", "simple", ("apple",)),
    ("banana", "simple", ("banana",)),
    ("fruit", "simple", ("apple", "orange", "banana")),
    ("cookies", "simple", ("cookies in the bag", "loose cookies")),  # a part and an object
)


def tabletop_scene(seed: int) -> DemoScene:
    """The tabletop: a 6 x 6 m room, 2.8 m high, with a round table holding a tea set and
    snacks."""
    d = Draws(np.random.default_rng([int(seed), 7]), jitter_amount=0.015)
    b = Builder()
    r = add_regions(b, _REGIONS)
    _room(b, r, d)
    _table(b, r, d)
    _teapot(b, r, d)
    _mugs(b, r, d)
    _cookies(b, r, d)
    _fruit_plate(b, r, d)
    q = [Query(query, qtype, tuple(r[name] for name in names)) for query, qtype, names in _QUERIES]
    assert all(rid in r.values() for qq in q for rid in qq.region_ids)
    key = normalize((-0.45, -0.55, 1.0))
    fill = normalize((0.6, 0.5, 0.45))
    return DemoScene(b.primitives, b.regions, q, key, fill)


def _room(b: Builder, r: dict[str, int], d: Draws) -> None:
    """Floor, walls and ceiling: planes that cast no shadows (the room is closed; the key light
    is "outside")."""
    I = np.eye(3)
    planks = Material(
        d.tint((0.55, 0.36, 0.20)), "planks", color2=(0.30, 0.18, 0.09), period=0.16, noise=0.10, noise_freq=20.0
    )
    b.add("plane", (0, 0, 0), I, (), planks, obj=r["floor"], casts_shadow=False)
    wallpaper = Material(
        d.tint((0.82, 0.78, 0.66)),
        "stripes",
        color2=d.tint((0.55, 0.62, 0.70)),
        period=0.22,
        duty=0.35,
        axis=0,
        noise=0.08,
        noise_freq=12.0,
    )
    add_walls(b, r["wall"], 3.0, 3.0, wallpaper)
    ceiling = Material((0.90, 0.89, 0.86), noise=0.03, noise_freq=5.0)
    b.add("plane", (0, 0, 2.8), I, (), ceiling, obj=r["wall"], casts_shadow=False)


def _table(b: Builder, r: dict[str, int], d: Draws) -> None:
    """The round table: a clothed top on a wooden pedestal and foot."""
    I = np.eye(3)
    table, base = r["table"], r["table base"]
    cloth = Material(
        d.tint((0.35, 0.62, 0.38)), "checker", color2=(0.93, 0.93, 0.90), period=0.07, noise=0.05, noise_freq=150.0
    )
    dark_wood = Material(
        (0.30, 0.19, 0.11),
        "stripes",
        color2=(0.22, 0.13, 0.07),
        period=0.03,
        duty=0.3,
        axis=2,
        noise=0.08,
        noise_freq=60.0,
    )
    b.add("cylinder", (0, 0, TABLE_HEIGHT - 0.02), I, (0.62, 0.02), cloth, part=r["tabletop"], obj=table)
    b.add("cylinder", (0, 0, 0.395), I, (0.05, 0.315), dark_wood, part=base, obj=table)
    b.add("cone", (0, 0, 0.04), I, (0.30, 0.06, 0.04), dark_wood, part=base, obj=table)


def _teapot(b: Builder, r: dict[str, int], d: Draws) -> None:
    """The teapot: body, lid with a knob, spout along local +x and handle along -x."""
    I = np.eye(3)
    teapot, lid, handle = r["teapot"], r["teapot lid"], r["teapot handle"]
    add = b.posed(d.jitter((-0.17, 0.15)), 0.5 + d.rng.uniform(-0.25, 0.25))
    porcelain = Material(
        d.tint((0.94, 0.92, 0.86), 0.02),
        "stripes",
        color2=(0.18, 0.32, 0.72),
        period=0.045,
        duty=0.22,
        axis=2,
        noise=0.04,
        noise_freq=90.0,
        specular=0.35,
    )
    cream = Material((0.93, 0.90, 0.83), noise=0.05, noise_freq=120.0, specular=0.3)
    lid_blue = Material(
        d.tint((0.16, 0.28, 0.68)), "dots", color2=(0.85, 0.88, 0.95), period=0.015, duty=0.25, noise=0.05, specular=0.3
    )
    add("ellipsoid", (0, 0, 0.10), I, (0.13, 0.13, 0.10), porcelain, part=r["teapot body"], obj=teapot)
    add("cylinder", (0, 0, 0.197), I, (0.062, 0.012), lid_blue, part=lid, obj=teapot)
    add("ellipsoid", (0, 0, 0.215), I, (0.022, 0.022, 0.017), lid_blue, part=lid, obj=teapot)
    spout_dir = normalize((1.0, 0.0, 1.0))
    add(
        "cone",
        np.array([0.10, 0.0, 0.08]) + 0.075 * spout_dir,
        frame_z(spout_dir),
        (0.034, 0.014, 0.075),
        cream,
        part=r["teapot spout"],
        obj=teapot,
    )
    bar_x = frame_z((1, 0, 0))
    for z in (0.05, 0.15):
        add("cylinder", (-0.155, 0, z), bar_x, (0.014, 0.05), cream, part=handle, obj=teapot)
    add("cylinder", (-0.205, 0, 0.10), I, (0.014, 0.064), cream, part=handle, obj=teapot)


def _mugs(b: Builder, r: dict[str, int], d: Draws) -> None:
    """A red mug and a blue mug with a white handle, both holding coffee (its surface slightly
    above the top cap)."""
    I = np.eye(3)
    coffee = Material((0.20, 0.11, 0.06), noise=0.10, noise_freq=200.0, specular=0.5)
    red = Material(
        d.tint((0.80, 0.12, 0.10)),
        "stripes",
        color2=(0.95, 0.93, 0.90),
        period=0.04,
        duty=0.15,
        axis=2,
        noise=0.05,
        noise_freq=100.0,
        specular=0.3,
    )
    add = b.posed(d.jitter((0.22, 0.32)), d.rng.uniform(0, 2 * np.pi))
    add("cylinder", (0, 0, 0.06), I, (0.055, 0.06), red, obj=r["red mug"])
    add("cylinder", (0, 0, 0.1205), I, (0.047, 0.0015), coffee, obj=r["red mug"])

    mug, body, handle = r["blue mug"], r["blue mug body"], r["blue mug handle"]
    blue = Material(
        d.tint((0.15, 0.30, 0.80)),
        "dots",
        color2=(0.90, 0.92, 0.98),
        period=0.02,
        duty=0.22,
        noise=0.05,
        noise_freq=100.0,
        specular=0.3,
    )
    white = Material((0.95, 0.95, 0.93), noise=0.04, noise_freq=150.0, specular=0.3)
    add = b.posed(d.jitter((0.33, 0.03)), -0.3 + d.rng.uniform(-0.3, 0.3))
    add("cylinder", (0, 0, 0.06), I, (0.055, 0.06), blue, part=body, obj=mug)
    add("cylinder", (0, 0, 0.1205), I, (0.047, 0.0015), coffee, part=body, obj=mug)
    bar_x = frame_z((1, 0, 0))
    for z in (0.03, 0.095):
        add("cylinder", (0.075, 0, z), bar_x, (0.011, 0.03), white, part=handle, obj=mug)
    add("cylinder", (0.105, 0, 0.0625), I, (0.011, 0.0435), white, part=handle, obj=mug)


def _cookies(b: Builder, r: dict[str, int], d: Draws) -> None:
    """A paper bag with two cookies standing up out of it, and loose cookies lying flat next
    to it (one cookie material for all)."""
    I = np.eye(3)
    cookie_bag, in_bag = r["bag of cookies"], r["cookies in the bag"]
    kraft = Material(
        d.tint((0.72, 0.55, 0.36)),
        "stripes",
        color2=(0.55, 0.40, 0.25),
        period=0.035,
        duty=0.12,
        axis=0,
        noise=0.08,
        noise_freq=120.0,
    )
    cookie = Material(
        d.tint((0.84, 0.62, 0.32)),
        "dots",
        color2=(0.25, 0.14, 0.07),
        period=0.011,
        duty=0.25,
        noise=0.08,
        noise_freq=200.0,
    )
    add = b.posed(d.jitter((-0.27, -0.22)), 0.4 + d.rng.uniform(-0.3, 0.3))
    add("box", (0, 0, 0.09), I, (0.07, 0.05, 0.09), kraft, part=r["bag"], obj=cookie_bag)
    for x, y, z, tilt in ((-0.027, 0.0, 0.182, 1.25), (0.026, 0.008, 0.176, 1.15)):
        axis = (0.0, math.sin(tilt), math.cos(tilt))
        add("cylinder", (x, y, z), frame_z(axis), (0.034, 0.007), cookie, part=in_bag, obj=cookie_bag)

    add = b.posed(d.jitter((0.0, -0.41), 0.01), d.rng.uniform(0, 2 * np.pi))
    for x, y in ((-0.06, 0.02), (0.02, 0.05), (0.05, -0.03), (-0.03, -0.06)):
        add("cylinder", (x, y, 0.007), I, (0.034, 0.007), cookie, obj=r["loose cookies"])


def _fruit_plate(b: Builder, r: dict[str, int], d: Draws) -> None:
    """A plate with an apple, an orange and a banana."""
    I = np.eye(3)
    plate = r["plate of fruit"]
    china = Material(
        (0.95, 0.95, 0.95), "rim", color2=(0.20, 0.45, 0.70), period=0.125, noise=0.03, noise_freq=150.0, specular=0.2
    )
    apple_skin = Material(
        d.tint((0.78, 0.10, 0.08)),
        "dots",
        color2=(0.85, 0.65, 0.15),
        period=0.02,
        duty=0.2,
        noise=0.08,
        noise_freq=150.0,
        specular=0.3,
    )
    stem = Material((0.30, 0.20, 0.08))
    peel = Material((0.98, 0.55, 0.08), noise=0.12, noise_freq=400.0, specular=0.15)
    banana_skin = Material(
        (0.95, 0.82, 0.20),
        "stripes",
        color2=(0.55, 0.45, 0.12),
        period=0.07,
        duty=0.08,
        axis=0,
        noise=0.06,
        noise_freq=120.0,
    )
    add = b.posed(d.jitter((0.30, -0.29), 0.01), d.rng.uniform(0, 2 * np.pi))
    add("cone", (0, 0, 0.012), I, (0.09, 0.14, 0.012), china, part=r["plate"], obj=plate)
    add("ellipsoid", (-0.045, 0.035, 0.065), I, (0.042, 0.042, 0.040), apple_skin, part=r["apple"], obj=plate)
    add("cylinder", (-0.045, 0.035, 0.108), I, (0.004, 0.008), stem, part=r["apple"], obj=plate)
    add("ellipsoid", (0.05, 0.03, 0.069), I, (0.045, 0.045, 0.045), peel, part=r["orange"], obj=plate)
    add("ellipsoid", (0.0, -0.06, 0.045), rot_z(0.2), (0.075, 0.021, 0.021), banana_skin, part=r["banana"], obj=plate)


def tabletop_cameras(num_views: int, width: int, height: int, seed: int, hfov_deg: float) -> list[Camera]:
    """Views orbiting the table once, looking at its centre, with elevation between ~23 and
    ~47 degrees and distance between 1.2 and 1.5 m."""
    rng = np.random.default_rng([int(seed), 11])
    fx = 0.5 * width / math.tan(math.radians(hfov_deg) / 2)
    cams = []
    for i in range(num_views):
        phase = 2 * math.pi * i / num_views
        azimuth = phase + rng.uniform(-0.05, 0.05)
        elevation = math.radians(35.0 + 12.0 * math.sin(2 * phase + 0.5))
        radius = 1.35 + 0.15 * math.sin(3 * phase)
        target = np.array([0.0, 0.0, TABLE_HEIGHT + 0.05]) + rng.uniform(-0.03, 0.03, size=3)
        eye = target + radius * np.array(
            [math.cos(elevation) * math.cos(azimuth), math.cos(elevation) * math.sin(azimuth), math.sin(elevation)]
        )
        R, t = look_at(eye, target, up=(0.0, 0.0, 1.0))
        cams.append(Camera(fx, fx, width / 2.0, height / 2.0, width, height, R=R, t=t))
    return cams
