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
:func:`generate_demo_scene`, :func:`write_contact_sheet`, :func:`query_mask`.

Modules: :mod:`.model` (materials, primitives, regions, queries, the builder), :mod:`.tabletop`
and :mod:`.lounge` (the layouts' objects and camera paths), :mod:`.layouts` (by name),
:mod:`.raytrace` (intersections, shadows), :mod:`.shading` (textures, shading, :func:`render_view`),
:mod:`.writer` (the scene folder), :mod:`.contact_sheet`.
"""

from __future__ import annotations

from .contact_sheet import write_contact_sheet
from .layouts import build_demo_scene, demo_cameras
from .model import (
    GENERATOR,
    GENERATOR_VERSION,
    LAYOUTS,
    LEVELS,
    LOUNGE_TABLE_HEIGHT,
    TABLE_HEIGHT,
    DemoScene,
    Material,
    Primitive,
    Query,
    Region,
)
from .raytrace import intersect, local_normals, occluded, trace
from .shading import ViewRender, albedo, render_view, value_noise
from .writer import generate_demo_scene, query_mask

__all__ = [
    "GENERATOR",
    "GENERATOR_VERSION",
    "LAYOUTS",
    "LEVELS",
    "LOUNGE_TABLE_HEIGHT",
    "TABLE_HEIGHT",
    "DemoScene",
    "Material",
    "Primitive",
    "Query",
    "Region",
    "ViewRender",
    "albedo",
    "build_demo_scene",
    "demo_cameras",
    "generate_demo_scene",
    "intersect",
    "local_normals",
    "occluded",
    "query_mask",
    "render_view",
    "trace",
    "value_noise",
    "write_contact_sheet",
]
