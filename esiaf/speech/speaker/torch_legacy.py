"""Reading a checkpoint in torch's legacy serialization format without torch.

``torch.save`` before torch 1.6 wrote a file that is a sequence of pickles, not a zip:
magic number, protocol version, system info, then the object (here a dict holding the state
dict) pickled with persistent ids standing for storages, then the list of storage keys, then,
for each key in that order, an int64 element count and the storage's raw little-endian bytes.
Reading it needs only :mod:`pickle` and numpy: tensors come back as numpy arrays. Doing it
here means no export step and no torch, not even at build time.
"""
from __future__ import annotations

import collections
import pickle
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np

MAGIC_NUMBER = 0x1950A86A20F9469CFC6C
PROTOCOL_VERSION = 1001
STORAGE_DTYPES = {"FloatStorage": np.float32, "DoubleStorage": np.float64, "HalfStorage": np.float16,
                  "LongStorage": np.int64, "IntStorage": np.int32, "ShortStorage": np.int16,
                  "CharStorage": np.int8, "ByteStorage": np.uint8, "BoolStorage": np.bool_}


class LegacyFormatError(ValueError):
    pass


class _Storage:
    def __init__(self, dtype: type, key: str, size: int):
        self.dtype, self.key, self.size = dtype, key, size
        self.data: np.ndarray | None = None


class _StorageType:
    def __init__(self, name: str):
        if name not in STORAGE_DTYPES:
            raise LegacyFormatError(f"unsupported storage type {name}")
        self.dtype = STORAGE_DTYPES[name]


class _Tensor:
    """A tensor view on a storage, resolved into an array once the storages are read."""

    def __init__(self, storage: _Storage, offset: int, shape: tuple[int, ...], strides: tuple[int, ...]):
        self.storage, self.offset, self.shape, self.strides = storage, offset, tuple(shape), tuple(strides)

    def array(self) -> np.ndarray:
        data = self.storage.data
        assert data is not None  # the storages are read before the tensors are resolved
        itemsize = data.itemsize
        view = np.lib.stride_tricks.as_strided(data[self.offset:], shape=self.shape,
                                               strides=tuple(s * itemsize for s in self.strides))
        return np.array(view)


def _rebuild_tensor_v2(storage, offset, shape, strides, *_ignored):
    return _Tensor(storage, offset, shape, strides)


class _Unpickler(pickle.Unpickler):
    def __init__(self, file: BinaryIO, storages: dict[str, _Storage]):
        super().__init__(file)
        self.storages = storages

    def find_class(self, module: str, name: str) -> Any:
        if module == "torch._utils" and name in ("_rebuild_tensor_v2", "_rebuild_tensor"):
            return _rebuild_tensor_v2
        if module == "torch" and name.endswith("Storage"):
            return _StorageType(name)
        if module == "collections" and name == "OrderedDict":
            return collections.OrderedDict
        raise LegacyFormatError(f"refusing to load {module}.{name} from a checkpoint")

    def persistent_load(self, pid: tuple) -> _Storage:
        kind, storage_type, key, _location, size = pid[:5]
        if kind != "storage":
            raise LegacyFormatError(f"unknown persistent id {kind!r}")
        if key not in self.storages:
            self.storages[key] = _Storage(storage_type.dtype, key, size)
        return self.storages[key]


def _resolve(value: Any) -> Any:
    if isinstance(value, _Tensor):
        return value.array()
    if isinstance(value, dict):
        return type(value)((k, _resolve(v)) for k, v in value.items())
    if isinstance(value, (list, tuple)):
        return type(value)(_resolve(v) for v in value)
    return value


def load(path: str | Path) -> Any:
    """The object saved in a legacy-format checkpoint, with every tensor as a numpy array."""
    with open(path, "rb") as file:
        if file.read(2) == b"PK":
            raise LegacyFormatError(f"{path} is a zip checkpoint, not the legacy format")
        file.seek(0)
        try:
            magic = pickle.load(file)
            protocol = pickle.load(file)
        except Exception as exc:  # pickle raises many types on garbage
            raise LegacyFormatError(f"{path} is not a torch checkpoint ({exc})") from None
        if magic != MAGIC_NUMBER or protocol != PROTOCOL_VERSION:
            raise LegacyFormatError(f"{path} is not a legacy torch checkpoint (magic {magic!r}, protocol {protocol!r})")
        pickle.load(file)  # system info: endianness and type sizes (little-endian assumed)
        storages: dict[str, _Storage] = {}
        obj = _Unpickler(file, storages).load()
        keys = pickle.load(file)
        for key in keys:
            storage = storages[key]
            count = int(np.frombuffer(file.read(8), "<i8")[0])
            raw = file.read(count * np.dtype(storage.dtype).itemsize)
            if len(raw) != count * np.dtype(storage.dtype).itemsize:
                raise LegacyFormatError(f"{path} is truncated in storage {key}")
            storage.data = np.frombuffer(raw, storage.dtype)
    return _resolve(obj)
