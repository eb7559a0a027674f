"""The 3D Gaussian Splatting stage: the model, INRIA PLY input/output, initialisation and RGB
fitting (``n2f2 fit-gaussians``)."""

from typing import TYPE_CHECKING

from .._lazy import lazy_exports

if TYPE_CHECKING:  # the lazily exported names, for static analysis
    from .fit import FitConfig as FitConfig
    from .fit import FitReport as FitReport
    from .fit import fit_gaussians as fit_gaussians
    from .init import init_from_points as init_from_points
    from .init import init_random_in_frusta as init_random_in_frusta
    from .model import Gaussians as Gaussians
    from .model import rgb_to_sh as rgb_to_sh
    from .model import sh_to_rgb as sh_to_rgb
    from .ply import read_ply as read_ply
    from .ply import write_ply as write_ply

__getattr__, __all__ = lazy_exports(
    __name__,
    {
        "FitConfig": "fit",
        "FitReport": "fit",
        "fit_gaussians": "fit",
        "init_from_points": "init",
        "init_random_in_frusta": "init",
        "Gaussians": "model",
        "rgb_to_sh": "model",
        "sh_to_rgb": "model",
        "read_ply": "ply",
        "write_ply": "ply",
    },
)
