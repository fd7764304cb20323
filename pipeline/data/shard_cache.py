"""The verification cache: shards already hashed and checked, so that strict verification does not re-read
every shard on every start (``pipeline.data.stream.verify_shards``; docs/dataset-format.md, "Verification").

An entry says: the file at ``url`` was read in full, its size, sha256 and record count matched the manifest
entry ``(bytes, sha256, num_motions)``, its records are ``record_ids``, and its metadata was ``fingerprint``
(:class:`pipeline.data.locations.Fingerprint`) before and after that read. A later check whose manifest entry and
fingerprint are the same takes the verdict and the ids from the entry instead of reading the file; anything
different (another manifest entry, a changed size / mtime / ctime / inode / content hash, another backend) reads
and hashes the file again. Only good shards are remembered, and only when the fingerprint can be trusted
(:meth:`Fingerprint.trusted`); a shard found bad is forgotten.

Which files are remembered: local files (size, mtime, ctime, inode), and URLs whose store reports a content hash
(GCS ``md5Hash``, HTTP ``Content-MD5`` / ``Digest``, the Hub's LFS sha256 or git blob id). A URL known only by its
ETag, Last-Modified or version id is hashed on every start: a weak validator is not a content hash (nginx's ETag is
the file's mtime and size, so a shard changed in place with its old mtime keeps it), and an entry remembered by one
(an earlier version did) is never used.

One JSON file per manifest location, under ``$MFM_VERIFY_CACHE`` (a folder; ``off`` disables the cache) or
``$XDG_CACHE_HOME/motion-flow-matching/verified-shards`` (``~/.cache/...``). It is written atomically (temporary
file + ``os.replace``); concurrent writers lose at most each other's new entries (those shards are hashed again
next time); an unreadable or foreign file is ignored; files not written for 30 days are removed. Deleting the
folder forces a full re-hash.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import threading
import time
from typing import Any, Iterable, Sequence

from pipeline.data.locations import Fingerprint

logger = logging.getLogger(__name__)

CACHE_ENV = "MFM_VERIFY_CACHE"
"""Environment variable: the cache folder, or ``off`` (also ``0``, ``false``, ``none``, empty) for no cache."""
CACHE_VERSION = 1
RACY_S = 2.0
"""A file changed less than this many seconds before it was hashed is not remembered by its times alone: a
rewrite within the clock's resolution could keep the same times (content hashes and version ids are exempt)."""
STALE_DAYS = 30
"""A cache file not written for this many days is removed when another one is written."""
_OFF = ("", "0", "off", "false", "none", "no")


def default_cache_dir() -> str | None:
    """``$MFM_VERIFY_CACHE``, else the user's cache folder; None when the variable turns the cache off."""
    configured = os.environ.get(CACHE_ENV)
    if configured is not None:
        return None if configured.strip().lower() in _OFF else os.path.expanduser(configured)
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "motion-flow-matching", "verified-shards")


class VerificationCache:
    """The remembered verdicts for one manifest (see the module docstring)."""

    def __init__(self, path: str, manifest_location: str):
        self.path = path
        self.manifest_location = manifest_location
        self._entries: dict[str, dict[str, Any]] = self._load()
        self._changed: dict[str, dict[str, Any] | None] = {}  # url -> new entry, None: forget
        self.hits = 0

    @classmethod
    def for_manifest(cls, manifest_location: str, folder: str | os.PathLike | bool | None = None
                     ) -> "VerificationCache | None":
        """The cache of a manifest: ``folder`` None → :func:`default_cache_dir` (env or user cache), False →
        none, True → the default folder even when the variable says off, a path → that folder."""
        if folder is False:
            return None
        if folder is None:
            folder = default_cache_dir()
            if folder is None:
                return None
        elif folder is True:
            base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
            folder = os.path.join(base, "motion-flow-matching", "verified-shards")
        name = hashlib.sha256(manifest_location.encode()).hexdigest()[:32] + ".json"
        return cls(os.path.join(os.fspath(folder), name), manifest_location)

    def _load(self) -> dict[str, dict[str, Any]]:
        try:
            with open(self.path, encoding="utf-8") as file:
                data = json.load(file)
        except FileNotFoundError:
            return {}
        except (OSError, ValueError) as exc:
            logger.info("verification cache %s unreadable (%s): every shard is hashed again", self.path, exc)
            return {}
        if (not isinstance(data, dict) or data.get("version") != CACHE_VERSION
                or data.get("manifest") != self.manifest_location or not isinstance(data.get("entries"), dict)):
            return {}
        return data["entries"]

    @staticmethod
    def _key(backend: str, bytes_: int, sha256: str, num_motions: int, fp: Fingerprint) -> dict[str, Any]:
        return {"backend": backend, "bytes": bytes_, "sha256": sha256, "num_motions": num_motions,
                "fingerprint": fp.as_json()}

    def lookup(self, url: str, backend: str, bytes_: int, sha256: str, num_motions: int,
               fp: Fingerprint) -> tuple[str, ...] | None:
        """The record ids of a shard verified before with this manifest entry and this fingerprint, else None."""
        entry = self._entries.get(url)
        if not isinstance(entry, dict) or not fp.identifies_content:
            return None
        if {k: entry.get(k) for k in ("backend", "bytes", "sha256", "num_motions", "fingerprint")} != \
                self._key(backend, bytes_, sha256, num_motions, fp):
            return None
        ids = entry.get("record_ids")
        if not isinstance(ids, list) or len(ids) != num_motions or not all(isinstance(i, str) for i in ids):
            return None
        self.hits += 1
        return tuple(ids)

    def remember(self, url: str, backend: str, bytes_: int, sha256: str, num_motions: int, fp: Fingerprint,
                 record_ids: Sequence[str]) -> None:
        entry = {**self._key(backend, bytes_, sha256, num_motions, fp), "record_ids": list(record_ids)}
        self._entries[url] = self._changed[url] = entry

    def forget(self, url: str) -> None:
        if url in self._entries:
            del self._entries[url]
            self._changed[url] = None

    def save(self, known_urls: Iterable[str] | None = None) -> None:
        """Write the changes (merged into what is on disk now); entries of files the manifest no longer lists
        (``known_urls``) are dropped. A cache that cannot be written is logged and otherwise ignored."""
        if not self._changed:
            return
        entries = self._load()
        for url, entry in self._changed.items():
            if entry is None:
                entries.pop(url, None)
            else:
                entries[url] = entry
        if known_urls is not None:
            known = set(known_urls)
            entries = {url: e for url, e in entries.items() if url in known}
        tmp = f"{self.path}.{os.getpid()}.{threading.get_ident()}.tmp"
        try:
            os.makedirs(os.path.dirname(self.path), exist_ok=True)
            with open(tmp, "w", encoding="utf-8") as file:
                json.dump({"version": CACHE_VERSION, "manifest": self.manifest_location, "entries": entries}, file)
            os.replace(tmp, self.path)
        except OSError as exc:
            logger.warning("cannot write the verification cache %s (%s): shards will be hashed again next time "
                           "(set %s to a writable folder, or to 'off')", self.path, exc, CACHE_ENV)
            try:
                os.unlink(tmp)
            except OSError:
                pass
            return
        self._changed.clear()
        self._drop_stale_files()

    def _drop_stale_files(self) -> None:
        """Cache files of manifests not verified for :data:`STALE_DAYS` days (deleted or moved datasets) go."""
        folder = os.path.dirname(self.path)
        cutoff = time.time() - STALE_DAYS * 86400
        try:
            names = os.listdir(folder)
        except OSError:
            return
        for name in names:
            path = os.path.join(folder, name)
            try:
                if name.endswith(".json") and path != self.path and os.path.getmtime(path) < cutoff:
                    os.unlink(path)
            except OSError:
                pass
