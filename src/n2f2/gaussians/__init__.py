"""The 3D Gaussian Splatting stage: the model, INRIA PLY input/output, initialisation and RGB
fitting (``n2f2 fit-gaussians``)."""

from .fit import FitConfig, FitReport, fit_gaussians
from .init import init_from_points, init_random_in_frusta
from .model import Gaussians, rgb_to_sh, sh_to_rgb
from .ply import read_ply, write_ply

__all__ = ["FitConfig", "FitReport", "fit_gaussians", "Gaussians", "init_from_points", "init_random_in_frusta", "read_ply", "write_ply",
           "rgb_to_sh", "sh_to_rgb"]
