"""Where pobax keeps derived files (Craftax textures, compiled programs)."""

import os
import shlex
from pathlib import Path


def cache_dir() -> Path:
    """`$POBAX_CACHE_DIR`, else `$XDG_CACHE_HOME/pobax`, else `~/.cache/pobax`."""
    if os.environ.get("POBAX_CACHE_DIR"):
        return Path(os.environ["POBAX_CACHE_DIR"])
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "pobax"


def printable(text: object) -> str:
    """`text` as it prints on one line: control characters (a newline in a directory's name) and bytes that are not
    UTF-8 (surrogates, as argv and the file system hand them over) escaped as Python writes them (`\\n`, `\\udcff`);
    other text as it is."""
    text = str(text)
    return text if text.isprintable() else "".join(
        c if c.isprintable() else c.encode("unicode_escape", "backslashreplace").decode("ascii") for c in text)


def shown(value: object) -> str:
    """`value` for a one-line message: an integer too long to read as its number of digits (`str()` refuses one of
    more than 4,300 digits), anything else as `str` gives it."""
    if isinstance(value, int) and abs(value) > 10**30:
        return f"an integer of about {int(abs(value).bit_length() * 0.30103) + 1:,} digits"
    return str(value)


def shell_word(text: object) -> str:
    """`text` quoted as one word for a POSIX shell, on one line: `shlex.quote`'s, or bash's `$'...'` with the
    characters that are not printable escaped (a name with a newline or a byte that is not UTF-8)."""
    text = str(text)
    if text.isprintable():
        return shlex.quote(text)
    out = []
    for c in text:
        if 0xDC80 <= ord(c) <= 0xDCFF:  # a byte that is not UTF-8, as a surrogate: the byte itself
            out.append(f"\\x{ord(c) - 0xDC00:02x}")
        elif c in "\\'":
            out.append("\\" + c)
        elif c.isprintable():
            out.append(c)
        else:
            out.append("".join(f"\\x{b:02x}" for b in c.encode("utf-8", "surrogatepass")))
    return "$'" + "".join(out) + "'"
