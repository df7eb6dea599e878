"""Read the tensors of a TorchScript archive (such as OpenAI's ViT-B-32.pt) without running it.

Loading it as TorchScript compiles and runs the archive's `code/`, and plain unpickling of its
`data.pkl` calls whatever globals the file names: a downloaded file could run anything.
Tensors need none of that: `data.pkl` is a tree of module objects whose attributes are tensors
rebuilt from raw storages in `data/<key>`. This reader unpickles it with a whitelist:

- `torch._utils._rebuild_tensor_v2` / `_rebuild_parameter`: replaced by local functions that
  view the raw storage bytes (any offset and stride, so sliced and non-contiguous tensors work);
- storage classes (`torch.HalfStorage`, `torch.FloatStorage`, ..., `torch.UntypedStorage`, the
  `torch.cuda.*` forms of old archives): only markers of the dtype, never constructed;
- `collections.OrderedDict`, and the inert helpers the TorchScript pickler writes for typed
  containers and devices (`torch.jit._pickle.*`, `torch.device`), replaced by local functions;
- `__torch__.*` (the archive's module classes): an inert placeholder that records its state.

Any other global (`os.system`, `builtins.exec`, ...) stops the read with `UnsafeArchiveError`
before anything is called. `code/` and `constants.pkl` are never read.
"""

from __future__ import annotations

import collections
import pickle
import zipfile
from pathlib import Path

import torch

__all__ = ["UnsafeArchiveError", "read_torchscript_tensors"]

_STORAGE_DTYPES = {
    "HalfStorage": torch.float16,
    "FloatStorage": torch.float32,
    "DoubleStorage": torch.float64,
    "BFloat16Storage": torch.bfloat16,
    "LongStorage": torch.int64,
    "IntStorage": torch.int32,
    "ShortStorage": torch.int16,
    "CharStorage": torch.int8,
    "ByteStorage": torch.uint8,
    "BoolStorage": torch.bool,
    "UntypedStorage": torch.uint8,
}
_FIX = "the file is damaged or is not a TorchScript archive (such as OpenAI's ViT-B-32.pt); download it again"


class UnsafeArchiveError(pickle.UnpicklingError):
    """data.pkl names a global that rebuilding tensors never needs."""


class _ScriptObject:
    """Stands in for an archive class (`__torch__.*`): keeps the pickled state, runs nothing."""

    args, state = (), None

    def __init__(self, *args):
        self.args = args

    def __setstate__(self, state):
        self.state = state


class _StorageType:
    def __init__(self, name: str, dtype: torch.dtype):
        self.name, self.dtype = name, dtype


def _rebuild_tensor(storage, offset, size, stride, *_ignored):
    """(flat storage tensor, offset, size, stride, requires_grad, hooks[, metadata]) -> a view."""
    size, stride = tuple(size), tuple(stride)
    extent = offset + sum((n - 1) * s for n, s in zip(size, stride)) + 1 if all(size) else offset
    if offset < 0 or any(s < 0 for s in stride) or extent > storage.numel():
        raise pickle.UnpicklingError(f"a tensor of size {size} at offset {offset} lies outside its storage")
    return storage.as_strided(size, stride, offset)


def _rebuild_parameter(data, requires_grad=False, backward_hooks=None, *_ignored):
    return data


def _restore_type_tag(value, type_str=None):
    return value


def _device(name):
    return str(name)


_ALLOWED = {
    ("torch._utils", "_rebuild_tensor_v2"): _rebuild_tensor,
    ("torch._utils", "_rebuild_parameter"): _rebuild_parameter,
    ("collections", "OrderedDict"): collections.OrderedDict,
    ("torch.jit._pickle", "restore_type_tag"): _restore_type_tag,
    ("torch", "device"): _device,
    **{("torch.jit._pickle", f"build_{kind}list"): list for kind in ("int", "double", "bool", "tensor")},
    **{
        (module, name): _StorageType(name, dtype)
        for name, dtype in _STORAGE_DTYPES.items()
        for module in ("torch", "torch.cuda")
    },
}


class _TensorUnpickler(pickle.Unpickler):
    def __init__(self, file, archive: zipfile.ZipFile, prefix: str, source: Path):
        super().__init__(file)
        self.archive, self.prefix, self.source = archive, prefix, source
        self.storages: dict[str, torch.Tensor] = {}

    def find_class(self, module: str, name: str):
        if module == "__torch__" or module.startswith("__torch__."):
            return _ScriptObject
        allowed = _ALLOWED.get((module, name))
        if allowed is None:
            raise UnsafeArchiveError(
                f"{self.source}: data.pkl references the global {module}.{name}, which a tensor archive "
                "never "
                "needs; refusing to read it (nothing from the file was run). Use a checkpoint from a trusted "
                "source."
            )
        return allowed

    def persistent_load(self, pid):
        # ("storage", storage type, key, location, number of elements)
        if not (
            isinstance(pid, tuple)
            and len(pid) >= 4
            and pid[0] == "storage"
            and isinstance(pid[1], _StorageType)
        ):
            raise pickle.UnpicklingError(f"unexpected persistent id {pid!r}")
        kind, key = pid[1], str(pid[2])
        if key not in self.storages:
            raw = bytearray(self.archive.read(f"{self.prefix}data/{key}"))
            itemsize = torch.empty(0, dtype=kind.dtype).element_size()
            numel = int(pid[4]) if len(pid) > 4 else len(raw) // itemsize
            if len(raw) < numel * itemsize:
                raise pickle.UnpicklingError(
                    f"storage data/{key} holds {len(raw)} bytes, expected {numel * itemsize}"
                )
            flat = (
                torch.frombuffer(raw, dtype=kind.dtype, count=numel)
                if numel
                else torch.empty(0, dtype=kind.dtype)
            )
            self.storages[key] = flat
        return self.storages[key]


def _walk(obj, prefix: str, out: dict[str, torch.Tensor], seen: set[int]) -> None:
    """Name every tensor under obj: module attributes, list/tuple items and dict keys, dotted."""
    if isinstance(obj, torch.Tensor):
        out[prefix] = obj
        return
    if id(obj) in seen:  # pickle memo can make cycles
        return
    seen = seen | {id(obj)}
    if isinstance(obj, _ScriptObject):
        _walk(obj.state, prefix, out, seen)
    elif isinstance(obj, dict):
        for key, value in obj.items():
            _walk(value, f"{prefix}.{key}" if prefix else str(key), out, seen)
    elif isinstance(obj, (list, tuple)):
        for i, value in enumerate(obj):
            _walk(value, f"{prefix}.{i}" if prefix else str(i), out, seen)


def read_torchscript_tensors(path: str | Path) -> dict[str, torch.Tensor]:
    """Every tensor attribute of a TorchScript archive by dotted name (`transformer.resblocks.0.
    attn.in_proj_weight`, `token_embedding.weight`, ...), with the archive's dtypes, on the CPU.
    Parameters and buffers, as in the module's state_dict, and any other tensor attribute."""
    path = Path(path)
    if not zipfile.is_zipfile(path):
        if not path.is_file():
            raise FileNotFoundError(f"TorchScript archive not found: {path}")
        raise ValueError(f"{path} is not a zip archive (or is cut short); {_FIX}")
    try:
        with zipfile.ZipFile(path) as archive:
            pickles = [
                n for n in archive.namelist() if n.rsplit("/", 1)[-1] == "data.pkl" and n.count("/") <= 1
            ]
            if pickles:
                prefix = min(pickles, key=len)[: -len("data.pkl")]
                with archive.open(prefix + "data.pkl") as fh:
                    root = _TensorUnpickler(fh, archive, prefix, path).load()
    except UnsafeArchiveError:
        raise
    except Exception as e:  # any failure to parse is a damaged file; nothing was executed
        raise ValueError(
            f"cannot read the TorchScript archive {path} ({type(e).__name__}: {e}); {_FIX}"
        ) from e
    if not pickles:
        raise ValueError(f"{path} is a zip archive without data.pkl; {_FIX}")
    tensors: dict[str, torch.Tensor] = {}
    _walk(root, "", tensors, set())
    return tensors
