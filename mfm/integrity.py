"""File checksums: the one sha256 used for text-encoder weights, dataset shards and checkpoints."""

from __future__ import annotations

import hashlib
import os

_CHUNK_BYTES = 1 << 20  # weights and shards are hundreds of MB: never read a whole file into memory


def sha256_file(path: str | os.PathLike) -> str:
    """Hex sha256 of a file's bytes, read in 1 MiB chunks."""
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        while chunk := handle.read(_CHUNK_BYTES):
            digest.update(chunk)
    return digest.hexdigest()
