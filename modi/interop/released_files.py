"""Reading checkpoint files written by the authors' released code: as data, never as code.

Their ``train.py`` pickles an ``argparse.Namespace`` of its options and numpy arrays (normalisation statistics)
beside the state dicts. ``torch.load(weights_only=True)`` with exactly those classes allowed reads them; any other
global in the file (a function, a module) is refused, so a file from someone else cannot run code.
"""
from __future__ import annotations

import argparse
import builtins
import copyreg
import io
import os
import pickle
from pathlib import Path
from typing import Any

import numpy as np
import numpy.dtypes as npd
from numpy._core import multiarray
from numpy.lib import format as npy_format

from modi.errors import CheckpointError
from modi.io.safe_load import load_data, numpy_data_globals

ALLOWED_GLOBALS = [argparse.Namespace, *numpy_data_globals()]


def load_released_file(path: str | os.PathLike, what: str = "released checkpoint") -> dict[str, Any]:
    """A released checkpoint's top-level dict, read as data through :func:`modi.io.safe_load.load_data` with
    exactly the classes their ``train.py`` pickles allowed; one ``CheckpointError`` line for anything else."""
    p = Path(path)
    st = load_data(p, what, allowed=ALLOWED_GLOBALS)
    if not isinstance(st, dict):
        raise CheckpointError(f"{p}: not a {what} (top level is {type(st).__name__}, not a dict)")
    return st


class ReleasedQuaternions:
    """What a pickled ``Motion.Quaternions.Quaternions`` of the released code becomes: its ``qs`` array, no code."""

    def __setstate__(self, state: dict) -> None:
        self.qs = np.asarray(state.get("qs"), dtype=np.float64)

    def __array__(self, dtype: Any = None, copy: Any = None) -> np.ndarray:
        return self.qs if dtype is None else self.qs.astype(dtype)


_NPY_GLOBALS = {
    ("numpy.core.multiarray", "_reconstruct"), ("numpy._core.multiarray", "_reconstruct"),
    ("numpy.core.multiarray", "scalar"), ("numpy._core.multiarray", "scalar"),
    ("numpy", "ndarray"), ("numpy", "dtype"), ("copyreg", "_reconstructor"), ("builtins", "object"),
}


def load_released_npy(path: str | os.PathLike) -> np.ndarray:
    """A released ``.npy`` of pickled per-clip dicts (their ``preprocess_edges.py`` output), read with a pickle
    loader that builds only numpy arrays, plain containers and :class:`ReleasedQuaternions`; any other class or
    function named in the file is refused instead of imported."""
    p = Path(path)

    class Restricted(pickle.Unpickler):
        def find_class(self, module: str, name: str) -> Any:
            if (module, name) in _NPY_GLOBALS:
                if name == "_reconstruct":
                    return multiarray._reconstruct
                if name == "scalar":
                    return multiarray.scalar
                return {"ndarray": np.ndarray, "dtype": np.dtype, "_reconstructor": copyreg._reconstructor,
                        "object": builtins.object}[name]
            if name == "Quaternions" and module.endswith("Quaternions"):
                return ReleasedQuaternions
            if module.startswith("numpy") and name.endswith("DType"):
                if hasattr(npd, name):
                    return getattr(npd, name)
            raise pickle.UnpicklingError(f"refusing {module}.{name}: it is code, not data")

    try:
        with open(p, "rb") as f:
            version = npy_format.read_magic(f)
            read_header = npy_format.read_array_header_1_0 if version == (1, 0) else npy_format.read_array_header_2_0
            shape, _, dtype = read_header(f)
            if dtype.hasobject:
                arr = Restricted(io.BufferedReader(f)).load()
            else:
                arr = np.fromfile(f, dtype=dtype).reshape(shape)
    except FileNotFoundError:
        raise CheckpointError(f"{p}: no such file") from None
    except Exception as exc:  # noqa: BLE001 - not an npy, truncated, or holding code we refuse
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise CheckpointError(f"{p}: not a readable released data file ({first[:200]})") from None
    return np.asarray(arr, dtype=object) if not isinstance(arr, np.ndarray) else arr


__all__ = ["ALLOWED_GLOBALS", "load_released_file", "load_released_npy", "ReleasedQuaternions"]
