"""Checks of the Python API's arguments, shared by its functions (as `train` checks its own): a value of the wrong
kind is refused in one line naming the function and the argument, before anything is trained or written, instead of
read as something else (a string "no" as True, a string as a tuple of its characters) or failing deep inside."""

import os
from pathlib import Path

import numpy as np


def check_bools(where: str, error: type[Exception] = ValueError, **flags) -> None:
    """`error` unless every flag is True or False (numpy's bool_ too): any other value would read as one of them."""
    for flag, value in flags.items():
        if not isinstance(value, (bool, np.bool_)):
            raise error(f"{where}: {flag} must be True or False, got {value!r}.")


def is_int(value) -> bool:
    """Whether `value` is an integer (numpy's too; not a bool, a float or a string of digits)."""
    return isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))


def is_count(value) -> bool:
    """Whether `value` is a positive integer (`is_int`)."""
    return is_int(value) and value >= 1


def as_path(where: str, name: str, value, error: type[Exception] = ValueError, *, none: bool = False,
            what: str = "a path") -> Path | None:
    """The path argument `value` (`what`: e.g. "a directory path") as a Path, `~` expanded as a shell would (None
    stays None where `none` allows it); `error` for anything else: a number, "" (which would mean the current
    directory), a path holding a NUL."""
    if value is None and none:
        return None
    text = os.fspath(value) if isinstance(value, (str, os.PathLike)) else None
    if not isinstance(text, str) or text == "":
        raise error(f"{where}: {name} must be {what} (a str or Path{', or None' if none else ''}), got {value!r}.")
    if "\x00" in text:
        raise error(f"{where}: {name} {text!r} holds a NUL character, which no path may: remove it.")
    return Path(os.path.expanduser(text))


def check_names(where: str, name: str, value, error: type[Exception] = ValueError, what: str = "names") -> None:
    """`error` where `value`, a tuple of names (or paths), is a bare string: it would be read one character at a
    time."""
    if isinstance(value, (str, bytes, os.PathLike)):
        raise error(f"{where}: {name} is a tuple (or list) of {what}, got the single value {value!r}: pass "
                    f"{name}=({value!r},).")
