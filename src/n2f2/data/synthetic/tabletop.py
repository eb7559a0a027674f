"""The ``tabletop`` layout: a round table with a tea set and snacks in a 6 x 6 m room, seen from a
closed ring of views (every preset was tuned on it)."""

from __future__ import annotations

import math

import numpy as np

from ...cameras import Camera, look_at
from .model import TABLE_HEIGHT, Builder, DemoScene, Material, Query, add_walls, frame_z, normalize, rot_z


def tabletop_scene(seed: int) -> DemoScene:
    """The tabletop: a 6 x 6 m room, 2.8 m high, with a round table holding a tea set and
    snacks."""
    rng = np.random.default_rng([int(seed), 7])
    b = Builder()
    I = np.eye(3)

    def jitter(xy, amount=0.015):
        return np.asarray(xy, dtype=np.float64) + rng.uniform(-amount, amount, size=2)

    def tint(color: tuple[float, float, float], amount: float = 0.04) -> tuple[float, float, float]:
        red, green, blue = (float(np.clip(c + rng.uniform(-amount, amount), 0.0, 1.0)) for c in color)
        return red, green, blue

    # ---- regions (ids are assigned in this order; unique across levels)
    room = b.region(2, "room", "the room around the table", None)
    floor = b.region(1, "floor", "the wooden floor", room)
    wall = b.region(1, "wall", "the striped wall in the background", room)
    table = b.region(1, "table", "a round table with a checkered tablecloth", room)
    tabletop = b.region(0, "tabletop", "the top of the table", table)
    table_base = b.region(0, "table base", "the base of the table", table)

    tea_set = b.region(2, "tea set", "a tea set", None)
    teapot = b.region(1, "teapot", "a white teapot with blue stripes", tea_set)
    pot_body = b.region(0, "teapot body", "the body of the teapot", teapot)
    pot_lid = b.region(0, "teapot lid", "the lid of the teapot", teapot)
    pot_spout = b.region(0, "teapot spout", "the spout of the teapot", teapot)
    pot_handle = b.region(0, "teapot handle", "the handle of the teapot", teapot)
    red_mug = b.region(1, "red mug", "a red mug", tea_set)
    blue_mug = b.region(1, "blue mug", "a blue mug with a white handle", tea_set)
    blue_body = b.region(0, "blue mug body", "the body of the blue mug", blue_mug)
    blue_handle = b.region(0, "blue mug handle", "the handle of the blue mug", blue_mug)

    snacks = b.region(2, "snacks", "snacks on the table", None)
    cookie_bag = b.region(1, "bag of cookies", "a bag of cookies", snacks)
    bag = b.region(0, "bag", "the paper bag", cookie_bag)
    bag_cookies = b.region(0, "cookies in the bag", "the cookies in the bag", cookie_bag)
    loose = b.region(1, "loose cookies", "loose cookies", snacks)
    fruit_plate = b.region(1, "plate of fruit", "a plate of fruit", snacks)
    plate = b.region(0, "plate", "the plate", fruit_plate)
    apple = b.region(0, "apple", "a red apple", fruit_plate)
    orange = b.region(0, "orange", "an orange", fruit_plate)
    banana = b.region(0, "banana", "a banana", fruit_plate)

    # ---- room: planes do not cast shadows (the room is closed; the key light is "outside")
    planks = Material(
        tint((0.55, 0.36, 0.20)), "planks", color2=(0.30, 0.18, 0.09), period=0.16, noise=0.10, noise_freq=20.0
    )
    b.add("plane", (0, 0, 0), I, (), planks, obj=floor, casts_shadow=False)
    wallpaper = Material(
        tint((0.82, 0.78, 0.66)),
        "stripes",
        color2=tint((0.55, 0.62, 0.70)),
        period=0.22,
        duty=0.35,
        axis=0,
        noise=0.08,
        noise_freq=12.0,
    )
    add_walls(b, wall, 3.0, 3.0, wallpaper)
    ceiling = Material((0.90, 0.89, 0.86), noise=0.03, noise_freq=5.0)
    b.add("plane", (0, 0, 2.8), I, (), ceiling, obj=wall, casts_shadow=False)

    # ---- table
    cloth = Material(
        tint((0.35, 0.62, 0.38)), "checker", color2=(0.93, 0.93, 0.90), period=0.07, noise=0.05, noise_freq=150.0
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
    b.add("cylinder", (0, 0, TABLE_HEIGHT - 0.02), I, (0.62, 0.02), cloth, part=tabletop, obj=table)
    b.add("cylinder", (0, 0, 0.395), I, (0.05, 0.315), dark_wood, part=table_base, obj=table)
    b.add("cone", (0, 0, 0.04), I, (0.30, 0.06, 0.04), dark_wood, part=table_base, obj=table)

    # ---- teapot: spout along local +x, handle along -x
    add = b.posed(jitter((-0.17, 0.15)), 0.5 + rng.uniform(-0.25, 0.25))
    porcelain = Material(
        tint((0.94, 0.92, 0.86), 0.02),
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
        tint((0.16, 0.28, 0.68)), "dots", color2=(0.85, 0.88, 0.95), period=0.015, duty=0.25, noise=0.05, specular=0.3
    )
    add("ellipsoid", (0, 0, 0.10), I, (0.13, 0.13, 0.10), porcelain, part=pot_body, obj=teapot)
    add("cylinder", (0, 0, 0.197), I, (0.062, 0.012), lid_blue, part=pot_lid, obj=teapot)
    add("ellipsoid", (0, 0, 0.215), I, (0.022, 0.022, 0.017), lid_blue, part=pot_lid, obj=teapot)
    spout_dir = normalize((1.0, 0.0, 1.0))
    add(
        "cone",
        np.array([0.10, 0.0, 0.08]) + 0.075 * spout_dir,
        frame_z(spout_dir),
        (0.034, 0.014, 0.075),
        cream,
        part=pot_spout,
        obj=teapot,
    )
    bar_x = frame_z((1, 0, 0))
    for z in (0.05, 0.15):
        add("cylinder", (-0.155, 0, z), bar_x, (0.014, 0.05), cream, part=pot_handle, obj=teapot)
    add("cylinder", (-0.205, 0, 0.10), I, (0.014, 0.064), cream, part=pot_handle, obj=teapot)

    # ---- mugs (coffee surface slightly above the top cap)
    coffee = Material((0.20, 0.11, 0.06), noise=0.10, noise_freq=200.0, specular=0.5)
    red = Material(
        tint((0.80, 0.12, 0.10)),
        "stripes",
        color2=(0.95, 0.93, 0.90),
        period=0.04,
        duty=0.15,
        axis=2,
        noise=0.05,
        noise_freq=100.0,
        specular=0.3,
    )
    add = b.posed(jitter((0.22, 0.32)), rng.uniform(0, 2 * np.pi))
    add("cylinder", (0, 0, 0.06), I, (0.055, 0.06), red, obj=red_mug)
    add("cylinder", (0, 0, 0.1205), I, (0.047, 0.0015), coffee, obj=red_mug)

    blue = Material(
        tint((0.15, 0.30, 0.80)),
        "dots",
        color2=(0.90, 0.92, 0.98),
        period=0.02,
        duty=0.22,
        noise=0.05,
        noise_freq=100.0,
        specular=0.3,
    )
    white = Material((0.95, 0.95, 0.93), noise=0.04, noise_freq=150.0, specular=0.3)
    add = b.posed(jitter((0.33, 0.03)), -0.3 + rng.uniform(-0.3, 0.3))
    add("cylinder", (0, 0, 0.06), I, (0.055, 0.06), blue, part=blue_body, obj=blue_mug)
    add("cylinder", (0, 0, 0.1205), I, (0.047, 0.0015), coffee, part=blue_body, obj=blue_mug)
    for z in (0.03, 0.095):
        add("cylinder", (0.075, 0, z), bar_x, (0.011, 0.03), white, part=blue_handle, obj=blue_mug)
    add("cylinder", (0.105, 0, 0.0625), I, (0.011, 0.0435), white, part=blue_handle, obj=blue_mug)

    # ---- bag of cookies: a paper bag with two cookies standing up out of it
    kraft = Material(
        tint((0.72, 0.55, 0.36)),
        "stripes",
        color2=(0.55, 0.40, 0.25),
        period=0.035,
        duty=0.12,
        axis=0,
        noise=0.08,
        noise_freq=120.0,
    )
    cookie = Material(
        tint((0.84, 0.62, 0.32)),
        "dots",
        color2=(0.25, 0.14, 0.07),
        period=0.011,
        duty=0.25,
        noise=0.08,
        noise_freq=200.0,
    )
    add = b.posed(jitter((-0.27, -0.22)), 0.4 + rng.uniform(-0.3, 0.3))
    add("box", (0, 0, 0.09), I, (0.07, 0.05, 0.09), kraft, part=bag, obj=cookie_bag)
    for x, y, z, tilt in ((-0.027, 0.0, 0.182, 1.25), (0.026, 0.008, 0.176, 1.15)):
        axis = (0.0, math.sin(tilt), math.cos(tilt))
        add("cylinder", (x, y, z), frame_z(axis), (0.034, 0.007), cookie, part=bag_cookies, obj=cookie_bag)

    # ---- loose cookies lying flat next to the bag
    add = b.posed(jitter((0.0, -0.41), 0.01), rng.uniform(0, 2 * np.pi))
    for x, y in ((-0.06, 0.02), (0.02, 0.05), (0.05, -0.03), (-0.03, -0.06)):
        add("cylinder", (x, y, 0.007), I, (0.034, 0.007), cookie, obj=loose)

    # ---- plate of fruit
    china = Material(
        (0.95, 0.95, 0.95), "rim", color2=(0.20, 0.45, 0.70), period=0.125, noise=0.03, noise_freq=150.0, specular=0.2
    )
    apple_skin = Material(
        tint((0.78, 0.10, 0.08)),
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
    add = b.posed(jitter((0.30, -0.29), 0.01), rng.uniform(0, 2 * np.pi))
    add("cone", (0, 0, 0.012), I, (0.09, 0.14, 0.012), china, part=plate, obj=fruit_plate)
    add("ellipsoid", (-0.045, 0.035, 0.065), I, (0.042, 0.042, 0.040), apple_skin, part=apple, obj=fruit_plate)
    add("cylinder", (-0.045, 0.035, 0.108), I, (0.004, 0.008), stem, part=apple, obj=fruit_plate)
    add("ellipsoid", (0.05, 0.03, 0.069), I, (0.045, 0.045, 0.045), peel, part=orange, obj=fruit_plate)
    add("ellipsoid", (0.0, -0.06, 0.045), rot_z(0.2), (0.075, 0.021, 0.021), banana_skin, part=banana, obj=fruit_plate)

    ids = {r.name: r.id for r in b.regions}
    q = [
        # group level
        Query("tea set", "simple", (tea_set,)),
        Query("snacks", "simple", (snacks,)),
        # object level
        Query("teapot", "simple", (teapot,)),
        Query("mug", "simple", (red_mug, blue_mug)),
        Query("red mug", "compound", (red_mug,)),
        Query("blue mug", "compound", (blue_mug,)),
        Query("table", "simple", (table,)),
        Query("floor", "simple", (floor,)),
        Query("bag of cookies", "compound", (cookie_bag,)),
        Query("loose cookies", "compound", (loose,)),
        Query("plate of fruit", "compound", (fruit_plate,)),
        # part level
        Query("lid of the teapot", "compound", (pot_lid,)),
        Query("spout of the teapot", "compound", (pot_spout,)),
        Query("handle of the teapot", "compound", (pot_handle,)),
        Query("handle of the blue mug", "compound", (blue_handle,)),
        Query("plate", "simple", (plate,)),
        Query("apple", "simple", (apple,)),
        Query("banana", "simple", (banana,)),
        Query("fruit", "simple", (apple, orange, banana)),
        Query("cookies", "simple", (bag_cookies, loose)),  # a part and an object
    ]
    assert all(rid in ids.values() for qq in q for rid in qq.region_ids)
    key = normalize((-0.45, -0.55, 1.0))
    fill = normalize((0.6, 0.5, 0.45))
    return DemoScene(b.primitives, b.regions, q, key, fill)


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
