"""Rebuilding a tree of Equinox modules with some of their static fields changed (the configuration that a program
passes down to the modules it runs, e.g. `pobax.memory.with_matmul_batch`)."""

import dataclasses

import equinox as eqx


def map_modules(fn, tree):
    """`tree` with every `eqx.Module` in it replaced by `fn(module)`, innermost first (`fn` sees its children
    already mapped). Modules are rebuilt field by field, as Equinox unflattens them, so static fields can change;
    the array leaves are the same objects (tracers included)."""

    def rebuild(x):
        if isinstance(x, eqx.Module):
            new = object.__new__(type(x))
            for f in dataclasses.fields(x):
                object.__setattr__(new, f.name, rebuild(getattr(x, f.name)))
            return fn(new)
        if isinstance(x, tuple) and hasattr(x, "_fields"):  # a named tuple
            return type(x)(*map(rebuild, x))
        if isinstance(x, (tuple, list)):
            return type(x)(map(rebuild, x))
        if isinstance(x, dict):
            return type(x)((k, rebuild(v)) for k, v in x.items())
        return x

    return rebuild(tree)


def replace_static(module: eqx.Module, **fields) -> eqx.Module:
    """A copy of `module` with these fields (static or not) set, without calling its `__init__`."""
    new = object.__new__(type(module))
    for f in dataclasses.fields(module):
        object.__setattr__(new, f.name, fields.get(f.name, getattr(module, f.name)))
    return new
