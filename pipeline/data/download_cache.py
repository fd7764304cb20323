"""The local shard cache (training's ``data.cache_dir``): a remote shard is downloaded once, checked against its
manifest entry, and read from a local file every later epoch and every later run (webdataset's ``cache_dir``, with
verification). Local shards are never copied.

Entries. One file per shard content, named by the manifest's sha256 (``<cache_dir>/<sha256>``): content-addressed,
so two manifests that list the same bytes share an entry, and a shard rebuilt with other bytes is a new entry. A
download is written to a temporary name in the same folder, hashed while it is written, and renamed to the entry's
name only when its size and sha256 are the manifest's; otherwise :class:`DownloadMismatch` names the URL and the
reason and the temporary file is removed (nothing is kept). The rename is atomic: a reader sees a whole verified
entry or none. Two writers of the same entry (DataLoader workers, ranks on one machine) each write their own
temporary file and the second rename replaces the first with identical verified bytes; a reader that opened the
first keeps reading it.

What is checked when. Written: size and sha256, always. Opened (every epoch): the size against the manifest's; a
different size (truncated by a crash or a user) is logged as a warning, the entry removed and the shard downloaded
again. The content of an entry is not hashed again on each open (a full read of the file before every epoch);
verification at the start of a run (``data.verify`` strict or tolerant) hashes every entry it uses, and one whose
bytes differ is removed and downloaded again (:func:`pipeline.data.stream.check_shard`). So a same-size corruption
on disk is caught at the next start, not in the middle of a run.

Size cap (``max_bytes``; training's ``data.cache_max_gb``, 0 = no cap). After each download the least recently used
entries (by modification time, which every open refreshes) are removed until the cache is under the cap; the entry
just written is kept even when it alone is over the cap (it is about to be read). A reader still holding a removed
entry open keeps reading it (POSIX). Files in the folder that are not entries are never touched, except this
module's own temporary files left by a crash (removed after a day).

Counting: :attr:`ShardDownloadCache.served` (shards read from an entry) and :attr:`ShardDownloadCache.fetched`
(downloads), per process; the loader sums its readers' counts (``MotionLoader.shards_from_cache`` /
``shards_fetched``) and verification reports its own (``VerificationReport.num_cache_served`` / ``num_downloaded``).
"""

from __future__ import annotations

import hashlib
import logging
import os
import re
import threading
import time
import uuid
from typing import BinaryIO

logger = logging.getLogger(__name__)

_ENTRY_NAME = re.compile(r"[0-9a-f]{64}")
_TMP_SUFFIX = ".download"
STALE_TMP_S = 86400.0
"""A temporary download file older than this is a crash's leftover: removed when the cache is trimmed."""
COPY_BLOCK = 1 << 20


class DownloadMismatch(ValueError):
    """The bytes downloaded are not the manifest's (size or sha256); nothing was kept. The message names the URL;
    ``reason`` is the same without it ("corrupted: ...", "truncated: ...")."""

    def __init__(self, url: str, reason: str):
        super().__init__(f"{url}: {reason}; nothing was kept in the shard cache")
        self.url, self.reason = url, reason


def _touch(path: str) -> None:
    try:
        os.utime(path)  # the last use: least-recently-used entries go first when the cache is trimmed
    except OSError:
        pass


class ShardDownloadCache:
    """Verified local copies of remote shards in ``folder`` (see the module docstring). ``max_bytes``: 0 or None, no
    cap. Picklable: each DataLoader worker gets its own copy, with its own counters."""

    def __init__(self, folder: str | os.PathLike, max_bytes: int | None = None):
        self.folder = os.path.abspath(os.path.expanduser(os.fspath(folder)))
        self.max_bytes = int(max_bytes or 0)
        if self.max_bytes < 0:
            raise ValueError(f"shard cache size cap must be >= 0 bytes (0: no cap), got {max_bytes!r}")
        self.served = 0
        self.fetched = 0

    def entry_path(self, sha256: str) -> str:
        """Where the entry of a shard with this sha256 lives. A manifest value that is not a sha256 (64 lower-case hex
        digits) is refused: it names a file in the cache folder."""
        if not isinstance(sha256, str) or not _ENTRY_NAME.fullmatch(sha256):
            raise ValueError(f"the manifest's sha256 {sha256!r} is not 64 hexadecimal digits, so it cannot name a "
                             "shard cache entry")
        return os.path.join(self.folder, sha256)

    def open_entry(self, url: str, size: int, sha256: str) -> BinaryIO | None:
        """The cached copy of the shard, open for reading, or None when there is none. An entry whose size is not
        ``size`` is removed (warning) and None returned: the caller downloads it again."""
        path = self.entry_path(sha256)
        try:
            file = open(path, "rb")  # noqa: SIM115  (handed to the caller, who closes it)
        except FileNotFoundError:
            return None
        found = os.fstat(file.fileno()).st_size
        if found != size:
            file.close()
            self.discard(sha256, f"{url}: shard cache entry {path} holds {found} bytes, the manifest says {size} "
                                 "(truncated or damaged)")
            return None
        _touch(path)
        self.served += 1
        return file

    def discard(self, sha256: str, why: str) -> None:
        """Remove an entry found wrong (``why`` is logged as a warning); it is downloaded again when next needed."""
        logger.warning("%s: removed from the shard cache, it will be downloaded again", why)
        try:
            os.unlink(self.entry_path(sha256))
        except FileNotFoundError:
            pass

    def store(self, url: str, size: int, sha256: str, stream: BinaryIO) -> BinaryIO:
        """Copy ``stream`` (the shard's bytes, front to back) into the cache, hashing as it writes; rename it to the
        entry only when size and sha256 are ``size`` and ``sha256``, else raise :class:`DownloadMismatch` (the
        temporary file is removed). Errors of ``stream`` propagate as they are (the caller retries transient
        ones). Returns the entry open for reading (opened before the rename, so a trim by another process cannot
        take it away first)."""
        path = self.entry_path(sha256)
        os.makedirs(self.folder, exist_ok=True)
        tmp = f"{path}.{os.getpid()}.{threading.get_ident()}.{uuid.uuid4().hex[:8]}{_TMP_SUFFIX}"
        digest, written = hashlib.sha256(), 0
        try:
            with open(tmp, "wb") as out:
                while block := stream.read(COPY_BLOCK):
                    digest.update(block)
                    out.write(block)
                    written += len(block)
            found = digest.hexdigest()
            if written != size or found != sha256:
                what = "truncated" if written < size else "size mismatch" if written != size else "corrupted"
                raise DownloadMismatch(url, f"{what}: the bytes downloaded are {written} bytes with sha256 "
                                            f"{found[:16]}…, the manifest says {size} bytes with sha256 {sha256[:16]}…")
            copy = open(tmp, "rb")  # noqa: SIM115  (returned open: see the docstring)
            try:
                os.replace(tmp, path)
            except BaseException:
                copy.close()
                raise
        except BaseException:
            try:
                os.unlink(tmp)
            except FileNotFoundError:
                pass
            raise
        self.fetched += 1
        logger.info("%s: downloaded into the shard cache (%d bytes, sha256 verified): %s", url, size, path)
        if self.max_bytes:
            self.trim(keep=path)
        return copy

    def entries(self) -> list[os.DirEntry]:
        """The cache's entries (files named by a sha256), in no particular order."""
        try:
            with os.scandir(self.folder) as found:
                return [e for e in found if _ENTRY_NAME.fullmatch(e.name) and e.is_file(follow_symlinks=False)]
        except FileNotFoundError:
            return []

    def trim(self, keep: str | None = None) -> None:
        """Remove least-recently-used entries until the cache is under ``max_bytes`` (``keep`` stays), and the
        temporary files of crashed downloads older than :data:`STALE_TMP_S`."""
        now = time.time()
        try:
            with os.scandir(self.folder) as found:
                for entry in found:
                    if entry.name.endswith(_TMP_SUFFIX) and _ENTRY_NAME.fullmatch(entry.name[:64]):
                        try:
                            if entry.stat().st_mtime < now - STALE_TMP_S:
                                os.unlink(entry.path)
                        except OSError:
                            pass
        except FileNotFoundError:
            return
        if not self.max_bytes:
            return
        stats = []
        for entry in self.entries():
            try:
                stat = entry.stat(follow_symlinks=False)
            except FileNotFoundError:  # removed by another process meanwhile
                continue
            stats.append((stat.st_mtime, entry.path, stat.st_size))
        total = sum(size for _, _, size in stats)
        for _, path, size in sorted(stats):
            if total <= self.max_bytes:
                break
            if path == keep:
                continue
            try:
                os.unlink(path)
                logger.info("shard cache over its cap of %d bytes: removed the least recently used entry %s",
                            self.max_bytes, path)
            except FileNotFoundError:
                pass
            total -= size
        if total > self.max_bytes:
            logger.warning("shard cache %s holds %d bytes, over its cap of %d bytes: the shard just downloaded is "
                           "larger than the cap by itself (raise data.cache_max_gb)", self.folder, total,
                           self.max_bytes)
