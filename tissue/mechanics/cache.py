"""On-disk cache of precomputed tissue tables, keyed by what they were computed from.

One file per key. The file is a short JSON header line (format, key, the digest of the mechanics' source
that computed it, payload length and SHA-256) followed by an ``.npz`` payload; it is written to a
temporary file in the same directory and renamed into place, so a reader never sees a half-written file.
A file that is truncated, corrupt, from another key, another format version or other mechanics code is
reported as a miss (and the caller recomputes and overwrites it): cached numbers are never trusted
without their checksum, nor once the code that made them has changed (a version number bumped by hand
was missed, and an analysis then read a solve of code that no longer existed: a tumour's score moved
from 38.2 to 37.2 depending on what the machine had cached before).
"""

from __future__ import annotations

import functools
import hashlib
import io
import json
import os
import tempfile
from pathlib import Path

import numpy as np

FORMAT = "palpation-console/tissue-tables"
ENV_VAR = "PALPATION_CACHE_DIR"


def default_cache_dir() -> Path:
    """``$PALPATION_CACHE_DIR`` if set, else the user cache directory of the application."""
    override = os.environ.get(ENV_VAR)
    if override:
        return Path(override)
    from platformdirs import user_cache_dir

    return Path(user_cache_dir("palpation-console"))


# The modules beside this package whose code the tables are computed from too: the phantom's surface, relief
# and inclusions as the mesh takes them (tissue.phantom), and the sensor's face (tissue.face). Without them a
# change to how a phantom's relief is drawn left every table of a relief phantom as the old relief gave it.
BEYOND = ("phantom.py", "face.py")


def sources(package: Path = Path(__file__).parent) -> list[Path]:
    """The source files every cached table comes from, in the order the digest reads them."""
    return sorted(package.glob("*.py")) + [package.parent / name for name in BEYOND]


def digest_of(package: Path) -> str:
    """The digest of the :func:`sources` of the mechanics package at ``package``."""
    digest = hashlib.sha256()
    for path in sources(package):
        digest.update(path.relative_to(package.parent).as_posix().encode() + b"\0" + path.read_bytes())
    return digest.hexdigest()[:16]


@functools.cache
def code_digest() -> str:
    """The digest of the code every cached table comes from (:func:`sources`)."""
    return digest_of(Path(__file__).parent)


def cache_path(cache_dir: Path, key: str) -> Path:
    return Path(cache_dir) / f"tissue-{key}.bin"


def load(path: Path, key: str) -> dict[str, np.ndarray] | None:
    """The arrays stored under ``key`` at ``path``, or None if absent or not trustworthy."""
    try:
        blob = Path(path).read_bytes()
    except OSError:
        return None
    head, sep, body = blob.partition(b"\n")
    if not sep:
        return None
    try:
        header = json.loads(head.decode("utf-8"))
        if (header.get("format") != FORMAT or header.get("key") != key or header.get("code") != code_digest()
                or header.get("length") != len(body)
                or header.get("sha256") != hashlib.sha256(body).hexdigest()):
            return None
        with np.load(io.BytesIO(body), allow_pickle=False) as npz:
            return {name: npz[name] for name in npz.files}
    except (ValueError, OSError, KeyError, UnicodeDecodeError, EOFError):
        return None


def store(path: Path, key: str, arrays: dict[str, np.ndarray]) -> None:
    """Write atomically (temporary file + rename); a failure leaves any previous file untouched."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    body = buf.getvalue()
    header = {"format": FORMAT, "key": key, "code": code_digest(), "length": len(body),
              "sha256": hashlib.sha256(body).hexdigest()}
    fd, tmp = tempfile.mkstemp(prefix=path.name + ".", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(json.dumps(header).encode("utf-8") + b"\n")
            fh.write(body)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise
