"""The constants of the real spherical-harmonics basis, degrees 0..3 (3DGS's values and signs):
one definition for the PyTorch basis (:mod:`n2f2.render.sh`) and the compiled one
(:mod:`n2f2.render.numba_sh`)."""

SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
SH_C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)
