"""Built-in demo scenes: procedural rooms rendered by an analytic NumPy ray tracer, with
exact ground truth (z-depth, part / object / group ids, captions, LangSplat labels).

Two layouts (``LAYOUTS``). The presets were tuned on ``tabletop`` (the default); ``lounge`` is a
different room, objects and camera path to check them on a scene they were not tuned on.

The ``tabletop`` scene (world z up, metres; a 6 x 6 m room; the table top is at z = 0.75),
seen from a closed ring of views 1.2-1.5 m from the table centre, looking down at it:

* group **the room**: ``floor`` (wooden planks), ``wall`` (striped walls and ceiling: the
  background), ``table`` with parts ``tabletop`` (checkered cloth) and ``table base``.
* group **tea set**: ``teapot`` with parts ``body``, ``lid``, ``spout``, ``handle``;
  ``red mug`` (no parts: its pixels have part id -1); ``blue mug`` with parts ``body`` and a
  white ``handle`` -- two objects that share a noun and differ by attribute.
* group **snacks**: ``bag of cookies`` with parts ``bag`` and ``cookies in the bag`` (the
  partitive case), ``loose cookies`` next to it (no parts), and ``plate of fruit`` with parts
  ``plate``, ``apple``, ``orange``, ``banana`` (the compound case).

The ``lounge`` scene (a 14 x 11 m room, 3.4 m high, so the walls are about twice as far away;
the coffee table top is at z = 0.425), seen from a partial elliptical arc in front of the sofa,
lower than the tabletop's ring, with three stretches of close views:

* group **the living room**: ``floor`` (tiles), ``wall`` (painted walls with a dado, and the
  ceiling), ``rug`` (no parts), ``painting`` with parts ``picture frame`` and ``canvas``.
* group **furniture**: ``sofa`` with parts ``seat``, ``back``, ``arms``; ``yellow cushion`` and
  ``blue cushion`` (no parts; a shared noun); ``coffee table`` with parts ``top`` and ``legs``;
  ``floor lamp`` with parts ``shade``, ``pole``, ``base``.
* group **things on the coffee table**: ``vase of flowers`` (parts ``vase`` and ``flowers``),
  ``stack of books`` (parts ``red book``, ``green book``, ``blue book``: one noun, three
  parts), ``bowl of fruit`` (parts ``bowl``, ``pear``, ``lemon``, ``grapes``), ``toy car``
  (parts ``body``, ``windows``, ``wheels``) and a ``candle`` (no parts).

Every pixel has an object and a group id (the room's floor and walls included, so the
background is labelled too); the part id is -1 on objects without parts.

Region ``extent`` (in ``regions.json``) is the diagonal of the axis-aligned bounding box of the
region's surface points seen at the pixel centres of all views (metres); ``extent_eig`` is the
largest eigenvalue of the covariance of the same points (m^2), and ``extent_diag`` repeats the
diagonal. Use them to rank regions by physical size.

The ray tracer is vectorised over all rays of a view (no per-pixel loops): primitives are
ellipsoids, capped cylinders, capped cone frusta, boxes and planes, each with a rigid local
frame. Rays are culled per object with a bounding sphere. RGB is Lambert + ambient shading with
a shadowed key light and procedural textures (planks, checker, stripes, dots, value noise), and
is averaged over ``supersample x supersample`` samples per pixel (odd, so the pixel centre is
one of them). Depth and ids are taken at the pixel centre ``(i + 0.5, j + 0.5)`` exactly, and
since each ray's camera-space z component is 1, the ray parameter *is* the z-depth.

Public API: :func:`build_demo_scene`, :func:`demo_cameras`, :func:`render_view`,
:func:`generate_demo_scene`, :func:`write_contact_sheet`.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Sequence

import numpy as np
from numpy.typing import ArrayLike

from ..cameras import Camera, look_at
from ..io import atomic_path, write_json, write_npy, write_png
from . import labels as labels_mod

LEVELS = ("part", "object", "group")
GENERATOR = "n2f2.data.synthetic"
GENERATOR_VERSION = 1
LAYOUTS = ("tabletop", "lounge")
TABLE_HEIGHT = 0.75  # tabletop layout: height of the table top
LOUNGE_TABLE_HEIGHT = 0.425  # lounge layout: height of the coffee table top
_EPS = 1e-7  # minimum ray parameter of a hit (metres along a unit-z ray)


# ============================================================================= scene description
@dataclass(frozen=True)
class Material:
    """Procedural surface colour, evaluated in the primitive's local frame (so patterns move
    with the object). ``pattern`` is one of:

    * ``plain``: ``color``;
    * ``checker``: squares of side ``period`` in local x/y, ``color`` / ``color2``;
    * ``stripes``: bands across local axis ``axis`` with period ``period``, ``color2`` on a
      fraction ``duty`` of each period;
    * ``planks``: floor boards ``period`` wide along local y, with per-board tint and grain;
    * ``dots``: blobs of ``color2`` where value noise at frequency 1 / ``period`` exceeds
      ``1 - duty``;
    * ``rim``: ``color2`` where the radial distance from the local z axis exceeds ``period``.

    Everything is multiplied by ``1 + noise * (2 * value_noise - 1)`` at frequency
    ``noise_freq`` (1/m), which gives 3DGS high-frequency content to fit.
    """

    color: tuple[float, float, float]
    pattern: str = "plain"
    color2: tuple[float, float, float] = (1.0, 1.0, 1.0)
    period: float = 0.05
    duty: float = 0.5
    axis: int = 2
    noise: float = 0.06
    noise_freq: float = 80.0
    specular: float = 0.0  # Blinn-Phong weight of the key light


@dataclass(frozen=True)
class Primitive:
    """A solid with a rigid local frame: ``x_local = rotation.T @ (x_world - center)``.

    ``size`` by ``kind`` (local frame, metres):

    * ``ellipsoid``: ``(rx, ry, rz)`` radii;
    * ``cylinder``: ``(r, half_height)``, axis = local z, capped at z = +-half_height;
    * ``cone``: ``(r_bottom, r_top, half_height)``, a capped frustum, radius r_bottom at
      z = -half_height and r_top at +half_height;
    * ``box``: ``(hx, hy, hz)`` half extents;
    * ``plane``: ``()``; the plane z_local = 0 (both sides), infinite.
    """

    kind: str
    center: np.ndarray  # [3] world
    rotation: np.ndarray  # [3, 3] columns = local axes in world coordinates
    size: tuple[float, ...]
    material: Material
    part: int = -1  # region ids (see Region); -1 = none
    object: int = -1
    group: int = -1
    casts_shadow: bool = True

    def to_local(self, points: np.ndarray) -> np.ndarray:  # points [..., 3] -> [..., 3]
        return (points - self.center) @ self.rotation

    def bounding_radius(self) -> float:
        s = self.size
        if self.kind == "ellipsoid":
            return float(max(s))
        if self.kind == "cylinder":
            return float(math.hypot(s[0], s[1]))
        if self.kind == "cone":
            return float(math.hypot(max(s[0], s[1]), s[2]))
        if self.kind == "box":
            return float(np.linalg.norm(s))
        return math.inf


@dataclass(frozen=True)
class Region:
    """A node of the group > object > part hierarchy."""

    id: int
    level: int  # 0 = part, 1 = object, 2 = group
    name: str
    caption: str
    parent: Optional[int]  # object -> group, part -> object, group -> None


@dataclass(frozen=True)
class Query:
    query: str
    type: str  # "simple" | "compound"
    region_ids: tuple[int, ...]


@dataclass
class DemoScene:
    primitives: list[Primitive]
    regions: list[Region]
    queries: list[Query]
    key_light: np.ndarray  # [3] unit vector towards the light (casts shadows)
    fill_light: np.ndarray  # [3] unit vector (no shadows)
    key_intensity: float = 0.72
    fill_intensity: float = 0.22
    ambient: float = 0.30
    _region_index: dict = field(default_factory=dict, repr=False)

    def region(self, name_or_id: str | int) -> Region:
        if not self._region_index:
            self._region_index.update({r.id: r for r in self.regions})
            self._region_index.update({r.name: r for r in self.regions})
        return self._region_index[name_or_id]

    def id_table(self) -> np.ndarray:  # [P, 3] int32 (part, object, group) per primitive
        return np.array([[p.part, p.object, p.group] for p in self.primitives], dtype=np.int32)


# ----------------------------------------------------------------------------- geometry helpers
def _rot_z(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _frame_z(axis: ArrayLike) -> np.ndarray:  # axis [3]
    """A rotation whose third column (local z) is ``axis``."""
    z = np.asarray(axis, dtype=np.float64)
    z = z / np.linalg.norm(z)
    helper = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z], axis=1)


def _normalize(v: ArrayLike) -> np.ndarray:  # v [3]
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v)


class _Builder:
    """Collects regions and primitives; objects are modelled in a local frame standing on the
    table (origin on the table surface) and posed with a yaw and an (x, y) position."""

    def __init__(self) -> None:
        self.regions: list[Region] = []
        self.primitives: list[Primitive] = []

    def region(self, level: int, name: str, caption: str, parent: Optional[int]) -> int:
        rid = len(self.regions)
        self.regions.append(Region(rid, level, name, caption, parent))
        return rid

    def add(
        self,
        kind: str,
        center,
        rotation,
        size,
        material: Material,
        *,
        part: int = -1,
        obj: int,
        casts_shadow: bool = True,
    ) -> None:
        group = self.regions[obj].parent
        self.primitives.append(
            Primitive(
                kind,
                np.asarray(center, dtype=np.float64),
                np.asarray(rotation, dtype=np.float64),
                tuple(float(s) for s in size),
                material,
                part,
                obj,
                -1 if group is None else group,
                casts_shadow,
            )
        )

    def posed(self, xy: np.ndarray | Sequence[float], yaw: float, z0: float = TABLE_HEIGHT):  # xy [2]
        """Returns ``add_local(kind, center_local, rotation_local, size, material, ...)``."""
        R = _rot_z(yaw)
        offset = np.array([xy[0], xy[1], z0])

        def add_local(kind, center, rotation, size, material, **kw):
            self.add(
                kind,
                R @ np.asarray(center, dtype=np.float64) + offset,
                R @ np.asarray(rotation, dtype=np.float64),
                size,
                material,
                **kw,
            )

        return add_local


def _add_walls(b: _Builder, wall: int, half_x: float, half_y: float, material: Material) -> None:
    """Four vertical wall planes at x = +-half_x and y = +-half_y (local x horizontal, local y
    = world z, local z = the inward normal); they cast no shadows."""
    for normal, axis_x in (
        ((1, 0, 0), (0, 1, 0)),
        ((-1, 0, 0), (0, -1, 0)),
        ((0, 1, 0), (-1, 0, 0)),
        ((0, -1, 0), (1, 0, 0)),
    ):
        n = np.asarray(normal, dtype=np.float64)
        x = np.asarray(axis_x, dtype=np.float64)
        rot = np.stack([x, np.cross(n, x), n], axis=1)
        half = half_x if n[0] else half_y
        b.add("plane", -half * n, rot, (), material, obj=wall, casts_shadow=False)


# ----------------------------------------------------------------------------- the demo scenes
def build_demo_scene(seed: int = 0, layout: str = "tabletop") -> DemoScene:
    """The demo scene of a layout (``LAYOUTS``): ``tabletop`` (the default) or ``lounge``.
    ``seed`` jitters object positions, orientations and colours a little; the hierarchy,
    captions and queries of a layout are the same for every seed."""
    if layout == "tabletop":
        return _tabletop_scene(seed)
    if layout == "lounge":
        return _lounge_scene(seed)
    raise ValueError(f"unknown demo layout {layout!r}; choose one of {', '.join(LAYOUTS)}")


def _tabletop_scene(seed: int) -> DemoScene:
    """The tabletop: a 6 x 6 m room, 2.8 m high, with a round table holding a tea set and
    snacks."""
    rng = np.random.default_rng([int(seed), 7])
    b = _Builder()
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
    _add_walls(b, wall, 3.0, 3.0, wallpaper)
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
    spout_dir = _normalize((1.0, 0.0, 1.0))
    add(
        "cone",
        np.array([0.10, 0.0, 0.08]) + 0.075 * spout_dir,
        _frame_z(spout_dir),
        (0.034, 0.014, 0.075),
        cream,
        part=pot_spout,
        obj=teapot,
    )
    bar_x = _frame_z((1, 0, 0))
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
        add("cylinder", (x, y, z), _frame_z(axis), (0.034, 0.007), cookie, part=bag_cookies, obj=cookie_bag)

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
    add("ellipsoid", (0.0, -0.06, 0.045), _rot_z(0.2), (0.075, 0.021, 0.021), banana_skin, part=banana, obj=fruit_plate)

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
    key = _normalize((-0.45, -0.55, 1.0))
    fill = _normalize((0.6, 0.5, 0.45))
    return DemoScene(b.primitives, b.regions, q, key, fill)


def _lounge_scene(seed: int) -> DemoScene:
    """The lounge: a room about 2.3 x 1.8 times the tabletop's (14 x 11 m, 3.4 m high) with a
    sofa, a floor lamp, a rug, a painting and a low coffee table holding small objects."""
    rng = np.random.default_rng([int(seed), 17])
    b = _Builder()
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
    _add_walls(b, wall, 7.0, 5.5, paint)
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
            "ellipsoid", (xy[0], xy[1], 0.62), _rot_z(rng.uniform(-0.15, 0.15)) @ lean, (0.23, 0.08, 0.19), mat, obj=obj
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
        axis = _normalize((0.35 * math.cos(ang), 0.35 * math.sin(ang), 1.0))
        base = np.array([0.0, 0.0, 0.24])
        add("cylinder", base + 0.09 * axis, _frame_z(axis), (0.006, 0.09), stem, part=flowers, obj=vase_of_flowers)
        add(
            "ellipsoid",
            base + 0.19 * axis,
            _frame_z(axis),
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
        add("box", (0, 0, z + hz), _rot_z(yaw), (hx, hy, hz), mat, part=part, obj=books)
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
    add("ellipsoid", (0.05, 0.03, 0.107), _rot_z(0.6), (0.048, 0.032, 0.032), lemon_skin, part=lemon, obj=fruit_bowl)
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
    axle = _frame_z((0, 1, 0))
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
    key = _normalize((0.5, -0.35, 1.0))
    fill = _normalize((-0.6, -0.7, 0.5))
    return DemoScene(b.primitives, b.regions, q, key, fill)


def demo_cameras(
    num_views: int = 40,
    width: int = 160,
    height: int = 120,
    seed: int = 0,
    hfov_deg: float = 60.0,
    layout: str = "tabletop",
) -> list[Camera]:
    """The views of a layout's camera path. PINHOLE, centred principal point."""
    if layout == "tabletop":
        return _tabletop_cameras(num_views, width, height, seed, hfov_deg)
    if layout == "lounge":
        return _lounge_cameras(num_views, width, height, seed, hfov_deg)
    raise ValueError(f"unknown demo layout {layout!r}; choose one of {', '.join(LAYOUTS)}")


def _tabletop_cameras(num_views: int, width: int, height: int, seed: int, hfov_deg: float) -> list[Camera]:
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


def _lounge_cameras(num_views: int, width: int, height: int, seed: int, hfov_deg: float) -> list[Camera]:
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


# ============================================================================= ray tracing
def _solve_quadratic(a: np.ndarray, b: np.ndarray, c: np.ndarray):
    """Roots t1 <= t2 of a t^2 + b t + c = 0 (NaN where there are none). [N] each."""
    disc = b * b - 4 * a * c
    ok = disc >= 0
    sq = np.sqrt(np.where(ok, disc, 0.0))
    # numerically stable form: q = -(b + sign(b) sqrt(disc)) / 2, roots q / a and c / q
    q = -0.5 * (b + np.where(b >= 0, sq, -sq))
    with np.errstate(divide="ignore", invalid="ignore"):
        r1 = q / a
        r2 = c / q
    t1 = np.minimum(r1, r2)
    t2 = np.maximum(r1, r2)
    t1 = np.where(ok, t1, np.nan)
    t2 = np.where(ok, t2, np.nan)
    return t1, t2


def _nearest(*candidates: np.ndarray) -> np.ndarray:
    """Smallest candidate > _EPS per ray (inf if none). NaN means no candidate."""
    out = None
    for c in candidates:
        c = np.where(np.isfinite(c) & (c > _EPS), c, np.inf)
        out = c if out is None else np.minimum(out, c)
    assert out is not None  # every caller passes at least one candidate
    return out


def intersect(
    prim: Primitive,
    origins: np.ndarray,  # [N, 3] or [1, 3] (shared) world
    dirs: np.ndarray,  # [N, 3] world (any length; t is in units of |dir|)
) -> np.ndarray:  # [N] ray parameter of the nearest hit > eps, inf if none
    """Nearest intersection of rays ``o + t d`` with a primitive (rays may start inside)."""
    if prim.kind == "plane":  # only the normal component matters
        normal = prim.rotation[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            return _nearest(((prim.center - origins) @ normal) / (dirs @ normal))
    o = (origins - prim.center) @ prim.rotation  # [N|1, 3]
    d = dirs @ prim.rotation
    ox, oy, oz = o[:, 0], o[:, 1], o[:, 2]
    dx, dy, dz = d[:, 0], d[:, 1], d[:, 2]
    s = prim.size
    with np.errstate(divide="ignore", invalid="ignore"):
        if prim.kind == "ellipsoid":
            r = np.asarray(s)
            os_, ds = o / r, d / r
            t1, t2 = _solve_quadratic((ds * ds).sum(1), 2 * (os_ * ds).sum(1), (os_ * os_).sum(1) - 1)
            return _nearest(t1, t2)
        if prim.kind == "box":
            h = np.asarray(s)
            inv = 1.0 / d
            ta = (-h - o) * inv
            tb = (h - o) * inv
            tmin = np.nanmax(np.minimum(ta, tb), axis=1)
            tmax = np.nanmin(np.maximum(ta, tb), axis=1)
            hit = tmax >= tmin
            return _nearest(np.where(hit, tmin, np.nan), np.where(hit, tmax, np.nan))
        if prim.kind == "cylinder":
            r, hh = s
            rb = rt = r
        elif prim.kind == "cone":
            rb, rt, hh = s
        else:
            raise ValueError(f"unknown primitive kind {prim.kind!r}")
        # side: x^2 + y^2 = (rm + k z)^2 for |z| <= hh (a cylinder has k = 0)
        rm, k = 0.5 * (rb + rt), (rt - rb) / (2 * hh)
        rz = rm + k * oz
        a = dx * dx + dy * dy - (k * dz) ** 2
        bq = 2 * (ox * dx + oy * dy - k * dz * rz)
        c = ox * ox + oy * oy - rz * rz
        t1, t2 = _solve_quadratic(a, bq, c)
        side = []
        for t in (t1, t2):
            z = oz + t * dz
            side.append(np.where(np.abs(z) <= hh, t, np.nan))
        caps = []
        for zc, rc in ((-hh, rb), (hh, rt)):
            t = (zc - oz) / dz
            x, y = ox + t * dx, oy + t * dy
            caps.append(np.where(x * x + y * y <= rc * rc, t, np.nan))
        return _nearest(*side, *caps)


def local_normals(prim: Primitive, pl: np.ndarray) -> np.ndarray:
    """Outward unit normals [N, 3] (local frame) at local surface points ``pl`` [N, 3]."""
    s = prim.size
    if prim.kind == "plane":
        n = np.zeros_like(pl)
        n[:, 2] = 1.0
        return n
    if prim.kind == "ellipsoid":
        n = pl / np.asarray(s) ** 2
    elif prim.kind == "box":
        h = np.asarray(s)
        rel = np.abs(pl) / h
        axis = np.argmax(rel, axis=1)
        n = np.zeros_like(pl)
        n[np.arange(len(pl)), axis] = np.sign(pl[np.arange(len(pl)), axis])
    else:
        if prim.kind == "cylinder":
            rb = rt = s[0]
            hh = s[1]
        else:
            rb, rt, hh = s
        k = (rt - rb) / (2 * hh)
        rz = 0.5 * (rb + rt) + k * pl[:, 2]
        rho = np.sqrt(pl[:, 0] ** 2 + pl[:, 1] ** 2)
        side_n = np.stack([pl[:, 0], pl[:, 1], -k * rz], 1)
        on_cap = np.abs(np.abs(pl[:, 2]) - hh) < np.abs(rho - rz)
        cap_n = np.zeros_like(pl)
        cap_n[:, 2] = np.sign(pl[:, 2])
        n = np.where(on_cap[:, None], cap_n, side_n)
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)


@dataclass
class _Cluster:
    """Primitives of one object with a bounding sphere (planes: unbounded)."""

    indices: list[int]
    center: Optional[np.ndarray]  # [3]; None = never culled
    radius: float


def _clusters(prims: Sequence[Primitive], shadow_only: bool = False) -> list[_Cluster]:
    out: list[_Cluster] = []
    by_obj: dict[int, list[int]] = {}
    for i, p in enumerate(prims):
        if shadow_only and not p.casts_shadow:
            continue
        if p.kind == "plane":
            out.append(_Cluster([i], None, math.inf))
        else:
            by_obj.setdefault(p.object, []).append(i)
    for idx in by_obj.values():
        centers = np.stack([prims[i].center for i in idx])
        c = centers.mean(axis=0)
        r = max(float(np.linalg.norm(prims[i].center - c)) + prims[i].bounding_radius() for i in idx)
        out.append(_Cluster(idx, c, r * 1.0001))
    return out


def _sphere_candidates(
    center: np.ndarray,
    radius: float,
    origins: np.ndarray,  # [N, 3]
    dirs: np.ndarray,  # [N, 3]
    t_best: np.ndarray,  # [N]
) -> np.ndarray:  # [M] indices of rays that may hit inside the sphere
    oc = origins - center
    a = (dirs * dirs).sum(1)
    bh = (oc * dirs).sum(1)
    c = (oc * oc).sum(1) - radius * radius
    disc = bh * bh - a * c
    sq = np.sqrt(np.maximum(disc, 0.0))
    t_near = (-bh - sq) / a
    t_far = (-bh + sq) / a
    return np.nonzero((disc >= 0) & (t_far > _EPS) & (t_near < t_best))[0]


def trace(
    scene: DemoScene,
    origins: np.ndarray,  # [N, 3], or [3] shared by all rays
    dirs: np.ndarray,  # [N, 3]
) -> tuple[np.ndarray, np.ndarray]:
    """Nearest hit of each ray: ray parameter t [N] (inf if none) and primitive index [N]
    (-1 if none)."""
    dirs = np.asarray(dirs, dtype=np.float64)
    origins = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
    shared = len(origins) == 1  # primary rays: keep one origin and let broadcasting work
    n = len(dirs)
    t_best = np.full(n, np.inf)
    p_best = np.full(n, -1, dtype=np.int64)
    for cl in _clusters(scene.primitives):
        if cl.center is None:  # unbounded (planes): every ray, no gather / scatter
            for i in cl.indices:
                t = intersect(scene.primitives[i], origins, dirs)
                better = t < t_best
                t_best[better] = t[better]
                p_best[better] = i
            continue
        sel = _sphere_candidates(cl.center, cl.radius, origins, dirs, t_best)
        if len(sel) == 0:
            continue
        o_s, d_s = (origins if shared else origins[sel]), dirs[sel]
        for i in cl.indices:
            t = intersect(scene.primitives[i], o_s, d_s)
            better = t < t_best[sel]
            t_best[sel[better]] = t[better]
            p_best[sel[better]] = i
    return t_best, p_best


def occluded(
    scene: DemoScene,
    origins: np.ndarray,  # [N, 3]
    direction: np.ndarray,  # [3] unit vector towards a directional light
) -> np.ndarray:  # [N] bool
    """Whether anything that casts shadows lies between each origin and the light."""
    dirs = np.broadcast_to(direction, origins.shape)
    blocked = np.zeros(len(origins), dtype=bool)
    far = np.full(len(origins), np.inf)
    for cl in _clusters(scene.primitives, shadow_only=True):
        if cl.center is None:
            sel = np.arange(len(origins))
        else:
            sel = _sphere_candidates(cl.center, cl.radius, origins, dirs, far)
        sel = sel[~blocked[sel]]
        if len(sel) == 0:
            continue
        hit = np.zeros(len(sel), dtype=bool)
        for i in cl.indices:
            hit |= np.isfinite(intersect(scene.primitives[i], origins[sel], dirs[sel]))
        blocked[sel[hit]] = True
    return blocked


# ============================================================================= textures
def _hash_float(ix: np.ndarray, iy: np.ndarray, iz: np.ndarray, seed: int) -> np.ndarray:
    """Deterministic integer hash of lattice coordinates -> float in [0, 1)."""
    h = np.full(ix.shape, (int(seed) * 0x9E3779B1 + 0x7F4A7C15) & 0xFFFFFFFF, dtype=np.uint32)
    for v, mult in ((ix, 0x85EBCA6B), (iy, 0xC2B2AE35), (iz, 0x27D4EB2F)):
        h ^= (v.astype(np.int64) & 0xFFFFFFFF).astype(np.uint32) * np.uint32(mult)
        h ^= h >> np.uint32(15)
        h *= np.uint32(0x2C1B3C6D)
        h ^= h >> np.uint32(12)
    h ^= h >> np.uint32(16)
    return h.astype(np.float64) / 4294967296.0


def value_noise(
    points: np.ndarray,  # [N, 3]
    freq: float,
    seed: int,
) -> np.ndarray:  # [N] in [0, 1]
    """Smooth 3D value noise (trilinear interpolation of hashed lattice values)."""
    q = points * freq
    i0 = np.floor(q)
    f = q - i0
    f = f * f * (3 - 2 * f)
    i0 = i0.astype(np.int64)
    out = np.zeros(len(points))
    for cx in (0, 1):
        wx = f[:, 0] if cx else 1 - f[:, 0]
        for cy in (0, 1):
            wy = f[:, 1] if cy else 1 - f[:, 1]
            for cz in (0, 1):
                wz = f[:, 2] if cz else 1 - f[:, 2]
                out += wx * wy * wz * _hash_float(i0[:, 0] + cx, i0[:, 1] + cy, i0[:, 2] + cz, seed)
    return out


def albedo(
    material: Material,
    pl: np.ndarray,  # [N, 3] local surface points
    seed: int,
) -> np.ndarray:  # [N, 3] in [0, 1]
    m = material
    c1 = np.asarray(m.color)
    c2 = np.asarray(m.color2)
    if m.pattern == "plain":
        w = np.zeros(len(pl))
    elif m.pattern == "checker":
        w = ((np.floor(pl[:, 0] / m.period) + np.floor(pl[:, 1] / m.period)) % 2).astype(np.float64)
    elif m.pattern == "stripes":
        w = ((pl[:, m.axis] / m.period) % 1.0 < m.duty).astype(np.float64)
    elif m.pattern == "dots":
        w = (value_noise(pl, 1.0 / m.period, seed + 101) > 1.0 - m.duty).astype(np.float64)
    elif m.pattern == "rim":
        w = (np.hypot(pl[:, 0], pl[:, 1]) > m.period).astype(np.float64)
    elif m.pattern == "planks":
        board = np.floor(pl[:, 1] / m.period)
        zeros = np.zeros_like(board, dtype=np.int64)
        shade = 0.8 + 0.4 * _hash_float(board.astype(np.int64), zeros, zeros, seed + 202)
        grain = 0.5 + 0.5 * np.sin(pl[:, 1] * 180.0 + 6.0 * value_noise(pl * [0.3, 1, 1], 8.0, seed + 203))
        w = 0.55 * grain**6
        gap = (pl[:, 1] / m.period) % 1.0 < 0.04
        w = np.where(gap, 1.0, w)
        col = (c1 * (1 - w[:, None]) + c2 * w[:, None]) * shade[:, None]
        return np.clip(col * _noise_factor(m, pl, seed)[:, None], 0, 1)
    else:
        raise ValueError(f"unknown texture pattern {m.pattern!r}")
    col = c1 * (1 - w[:, None]) + c2 * w[:, None]
    return np.clip(col * _noise_factor(m, pl, seed)[:, None], 0, 1)


def _noise_factor(m: Material, pl: np.ndarray, seed: int) -> np.ndarray:
    if m.noise <= 0:
        return np.ones(len(pl))
    return 1.0 + m.noise * (2.0 * value_noise(pl, m.noise_freq, seed + 303) - 1.0)


# ============================================================================= rendering
@dataclass
class ViewRender:
    rgb: np.ndarray  # [H, W, 3] float32 in [0, 1] (supersampled)
    depth: np.ndarray  # [H, W] float64 z-depth at pixel centres
    primitive: np.ndarray  # [H, W] int64 primitive index at pixel centres
    regions: np.ndarray  # [3, H, W] int32 (part, object, group) at pixel centres
    points: np.ndarray  # [H, W, 3] float64 world hit points at pixel centres


def render_view(
    scene: DemoScene, camera: Camera, supersample: int = 3, seed: int = 0, chunk: int = 16384
) -> ViewRender:
    """Ray-trace one view. ``supersample`` must be odd: the RGB is the mean of an
    ``s x s`` grid of samples per pixel whose middle sample is the pixel centre, where depth,
    ids and surface points are taken."""
    s = int(supersample)
    if s < 1 or s % 2 == 0:
        raise ValueError(f"supersample must be an odd positive integer, got {supersample}")
    H, W = camera.height, camera.width
    offs = (np.arange(s) + 0.5) / s  # middle one is exactly 0.5
    u = (np.arange(W)[:, None] + offs[None, :]).reshape(-1)  # [W*s]
    v = (np.arange(H)[:, None] + offs[None, :]).reshape(-1)  # [H*s]
    uu, vv = np.meshgrid(u, v)  # [H*s, W*s]
    d_cam = np.stack([(uu - camera.cx) / camera.fx, (vv - camera.cy) / camera.fy, np.ones_like(uu)], axis=-1).reshape(
        -1, 3
    )
    dirs = d_cam @ camera.R  # R^T d: camera z component stays 1, so t = z-depth
    origin = camera.center
    # Chunks of rays keep NumPy's temporaries in cache (about 2x faster than one big batch).
    n = len(dirs)
    t = np.empty(n)
    prim = np.empty(n, dtype=np.int64)
    rgb = np.empty((n, 3))
    for a in range(0, n, chunk):
        b_ = min(n, a + chunk)
        t[a:b_], prim[a:b_] = trace(scene, origin, dirs[a:b_])
        pts = origin + t[a:b_, None] * dirs[a:b_]
        if not np.isfinite(pts).all():
            raise RuntimeError("a ray left the room; the demo scene should be closed")
        rgb[a:b_] = _shade(scene, pts, dirs[a:b_], prim[a:b_], seed)
    points = origin + t[:, None] * dirs

    rgb = rgb.reshape(H, s, W, s, 3).mean(axis=(1, 3)).astype(np.float32)
    c = s // 2
    centre = lambda a: a.reshape(H, s, W, s, *a.shape[1:])[:, c, :, c]  # noqa: E731
    prim_c = centre(prim)
    ids = scene.id_table()[prim_c]  # [H, W, 3]
    return ViewRender(
        rgb=rgb,
        depth=centre(t),
        primitive=prim_c,
        regions=np.ascontiguousarray(ids.transpose(2, 0, 1)).astype(np.int32),
        points=centre(points),
    )


def _shade(
    scene: DemoScene,
    points: np.ndarray,  # [N, 3]
    dirs: np.ndarray,  # [N, 3]
    prim: np.ndarray,  # [N]
    seed: int,
) -> np.ndarray:  # [N, 3]
    n = len(points)
    normals = np.zeros((n, 3))
    base = np.zeros((n, 3))
    spec_w = np.zeros(n)
    order = np.argsort(prim, kind="stable")
    bounds = np.searchsorted(prim[order], np.arange(len(scene.primitives) + 1))
    for i, p in enumerate(scene.primitives):
        sel = order[bounds[i] : bounds[i + 1]]
        if len(sel) == 0:
            continue
        pl = p.to_local(points[sel])
        normals[sel] = local_normals(p, pl) @ p.rotation.T
        base[sel] = albedo(p.material, pl, seed)
        spec_w[sel] = p.material.specular
    view = -dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    # two-sided surfaces: the normal faces the viewer
    flip = (normals * view).sum(1) < 0
    normals[flip] *= -1
    key = scene.key_light
    ndl_key = normals @ key
    lit = ndl_key > 0
    shadow = np.zeros(n, dtype=bool)
    idx = np.nonzero(lit)[0]
    shadow[idx] = occluded(scene, points[idx] + 1e-5 * normals[idx], key)
    vis = (lit & ~shadow).astype(np.float64)
    ndl_fill = np.maximum(normals @ scene.fill_light, 0.0)
    light = scene.ambient + scene.key_intensity * np.maximum(ndl_key, 0) * vis + scene.fill_intensity * ndl_fill
    half = view + key
    half /= np.maximum(np.linalg.norm(half, axis=1, keepdims=True), 1e-12)
    spec = spec_w * np.maximum((normals * half).sum(1), 0.0) ** 40 * vis
    return np.clip(base * light[:, None] + spec[:, None], 0.0, 1.0)


# ============================================================================= writing a scene
class _RegionStats:
    """Running sums for the covariance and bounding box of each region's surface points."""

    def __init__(self, num_regions: int) -> None:
        r = self.num_regions = num_regions
        self.count = np.zeros(r)  # [R]
        self.s1 = np.zeros((r, 3))  # [R, 3] sum of points
        self.s2 = np.zeros((r, 3, 3))  # [R, 3, 3] sum of outer products
        self.lo = np.full((r, 3), np.inf)  # [R, 3] bbox
        self.hi = np.full((r, 3), -np.inf)

    def add(
        self,
        regions: np.ndarray,  # [3, H, W]
        points: np.ndarray,  # [H, W, 3]
    ) -> None:
        pts = points.reshape(-1, 3)
        outer = (pts[:, :, None] * pts[:, None, :]).reshape(-1, 9)
        for level in range(regions.shape[0]):
            ids = regions[level].reshape(-1)
            ok = ids >= 0
            ids_ok, p_ok = ids[ok], pts[ok]
            r = self.num_regions
            self.count += np.bincount(ids_ok, minlength=r)
            for k in range(3):
                self.s1[:, k] += np.bincount(ids_ok, weights=p_ok[:, k], minlength=r)
            o = outer[ok]
            for k in range(9):
                self.s2[:, k // 3, k % 3] += np.bincount(ids_ok, weights=o[:, k], minlength=r)
            np.minimum.at(self.lo, ids_ok, p_ok)
            np.maximum.at(self.hi, ids_ok, p_ok)

    def extents(self) -> tuple[np.ndarray, np.ndarray]:
        """(largest covariance eigenvalue [R], bbox diagonal [R]); NaN for unseen regions."""
        cnt = np.maximum(self.count, 1)[:, None]
        mean = self.s1 / cnt
        cov = self.s2 / cnt[:, :, None] - mean[:, :, None] * mean[:, None, :]
        eig = np.linalg.eigvalsh(cov)[:, -1]
        diag = np.linalg.norm(self.hi - self.lo, axis=1)
        seen = self.count > 0
        return np.where(seen, np.maximum(eig, 0.0), np.nan), np.where(seen, diag, np.nan)


def _default_labelled_views(num_views: int) -> list[int]:
    step = max(1, num_views // 8)
    return list(range(step // 2, num_views, step))[:8]


def generate_demo_scene(
    out_dir: str | Path,
    *,
    num_views: int = 40,
    width: int = 160,
    height: int = 120,
    seed: int = 0,
    labelled_views: Optional[Sequence[int]] = None,
    supersample: int = 3,
    num_points: int = 4000,
    show_progress: bool = True,
    layout: str = "tabletop",
) -> Path:
    """Render the demo scene of ``layout`` (``LAYOUTS``) and write it as a normal scene folder (layout in
    docs/architecture.md): images, ``transforms.json``, COLMAP text, depth, region ids,
    ``regions.json``, ``queries.json``, LangSplat labels and ``scene.json``.

    Also writes ``points_source.npy`` (int32 [P, 3]: view index, row, column of the pixel
    centre each sparse point was traced from; sparse points are in COLMAP point-id order).

    Defaults: 40 views of 160x120, 3x3 supersampling, labels on 8 spread-out views, and every
    8th view (index % 8 == 0) held out for testing. Re-generating into a folder that holds a
    demo scene replaces it; any other non-empty folder is refused (InputError). ``scene.json``
    is written last: a folder without it is an interrupted generation. It records the
    ``layout`` (scenes written before layouts existed have none: they are tabletops).
    """
    from tqdm import tqdm

    from .colmap import write_colmap_text
    from .nerfstudio import write_transforms

    out = Path(out_dir)
    if num_views < 1 or width < 8 or height < 8:
        raise ValueError("the demo scene needs at least 1 view of at least 8x8 pixels")
    if layout not in LAYOUTS:
        raise ValueError(f"unknown demo layout {layout!r}; choose one of {', '.join(LAYOUTS)}")
    _prepare_output_dir(out)
    if labelled_views is None:
        labelled_views = _default_labelled_views(num_views)
    labelled_views = sorted({int(v) for v in labelled_views})
    if labelled_views and not (0 <= labelled_views[0] and labelled_views[-1] < num_views):
        raise ValueError(f"labelled views must be in [0, {num_views}), got {labelled_views}")
    start = time.perf_counter()

    scene = build_demo_scene(seed, layout)
    cameras = demo_cameras(num_views, width, height, seed, layout=layout)
    names = [labels_mod.frame_name(i) for i in range(num_views)]
    stats = _RegionStats(len(scene.regions))
    rng = np.random.default_rng([int(seed), 13])
    per_view = int(math.ceil(num_points / num_views))
    pts, cols, src = [], [], []
    labelled_regions = {}

    for i in tqdm(range(num_views), desc=f"rendering demo scene ({layout})", disable=not show_progress):
        view = render_view(scene, cameras[i], supersample=supersample, seed=seed)
        rgb8 = (np.clip(view.rgb, 0, 1) * 255.0 + 0.5).astype(np.uint8)
        write_png(out / "images" / f"{names[i]}.png", rgb8)
        write_npy(out / "depth" / f"{names[i]}.npy", view.depth.astype(np.float32))
        write_npy(out / "regions" / f"{names[i]}.npy", view.regions)
        stats.add(view.regions, view.points)
        pick = rng.choice(width * height, size=min(per_view, width * height), replace=False)
        rows, colsi = np.divmod(np.sort(pick), width)
        pts.append(view.points[rows, colsi])
        cols.append(rgb8[rows, colsi])
        src.append(np.stack([np.full_like(rows, i), rows, colsi], axis=1))
        if i in labelled_views:
            labelled_regions[i] = (view.regions, rgb8)

    points = np.concatenate(pts)[:num_points]
    colors = np.concatenate(cols)[:num_points]
    sources = np.concatenate(src)[:num_points].astype(np.int32)

    image_files = [f"{n}.png" for n in names]
    write_colmap_text(out / "sparse" / "0", cameras, image_files, points=points, colors=colors)
    write_transforms(
        out / "transforms.json", cameras, [f"images/{f}" for f in image_files], points=points, colors=colors
    )
    write_npy(out / "points_source.npy", sources)

    eig, diag = stats.extents()
    regions_json = {
        "levels": list(LEVELS),
        "extent_definition": "extent = extent_diag = bbox diagonal (m) of the region's surface points at the "
        "pixel centres of all views; extent_eig = largest eigenvalue (m^2) of their covariance",
        "regions": [
            {
                "id": r.id,
                "level": r.level,
                "name": r.name,
                "caption": r.caption,
                "parent": r.parent,
                "extent": _num(diag[r.id]),
                "extent_eig": _num(eig[r.id]),
                "extent_diag": _num(diag[r.id]),
                "pixels": int(stats.count[r.id]),
            }
            for r in scene.regions
        ],
    }
    write_json(out / "regions.json", regions_json)
    write_json(
        out / "queries.json",
        {"queries": [{"query": q.query, "type": q.type, "region_ids": list(q.region_ids)} for q in scene.queries]},
    )

    for i, (reg, rgb8) in labelled_regions.items():
        masks = {q.query: query_mask(reg, scene.regions, q.region_ids) for q in scene.queries}
        fl = labels_mod.labels_from_masks(names[i], masks)
        labels_mod.write_frame_labels(out / "label" / f"{names[i]}.json", fl)
        _write_jpeg(out / "label" / f"{names[i]}.jpg", rgb8)  # as in LangSplat's label folders

    write_json(
        out / "scene.json",
        {
            "generator": GENERATOR,
            "version": GENERATOR_VERSION,
            "layout": layout,
            "seed": int(seed),
            "num_views": num_views,
            "width": width,
            "height": height,
            "supersample": supersample,
            "camera_model": "PINHOLE",
            "up": [0.0, 0.0, 1.0],
            "depth": "z-depth (metres)",
            "test_views": [i for i in range(num_views) if i % 8 == 0],
            "labelled_views": labelled_views,
            "num_points": int(len(points)),
            "points_source": "points_source.npy",
        },
    )
    if show_progress:
        print(
            f"demo scene ({layout}): {num_views} views of {width}x{height} written to {out} "
            f"in {time.perf_counter() - start:.1f} s"
        )
    return out


# What a previous generation may have left (removed before writing a new scene there, so that
# no stale frame survives a smaller re-generation).
_OUTPUT_DIRS = ("images", "depth", "regions", "label", "sparse")
_OUTPUT_FILES = ("transforms.json", "sparse_pc.ply", "regions.json", "queries.json", "points_source.npy", "scene.json")


def _prepare_output_dir(out: Path) -> None:
    """Refuse a non-empty folder that is not a demo scene; clear an old demo scene's outputs.
    ``scene.json`` is written last, so a folder without it is an interrupted generation."""
    import shutil

    from ..errors import InputError
    from .scene import SCENE_META_NAME, read_scene_meta

    if out.exists() and not out.is_dir():
        raise InputError(out, "output path exists and is not a folder")
    if not out.exists() or not any(out.iterdir()):
        return
    meta_path = out / SCENE_META_NAME
    is_demo = False
    if meta_path.is_file():
        try:
            is_demo = read_scene_meta(out).get("generator") == GENERATOR
        except InputError:
            is_demo = False
    else:  # an interrupted generation: only our own names inside
        names = {p.name for p in out.iterdir()}
        is_demo = names <= set(_OUTPUT_DIRS) | set(_OUTPUT_FILES)
    if not is_demo:
        raise InputError(out, "output folder is not empty and does not hold a demo scene; choose a new or empty folder")
    meta_path.unlink(missing_ok=True)  # first, so a crash below leaves an "interrupted" folder
    for name in _OUTPUT_DIRS:
        if (out / name).is_dir():
            shutil.rmtree(out / name)
    for name in _OUTPUT_FILES:
        (out / name).unlink(missing_ok=True)


def query_mask(
    regions: np.ndarray,  # [3, H, W] int32
    region_list: Sequence[Region] | Sequence[dict],
    region_ids: Sequence[int],
) -> np.ndarray:  # [H, W] bool
    """Union of the pixels of the given regions (each compared at its own level)."""
    level_of = {
        (r["id"] if isinstance(r, dict) else r.id): (r["level"] if isinstance(r, dict) else r.level)
        for r in region_list
    }
    mask = np.zeros(regions.shape[1:], dtype=bool)
    for rid in region_ids:
        mask |= regions[level_of[rid]] == rid
    return mask


def _num(x: float) -> Optional[float]:
    return None if not np.isfinite(x) else round(float(x), 6)


def _write_jpeg(path: Path, rgb8: np.ndarray) -> None:
    from PIL import Image

    with atomic_path(path) as tmp:
        Image.fromarray(rgb8).save(tmp, format="JPEG", quality=95)


# ============================================================================= contact sheet
def _palette(ids: np.ndarray) -> np.ndarray:
    """Distinct colours [..., 3] float for region ids (black for -1), stable per id."""
    golden = 0.618033988749895
    hue = (np.asarray(ids, dtype=np.float64) * golden + 0.11) % 1.0
    sat = 0.55 + 0.35 * ((np.asarray(ids) * 7) % 3) / 2
    val = 0.95 - 0.25 * ((np.asarray(ids) * 5) % 2)
    import matplotlib.colors as mcolors

    rgb = mcolors.hsv_to_rgb(np.stack([hue, sat, val], axis=-1))
    return np.where((np.asarray(ids) < 0)[..., None], 0.0, rgb)


def write_contact_sheet(scene_dir: str | Path, out_png: str | Path, max_views: int = 8) -> Path:
    """A PNG grid: one column per view (spread over the scene), rows = RGB and the part,
    object and group ids coloured per region, with a legend of region captions per level."""
    import json

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Patch

    from ..errors import InputError
    from .scene import read_scene_meta

    scene_dir = Path(scene_dir)
    try:
        reg_info = json.loads((scene_dir / "regions.json").read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise InputError(scene_dir / "regions.json", f"cannot read regions ({e})") from None
    images = sorted((scene_dir / "images").glob("*.png"))
    if not images:
        raise InputError(scene_dir / "images", "no images")
    count = min(max_views, len(images))
    pick = np.unique(np.linspace(0, len(images) - 1, count).round().astype(int))
    levels = reg_info["levels"]
    from PIL import Image

    rows = 1 + len(levels)
    fig, axes = plt.subplots(
        rows,
        len(pick) + 1,
        figsize=(1.9 * len(pick) + 3.6, 1.55 * rows),
        gridspec_kw={"width_ratios": [1] * len(pick) + [1.9]},
        squeeze=False,
    )
    seen_per_level = [set() for _ in levels]
    for col, i in enumerate(pick):
        stem = images[i].stem
        with Image.open(images[i]) as im:
            axes[0, col].imshow(np.asarray(im.convert("RGB")))
        axes[0, col].set_title(f"{stem} (view {i})", fontsize=6)
        reg = np.load(scene_dir / "regions" / f"{stem}.npy")
        for lv in range(len(levels)):
            axes[lv + 1, col].imshow(_palette(reg[lv]), interpolation="nearest")
            seen_per_level[lv].update(int(x) for x in np.unique(reg[lv]) if x >= 0)
    for r in range(rows):
        for c in range(len(pick) + 1):
            axes[r, c].set_xticks([])
            axes[r, c].set_yticks([])
        axes[r, 0].set_ylabel("rgb" if r == 0 else f"{levels[r - 1]} ids", fontsize=7)
        axes[r, -1].axis("off")
    by_id = {r["id"]: r for r in reg_info["regions"]}
    for lv in range(len(levels)):
        handles = [
            # matplotlib takes an RGB array as a colour; its ColorType alias lists only tuples and strings.
            Patch(color=_palette(np.array(rid)), label=by_id[rid]["caption"])  # pyright: ignore[reportArgumentType]
            for rid in sorted(seen_per_level[lv])
        ]
        axes[lv + 1, -1].legend(
            handles=handles,
            loc="center left",
            fontsize=5,
            frameon=False,
            ncol=1 + len(handles) // 8,
            handlelength=1.0,
            borderaxespad=0,
        )
    try:
        layout = read_scene_meta(scene_dir).get("layout", "tabletop")
    except InputError:
        layout = "?"
    axes[0, -1].text(
        0.0, 0.5, f"{scene_dir.name} ({layout})\n{len(images)} views\nblack = no region", fontsize=7, va="center"
    )
    fig.tight_layout(pad=0.3)
    out_png = Path(out_png)
    with atomic_path(out_png) as tmp:
        fig.savefig(tmp, dpi=150, format="png")
    plt.close(fig)
    return out_png
