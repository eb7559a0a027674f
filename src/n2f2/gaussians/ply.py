"""Read and write Gaussian splats in the INRIA 3DGS PLY layout.

This is the file that original 3DGS (``point_cloud/iteration_*/point_cloud.ply``), gsplat and
nerfstudio's splatfacto export write, so a splat trained elsewhere can be brought in. One
``vertex`` element with float properties::

    x y z  nx ny nz  f_dc_0..2  f_rest_0..3(K-1)-1  opacity  scale_0..2  rot_0..3

* ``f_rest`` is channel-major: all R coefficients of degrees >= 1 first, then G, then B.
* ``opacity`` is the logit, ``scale_*`` the log of the standard deviation, ``rot_*`` the
  quaternion w, x, y, z (not necessarily normalised). Normals are written as zeros and ignored.
* The SH degree is inferred from the number of ``f_rest_*`` properties.

Reading is tolerant about property order, extra properties, property types and the PLY format
(binary little/big endian or ascii); anything that would give a broken model is an InputError.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Mapping, Optional

import numpy as np
import torch

from ..data.nerfstudio import PLY_TYPES
from ..errors import InputError
from ..io import atomic_path
from ..validate import NonFiniteError
from .model import Gaussians, num_sh_bases, sh_degree_from_bases

_FORMATS = {"binary_little_endian": "<", "binary_big_endian": ">", "ascii": None}
_REQUIRED = (
    "x",
    "y",
    "z",
    "f_dc_0",
    "f_dc_1",
    "f_dc_2",
    "opacity",
    "scale_0",
    "scale_1",
    "scale_2",
    "rot_0",
    "rot_1",
    "rot_2",
    "rot_3",
)


def property_names(sh_degree: int) -> list[str]:
    """The INRIA vertex property names, in the order 3DGS writes them."""
    n_rest = 3 * (num_sh_bases(sh_degree) - 1)
    return (
        ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
        + [f"f_rest_{i}" for i in range(n_rest)]
        + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    )


# ---------------------------------------------------------------------------------- writing
def write_ply(
    path: str | Path,
    gaussians: Gaussians,
    extra: Optional[Mapping[str, np.ndarray]] = None,  # name -> [N] int32: properties after the INRIA ones
) -> None:
    """Write ``gaussians`` (all ``max_sh_degree`` coefficients) as an INRIA 3DGS PLY, atomically.
    ``extra`` int properties (the hierarchy's ``node_0 ...``) follow the INRIA ones; other 3DGS
    tools skip properties they do not know, and :func:`read_ply_ints` reads them back."""
    extra = dict(extra or {})
    with torch.no_grad():
        g = gaussians
        n = g.num
        k = num_sh_bases(g.max_sh_degree)
        names = property_names(g.max_sh_degree)
        columns = [
            g.means,
            torch.zeros(n, 3, device=g.device),
            g.sh[:, 0, :],
            # [N, K-1, 3] -> [N, 3, K-1] -> channel-major [N, 3 (K-1)], as 3DGS's save_ply.
            g.sh[:, 1:, :].transpose(1, 2).reshape(n, 3 * (k - 1)),
            g.opacity_logits[:, None],
            g.log_scales,
            g.quats,
        ]
        data = torch.cat([c.detach().float().cpu() for c in columns], dim=1).numpy()
    if not np.isfinite(data).all():
        bad = int((~np.isfinite(data).all(axis=1)).sum())
        raise NonFiniteError(path, f"refusing to write: {bad} of {n} Gaussians have NaN or infinite parameters")
    for name, col in extra.items():
        if name in names or np.shape(col) != (n,):
            raise ValueError(f"extra PLY property {name!r} must be a new name with {n} values, got {np.shape(col)}")
    rows = np.empty(n, dtype=[(p, "<f4") for p in names] + [(p, "<i4") for p in extra])
    for i, p in enumerate(names):
        rows[p] = data[:, i]
    for p, col in extra.items():
        rows[p] = np.asarray(col, dtype=np.int32)
    header = (
        "\n".join(
            ["ply", "format binary_little_endian 1.0", f"element vertex {n}"]
            + [f"property float {name}" for name in names]
            + [f"property int {name}" for name in extra]
            + ["end_header"]
        )
        + "\n"
    )
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(header.encode("ascii"))
            f.write(rows.tobytes())


def read_ply_ints(path: str | Path, prefix: str) -> dict[str, np.ndarray]:
    """The integer vertex properties of ``path`` whose names start with ``prefix`` (``node_``),
    in file order, as int64 ``[N]`` arrays (what :func:`write_ply`'s ``extra`` wrote)."""
    v = _read_vertices(Path(path))
    return {
        p: np.asarray(v[p], dtype=np.int64)
        for p in v.dtype.names or ()
        if p.startswith(prefix) and np.issubdtype(v.dtype[p], np.integer)
    }


# ---------------------------------------------------------------------------------- reading
def _parse_header(path: Path, f) -> tuple[str, list[tuple[str, int, list[tuple[str, str]]]]]:
    """Returns (format, elements); each element is (name, count, [(property, dtype char)])."""
    magic = f.readline()
    if magic.strip() != b"ply":
        raise InputError(path, "not a PLY file (missing 'ply' magic line)")
    fmt = None
    elements: list[tuple[str, int, list[tuple[str, str]]]] = []
    while True:
        raw = f.readline()
        if not raw:
            raise InputError(path, "PLY header has no 'end_header' line (file truncated?)")
        line = raw.decode("ascii", errors="replace").strip()
        if line == "end_header":
            break
        words = line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "format":
            if len(words) < 2 or words[1] not in _FORMATS:
                raise InputError(path, f"unsupported PLY format line {line!r}")
            fmt = words[1]
        elif words[0] == "element":
            if len(words) != 3 or not re.fullmatch(r"\d+", words[2]):
                raise InputError(path, f"bad PLY element line {line!r}")
            elements.append((words[1], int(words[2]), []))
        elif words[0] == "property":
            if not elements:
                raise InputError(path, f"PLY property before any element: {line!r}")
            if len(words) >= 2 and words[1] == "list":
                elements[-1][2].append((words[-1], "list"))
            elif len(words) == 3 and words[1] in PLY_TYPES:
                elements[-1][2].append((words[2], PLY_TYPES[words[1]]))
            else:
                raise InputError(path, f"bad PLY property line {line!r}")
        else:
            raise InputError(path, f"unexpected PLY header line {line!r}")
    if fmt is None:
        raise InputError(path, "PLY header has no 'format' line")
    return fmt, elements


def _read_vertices(path: Path) -> np.ndarray:
    """The vertex element as a numpy structured array. Element counts are checked against the
    file's size before anything is allocated."""
    size = path.stat().st_size
    with open(path, "rb") as f:
        fmt, elements = _parse_header(path, f)
        body = size - f.tell()
        names = [e[0] for e in elements]
        if "vertex" not in names:
            raise InputError(path, "PLY has no 'vertex' element")
        vi = names.index("vertex")
        for name, count, props in elements[: vi + 1]:
            if any(t == "list" for _, t in props):
                # Variable-length rows before the vertices would have to be parsed one by one;
                # splat files never have them.
                raise InputError(
                    path,
                    f"PLY element {name!r} has list properties before/in the vertex element; not a Gaussian splat file",
                )
        _, count, props = elements[vi]
        if len({p for p, _ in props}) != len(props):
            raise InputError(path, "PLY vertex element has duplicate property names")
        if not props:
            raise InputError(path, "PLY vertex element has no properties")
        if fmt == "ascii":
            lines_before = sum(c for _, c, _ in elements[:vi])
            # Every value but the file's last takes at least two bytes ("0 ", "0\n"): a count the
            # file cannot hold is refused before reading.
            if 2 * (lines_before + count * len(props)) - 1 > body:
                raise InputError(
                    path,
                    f"PLY truncated: header says {count} vertices of {len(props)} values, "
                    f"the file holds {body} bytes after the header",
                )
            for _ in range(lines_before):
                f.readline()
            dtype = np.dtype([(p, t) for p, t in props])
            rows = []
            for i in range(count):
                words = f.readline().split()
                if len(words) < len(props):
                    raise InputError(
                        path, f"PLY truncated: header says {count} vertices, vertex row {i} is missing or short"
                    )
                try:
                    rows.append(tuple(float(w) for w in words[: len(props)]))
                except ValueError:
                    raise InputError(
                        path,
                        f"vertex row {i} holds something that is not a number: "
                        f"{b' '.join(words[: len(props)]).decode('ascii', 'replace')[:80]!r}",
                    ) from None
            return np.array(rows, dtype=dtype) if rows else np.zeros(0, dtype)
        endian = _FORMATS[fmt]
        skip = sum(c * np.dtype([(p, endian + t) for p, t in pr]).itemsize for _, c, pr in elements[:vi])
        dtype = np.dtype([(p, endian + t) for p, t in props])
        if skip + count * dtype.itemsize > body:
            raise InputError(
                path,
                f"PLY truncated: header says {count} vertices ({count * dtype.itemsize} bytes), "
                f"the file holds {max(0, body - skip)} bytes for them",
            )
        f.seek(skip, 1)
        payload = f.read(count * dtype.itemsize)
    if len(payload) < count * dtype.itemsize:
        raise InputError(
            path,
            f"PLY truncated: header says {count} vertices "
            f"({count * dtype.itemsize} bytes), file holds {len(payload)} bytes",
        )
    return np.frombuffer(payload, dtype=dtype, count=count)


def read_ply(path: str | Path, device: torch.device | str | None = None) -> Gaussians:
    """Read an INRIA-layout 3DGS PLY. Raises :class:`InputError` naming the file for missing
    properties, a truncated file, NaN/infinite values, zero scales or zero quaternions."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "PLY file does not exist")
    v = _read_vertices(path)
    if len(v) == 0:
        raise InputError(path, "PLY holds no Gaussians (0 vertices)")
    have = set(v.dtype.names or ())
    missing = [p for p in _REQUIRED if p not in have]
    rest_ids = sorted(int(m.group(1)) for p in have if (m := re.fullmatch(r"f_rest_(\d+)", p)))
    if rest_ids != list(range(len(rest_ids))):
        gaps = sorted(set(range(max(rest_ids) + 1)) - set(rest_ids))
        missing += [f"f_rest_{i}" for i in gaps]
    if missing:
        raise InputError(
            path, f"PLY vertex element is missing properties required by the INRIA 3DGS layout: {', '.join(missing)}"
        )
    n_rest = len(rest_ids)
    if n_rest % 3 != 0:
        raise InputError(path, f"{n_rest} f_rest_* properties is not a multiple of 3")
    try:
        degree = sh_degree_from_bases(n_rest // 3 + 1)
    except ValueError:
        raise InputError(
            path, f"{n_rest} f_rest_* properties does not match any SH degree (expected 0, 9, 24 or 45 for degrees 0-3)"
        ) from None

    def cols(names: list[str]) -> np.ndarray:
        return (
            np.stack([np.asarray(v[p], dtype=np.float32) for p in names], axis=1)
            if names
            else np.zeros((len(v), 0), np.float32)
        )

    n = len(v)
    means = cols(["x", "y", "z"])
    dc = cols(["f_dc_0", "f_dc_1", "f_dc_2"])
    rest = cols([f"f_rest_{i}" for i in range(n_rest)])
    opacity = cols(["opacity"])[:, 0]
    log_scales = cols(["scale_0", "scale_1", "scale_2"])
    quats = cols(["rot_0", "rot_1", "rot_2", "rot_3"])

    if not np.isfinite(means).all():
        bad = int((~np.isfinite(means).all(axis=1)).sum())
        raise InputError(path, f"{bad} of {n} Gaussians have NaN or infinite means (x, y, z)")
    if (np.isneginf(log_scales) | (np.exp(log_scales.astype(np.float64)) == 0.0)).any():
        bad = int((np.isneginf(log_scales) | (np.exp(log_scales.astype(np.float64)) == 0)).any(axis=1).sum())
        raise InputError(path, f"{bad} of {n} Gaussians have zero scale (log-scale -inf)")
    # INRIA files store log-scales; a Gaussian whose three stored scales are exactly 0.0 is what a
    # tool writing *linear* scales produces for a degenerate Gaussian (a trained log-scale never
    # lands on exactly 0.0 on all three axes), so it is rejected rather than read as unit scale.
    zero_rows = (log_scales == 0.0).all(axis=1)
    if zero_rows.any():
        raise InputError(
            path,
            f"{int(zero_rows.sum())} of {n} Gaussians have scale_0..2 all exactly 0: "
            "the INRIA layout stores log-scales, so this file looks like it stores "
            "zero linear scales",
        )
    for label, arr in (
        ("f_dc_*", dc),
        ("f_rest_*", rest),
        ("opacity", opacity),
        ("scale_*", log_scales),
        ("rot_*", quats),
    ):
        if not np.isfinite(arr).all():
            raise InputError(path, f"property {label} has NaN or infinite values")
    if (np.linalg.norm(quats.astype(np.float64), axis=1) == 0).any():
        raise InputError(
            path, f"{int((np.abs(quats).sum(1) == 0).sum())} Gaussians have an all-zero rotation quaternion (rot_0..3)"
        )

    k = num_sh_bases(degree)
    sh = np.empty((n, k, 3), dtype=np.float32)
    sh[:, 0, :] = dc
    # channel-major [N, 3 (K-1)] -> [N, 3, K-1] -> [N, K-1, 3]
    sh[:, 1:, :] = rest.reshape(n, 3, k - 1).transpose(0, 2, 1)
    t = lambda a: torch.from_numpy(np.ascontiguousarray(a)).to(device)  # noqa: E731
    return Gaussians(t(means), t(quats), t(log_scales), t(opacity), t(sh))
