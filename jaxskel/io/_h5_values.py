"""Writing values into HDF5 groups: strings as UTF-8, large arrays compressed."""

from __future__ import annotations

from typing import Any

import h5py
import numpy as np

__all__ = ["put", "strings"]

_STR = h5py.string_dtype(encoding="utf-8")


def strings(values: Any) -> np.ndarray:
    return np.asarray([str(v) for v in values], dtype=object)


def put(group: h5py.Group, name: str, value: Any) -> None:
    arr = np.asarray(value)
    if arr.dtype.kind in ("U", "O", "S"):
        group.create_dataset(name, data=strings(arr.ravel()).reshape(arr.shape), dtype=_STR)
    elif arr.ndim >= 2 and arr.size > 4096:
        group.create_dataset(name, data=arr, compression="gzip", compression_opts=4, shuffle=True)
    else:
        group.create_dataset(name, data=arr)
