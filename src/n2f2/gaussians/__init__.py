"""The 3D Gaussian Splatting stage: the model, INRIA PLY input/output, initialisation and RGB
fitting (``n2f2 fit-gaussians``)."""

from .._lazy import lazy_exports

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
