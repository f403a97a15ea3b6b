"""Reads the NRRD volumes palpsim-prep writes (raw or gzip encoding, 3-D, LPS space),
with their physical geometry, so that clients can compare results with the patient."""

from __future__ import annotations

import gzip
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

_TYPES = {"float": "<f4", "double": "<f8", "uint8": "u1", "unsigned char": "u1", "uchar": "u1",
          "int16": "<i2", "short": "<i2", "uint16": "<u2", "int32": "<i4", "int": "<i4"}


class NrrdError(ValueError):
    """A NRRD file this reader cannot use; the message names the file and the field."""


@dataclass
class NrrdVolume:
    """Voxels as data[k, j, i] (i fastest on disk) and the index-to-physical map (mm)."""

    data: np.ndarray
    origin_mm: np.ndarray      # physical point of voxel (0, 0, 0)
    directions: np.ndarray     # 3x3, column a = physical step (mm) of index axis a

    def to_index(self, p_mm: np.ndarray) -> np.ndarray:
        """Continuous (i, j, k) index of physical points (..., 3)."""
        inv = np.linalg.inv(self.directions)
        return (np.asarray(p_mm, dtype=float) - self.origin_mm) @ inv.T

    def to_physical(self, ijk: np.ndarray) -> np.ndarray:
        """Physical points (mm) of (i, j, k) indices (..., 3)."""
        return np.asarray(ijk, dtype=float) @ self.directions.T + self.origin_mm


def _vectors(text: str) -> list[list[float]]:
    return [[float(x) for x in m.split(",")] for m in re.findall(r"\(([^)]*)\)", text)]


def read_nrrd(path: str | Path) -> NrrdVolume:
    """Reads a 3-D NRRD file (attached header, raw or gzip, little-endian)."""
    path = Path(path)
    raw = path.read_bytes()
    end = raw.find(b"\n\n")
    if not raw.startswith(b"NRRD") or end < 0:
        raise NrrdError(f"{path}: not a NRRD file with an attached header")
    fields: dict[str, str] = {}
    for line in raw[:end].decode("latin-1").splitlines()[1:]:
        if line.startswith("#") or ":" not in line:
            continue
        key, value = line.split(":", 1)
        fields[key.strip().lower()] = value.strip().lstrip("=").strip()

    def need(key: str) -> str:
        if key not in fields:
            raise NrrdError(f"{path}: header field '{key}' is missing")
        return fields[key]

    if need("dimension") != "3":
        raise NrrdError(f"{path}: dimension: only 3-D volumes are read, got {fields['dimension']}")
    dtype = _TYPES.get(need("type"))
    if dtype is None:
        raise NrrdError(f"{path}: type: unsupported voxel type {fields['type']!r}")
    if fields.get("endian", "little") != "little" and np.dtype(dtype).itemsize > 1:
        raise NrrdError(f"{path}: endian: only little-endian data is read")
    sizes = [int(x) for x in need("sizes").split()]
    body = raw[end + 2:]
    encoding = need("encoding")
    if encoding in ("gzip", "gz"):
        body = gzip.decompress(body)
    elif encoding != "raw":
        raise NrrdError(f"{path}: encoding: only raw and gzip are read, got {encoding!r}")
    count = sizes[0] * sizes[1] * sizes[2]
    need_bytes = count * np.dtype(dtype).itemsize
    if len(body) < need_bytes:
        raise NrrdError(f"{path}: truncated: {len(body)} data bytes, expected {need_bytes}")
    data = np.frombuffer(body[:need_bytes], dtype=dtype).reshape(sizes[2], sizes[1], sizes[0])
    dirs = _vectors(need("space directions"))
    origin = _vectors(fields.get("space origin", "(0,0,0)"))
    if len(dirs) != 3 or any(len(d) != 3 for d in dirs) or len(origin) != 1:
        raise NrrdError(f"{path}: space directions / space origin: expected 3-D vectors")
    if fields.get("space", "left-posterior-superior") not in ("left-posterior-superior", "LPS"):
        raise NrrdError(f"{path}: space: only left-posterior-superior is read, got {fields['space']!r}")
    return NrrdVolume(data=data, origin_mm=np.array(origin[0]),
                      directions=np.array(dirs, dtype=float).T)
