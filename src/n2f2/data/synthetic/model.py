"""The demo scenes' description: materials, primitives, the region hierarchy, queries, and the
builder the layouts (:mod:`.tabletop`, :mod:`.lounge`) model their objects with."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Optional, Sequence

import numpy as np
from numpy.typing import ArrayLike

LEVELS = ("part", "object", "group")
GENERATOR = "n2f2.data.synthetic"
GENERATOR_VERSION = 1
LAYOUTS = ("tabletop", "lounge")
TABLE_HEIGHT = 0.75  # tabletop layout: height of the table top
LOUNGE_TABLE_HEIGHT = 0.425  # lounge layout: height of the coffee table top


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
def rot_z(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def frame_z(axis: ArrayLike) -> np.ndarray:  # axis [3]
    """A rotation whose third column (local z) is ``axis``."""
    z = np.asarray(axis, dtype=np.float64)
    z = z / np.linalg.norm(z)
    helper = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z], axis=1)


def normalize(v: ArrayLike) -> np.ndarray:  # v [3]
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v)


@dataclass
class Draws:
    """A layout's random draws, all from one generator in the order the layout makes them, so
    a seed fixes the scene: the objects' positions on the table and their materials' tints."""

    rng: np.random.Generator
    jitter_amount: float  # default half-width of a position's jitter, metres

    def jitter(self, xy: ArrayLike, amount: Optional[float] = None) -> np.ndarray:  # xy [2] -> [2]
        """``xy`` plus uniform noise in [-amount, amount] per coordinate."""
        amount = self.jitter_amount if amount is None else amount
        return np.asarray(xy, dtype=np.float64) + self.rng.uniform(-amount, amount, size=2)

    def tint(self, color: tuple[float, float, float], amount: float = 0.04) -> tuple[float, float, float]:
        """``color`` plus uniform noise in [-amount, amount] per channel, clipped to [0, 1]."""
        red, green, blue = (float(np.clip(c + self.rng.uniform(-amount, amount), 0.0, 1.0)) for c in color)
        return red, green, blue


class Builder:
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
        R = rot_z(yaw)
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


def add_regions(b: Builder, table: Sequence[tuple[int, str, str, Optional[str]]]) -> dict[str, int]:
    """Add ``table``'s regions, ``(level, name, caption, parent's name or None)`` in order (a
    parent before its children), to ``b``; returns each name's id."""
    ids: dict[str, int] = {}
    for level, name, caption, parent in table:
        ids[name] = b.region(level, name, caption, None if parent is None else ids[parent])
    return ids


def add_walls(b: Builder, wall: int, half_x: float, half_y: float, material: Material) -> None:
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
