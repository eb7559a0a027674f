"""The ``lounge`` layout: a sofa, a floor lamp and a coffee table holding small objects in a 14 x 11 m
room, seen from a partial arc with close views (a scene the presets were not tuned on)."""

from __future__ import annotations

import math

import numpy as np

from ...cameras import Camera, look_at
from .model import LOUNGE_TABLE_HEIGHT, Builder, DemoScene, Material, Query, add_walls, frame_z, normalize, rot_z


def lounge_scene(seed: int) -> DemoScene:
    """The lounge: a room about 2.3 x 1.8 times the tabletop's (14 x 11 m, 3.4 m high) with a
    sofa, a floor lamp, a rug, a painting and a low coffee table holding small objects."""
    rng = np.random.default_rng([int(seed), 17])
    b = Builder()
    I = np.eye(3)
    top = LOUNGE_TABLE_HEIGHT

    def jitter(xy, amount=0.012):
        return np.asarray(xy, dtype=np.float64) + rng.uniform(-amount, amount, size=2)

    def tint(color: tuple[float, float, float], amount: float = 0.04) -> tuple[float, float, float]:
        red, green, blue = (float(np.clip(c + rng.uniform(-amount, amount), 0.0, 1.0)) for c in color)
        return red, green, blue

    # ---- regions (ids are assigned in this order; unique across levels)
    room = b.region(2, "room", "the living room", None)
    floor = b.region(1, "floor", "the tiled floor", room)
    wall = b.region(1, "wall", "the painted walls of the room", room)
    rug = b.region(1, "rug", "a round blue rug", room)
    painting = b.region(1, "painting", "a painting on the wall", room)
    frame = b.region(0, "picture frame", "the frame of the painting", painting)
    canvas = b.region(0, "canvas", "the canvas of the painting", painting)

    furniture = b.region(2, "furniture", "the furniture", None)
    sofa = b.region(1, "sofa", "a grey sofa", furniture)
    sofa_seat = b.region(0, "sofa seat", "the seat of the sofa", sofa)
    sofa_back = b.region(0, "sofa back", "the back of the sofa", sofa)
    sofa_arms = b.region(0, "sofa arms", "the arms of the sofa", sofa)
    yellow_cushion = b.region(1, "yellow cushion", "a yellow cushion", furniture)
    blue_cushion = b.region(1, "blue cushion", "a blue striped cushion", furniture)
    coffee_table = b.region(1, "coffee table", "a low wooden coffee table", furniture)
    table_top = b.region(0, "coffee table top", "the top of the coffee table", coffee_table)
    table_legs = b.region(0, "coffee table legs", "the legs of the coffee table", coffee_table)
    lamp = b.region(1, "floor lamp", "a tall floor lamp", furniture)
    shade = b.region(0, "lamp shade", "the shade of the lamp", lamp)
    pole = b.region(0, "lamp pole", "the pole of the lamp", lamp)
    lamp_base = b.region(0, "lamp base", "the base of the lamp", lamp)

    things = b.region(2, "things on the coffee table", "the things on the coffee table", None)
    vase_of_flowers = b.region(1, "vase of flowers", "a vase of flowers", things)
    vase = b.region(0, "vase", "the blue vase", vase_of_flowers)
    flowers = b.region(0, "flowers", "the flowers in the vase", vase_of_flowers)
    books = b.region(1, "stack of books", "a stack of books", things)
    red_book = b.region(0, "red book", "the red book", books)
    green_book = b.region(0, "green book", "the green book", books)
    blue_book = b.region(0, "blue book", "the blue book", books)
    fruit_bowl = b.region(1, "bowl of fruit", "a bowl of fruit", things)
    bowl = b.region(0, "bowl", "the bowl", fruit_bowl)
    pear = b.region(0, "pear", "a green pear", fruit_bowl)
    lemon = b.region(0, "lemon", "a lemon", fruit_bowl)
    grapes = b.region(0, "grapes", "a bunch of grapes", fruit_bowl)
    car = b.region(1, "toy car", "a small red toy car", things)
    car_body = b.region(0, "toy car body", "the body of the toy car", car)
    car_windows = b.region(0, "toy car windows", "the windows of the toy car", car)
    car_wheels = b.region(0, "toy car wheels", "the wheels of the toy car", car)
    candle = b.region(1, "candle", "a white candle", things)

    # ---- room: planes do not cast shadows; the lower 0.9 m of the walls is a darker dado
    tiles = Material(
        tint((0.74, 0.71, 0.66)), "checker", color2=tint((0.62, 0.60, 0.57)), period=0.5, noise=0.07, noise_freq=9.0
    )
    b.add("plane", (0, 0, 0), I, (), tiles, obj=floor, casts_shadow=False)
    paint = Material(
        tint((0.80, 0.74, 0.62)),
        "stripes",
        color2=tint((0.36, 0.46, 0.40)),
        period=6.0,
        duty=0.15,
        axis=1,
        noise=0.07,
        noise_freq=3.0,
    )
    add_walls(b, wall, 7.0, 5.5, paint)
    ceiling = Material((0.93, 0.92, 0.90), noise=0.03, noise_freq=2.0)
    b.add("plane", (0, 0, 3.4), I, (), ceiling, obj=wall, casts_shadow=False)

    rug_wool = Material(
        tint((0.25, 0.36, 0.62)), "rim", color2=(0.86, 0.80, 0.62), period=1.18, noise=0.12, noise_freq=25.0
    )
    b.add("cylinder", (0.0, 0.1, 0.004), I, (1.35, 0.004), rug_wool, obj=rug)

    # the painting hangs on the wall behind the sofa (y = 5.5); the canvas stands 1 cm proud
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
        tint((0.20, 0.42, 0.66)), "dots", color2=(0.95, 0.72, 0.22), period=0.16, duty=0.4, noise=0.10, noise_freq=8.0
    )
    b.add("box", (0.4, 5.47, 1.8), I, (0.95, 0.03, 0.65), gilt, part=frame, obj=painting)
    b.add("box", (0.4, 5.46, 1.8), I, (0.82, 0.03, 0.52), art, part=canvas, obj=painting)

    # ---- sofa against the painting's side, facing -y
    fabric = Material(
        tint((0.47, 0.49, 0.52)), "dots", color2=(0.40, 0.42, 0.45), period=0.03, duty=0.35, noise=0.06, noise_freq=60.0
    )
    cushion_fabric = Material(
        fabric.color, "stripes", color2=(0.42, 0.44, 0.47), period=0.45, duty=0.04, axis=0, noise=0.06, noise_freq=60.0
    )
    b.add("box", (0.0, 1.32, 0.21), I, (0.90, 0.42, 0.21), cushion_fabric, part=sofa_seat, obj=sofa)
    b.add("box", (0.0, 1.70, 0.58), I, (0.90, 0.12, 0.36), fabric, part=sofa_back, obj=sofa)
    for x in (-1.0, 1.0):
        b.add("box", (x, 1.36, 0.32), I, (0.10, 0.46, 0.32), fabric, part=sofa_arms, obj=sofa)
    cl, sl = math.cos(0.3), math.sin(0.3)  # cushions lean back against the sofa back (+y)
    lean = np.array([[1.0, 0.0, 0.0], [0.0, cl, sl], [0.0, -sl, cl]])
    yellow = Material(tint((0.92, 0.74, 0.16)), noise=0.10, noise_freq=40.0)
    blue_stripes = Material(
        tint((0.18, 0.32, 0.66)),
        "stripes",
        color2=(0.92, 0.92, 0.88),
        period=0.07,
        duty=0.3,
        axis=0,
        noise=0.06,
        noise_freq=40.0,
    )
    for obj, x, mat in ((yellow_cushion, -0.52, yellow), (blue_cushion, 0.50, blue_stripes)):
        xy = jitter((x, 1.50), 0.03)
        b.add(
            "ellipsoid", (xy[0], xy[1], 0.62), rot_z(rng.uniform(-0.15, 0.15)) @ lean, (0.23, 0.08, 0.19), mat, obj=obj
        )

    # ---- coffee table on the rug
    oak = Material(
        tint((0.66, 0.47, 0.28)),
        "stripes",
        color2=(0.55, 0.37, 0.20),
        period=0.025,
        duty=0.3,
        axis=1,
        noise=0.08,
        noise_freq=50.0,
        specular=0.15,
    )
    b.add("box", (0.0, 0.0, top - 0.025), I, (0.60, 0.35, 0.025), oak, part=table_top, obj=coffee_table)
    leg_h = 0.5 * (top - 0.05)
    for x in (-0.54, 0.54):
        for y in (-0.29, 0.29):
            b.add("box", (x, y, leg_h), I, (0.03, 0.03, leg_h), oak, part=table_legs, obj=coffee_table)

    # ---- floor lamp beside the sofa
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
    lx, ly = jitter((-1.55, 1.15), 0.03)
    b.add("cylinder", (lx, ly, 0.02), I, (0.18, 0.02), black, part=lamp_base, obj=lamp)
    b.add("cylinder", (lx, ly, 0.76), I, (0.018, 0.72), brass, part=pole, obj=lamp)
    b.add("cone", (lx, ly, 1.46), I, (0.27, 0.16, 0.17), linen, part=shade, obj=lamp)

    # ---- vase of flowers: a round vase with a neck, flowers on stems leaning out of it
    glaze = Material(
        tint((0.14, 0.34, 0.62)),
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
        Material(tint(c), "dots", color2=(0.98, 0.88, 0.30), period=0.012, duty=0.2, noise=0.06, noise_freq=200.0)
        for c in ((0.92, 0.36, 0.55), (0.97, 0.95, 0.92), (0.90, 0.20, 0.22))
    ]
    add = b.posed(jitter((-0.36, 0.12)), rng.uniform(0, 2 * np.pi), z0=top)
    add("ellipsoid", (0, 0, 0.10), I, (0.07, 0.07, 0.10), glaze, part=vase, obj=vase_of_flowers)
    add("cylinder", (0, 0, 0.215), I, (0.036, 0.04), glaze, part=vase, obj=vase_of_flowers)
    for k in range(5):
        ang = 2 * math.pi * k / 5
        axis = normalize((0.35 * math.cos(ang), 0.35 * math.sin(ang), 1.0))
        base = np.array([0.0, 0.0, 0.24])
        add("cylinder", base + 0.09 * axis, frame_z(axis), (0.006, 0.09), stem, part=flowers, obj=vase_of_flowers)
        add(
            "ellipsoid",
            base + 0.19 * axis,
            frame_z(axis),
            (0.038, 0.038, 0.022),
            petals[k % 3],
            part=flowers,
            obj=vase_of_flowers,
        )

    # ---- stack of three books, each turned a little
    cover = [
        Material(
            tint(c), "stripes", color2=(0.93, 0.90, 0.80), period=0.5, duty=0.06, axis=0, noise=0.06, noise_freq=70.0
        )
        for c in ((0.72, 0.14, 0.12), (0.18, 0.48, 0.26), (0.16, 0.26, 0.60))
    ]
    add = b.posed(jitter((0.02, -0.13)), 0.1 + rng.uniform(-0.2, 0.2), z0=top)
    z = 0.0
    for part, mat, (hx, hy, hz), yaw in (
        (red_book, cover[0], (0.125, 0.09, 0.02), 0.0),
        (green_book, cover[1], (0.11, 0.08, 0.017), 0.18),
        (blue_book, cover[2], (0.10, 0.072, 0.015), -0.12),
    ):
        add("box", (0, 0, z + hz), rot_z(yaw), (hx, hy, hz), mat, part=part, obj=books)
        z += 2 * hz

    # ---- bowl of fruit
    ceramic = Material(
        tint((0.93, 0.90, 0.84)),
        "rim",
        color2=(0.70, 0.30, 0.18),
        period=0.115,
        noise=0.04,
        noise_freq=120.0,
        specular=0.25,
    )
    pear_skin = Material(
        tint((0.60, 0.74, 0.22)),
        "dots",
        color2=(0.45, 0.52, 0.15),
        period=0.015,
        duty=0.25,
        noise=0.08,
        noise_freq=150.0,
        specular=0.2,
    )
    lemon_skin = Material((0.98, 0.86, 0.18), noise=0.12, noise_freq=300.0, specular=0.25)
    grape_skin = Material(tint((0.42, 0.16, 0.40)), noise=0.08, noise_freq=150.0, specular=0.5)
    brown = Material((0.32, 0.22, 0.10))
    add = b.posed(jitter((0.38, 0.10)), rng.uniform(0, 2 * np.pi), z0=top)
    add("cone", (0, 0, 0.04), I, (0.07, 0.13, 0.04), ceramic, part=bowl, obj=fruit_bowl)
    add("ellipsoid", (-0.04, 0.035, 0.115), I, (0.038, 0.038, 0.042), pear_skin, part=pear, obj=fruit_bowl)
    add("ellipsoid", (-0.04, 0.035, 0.165), I, (0.024, 0.024, 0.032), pear_skin, part=pear, obj=fruit_bowl)
    add("cylinder", (-0.04, 0.035, 0.202), I, (0.004, 0.01), brown, part=pear, obj=fruit_bowl)
    add("ellipsoid", (0.05, 0.03, 0.107), rot_z(0.6), (0.048, 0.032, 0.032), lemon_skin, part=lemon, obj=fruit_bowl)
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
        add("ellipsoid", (gx, gy, gz), I, (0.017, 0.017, 0.017), grape_skin, part=grapes, obj=fruit_bowl)

    # ---- toy car: wheel axles along local y, nose along +x
    paintwork = Material(tint((0.85, 0.10, 0.10)), noise=0.05, noise_freq=150.0, specular=0.6)
    glass = Material((0.55, 0.72, 0.85), noise=0.04, noise_freq=150.0, specular=0.7)
    wheel = Material(
        (0.75, 0.75, 0.78), "rim", color2=(0.08, 0.08, 0.08), period=0.011, noise=0.04, noise_freq=150.0, specular=0.4
    )  # grey hub, black tyre
    add = b.posed(jitter((0.06, 0.19)), -0.5 + rng.uniform(-0.3, 0.3), z0=top)
    add("box", (0, 0, 0.038), I, (0.085, 0.042, 0.018), paintwork, part=car_body, obj=car)
    add("box", (-0.012, 0, 0.072), I, (0.045, 0.036, 0.017), glass, part=car_windows, obj=car)
    axle = frame_z((0, 1, 0))
    for x in (-0.052, 0.052):
        for y in (-0.044, 0.044):
            add("cylinder", (x, y, 0.022), axle, (0.022, 0.009), wheel, part=car_wheels, obj=car)

    # ---- candle with its flame (no parts)
    wax = Material((0.96, 0.95, 0.90), noise=0.04, noise_freq=120.0, specular=0.2)
    flame = Material((1.0, 0.78, 0.25), noise=0.0)
    add = b.posed(jitter((-0.40, -0.19)), 0.0, z0=top)
    add("cylinder", (0, 0, 0.06), I, (0.03, 0.06), wax, obj=candle)
    add("ellipsoid", (0, 0, 0.138), I, (0.009, 0.009, 0.02), flame, obj=candle, casts_shadow=False)

    q = [
        # group level
        Query("furniture", "simple", (furniture,)),
        Query("things on the coffee table", "compound", (things,)),
        # object level
        Query("sofa", "simple", (sofa,)),
        Query("cushion", "simple", (yellow_cushion, blue_cushion)),
        Query("yellow cushion", "compound", (yellow_cushion,)),
        Query("coffee table", "compound", (coffee_table,)),
        Query("lamp", "simple", (lamp,)),
        Query("rug", "simple", (rug,)),
        Query("vase of flowers", "compound", (vase_of_flowers,)),
        Query("stack of books", "compound", (books,)),
        Query("bowl of fruit", "compound", (fruit_bowl,)),
        Query("toy car", "compound", (car,)),
        Query("candle", "simple", (candle,)),
        # part level
        Query("back of the sofa", "compound", (sofa_back,)),
        Query("legs of the coffee table", "compound", (table_legs,)),
        Query("shade of the lamp", "compound", (shade,)),
        Query("frame of the painting", "compound", (frame,)),
        Query("flowers", "simple", (flowers,)),
        Query("book", "simple", (red_book, green_book, blue_book)),
        Query("red book", "compound", (red_book,)),
        Query("wheels of the toy car", "compound", (car_wheels,)),
        Query("bowl", "simple", (bowl,)),
        Query("pear", "simple", (pear,)),
        Query("fruit", "simple", (pear, lemon, grapes)),
    ]
    key = normalize((0.5, -0.35, 1.0))
    fill = normalize((-0.6, -0.7, 0.5))
    return DemoScene(b.primitives, b.regions, q, key, fill)


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
