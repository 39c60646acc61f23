"""Reading the small TOML files the project is configured with (phantoms here; settings above), bounded."""

from __future__ import annotations

import os
import stat
import tomllib
from pathlib import Path
from typing import Any

MAX_TOML_BYTES = 1 << 20  # configuration and phantom files are a few kB; this bounds what reading one costs


class UnreadableFile(ValueError):
    """A file that cannot serve as the TOML table it was asked for; ``problem`` says why in a few words."""

    def __init__(self, path: str, problem: str):
        super().__init__(f"{path}: {problem}")
        self.path, self.problem = path, problem


def read_toml(path: Path, what: str) -> dict[str, Any]:
    """A TOML file's table, or UnreadableFile for any file that cannot serve: missing, a folder, not a
    regular file (a FIFO or a device would block or never end), unreadable, over ``MAX_TOML_BYTES``, not
    UTF-8, not TOML, or nested beyond what the parser can follow. ``what`` names the file in the message."""
    key = str(path)
    try:
        # opened without blocking, so that a FIFO with no writer is refused instead of waited on
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
        with open(fd, "rb") as f:
            if not stat.S_ISREG(os.fstat(f.fileno()).st_mode):
                raise UnreadableFile(key, f"not a regular file: not a {what}")
            raw = f.read(MAX_TOML_BYTES + 1)
    except FileNotFoundError:
        raise UnreadableFile(key, f"no such {what}") from None
    except IsADirectoryError:
        raise UnreadableFile(key, f"is a folder, not a {what}") from None
    except OSError as err:
        raise UnreadableFile(key, f"cannot read it ({err.strerror or err})") from None
    if len(raw) > MAX_TOML_BYTES:
        raise UnreadableFile(key, f"larger than {MAX_TOML_BYTES >> 10} kB: not a {what}")
    try:
        return tomllib.loads(raw.decode("utf-8"))
    except UnicodeDecodeError:
        raise UnreadableFile(key, "not UTF-8 text") from None
    except tomllib.TOMLDecodeError as err:
        raise UnreadableFile(key, f"not valid TOML: {err}") from None
    except RecursionError:
        raise UnreadableFile(key, "nested too deeply to be a settings file") from None
