"""Memories by name: the built-in ones (`MEMORIES`, the one place that lists them) and a user's cell given as
`package.module:ClassName`."""

import importlib
import inspect
import os
import sys

from ._base import AbstractMemory
from ._gru import GRU
from ._ffm import FFM
from ._lru import LRU
from ._lstm import LSTM
from ._memax import S6
from ._memoryless import Memoryless
from ._trxl import TransformerXL

#: The built-in memories by name. The paper's three (memoryless, gru, trxl) take their own options (`TrainConfig`'s
#: GRU and Transformer-XL fields); the zoo's and a user's cells are built as `Class(in_size, hidden_size, key=key)`.
BUILTIN: dict[str, type[AbstractMemory]] = {
    "memoryless": Memoryless,
    "gru": GRU,
    "trxl": TransformerXL,
    "lstm": LSTM,
    "lru": LRU,
    "s6": S6,
    "ffm": FFM,
}
MEMORIES: tuple[str, ...] = tuple(BUILTIN)
#: The memories of the paper's agents, which have presets of their own in the registry.
PAPER_MEMORIES: tuple[str, ...] = ("memoryless", "gru", "trxl")
#: The zoo: the built-in memories beyond the paper's.
ZOO: tuple[str, ...] = tuple(name for name in MEMORIES if name not in PAPER_MEMORIES)


def memory_class(spec: str) -> type[AbstractMemory]:
    """The memory class that `spec` names: a built-in name (`MEMORIES`) or `package.module:ClassName`, a subclass of
    `AbstractMemory` importable from `sys.path` or the current directory. Raises ValueError (one line) otherwise."""
    if not isinstance(spec, str):
        raise ValueError(f"A memory is a name or package.module:ClassName, got {spec!r}.")
    if spec in BUILTIN:
        return BUILTIN[spec]
    if ":" not in spec:
        raise ValueError(f"Unknown memory {spec!r}: the built-in memories are {', '.join(MEMORIES)}; give your own "
                         f"cell as package.module:ClassName.")
    module_name, _, name = spec.partition(":")
    if not module_name or not name or ":" in name:
        raise ValueError(f"Memory {spec!r} is not of the form package.module:ClassName.")
    module = _import(spec, module_name)
    cls = module
    for part in name.split("."):
        if not hasattr(cls, part):
            raise ValueError(f"Memory {spec!r}: module {module_name!r} has no attribute {name!r}.")
        cls = getattr(cls, part)
    if not (isinstance(cls, type) and issubclass(cls, AbstractMemory)):
        raise ValueError(f"Memory {spec!r}: {name} is not a subclass of pobax.memory.AbstractMemory "
                         f"({type(cls).__name__} {cls!r}).")
    try:
        inspect.signature(cls).bind(1, 1, key=None)
    except TypeError as e:
        raise ValueError(f"Memory {spec!r}: pobax builds it as {name}(in_size, hidden_size, key=key), which its "
                         f"signature {inspect.signature(cls)} does not accept ({e}).") from None
    except ValueError:  # no signature to inspect (e.g. a C extension): found out when it is built
        pass
    return cls


def _import(spec: str, module_name: str):
    try:
        return importlib.import_module(module_name)
    except ModuleNotFoundError as e:
        # Like `python -m`: a module in the current directory is found even when pobax runs as an installed script.
        top = module_name.split(".")[0]
        if e.name != top or os.getcwd() in sys.path or not _in_cwd(top):
            raise ValueError(f"Memory {spec!r}: cannot import {module_name!r} ({e}); is it on PYTHONPATH?") from None
        sys.path.append(os.getcwd())
        return _import(spec, module_name)
    except Exception as e:  # noqa: BLE001  (the user's module failed while importing)
        first = str(e).splitlines()[0] if str(e) else ""
        raise ValueError(f"Memory {spec!r}: importing {module_name!r} failed ({type(e).__name__}: {first}).") from None


def _in_cwd(top: str) -> bool:
    return os.path.isfile(f"{top}.py") or os.path.isfile(os.path.join(top, "__init__.py"))
