"""Read and write 3D Gaussian Splatting PLY files in the Inria layout (Kerbl et al. 2023, "3D Gaussian
Splatting for Real-Time Radiance Field Rendering", reference code ``scene/gaussian_model.py``).

One ``vertex`` element, every property ``float`` (float32), ``binary_little_endian``::

    x y z  nx ny nz  f_dc_0 f_dc_1 f_dc_2  f_rest_0 .. f_rest_{3*(D-1)-1}  opacity  scale_0..2  rot_0..3

Stored values are the optimiser's raw parameters; this module converts to and from *activated* values:

* ``means`` (N, 3) m, stored as is;
* ``scales`` (N, 3) m, per-axis standard deviations, stored as ``log(scale)``;
* ``rotations`` (N, 4) 1, unit quaternions ``w, x, y, z`` (w first, as in the reference code), stored as is
  (the reader normalises them);
* ``opacities`` (N,) 1 in (0, 1), stored as ``logit(opacity)``;
* ``colors`` (N, 3) 1, linear RGB.  3DGS files and every splat viewer take ``0.5 + C0 f_dc`` as the *display*
  (sRGB-encoded) colour, so the writer stores ``f_dc = (srgb(rgb) - 0.5) / C0`` and the reader returns
  ``linear(clip(0.5 + C0 f_dc, 0, 1))`` (IEC 61966-2-1 transfer function, :func:`srgb_to_linear` /
  :func:`linear_to_srgb`), ``C0 = 0.28209479177387814`` (the SH band-0 constant); the display colour itself is
  returned as ``display_colors``.  Higher SH bands (view-dependent colour) are read as ``sh_rest`` and not used by
  the pipeline (a user's PLY is rendered view-independently with its band-0 colour);
* ``f_rest`` are the higher SH bands, channel-major (all coefficients of R, then G, then B), so
  ``f_rest_{c * K + j}`` is coefficient ``j`` of channel ``c`` with ``K = (sh_degree + 1)^2 - 1``.  The writer
  stores zeros (a view-independent, degree-0 export) for ``sh_degree`` 3 by default so that viewers expecting
  the reference layout load the file.

No ``plyfile`` dependence: the header is parsed by hand and the body read with ``np.frombuffer`` and a
structured dtype.  ``binary_little_endian``, ``binary_big_endian`` and ``ascii`` bodies are read; other
elements (e.g. faces) after the vertices are ignored.  Every error is one line naming the file and the fix.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from tasks.core.excerpt import excerpt

__all__ = ["C0", "GaussianPlyError", "write_gaussian_ply", "read_gaussian_ply", "REQUIRED_PROPERTIES",
           "REFERENCE_PROPERTIES", "srgb_to_linear", "linear_to_srgb"]

C0 = 0.28209479177387814  # SH band-0 constant 1 / (2 sqrt(pi))

REQUIRED_PROPERTIES: tuple[str, ...] = (
    "x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
    "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3",
)

# The reference 3DGS layout (Kerbl et al. 2023, scene/gaussian_model.py construct_list_of_attributes) at SH degree 3
REFERENCE_PROPERTIES: tuple[str, ...] = (
    "x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", *(f"f_rest_{i}" for i in range(45)),
    "opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3",
)


def srgb_to_linear(srgb: Any) -> np.ndarray:
    """Linear RGB of sRGB-encoded values in [0, 1] (IEC 61966-2-1; input clipped to [0, 1])."""
    c = np.clip(np.asarray(srgb, dtype=np.float64), 0.0, 1.0)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(linear: Any) -> np.ndarray:
    """sRGB encoding of linear RGB in [0, 1] (IEC 61966-2-1; input clipped to [0, 1])."""
    c = np.clip(np.asarray(linear, dtype=np.float64), 0.0, 1.0)
    return np.where(c <= 0.0031308, 12.92 * c, 1.055 * c ** (1.0 / 2.4) - 0.055)


_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}


class GaussianPlyError(ValueError):
    """A PLY file that is not a readable 3DGS (Inria layout) file; the message names the file and the fix."""


def _logit(p: np.ndarray) -> np.ndarray:
    p = np.asarray(p, dtype=np.float64)
    return np.log(p) - np.log1p(-p)


def _sigmoid(x: np.ndarray) -> np.ndarray:
    x = np.asarray(x, dtype=np.float64)
    out = np.empty_like(x)
    pos = x >= 0
    out[pos] = 1.0 / (1.0 + np.exp(-x[pos]))
    e = np.exp(x[~pos])
    out[~pos] = e / (1.0 + e)
    return out


def write_gaussian_ply(
    path: str | Path,
    means: Any,
    scales: Any,
    rotations: Any,
    opacities: Any,
    colors: Any,
    *,
    normals: Any = None,
    sh_degree: int = 3,
) -> Path:
    """Write Gaussians as a binary little-endian 3DGS PLY (Inria layout, see module doc).

    Args:
        path: output file (parent folders are created).
        means: (N, 3) m, Gaussian centres.
        scales: (N, 3) m, per-axis standard deviations (> 0), stored as ``log``.
        rotations: (N, 4) 1, quaternions ``w, x, y, z`` (normalised before writing).
        opacities: (N,) 1 in (0, 1), stored as ``logit``.
        colors: (N, 3) 1, linear RGB, stored as ``f_dc = (srgb(rgb) - 0.5) / C0`` (the display colour).
        normals: optional (N, 3) 1, stored in ``nx, ny, nz`` (zeros when omitted, as the reference code does).
        sh_degree: SH degree of the layout; ``3 * ((sh_degree + 1)^2 - 1)`` zero ``f_rest_*`` values are written.
    Returns:
        the path written.
    """
    path = Path(path)
    means = np.asarray(means, dtype=np.float64).reshape(-1, 3)
    n = means.shape[0]

    def shaped(name: str, value: Any, cols: int | None) -> np.ndarray:
        arr = np.asarray(value, dtype=np.float64)
        want = (n, cols) if cols else (n,)
        if arr.shape != want:
            raise ValueError(f"write_gaussian_ply({path}): {name} must have shape {want}, got {arr.shape}")
        if not np.all(np.isfinite(arr)):
            raise ValueError(f"write_gaussian_ply({path}): {name} has non-finite values")
        return arr

    scales = shaped("scales", scales, 3)
    rotations = shaped("rotations", rotations, 4)
    opacities = shaped("opacities", opacities, None)
    colors = shaped("colors", colors, 3)
    normals = np.zeros((n, 3)) if normals is None else shaped("normals", normals, 3)
    if np.any(scales <= 0):
        raise ValueError(f"write_gaussian_ply({path}): scales must be > 0 m (stored as log)")
    if np.any((opacities <= 0) | (opacities >= 1)):
        raise ValueError(f"write_gaussian_ply({path}): opacities must be in (0, 1) (stored as logit)")
    qn = np.linalg.norm(rotations, axis=1, keepdims=True)
    if np.any(qn < 1e-12):
        raise ValueError(f"write_gaussian_ply({path}): rotations contain a zero quaternion")
    n_rest = 3 * ((int(sh_degree) + 1) ** 2 - 1)

    names = (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
             + [f"f_rest_{i}" for i in range(n_rest)]
             + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])
    data = np.zeros(n, dtype=np.dtype([(name, "<f4") for name in names]))
    for i, c in enumerate("xyz"):
        data[c] = means[:, i]
        data[f"n{c}"] = normals[:, i]
    for i in range(3):
        data[f"f_dc_{i}"] = (linear_to_srgb(colors[:, i]) - 0.5) / C0
        data[f"scale_{i}"] = np.log(scales[:, i])
    data["opacity"] = _logit(opacities)
    rot = rotations / qn
    for i in range(4):
        data[f"rot_{i}"] = rot[:, i]
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {n}"]
    header += [f"property float {name}" for name in names]
    header += ["end_header"]
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as fh:
        fh.write(("\n".join(header) + "\n").encode("ascii"))
        fh.write(data.tobytes())
    return path


def _parse_header(path: Path, raw: bytes) -> tuple[str, list[tuple[str, int, list]], int]:
    """(format, [(element name, count, [(prop name, dtype or None for list)])], body offset)."""
    if not raw.startswith(b"ply"):
        raise GaussianPlyError(f"{path} is not a PLY file (no 'ply' magic line): give a 3DGS .ply file")
    end = raw.find(b"end_header")
    if end < 0:
        raise GaussianPlyError(f"PLY {path} has no 'end_header' line: the header is truncated or malformed")
    nl = raw.find(b"\n", end)
    if nl < 0:
        raise GaussianPlyError(f"PLY {path} ends right after 'end_header': the file has no data")
    body = nl + 1
    try:
        lines = raw[:end].decode("ascii").replace("\r", "").split("\n")
    except UnicodeDecodeError:
        raise GaussianPlyError(f"PLY {path} has a non-ASCII header: the file is corrupt") from None
    fmt = None
    elements: list[tuple[str, int, list]] = []
    for ln in lines[1:]:
        tok = ln.split()
        if not tok or tok[0] in ("comment", "obj_info"):
            continue
        if tok[0] == "format" and len(tok) >= 2:
            fmt = tok[1]
        elif tok[0] == "element" and len(tok) == 3:
            try:
                elements.append((tok[1], int(tok[2]), []))
            except ValueError:
                raise GaussianPlyError(f"PLY {path}: bad element line {excerpt(ln)} (count is not an integer)") from None
        elif tok[0] == "property" and elements:
            if len(tok) >= 5 and tok[1] == "list":
                elements[-1][2].append((tok[4], None))
            elif len(tok) == 3 and tok[1] in _PLY_TYPES:
                elements[-1][2].append((tok[2], _PLY_TYPES[tok[1]]))
            else:
                raise GaussianPlyError(f"PLY {path}: unsupported property line {excerpt(ln)}")
        else:
            raise GaussianPlyError(f"PLY {path}: malformed header line {excerpt(ln)}")
    if fmt not in ("binary_little_endian", "binary_big_endian", "ascii"):
        raise GaussianPlyError(f"PLY {path}: unsupported or missing format {fmt!r} "
                               "(binary_little_endian, binary_big_endian or ascii)")
    return fmt, elements, body


def read_gaussian_ply(path: str | Path) -> dict[str, np.ndarray]:
    """Read a 3DGS PLY (Inria layout) into activated values.

    Returns a dict with ``means`` (N, 3) m, ``scales`` (N, 3) m (``exp`` of the stored log-scales),
    ``rotations`` (N, 4) 1 (normalised quaternions, w first), ``opacities`` (N,) 1 (sigmoid of the stored
    logits), ``colors`` (N, 3) 1 (linear RGB of the display colour ``0.5 + C0 * f_dc`` clipped to [0, 1]),
    ``display_colors`` (N, 3) 1 (``0.5 + C0 * f_dc`` itself, sRGB, *not* clipped: SH colours may leave [0, 1]),
    ``normals`` (N, 3) 1 (the stored nx, ny, nz or zeros) and ``sh_rest`` (N, K, 3) 1 (higher SH bands,
    coefficient-major after un-doing the channel-major storage; K = 0 when absent), all float32.

    Raises :class:`GaussianPlyError` (one line naming the file and the fix) for a missing file, a malformed
    header, missing Gaussian properties (named), or a truncated body.
    """
    path = Path(path).expanduser()
    if not path.is_file():
        raise GaussianPlyError(f"3DGS PLY {path} does not exist: set object.geometry.path to an existing .ply file")
    raw = path.read_bytes()
    fmt, elements, body = _parse_header(path, raw)
    names = [e[0] for e in elements]
    if "vertex" not in names:
        raise GaussianPlyError(f"PLY {path} has no 'vertex' element: it holds no Gaussians")
    vi = names.index("vertex")
    _, count, props = elements[vi]
    if any(dt is None for _, dt in props):
        raise GaussianPlyError(f"PLY {path}: the vertex element has list properties; a 3DGS PLY has only scalars")
    prop_names = [p for p, _ in props]
    missing = [p for p in REQUIRED_PROPERTIES if p not in prop_names]
    faces = sum(e[1] for e in elements if e[0] == "face")
    if missing and faces:
        raise GaussianPlyError(
            f"PLY {path} is a triangle mesh ({faces} faces, no Gaussian properties such as {missing[0]}), not a "
            "3DGS splat: give it as a mesh with geometry.kind=mesh (e.g. object.geometry.kind=mesh)")
    if missing:
        raise GaussianPlyError(
            f"PLY {path} lacks the 3DGS properties {missing}: it is not a Gaussian splat in the Inria layout "
            "(x y z f_dc_0..2 opacity scale_0..2 rot_0..3); export it from a 3DGS trainer")
    if count <= 0:
        raise GaussianPlyError(f"PLY {path} declares {count} vertices: it holds no Gaussians")

    if fmt == "ascii":
        text = raw[body:].decode("ascii", errors="replace").split("\n")
        skip = sum(e[1] for e in elements[:vi])
        rows = [ln for ln in text[skip:skip + count]]
        try:
            table = np.array([[float(v) for v in ln.split()] for ln in rows], dtype=np.float64)
        except ValueError:
            raise GaussianPlyError(f"PLY {path}: non-numeric value in the ascii vertex data") from None
        if table.shape != (count, len(props)):
            raise GaussianPlyError(f"PLY {path} is truncated: header declares {count} vertices with "
                                   f"{len(props)} properties, the ascii body has shape {table.shape}")
        col = {p: table[:, i] for i, p in enumerate(prop_names)}
    else:
        endian = "<" if fmt == "binary_little_endian" else ">"
        offset = body
        for ename, ecount, eprops in elements[:vi]:
            if any(dt is None for _, dt in eprops):
                raise GaussianPlyError(f"PLY {path}: element {ename!r} with list properties precedes the vertices; "
                                       "re-export with the vertex element first")
            offset += ecount * np.dtype([(p, endian + dt) for p, dt in eprops]).itemsize
        dtype = np.dtype([(p, endian + dt) for p, dt in props])
        need = count * dtype.itemsize
        have = len(raw) - offset
        if have < need:
            raise GaussianPlyError(f"PLY {path} is truncated: header declares {count} vertices ({need} bytes) "
                                   f"but only {max(have, 0)} bytes follow the header")
        arr = np.frombuffer(raw, dtype=dtype, count=count, offset=offset)
        col = {p: arr[p].astype(np.float64) for p in prop_names}

    means = np.stack([col["x"], col["y"], col["z"]], axis=1)
    f_dc = np.stack([col[f"f_dc_{i}"] for i in range(3)], axis=1)
    log_s = np.stack([col[f"scale_{i}"] for i in range(3)], axis=1)
    rot = np.stack([col[f"rot_{i}"] for i in range(4)], axis=1)
    stacked = np.concatenate([means, f_dc, log_s, rot, col["opacity"][:, None]], axis=1)
    if not np.all(np.isfinite(stacked)):
        rows = ~np.isfinite(stacked)
        names = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1",
                 "rot_2", "rot_3", "opacity"]
        where = ", ".join(n for n, hit in zip(names, rows.any(axis=0)) if hit)
        bad = np.flatnonzero(rows.any(axis=1))
        what = "1 Gaussian has" if len(bad) == 1 else f"{len(bad)} Gaussians have"
        raise GaussianPlyError(f"PLY {path}: {what} NaN/inf values (in {where}, e.g. Gaussian {int(bad[0])}): remove "
                               f"them from the splat (or export it again) before loading")
    qn = np.linalg.norm(rot, axis=1, keepdims=True)
    if np.any(qn < 1e-12):
        raise GaussianPlyError(f"PLY {path}: {int((qn < 1e-12).sum())} Gaussians have a zero rotation quaternion")
    normals = (np.stack([col[c] for c in ("nx", "ny", "nz")], axis=1)
               if all(c in col for c in ("nx", "ny", "nz")) else np.zeros((count, 3)))
    rest_names = sorted((p for p in prop_names if p.startswith("f_rest_")), key=lambda s: int(s.split("_")[-1]))
    k = len(rest_names) // 3
    if rest_names:
        rest = np.stack([col[p] for p in rest_names[: 3 * k]], axis=1).reshape(count, 3, k)
        sh_rest = np.transpose(rest, (0, 2, 1))
    else:
        sh_rest = np.zeros((count, 0, 3))
    f32 = np.float32
    return {
        "means": means.astype(f32),
        "scales": np.exp(log_s).astype(f32),
        "rotations": (rot / qn).astype(f32),
        "opacities": _sigmoid(col["opacity"]).astype(f32),
        "colors": srgb_to_linear(0.5 + C0 * f_dc).astype(f32),
        "display_colors": (0.5 + C0 * f_dc).astype(f32),
        "normals": normals.astype(f32),
        "sh_rest": sh_rest.astype(f32),
    }
