"""The ``lounge`` layout: a sofa, a floor lamp and a coffee table holding small objects in a 14 x 11 m
room, seen from a partial arc with close views (a scene the presets were not tuned on)."""

from __future__ import annotations

import math

import numpy as np

from ...cameras import Camera, look_at
from .model import (
    LOUNGE_TABLE_HEIGHT,
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
    (2, "room", "the living room", None),
    (1, "floor", "the tiled floor", "room"),
    (1, "wall", "the painted walls of the room", "room"),
    (1, "rug", "a round blue rug", "room"),
    (1, "painting", "a painting on the wall", "room"),
    (0, "picture frame", "the frame of the painting", "painting"),
    (0, "canvas", "the canvas of the painting", "painting"),
    (2, "furniture", "the furniture", None),
    (1, "sofa", "a grey sofa", "furniture"),
    (0, "sofa seat", "the seat of the sofa", "sofa"),
    (0, "sofa back", "the back of the sofa", "sofa"),
    (0, "sofa arms", "the arms of the sofa", "sofa"),
    (1, "yellow cushion", "a yellow cushion", "furniture"),
    (1, "blue cushion", "a blue striped cushion", "furniture"),
    (1, "coffee table", "a low wooden coffee table", "furniture"),
    (0, "coffee table top", "the top of the coffee table", "coffee table"),
    (0, "coffee table legs", "the legs of the coffee table", "coffee table"),
    (1, "floor lamp", "a tall floor lamp", "furniture"),
    (0, "lamp shade", "the shade of the lamp", "floor lamp"),
    (0, "lamp pole", "the pole of the lamp", "floor lamp"),
    (0, "lamp base", "the base of the lamp", "floor lamp"),
    (2, "things on the coffee table", "the things on the coffee table", None),
    (1, "vase of flowers", "a vase of flowers", "things on the coffee table"),
    (0, "vase", "the blue vase", "vase of flowers"),
    (0, "flowers", "the flowers in the vase", "vase of flowers"),
    (1, "stack of books", "a stack of books", "things on the coffee table"),
    (0, "red book", "the red book", "stack of books"),
    (0, "green book", "the green book", "stack of books"),
    (0, "blue book", "the blue book", "stack of books"),
    (1, "bowl of fruit", "a bowl of fruit", "things on the coffee table"),
    (0, "bowl", "the bowl", "bowl of fruit"),
    (0, "pear", "a green pear", "bowl of fruit"),
    (0, "lemon", "a lemon", "bowl of fruit"),
    (0, "grapes", "a bunch of grapes", "bowl of fruit"),
    (1, "toy car", "a small red toy car", "things on the coffee table"),
    (0, "toy car body", "the body of the toy car", "toy car"),
    (0, "toy car windows", "the windows of the toy car", "toy car"),
    (0, "toy car wheels", "the wheels of the toy car", "toy car"),
    (1, "candle", "a white candle", "things on the coffee table"),
)
# (query, type, the names of the regions it refers to), by level: group, object, part.
_QUERIES = (
    ("furniture", "simple", ("furniture",)),
    ("things on the coffee table", "compound", ("things on the coffee table",)),
    ("sofa", "simple", ("sofa",)),
    ("cushion", "simple", ("yellow cushion", "blue cushion")),
    ("yellow cushion", "compound", ("yellow cushion",)),
    ("coffee table", "compound", ("coffee table",)),
    ("lamp", "simple", ("floor lamp",)),
    ("rug", "simple", ("rug",)),
    ("vase of flowers", "compound", ("vase of flowers",)),
    ("stack of books", "compound", ("stack of books",)),
    ("bowl of fruit", "compound", ("bowl of fruit",)),
    ("toy car", "compound", ("toy car",)),
    ("candle", "simple", ("candle",)),
    ("back of the sofa", "compound", ("sofa back",)),
    ("legs of the coffee table", "compound", ("coffee table legs",)),
    ("shade of the lamp", "compound", ("lamp shade",)),
    ("frame of the painting", "compound", ("picture frame",)),
    ("flowers", "simple", ("flowers",)),
    ("book", "simple", ("red book", "green book", "blue book")),
    ("red book", "compound", ("red book",)),
    ("wheels of the toy car", "compound", ("toy car wheels",)),
    ("bowl", "simple", ("bowl",)),
    ("pear", "simple", ("pear",)),
    ("fruit", "simple", ("pear", "lemon", "grapes")),
)


def lounge_scene(seed: int) -> DemoScene:
    """The lounge: a room about 2.3 x 1.8 times the tabletop's (14 x 11 m, 3.4 m high) with a
    sofa, a floor lamp, a rug, a painting and a low coffee table holding small objects."""
    d = Draws(np.random.default_rng([int(seed), 17]), jitter_amount=0.012)
    b = Builder()
    r = add_regions(b, _REGIONS)
    _room(b, r, d)
    _sofa(b, r, d)
    _coffee_table(b, r, d)
    _floor_lamp(b, r, d)
    _vase_of_flowers(b, r, d)
    _books(b, r, d)
    _fruit_bowl(b, r, d)
    _toy_car(b, r, d)
    _candle(b, r, d)
    q = [Query(query, qtype, tuple(r[name] for name in names)) for query, qtype, names in _QUERIES]
    key = normalize((0.5, -0.35, 1.0))
    fill = normalize((-0.6, -0.7, 0.5))
    return DemoScene(b.primitives, b.regions, q, key, fill)


def _room(b: Builder, r: dict[str, int], d: Draws) -> None:
    """Floor, walls and ceiling (planes do not cast shadows; the lower 0.9 m of the walls is a
    darker dado), the rug, and the painting on the wall behind the sofa (y = 5.5), its canvas
    1 cm proud of the frame."""
    I = np.eye(3)
    tiles = Material(
        d.tint((0.74, 0.71, 0.66)),
        "checker",
        color2=d.tint((0.62, 0.60, 0.57)),
        period=0.5,
        noise=0.07,
        noise_freq=9.0,
    )
    b.add("plane", (0, 0, 0), I, (), tiles, obj=r["floor"], casts_shadow=False)
    paint = Material(
        d.tint((0.80, 0.74, 0.62)),
        "stripes",
        color2=d.tint((0.36, 0.46, 0.40)),
        period=6.0,
        duty=0.15,
        axis=1,
        noise=0.07,
        noise_freq=3.0,
    )
    add_walls(b, r["wall"], 7.0, 5.5, paint)
    ceiling = Material((0.93, 0.92, 0.90), noise=0.03, noise_freq=2.0)
    b.add("plane", (0, 0, 3.4), I, (), ceiling, obj=r["wall"], casts_shadow=False)

    rug_wool = Material(
        d.tint((0.25, 0.36, 0.62)), "rim", color2=(0.86, 0.80, 0.62), period=1.18, noise=0.12, noise_freq=25.0
    )
    b.add("cylinder", (0.0, 0.1, 0.004), I, (1.35, 0.004), rug_wool, obj=r["rug"])

    gilt = Material(
        (0.55, 0.42, 0.20),
        "stripes",
        color2=(0.35, 0.25, 0.10),
        period=0.05,
        duty=0.3,
        axis=0,
        noise=0.08,
        noise_freq=30.0,
        specular=0.3,
    )
    art = Material(
        d.tint((0.20, 0.42, 0.66)), "dots", color2=(0.95, 0.72, 0.22), period=0.16, duty=0.4, noise=0.10, noise_freq=8.0
    )
    b.add("box", (0.4, 5.47, 1.8), I, (0.95, 0.03, 0.65), gilt, part=r["picture frame"], obj=r["painting"])
    b.add("box", (0.4, 5.46, 1.8), I, (0.82, 0.03, 0.52), art, part=r["canvas"], obj=r["painting"])


def _sofa(b: Builder, r: dict[str, int], d: Draws) -> None:
    """The sofa against the painting's side, facing -y, with two cushions leaning back against
    its back."""
    I = np.eye(3)
    sofa = r["sofa"]
    fabric = Material(
        d.tint((0.47, 0.49, 0.52)),
        "dots",
        color2=(0.40, 0.42, 0.45),
        period=0.03,
        duty=0.35,
        noise=0.06,
        noise_freq=60.0,
    )
    cushion_fabric = Material(
        fabric.color, "stripes", color2=(0.42, 0.44, 0.47), period=0.45, duty=0.04, axis=0, noise=0.06, noise_freq=60.0
    )
    b.add("box", (0.0, 1.32, 0.21), I, (0.90, 0.42, 0.21), cushion_fabric, part=r["sofa seat"], obj=sofa)
    b.add("box", (0.0, 1.70, 0.58), I, (0.90, 0.12, 0.36), fabric, part=r["sofa back"], obj=sofa)
    for x in (-1.0, 1.0):
        b.add("box", (x, 1.36, 0.32), I, (0.10, 0.46, 0.32), fabric, part=r["sofa arms"], obj=sofa)
    cl, sl = math.cos(0.3), math.sin(0.3)  # cushions lean back against the sofa back (+y)
    lean = np.array([[1.0, 0.0, 0.0], [0.0, cl, sl], [0.0, -sl, cl]])
    yellow = Material(d.tint((0.92, 0.74, 0.16)), noise=0.10, noise_freq=40.0)
    blue_stripes = Material(
        d.tint((0.18, 0.32, 0.66)),
        "stripes",
        color2=(0.92, 0.92, 0.88),
        period=0.07,
        duty=0.3,
        axis=0,
        noise=0.06,
        noise_freq=40.0,
    )
    for obj, x, mat in ((r["yellow cushion"], -0.52, yellow), (r["blue cushion"], 0.50, blue_stripes)):
        xy = d.jitter((x, 1.50), 0.03)
        b.add(
            "ellipsoid",
            (xy[0], xy[1], 0.62),
            rot_z(d.rng.uniform(-0.15, 0.15)) @ lean,
            (0.23, 0.08, 0.19),
            mat,
            obj=obj,
        )


def _coffee_table(b: Builder, r: dict[str, int], d: Draws) -> None:
    """The coffee table on the rug: an oak top on four legs."""
    I = np.eye(3)
    top = LOUNGE_TABLE_HEIGHT
    table = r["coffee table"]
    oak = Material(
        d.tint((0.66, 0.47, 0.28)),
        "stripes",
        color2=(0.55, 0.37, 0.20),
        period=0.025,
        duty=0.3,
        axis=1,
        noise=0.08,
        noise_freq=50.0,
        specular=0.15,
    )
    b.add("box", (0.0, 0.0, top - 0.025), I, (0.60, 0.35, 0.025), oak, part=r["coffee table top"], obj=table)
    leg_h = 0.5 * (top - 0.05)
    for x in (-0.54, 0.54):
        for y in (-0.29, 0.29):
            b.add("box", (x, y, leg_h), I, (0.03, 0.03, leg_h), oak, part=r["coffee table legs"], obj=table)


def _floor_lamp(b: Builder, r: dict[str, int], d: Draws) -> None:
    """The floor lamp beside the sofa: base, pole and shade."""
    I = np.eye(3)
    lamp = r["floor lamp"]
    linen = Material(
        (0.95, 0.88, 0.70),
        "stripes",
        color2=(0.80, 0.62, 0.38),
        period=0.32,
        duty=0.08,
        axis=2,
        noise=0.05,
        noise_freq=30.0,
    )
    brass = Material((0.70, 0.56, 0.28), noise=0.05, noise_freq=60.0, specular=0.5)
    black = Material((0.10, 0.10, 0.11), noise=0.05, noise_freq=60.0, specular=0.3)
    lx, ly = d.jitter((-1.55, 1.15), 0.03)
    b.add("cylinder", (lx, ly, 0.02), I, (0.18, 0.02), black, part=r["lamp base"], obj=lamp)
    b.add("cylinder", (lx, ly, 0.76), I, (0.018, 0.72), brass, part=r["lamp pole"], obj=lamp)
    b.add("cone", (lx, ly, 1.46), I, (0.27, 0.16, 0.17), linen, part=r["lamp shade"], obj=lamp)


def _vase_of_flowers(b: Builder, r: dict[str, int], d: Draws) -> None:
    """A round vase with a neck, five flowers on stems leaning out of it."""
    I = np.eye(3)
    obj, vase, flowers = r["vase of flowers"], r["vase"], r["flowers"]
    glaze = Material(
        d.tint((0.14, 0.34, 0.62)),
        "stripes",
        color2=(0.88, 0.90, 0.95),
        period=0.05,
        duty=0.15,
        axis=2,
        noise=0.04,
        noise_freq=90.0,
        specular=0.4,
    )
    stem = Material((0.25, 0.50, 0.18), noise=0.08, noise_freq=200.0)
    petals = [
        Material(d.tint(c), "dots", color2=(0.98, 0.88, 0.30), period=0.012, duty=0.2, noise=0.06, noise_freq=200.0)
        for c in ((0.92, 0.36, 0.55), (0.97, 0.95, 0.92), (0.90, 0.20, 0.22))
    ]
    add = b.posed(d.jitter((-0.36, 0.12)), d.rng.uniform(0, 2 * np.pi), z0=LOUNGE_TABLE_HEIGHT)
    add("ellipsoid", (0, 0, 0.10), I, (0.07, 0.07, 0.10), glaze, part=vase, obj=obj)
    add("cylinder", (0, 0, 0.215), I, (0.036, 0.04), glaze, part=vase, obj=obj)
    for k in range(5):
        ang = 2 * math.pi * k / 5
        axis = normalize((0.35 * math.cos(ang), 0.35 * math.sin(ang), 1.0))
        base = np.array([0.0, 0.0, 0.24])
        add("cylinder", base + 0.09 * axis, frame_z(axis), (0.006, 0.09), stem, part=flowers, obj=obj)
        add("ellipsoid", base + 0.19 * axis, frame_z(axis), (0.038, 0.038, 0.022), petals[k % 3], part=flowers, obj=obj)


def _books(b: Builder, r: dict[str, int], d: Draws) -> None:
    """A stack of three books, each turned a little."""
    cover = [
        Material(
            d.tint(c), "stripes", color2=(0.93, 0.90, 0.80), period=0.5, duty=0.06, axis=0, noise=0.06, noise_freq=70.0
        )
        for c in ((0.72, 0.14, 0.12), (0.18, 0.48, 0.26), (0.16, 0.26, 0.60))
    ]
    add = b.posed(d.jitter((0.02, -0.13)), 0.1 + d.rng.uniform(-0.2, 0.2), z0=LOUNGE_TABLE_HEIGHT)
    z = 0.0
    for part, mat, (hx, hy, hz), yaw in (
        (r["red book"], cover[0], (0.125, 0.09, 0.02), 0.0),
        (r["green book"], cover[1], (0.11, 0.08, 0.017), 0.18),
        (r["blue book"], cover[2], (0.10, 0.072, 0.015), -0.12),
    ):
        add("box", (0, 0, z + hz), rot_z(yaw), (hx, hy, hz), mat, part=part, obj=r["stack of books"])
        z += 2 * hz


def _fruit_bowl(b: Builder, r: dict[str, int], d: Draws) -> None:
    """A bowl holding a pear, a lemon and a bunch of grapes."""
    I = np.eye(3)
    obj, pear = r["bowl of fruit"], r["pear"]
    ceramic = Material(
        d.tint((0.93, 0.90, 0.84)),
        "rim",
        color2=(0.70, 0.30, 0.18),
        period=0.115,
        noise=0.04,
        noise_freq=120.0,
        specular=0.25,
    )
    pear_skin = Material(
        d.tint((0.60, 0.74, 0.22)),
        "dots",
        color2=(0.45, 0.52, 0.15),
        period=0.015,
        duty=0.25,
        noise=0.08,
        noise_freq=150.0,
        specular=0.2,
    )
    lemon_skin = Material((0.98, 0.86, 0.18), noise=0.12, noise_freq=300.0, specular=0.25)
    grape_skin = Material(d.tint((0.42, 0.16, 0.40)), noise=0.08, noise_freq=150.0, specular=0.5)
    brown = Material((0.32, 0.22, 0.10))
    add = b.posed(d.jitter((0.38, 0.10)), d.rng.uniform(0, 2 * np.pi), z0=LOUNGE_TABLE_HEIGHT)
    add("cone", (0, 0, 0.04), I, (0.07, 0.13, 0.04), ceramic, part=r["bowl"], obj=obj)
    add("ellipsoid", (-0.04, 0.035, 0.115), I, (0.038, 0.038, 0.042), pear_skin, part=pear, obj=obj)
    add("ellipsoid", (-0.04, 0.035, 0.165), I, (0.024, 0.024, 0.032), pear_skin, part=pear, obj=obj)
    add("cylinder", (-0.04, 0.035, 0.202), I, (0.004, 0.01), brown, part=pear, obj=obj)
    add("ellipsoid", (0.05, 0.03, 0.107), rot_z(0.6), (0.048, 0.032, 0.032), lemon_skin, part=r["lemon"], obj=obj)
    for gx, gy, gz in (
        (0.0, -0.06, 0.096),
        (0.03, -0.06, 0.096),
        (-0.03, -0.06, 0.096),
        (0.015, -0.035, 0.097),
        (-0.015, -0.035, 0.097),
        (0.015, -0.085, 0.097),
        (-0.015, -0.085, 0.097),
        (0.0, -0.06, 0.124),
        (0.016, -0.048, 0.122),
    ):
        add("ellipsoid", (gx, gy, gz), I, (0.017, 0.017, 0.017), grape_skin, part=r["grapes"], obj=obj)


def _toy_car(b: Builder, r: dict[str, int], d: Draws) -> None:
    """A toy car: wheel axles along local y, nose along +x."""
    I = np.eye(3)
    car = r["toy car"]
    paintwork = Material(d.tint((0.85, 0.10, 0.10)), noise=0.05, noise_freq=150.0, specular=0.6)
    glass = Material((0.55, 0.72, 0.85), noise=0.04, noise_freq=150.0, specular=0.7)
    wheel = Material(
        (0.75, 0.75, 0.78), "rim", color2=(0.08, 0.08, 0.08), period=0.011, noise=0.04, noise_freq=150.0, specular=0.4
    )  # grey hub, black tyre
    add = b.posed(d.jitter((0.06, 0.19)), -0.5 + d.rng.uniform(-0.3, 0.3), z0=LOUNGE_TABLE_HEIGHT)
    add("box", (0, 0, 0.038), I, (0.085, 0.042, 0.018), paintwork, part=r["toy car body"], obj=car)
    add("box", (-0.012, 0, 0.072), I, (0.045, 0.036, 0.017), glass, part=r["toy car windows"], obj=car)
    axle = frame_z((0, 1, 0))
    for x in (-0.052, 0.052):
        for y in (-0.044, 0.044):
            add("cylinder", (x, y, 0.022), axle, (0.022, 0.009), wheel, part=r["toy car wheels"], obj=car)


def _candle(b: Builder, r: dict[str, int], d: Draws) -> None:
    """A candle with its flame (no parts)."""
    I = np.eye(3)
    wax = Material((0.96, 0.95, 0.90), noise=0.04, noise_freq=120.0, specular=0.2)
    flame = Material((1.0, 0.78, 0.25), noise=0.0)
    add = b.posed(d.jitter((-0.40, -0.19)), 0.0, z0=LOUNGE_TABLE_HEIGHT)
    add("cylinder", (0, 0, 0.06), I, (0.03, 0.06), wax, obj=r["candle"])
    add("ellipsoid", (0, 0, 0.138), I, (0.009, 0.009, 0.02), flame, obj=r["candle"], casts_shadow=False)


def lounge_cameras(num_views: int, width: int, height: int, seed: int, hfov_deg: float) -> list[Camera]:
    """A partial elliptical arc (210 degrees, 4.2 x 3.2 m) in front of the sofa, not a closed
    ring, at eye heights of about 0.75 to 1.3 m. Three short stretches of the path swing in to
    0.4 of the arc's radius at 0.8 m high, beside the coffee table, so those views have objects
    (and Gaussians) about half a metre from the camera."""
    rng = np.random.default_rng([int(seed), 19])
    fx = 0.5 * width / math.tan(math.radians(hfov_deg) / 2)
    cams = []
    for i in range(num_views):
        s = i / (num_views - 1) if num_views > 1 else 0.5
        azimuth = math.radians(-195.0 + 210.0 * s) + rng.uniform(-0.02, 0.02)
        close = (0.5 - 0.5 * math.cos(6 * math.pi * s)) ** 4  # 1 at s = 1/6, 1/2, 5/6
        shrink = 1.0 - 0.6 * close
        eye = np.array(
            [
                2.1 * shrink * math.cos(azimuth),
                -0.1 + 1.6 * shrink * math.sin(azimuth),
                (1.0 - close) * (1.05 + 0.3 * math.sin(3 * math.pi * s + 0.3)) + 0.8 * close,
            ]
        )
        eye += rng.uniform(-0.03, 0.03, size=3)
        # far views look past the table towards the sofa, close ones down at the table
        target = np.array(
            [0.35 * math.sin(2 * math.pi * s), 0.45 * (1.0 - close), LOUNGE_TABLE_HEIGHT + 0.05 + 0.25 * (1.0 - close)]
        )
        target += rng.uniform(-0.03, 0.03, size=3)
        R, t = look_at(eye, target, up=(0.0, 0.0, 1.0))
        cams.append(Camera(fx, fx, width / 2.0, height / 2.0, width, height, R=R, t=t))
    return cams
