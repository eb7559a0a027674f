"""A layout's scene and camera path, by name (``LAYOUTS``)."""

from __future__ import annotations

from ...cameras import Camera
from .lounge import lounge_cameras, lounge_scene
from .model import LAYOUTS, DemoScene
from .tabletop import tabletop_cameras, tabletop_scene


def build_demo_scene(seed: int = 0, layout: str = "tabletop") -> DemoScene:
    """The demo scene of a layout (``LAYOUTS``): ``tabletop`` (the default) or ``lounge``.
    ``seed`` jitters object positions, orientations and colours a little; the hierarchy,
    captions and queries of a layout are the same for every seed."""
    if layout == "tabletop":
        return tabletop_scene(seed)
    if layout == "lounge":
        return lounge_scene(seed)
    raise ValueError(f"unknown demo layout {layout!r}; choose one of {', '.join(LAYOUTS)}")


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
        return tabletop_cameras(num_views, width, height, seed, hfov_deg)
    if layout == "lounge":
        return lounge_cameras(num_views, width, height, seed, hfov_deg)
    raise ValueError(f"unknown demo layout {layout!r}; choose one of {', '.join(LAYOUTS)}")
