"""Where shards and manifests live: local paths, ``file://``, and any fsspec URL (``s3://``, ``gs://``,
``https://``, ``hf://``, ``memory://``, ...), opened the same way for training, verification and tools; and
how reads of them ride out transient errors (retries with exponential back-off).

Schemes. A plain path or ``file://`` URL is opened with ``open``; ``pipe:`` (a webdataset idiom) and the
schemes only webdataset's ``gopen`` knows (``ais``, ``scp``, ``ftps``, ``htgs``) go through ``gopen``; every other
URL goes through fsspec. The cloud packages are the optional extra ``remote`` (``pip install
'motion-flow-matching[remote]'``: ``fsspec[http]`` (aiohttp) for ``http(s)://``, ``s3fs`` for ``s3://``, ``gcsfs``
for ``gs://``); without the package a scheme needs, opening raises :class:`RemoteSupportMissing` naming the extra.
Credentials are fsspec's (each package's usual environment variables and config files). HTTP(S) shards are
read as one streamed GET (no ``Range`` requests); Parquet parts need random access, which HTTP servers give
through ``Range`` (every object store and CDN does).

Retries (:class:`RetryPolicy`, training's ``data.retries`` / ``data.retry_backoff_s``). An error is transient
(:func:`is_transient`) when it is a reset/aborted/refused connection, a timeout, an interrupted transfer, or an
HTTP 408/429/5xx, anywhere in its chain of causes; it is retried ``retries`` times, waiting ``backoff_s``,
then twice as long each time (at most :data:`MAX_BACKOFF_S`), and every retry is logged as a warning. A
permanent error (404/missing, 403/permission, any other 4xx, a damaged file, anything not known to be
transient) is never retried. How a shard read that failed half way resumes: see
``pipeline.data.stream.read_shard``.
"""

from __future__ import annotations

import asyncio
import datetime as _dt
import email.utils
import errno
import io
import logging
import math
import os
import sys
import time
from dataclasses import dataclass
from typing import Any, BinaryIO, Callable, TypeVar
from urllib.parse import urlsplit, urlunsplit
from urllib.request import url2pathname

from webdataset.gopen import gopen, gopen_schemes

logger = logging.getLogger(__name__)

T = TypeVar("T")

REMOTE_EXTRA = "motion-flow-matching[remote]"
"""The optional extra that installs the packages of the cloud schemes (pyproject.toml)."""
_SCHEME_PACKAGES = {"s3": "s3fs", "s3a": "s3fs", "gs": "gcsfs", "gcs": "gcsfs", "http": "aiohttp (fsspec[http])",
                    "https": "aiohttp (fsspec[http])"}
# fsspec open options per scheme for sequential reads: an HTTP(S) shard is one streamed GET (a block-cached
# HTTPFile would first HEAD the file and then fetch it in Range requests).
_STREAM_OPTIONS: dict[str, dict[str, Any]] = {"http": {"block_size": 0}, "https": {"block_size": 0}}
_LOCAL_SCHEMES = ("", "file")  # opened with open(); pipe: and what only gopen knows go to webdataset's gopen


class RemoteSupportMissing(ImportError):
    """A location's scheme needs a package that is not installed; the message names it and the extra."""


class RetriesExhausted(RuntimeError):
    """A location kept failing with transient errors through every retry (the last error is the cause). Not an
    OSError on purpose: it says nothing about the data, so verification does not count the shard as bad."""


# ----------------------------------------------------------------------------------------------------------
# Locations
# ----------------------------------------------------------------------------------------------------------


def is_url(location: str) -> bool:
    """True for ``scheme://...`` and ``pipe:...`` (a one-letter scheme is a Windows drive, not a URL)."""
    return len(urlsplit(str(location)).scheme) > 1


def scheme_of(location: str) -> str:
    """The lower-case scheme of a URL, "" for a plain path."""
    return urlsplit(str(location)).scheme.lower() if is_url(location) else ""


def local_path(location: str) -> str | None:
    """The local file a location names (a plain path, or a ``file://`` URL), None for any other URL."""
    location = str(location)
    if not is_url(location):
        return location
    parts = urlsplit(location)
    return url2pathname(parts.path) if parts.scheme.lower() == "file" else None


def resolve_location(manifest_location: str, relative: str) -> str:
    """A shard path from the manifest, resolved against the manifest's own location (path or URL): a manifest at
    ``s3://bucket/ds/manifest.json`` lists ``train/shard-00000.tar`` at ``s3://bucket/ds/train/shard-00000.tar``.
    Absolute paths and URLs are kept as they are (whether a manifest may name them is the manifest reader's
    decision: ``pipeline.data.stream.Manifest.shard_location`` refuses them by default). The query string or fragment
    of an HTTP(S) manifest URL (a signed URL) is not carried over to its shards."""
    if is_url(relative) or os.path.isabs(relative):
        return relative
    if is_url(manifest_location):
        base = manifest_location
        if scheme_of(base) in ("http", "https"):
            base = urlunsplit(urlsplit(base)._replace(query="", fragment=""))
        return base.rsplit("/", 1)[0] + "/" + relative
    return os.path.join(os.path.dirname(os.path.abspath(manifest_location)), relative)


def _uses_fsspec(scheme: str) -> bool:
    if scheme in _LOCAL_SCHEMES or scheme == "pipe":
        return False
    if scheme not in gopen_schemes:
        return True
    import fsspec

    return scheme in fsspec.available_protocols()


def remote_filesystem(location: str):
    """``(fsspec filesystem, path)`` for a URL. A scheme whose package is missing raises
    :class:`RemoteSupportMissing` naming the package and the ``remote`` extra; an unknown scheme a ValueError."""
    import fsspec

    scheme = scheme_of(location)
    try:
        return fsspec.core.url_to_fs(location)
    except ImportError as exc:
        package = _SCHEME_PACKAGES.get(scheme, "the package named below")
        raise RemoteSupportMissing(
            f"{location}: reading {scheme}:// locations needs {package}, which is not installed; install the "
            f"optional extra: pip install '{REMOTE_EXTRA}' ({exc})") from exc
    except ValueError as exc:
        raise ValueError(f"{location}: no filesystem reads {scheme}:// locations ({exc})") from exc


def require_support(location: str) -> None:
    """Fail now (not in a DataLoader worker later) when the package a location's scheme needs is missing."""
    scheme = scheme_of(location)
    if not _uses_fsspec(scheme):
        return
    import fsspec

    try:
        fsspec.get_filesystem_class(scheme)
    except ImportError:
        remote_filesystem(location)  # raises RemoteSupportMissing with the message
    except ValueError as exc:
        raise ValueError(f"{location}: no filesystem reads {scheme}:// locations ({exc})") from exc


def open_binary(location: str) -> BinaryIO:
    """Open a local path or URL for a front-to-back read (see the module docstring for which opener)."""
    path = local_path(location)
    if path is not None:
        return open(path, "rb")
    scheme = scheme_of(location)
    if not _uses_fsspec(scheme):
        return gopen(location, "rb")
    fs, remote = remote_filesystem(location)
    return io.BufferedReader(_RawStream(fs.open(remote, "rb", **_STREAM_OPTIONS.get(scheme, {}))), READ_BUFFER)


READ_BUFFER = 1 << 20
"""Bytes fetched per read of a URL stream: tar parsing reads 10 KiB at a time, and every read of an fsspec
file is a round trip into its event loop (HTTP)."""


class _RawStream(io.RawIOBase):
    """An fsspec file as the raw stream of an ``io.BufferedReader``."""

    def __init__(self, file):
        self._file = file

    def readable(self) -> bool:
        return True

    def readinto(self, buffer) -> int:
        data = self._file.read(len(buffer))
        buffer[:len(data)] = data
        return len(data)

    def close(self) -> None:
        if not self.closed:
            try:
                self._file.close()
            finally:
                super().close()


def open_seekable(location: str):
    """Parquet needs random access: a local path as it is, any URL as an fsspec file (block cache)."""
    path = local_path(location)
    if path is not None:
        return path
    fs, remote = remote_filesystem(location)
    return fs.open(remote, "rb")


# ----------------------------------------------------------------------------------------------------------
# Retries
# ----------------------------------------------------------------------------------------------------------

MAX_BACKOFF_S = 60.0
"""The longest wait between two attempts, however many retries."""


@dataclass(frozen=True)
class RetryPolicy:
    """How many times a read that failed with a transient error is tried again, and how long to wait first."""

    retries: int = 3
    """Retries after the first attempt (0: fail at the first error). A read that made progress since its last
    failure (a shard that yielded records) starts counting again."""
    backoff_s: float = 1.0
    """Wait before the first retry; doubled for each further retry, at most ``MAX_BACKOFF_S``."""

    def __post_init__(self) -> None:
        if not isinstance(self.retries, int) or self.retries < 0:
            raise ValueError(f"retries must be an integer >= 0, got {self.retries!r}")
        if not math.isfinite(self.backoff_s) or self.backoff_s < 0:
            raise ValueError(f"retry back-off must be a finite number of seconds >= 0, got {self.backoff_s!r}")

    def delay(self, retry: int) -> float:
        """Seconds to wait before retry number ``retry`` (1, 2, ...)."""
        return min(MAX_BACKOFF_S, self.backoff_s * 2.0 ** (retry - 1))


DEFAULT_RETRY = RetryPolicy()

_PERMANENT_TYPES = (FileNotFoundError, PermissionError, IsADirectoryError, NotADirectoryError)
_TRANSIENT_ERRNOS = frozenset(getattr(errno, name) for name in (
    "ECONNRESET", "ECONNABORTED", "ECONNREFUSED", "ETIMEDOUT", "EPIPE", "EAGAIN", "EBUSY", "ENETDOWN",
    "ENETUNREACH", "ENETRESET", "EHOSTUNREACH", "EHOSTDOWN") if hasattr(errno, name))
# Transfer errors of HTTP clients and SDKs that may not be installed (matched by class name, anywhere in the MRO).
_TRANSIENT_NAMES = frozenset((
    "IncompleteRead", "RemoteDisconnected", "ChunkedEncodingError", "ProtocolError", "ReadTimeoutError",
    "ConnectTimeoutError", "EndpointConnectionError", "ConnectionClosedError", "ResponseStreamingError",
    "IncompleteReadError", "ClientPayloadError", "ClientConnectionError", "ServerTimeoutError", "FSTimeoutError",
    "TransportError", "RetryError"))


def http_status(exc: BaseException) -> int | None:
    """The HTTP status an exception carries (aiohttp ``status``, requests/botocore responses, gcsfs/urllib
    ``code``), or None."""
    for attr in ("status", "status_code", "code"):
        value = getattr(exc, attr, None)
        if isinstance(value, int) and not isinstance(value, bool) and 100 <= value < 600:
            return value
    response = getattr(exc, "response", None)
    if isinstance(response, dict):  # botocore ClientError
        value = response.get("ResponseMetadata", {}).get("HTTPStatusCode")
    else:
        value = getattr(response, "status_code", None) or getattr(response, "status", None)
    return value if isinstance(value, int) and 100 <= value < 600 else None


def _transient_here(exc: BaseException) -> bool | None:
    """True/False when this exception alone decides, None to look at its causes."""
    if isinstance(exc, RetriesExhausted):  # retried already
        return False
    if isinstance(exc, _PERMANENT_TYPES):
        # fsspec's HTTP info() turns any failed HEAD+GET into FileNotFoundError(url) from the HTTP error: a 503
        # there is not a missing file. A FileNotFoundError of its own (a local file, an HTTP 404) has no cause.
        cause = exc.__cause__
        return cause is not None and http_status(cause) is not None and is_transient(cause)
    status = http_status(exc)
    if status is not None:
        return status in (408, 429) or status >= 500
    if isinstance(exc, (ConnectionError, TimeoutError, asyncio.TimeoutError)):
        return True
    if isinstance(exc, OSError) and exc.errno in _TRANSIENT_ERRNOS:
        return True
    aiohttp = sys.modules.get("aiohttp")
    if aiohttp is not None and isinstance(exc, (aiohttp.ClientConnectionError, aiohttp.ClientPayloadError)):
        return True
    if any(cls.__name__ in _TRANSIENT_NAMES for cls in type(exc).__mro__):
        return True
    return None


def is_transient(exc: BaseException) -> bool:
    """Whether retrying may help: see the module docstring. The chain of causes is searched (a reader wraps a
    connection reset in its own error); a permanent error anywhere in it first decides no."""
    seen: set[int] = set()
    current: BaseException | None = exc
    while current is not None and id(current) not in seen:
        seen.add(id(current))
        verdict = _transient_here(current)
        if verdict is not None:
            return verdict
        current = current.__cause__ or (None if current.__suppress_context__ else current.__context__)
    return False


def describe(exc: BaseException) -> str:
    status = http_status(exc)
    return f"{type(exc).__name__}{f' (HTTP {status})' if status else ''}: {exc}"


def wait_before_retry(location: str, what: str, exc: BaseException, retry: int, policy: RetryPolicy) -> None:
    """Log a retry (warning) and sleep its back-off."""
    delay = policy.delay(retry)
    logger.warning("%s: transient error while %s (%s); retry %d of %d in %.2f s", location, what, describe(exc),
                   retry, policy.retries, delay)
    if delay > 0:
        time.sleep(delay)


def call_with_retries(fn: Callable[[], T], location: str, what: str, policy: RetryPolicy | None = None) -> T:
    """``fn()``, tried again after transient errors per ``policy``; a permanent error is raised at once as it
    is, and the last transient one, after the last retry, as :class:`RetriesExhausted` naming the location."""
    policy = policy or DEFAULT_RETRY
    retry = 0
    while True:
        try:
            return fn()
        except Exception as exc:
            if not is_transient(exc):
                raise
            if retry >= policy.retries:
                raise RetriesExhausted(f"{location}: {what} failed after {policy.retries} retries: "
                                       f"{describe(exc)}") from exc
            retry += 1
            wait_before_retry(location, what, exc, retry, policy)


# ----------------------------------------------------------------------------------------------------------
# Fingerprints: has a file changed since it was hashed? (the verification cache, pipeline.data.stream)
# ----------------------------------------------------------------------------------------------------------

# Metadata that is a hash of an object's content: equal values mean equal bytes, whoever wrote them and when.
_CONTENT_HASH_KEYS = ("md5Hash", "Content-MD5", "Digest", "lfs", "blob_id")
# Validators that change when an object is rewritten but are not its content hash: an ETag is whatever the server
# makes of it (nginx and Apache derive it from the size and the modification time, so a file changed in place with
# its old mtime keeps it), GCS's crc32c is a 32-bit checksum, generations and version ids are per upload.
_VALIDATOR_KEYS = ("ETag", "etag", "generation", "crc32c", "VersionId", "version_id")
# Modification times (a rewrite within their resolution is invisible: see Fingerprint.trusted).
_TIME_KEYS = ("LastModified", "Last-Modified", "last_modified", "updated", "mtime", "modified", "created")


@dataclass(frozen=True)
class Fingerprint:
    """What a file's metadata says about its version, without reading it."""

    size: int | None
    fields: tuple[tuple[str, str], ...]
    modified: float | None  # seconds since the epoch, when known
    local: bool  # a local file: size, mtime, ctime and inode from os.stat
    content_hash: bool  # a content hash is among the fields (a URL whose store hashes its objects)

    @property
    def identifies_content(self) -> bool:
        """Whether an unchanged fingerprint can stand for unchanged bytes at all: a local file's (its ctime and inode
        cannot be set back by users), or a URL's with a content hash. A URL's other metadata (ETag, Last-Modified, a
        version id) is the server's word: a server that derives the ETag from size and mtime keeps it through an
        in-place rewrite that puts the old mtime back."""
        return bool(self.fields) and self.size is not None and (self.local or self.content_hash)

    def trusted(self, hashed_at: float, racy_s: float) -> bool:
        """Can this fingerprint stand for the bytes hashed from ``hashed_at`` on? A URL's with a content hash,
        always; a local file's when it was last changed more than ``racy_s`` before: a rewrite in the same clock
        tick as the version hashed would otherwise keep its time (git's "racy" entries)."""
        if not self.identifies_content:
            return False
        return self.content_hash or (self.modified is not None and self.modified < hashed_at - racy_s)

    def as_json(self) -> dict[str, Any]:
        return {"size": self.size, **dict(self.fields)}


def _epoch_seconds(value: Any) -> float | None:
    if isinstance(value, _dt.datetime):
        return (value if value.tzinfo else value.replace(tzinfo=_dt.timezone.utc)).timestamp()
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        return float(value)
    if isinstance(value, str):
        try:
            return email.utils.parsedate_to_datetime(value).timestamp()
        except (TypeError, ValueError, IndexError):
            pass
        try:
            return _epoch_seconds(_dt.datetime.fromisoformat(value.replace("Z", "+00:00")))
        except ValueError:
            return None
    return None


def fingerprint(location: str, policy: RetryPolicy | None = None) -> Fingerprint:
    """The file's size and version metadata: ``os.stat`` for a local file (size, mtime, ctime, inode: a copy,
    an edit, even one that puts the old mtime back, changes ctime), the filesystem's ``info`` for a URL (object
    stores: ETag, generation, md5Hash; HTTP: ETag, Last-Modified, Content-MD5). Raises FileNotFoundError/PermissionError (and
    :class:`RetriesExhausted`) like opening it would."""
    path = local_path(location)
    if path is not None:
        st = os.stat(path)
        return Fingerprint(size=st.st_size, local=True, content_hash=False,
                           modified=max(st.st_mtime_ns, st.st_ctime_ns) / 1e9,
                           fields=(("mtime_ns", str(st.st_mtime_ns)), ("ctime_ns", str(st.st_ctime_ns)),
                                   ("ino", str(st.st_ino))))
    fs, remote = remote_filesystem(location)
    info = call_with_retries(lambda: fs.info(remote), location, "reading its metadata", policy)
    size = info.get("size")
    keys = _CONTENT_HASH_KEYS + _VALIDATOR_KEYS + _TIME_KEYS
    fields = tuple((key, str(info[key])) for key in keys if info.get(key) not in (None, ""))
    modified = next((t for t in (_epoch_seconds(info.get(key)) for key in _TIME_KEYS) if t is not None), None)
    return Fingerprint(size=int(size) if isinstance(size, (int, float)) else None, fields=fields, modified=modified,
                       local=False, content_hash=any(info.get(key) not in (None, "") for key in _CONTENT_HASH_KEYS))
