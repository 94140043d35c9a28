"""The geometry (vertices, triangles) of a binary PLY file, read with numpy (0.6 ms per
``models_eval`` mesh of the synthetic dataset).

The evaluator and the dataset checker need only the geometry of each model; trimesh, which reads
every model for the rest of the package, takes 5 ms per such mesh and 0.2 s to import (after
scipy, which the evaluator imports anyway: its own modules and networkx). BOP models are binary
triangle meshes (``vertex``: x, y, z, ...; ``face``: a ``vertex_indices`` list of 3); anything
else (ASCII, polygons, variable-length lists, a damaged header or a short file) is left to trimesh:
:func:`read_triangles` returns None for it, so both readers give the same arrays or the same error.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

_TYPES = {  # PLY scalar type -> numpy type (without byte order)
    b"char": "i1", b"int8": "i1", b"uchar": "u1", b"uint8": "u1", b"short": "i2", b"int16": "i2",
    b"ushort": "u2", b"uint16": "u2", b"int": "i4", b"int32": "i4", b"uint": "u4", b"uint32": "u4",
    b"float": "f4", b"float32": "f4", b"double": "f8", b"float64": "f8",
}
_ORDERS = {b"binary_little_endian": "<", b"binary_big_endian": ">"}
_INDEX_NAMES = (b"vertex_indices", b"vertex_index")


def _header(f) -> tuple[str, list[tuple[bytes, int, list[list[bytes]]]]] | None:
    """(byte order, [(element name, count, [property words])]) of a binary PLY header, or None."""
    if f.readline().strip() != b"ply":
        return None
    order: str | None = None
    elements: list[tuple[bytes, int, list[list[bytes]]]] = []
    for line in iter(f.readline, b""):
        words = line.split()
        if not words or words[0] in (b"comment", b"obj_info"):
            continue
        if words[0] == b"end_header":
            return (order, elements) if order is not None else None
        if words[0] == b"format" and len(words) == 3:
            order = _ORDERS.get(words[1])
        elif words[0] == b"element" and len(words) == 3 and words[2].isdigit():
            elements.append((words[1], int(words[2]), []))
        elif words[0] == b"property" and elements and len(words) in (3, 5):
            elements[-1][2].append(words[1:])
        else:
            return None
    return None


def _record_dtype(props: list[list[bytes]], order: str, data: memoryview, offset: int) -> np.dtype | None:
    """Structured dtype of one element record, lists sized as in the record at ``offset`` (None if
    a type is unknown or the data ends first)."""
    fields: list[tuple] = []
    size = 0
    for i, p in enumerate(props):
        if p[0] != b"list":
            if p[0] not in _TYPES:
                return None
            t = np.dtype(order + _TYPES[p[0]])
            fields.append((f"p{i}", t))
            size += t.itemsize
            continue
        if _TYPES.get(p[1], "f")[0] not in "iu" or p[2] not in _TYPES:  # counts are integers
            return None
        ct, it = np.dtype(order + _TYPES[p[1]]), np.dtype(order + _TYPES[p[2]])
        if offset + size + ct.itemsize > len(data):
            return None
        n = int(np.frombuffer(data, ct, 1, offset + size)[0])
        if not 0 <= n <= len(data) // it.itemsize:
            return None
        fields += [(f"n{i}", ct), (f"p{i}", it, (n,))]
        size += ct.itemsize + n * it.itemsize
    return np.dtype(fields)


def read_triangles(path: str | Path) -> tuple[np.ndarray, np.ndarray] | None:
    """(vertices [N,3] float64 in the file's units, faces [F,3] int64) of a binary PLY triangle mesh,
    exactly as ``trimesh.load(path, process=False)`` gives them; None for a file of another shape."""
    with open(path, "rb") as f:
        head = _header(f)
        if head is None:
            return None
        order, elements = head
        data = memoryview(f.read())
    arrays, offset = {}, 0
    for name, count, props in elements:
        dtype = _record_dtype(props, order, data, offset) if count else None
        if dtype is None or offset + count * dtype.itemsize > len(data):
            return None
        rec = np.frombuffer(data, dtype, count, offset)
        offset += count * dtype.itemsize
        for i, p in enumerate(props):  # every list the length of the first record's
            if p[0] == b"list" and np.any(rec[f"n{i}"] != dtype[f"p{i}"].shape[0]):
                return None
        arrays[name] = (rec, [p[-1] for p in props])
    if b"vertex" not in arrays or b"face" not in arrays:
        return None
    (vrec, vnames), (frec, fnames) = arrays[b"vertex"], arrays[b"face"]
    if not {b"x", b"y", b"z"} <= set(vnames):
        return None
    index = next((fnames.index(n) for n in _INDEX_NAMES if n in fnames), None)
    if index is None or frec[f"p{index}"].shape[1:] != (3,):
        return None
    vertices = np.stack([vrec[f"p{vnames.index(a)}"] for a in (b"x", b"y", b"z")], axis=1).astype(np.float64)
    return vertices, frec[f"p{index}"].astype(np.int64)
