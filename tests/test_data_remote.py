"""Data where people keep it (issue 18, item 4): shards and manifests streamed through fsspec from a local HTTP
server and from fsspec's in-memory filesystem, with injected transient failures (HTTP 503, a connection cut
mid-body, a ConnectionResetError mid-read), retries with back-off, permanent errors (404) named, the exact-resume
guarantee over a remote source, and the verification cache (pipeline/data/locations.py, pipeline/data/shard_cache.py,
pipeline/data/stream.py). No real bucket is reachable from the tests: s3:// and gs:// are only checked for the error
that names the ``remote`` extra when their package is missing."""

from __future__ import annotations

import contextlib
import hashlib
import importlib.util
import os
import re
import shutil
import tarfile
import threading
import time
import uuid
from http import HTTPStatus
from http.server import SimpleHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import fsspec
import numpy as np
import pytest
from conftest import flip_byte as flip_byte_at
from fsspec.implementations.memory import MemoryFileSystem
from test_data import (
    UNEVEN,
    assert_batches_equal,
    edit_manifest,
    flip_byte,
    opts,
    read_in_resumed_segments,
    take,
    write_fixture_dataset,
)

import pipeline.data.stream as data_module
from pipeline.config import ConfigError, DataConfig
from pipeline.data.locations import (
    RemoteSupportMissing,
    fingerprint,
    RetriesExhausted,
    RetryPolicy,
    is_transient,
    resolve_location,
)
from pipeline.data.shard_cache import VerificationCache
from pipeline.data.stream import (
    MotionLoader,
    ShardChangedError,
    ShardReadError,
    ShardVerificationError,
    check_shard,
    iter_motions,
    open_manifest,
    read_shard,
    split_shards,
    verified_split,
    verify_shards,
)
from preprocess.shards import ManifestError

FAST = dict(retries=3, retry_backoff_s=0.01)  # back-off short enough for tests


@pytest.fixture(autouse=True)
def _own_verification_cache(tmp_path, monkeypatch):
    """Each test its own cache folder (none of the user's)."""
    monkeypatch.setenv("MFM_VERIFY_CACHE", str(tmp_path / "verify-cache"))


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    return write_fixture_dataset(tmp_path_factory.mktemp("remote-data"))


# ----------------------------------------------------------------------------------------------------------
# A local HTTP server (GET with Range, HEAD, Last-Modified, an nginx-style ETag) that can fail on purpose
# ----------------------------------------------------------------------------------------------------------


def nginx_etag(path: Path) -> str:
    """The ETag nginx sends for a static file: its modification time and size in hex, nothing of its content."""
    stat = path.stat()
    return f'"{int(stat.st_mtime):x}-{stat.st_size:x}"'


class _Handler(SimpleHTTPRequestHandler):
    """Serves ``server.root`` as nginx does (ETag from mtime and size, Last-Modified). ``server.faults[path]`` is a
    list of failures for the next GETs of that path: an int answers that HTTP status, "cut" sends the headers of
    the whole file, half of it, and closes."""

    protocol_version = "HTTP/1.1"

    def __init__(self, request, client_address, server):
        super().__init__(request, client_address, server, directory=str(server.root))

    def log_message(self, *args) -> None:  # quiet
        pass

    def _fault(self):
        with self.server.lock:
            self.server.requests.append((self.command, self.path))
            faults = self.server.faults.get(self.path)
            return faults.pop(0) if faults and self.command == "GET" else None

    def _validators(self, path: Path) -> None:
        self.send_header("Last-Modified", self.date_time_string(int(path.stat().st_mtime)))
        self.send_header("ETag", nginx_etag(path))

    def do_HEAD(self) -> None:
        self._fault()  # recorded; HEAD requests do not fail
        path = Path(self.translate_path(self.path))
        if not path.is_file():
            self.send_error(HTTPStatus.NOT_FOUND)
            return
        self.send_response(HTTPStatus.OK)
        self.send_header("Content-Length", str(path.stat().st_size))
        self.send_header("Accept-Ranges", "bytes")
        self._validators(path)
        self.end_headers()

    def do_GET(self) -> None:
        fault = self._fault()
        if isinstance(fault, int):
            self.send_response(fault)
            self.send_header("Content-Length", "0")
            self.end_headers()
            return
        path = Path(self.translate_path(self.path))
        if not path.is_file():
            self.send_error(HTTPStatus.NOT_FOUND)
            return
        body = path.read_bytes()
        start, end = 0, len(body)
        match = re.fullmatch(r"bytes=(\d+)-(\d*)", self.headers.get("Range", ""))
        if match:
            start, end = int(match[1]), min(len(body), int(match[2]) + 1 if match[2] else len(body))
            self.send_response(HTTPStatus.PARTIAL_CONTENT)
            self.send_header("Content-Range", f"bytes {start}-{end - 1}/{len(body)}")
        else:
            self.send_response(HTTPStatus.OK)
        self.send_header("Content-Length", str(end - start))
        self.send_header("Accept-Ranges", "bytes")
        self._validators(path)
        self.end_headers()
        if fault == "cut":
            self.wfile.write(body[start:start + (end - start) // 2])
            self.wfile.flush()
            time.sleep(0.3)  # the client reads (and yields records from) the first half before the cut
            self.close_connection = True
            with contextlib.suppress(OSError):
                self.connection.shutdown(2)
            return
        self.wfile.write(body[start:end])


@contextlib.contextmanager
def serving(root: Path):
    """Serve the folder ``root`` over HTTP for the block: ``(base URL, server)``."""
    server = ThreadingHTTPServer(("127.0.0.1", 0), _Handler)
    server.root, server.faults, server.requests, server.lock = root, {}, [], threading.Lock()
    server.daemon_threads = True
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}", server
    finally:
        server.shutdown()
        server.server_close()


@pytest.fixture
def http_root(tmp_path, dataset):
    """A copy of the dataset served over HTTP: ``(root folder, base URL, server)``."""
    root = tmp_path / "served"
    shutil.copytree(dataset.parent, root)
    with serving(root) as (base, server):
        yield root, base, server


def rewrite_in_place(path: Path) -> None:
    """Change one byte of a file's content (inside a record's payload for a tar) and put its modification time
    back: size, mtime, and so nginx's ETag and Last-Modified, are as they were; only the bytes differ."""
    stat = path.stat()
    offset = stat.st_size // 2
    if path.suffix == ".tar":
        with tarfile.open(path) as tar:
            member = max(tar.getmembers(), key=lambda m: m.size)
            offset = member.offset_data + member.size - 3  # the last bytes of an npy array's data
    flip_byte_at(path, offset)
    os.utime(path, ns=(stat.st_atime_ns, stat.st_mtime_ns))
    assert path.stat().st_size == stat.st_size and path.stat().st_mtime_ns == stat.st_mtime_ns


needs_http = pytest.mark.skipif(importlib.util.find_spec("aiohttp") is None,
                                     reason="http(s):// needs aiohttp (pip install 'motion-flow-matching[remote]')")


# ----------------------------------------------------------------------------------------------------------
# fsspec's in-memory filesystem, with a file that raises ConnectionResetError once mid-read
# ----------------------------------------------------------------------------------------------------------


class _FlakyFile:
    """Wraps a memory file: the first read past ``fail_at`` bytes raises ConnectionResetError (once)."""

    def __init__(self, inner, fail_at: int, armed: list[bool]):
        self._inner, self._fail_at, self._armed = inner, fail_at, armed

    def read(self, size=-1):
        position = self._inner.tell()
        wanted = (self._inner.size if hasattr(self._inner, "size") else 1 << 62) if size is None or size < 0 else size
        if self._armed[0] and position + wanted > self._fail_at:
            self._armed[0] = False
            raise ConnectionResetError(104, "Connection reset by peer (injected)")
        return self._inner.read(size)

    def __getattr__(self, name):
        return getattr(self._inner, name)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self._inner.close()

    def __iter__(self):
        return iter(self._inner)


@pytest.fixture
def memory_dataset(dataset, monkeypatch):
    """The dataset copied into ``memory://<unique>/``; returns ``(manifest URL, arm)`` where ``arm(name, at)``
    makes the next read of file ``name`` past byte ``at`` raise ConnectionResetError once (in this process)."""
    fs = fsspec.filesystem("memory")
    base = f"/remote-{uuid.uuid4().hex[:8]}"
    for path in dataset.parent.rglob("*"):
        if path.is_file():
            fs.pipe(f"{base}/{path.relative_to(dataset.parent).as_posix()}", path.read_bytes())
    armed: dict[str, list[bool]] = {}
    real_open = MemoryFileSystem._open

    def flaky_open(self, path, mode="rb", **kwargs):
        handle = real_open(self, path, mode, **kwargs)
        name = self._strip_protocol(path)
        if mode == "rb" and name in armed:
            return _FlakyFile(handle, armed[name][1], armed[name][0])
        return handle

    monkeypatch.setattr(MemoryFileSystem, "_open", flaky_open)

    def arm(name: str, at: int) -> None:
        armed[f"{base}/{name}"] = ([True], at)

    def fired() -> list[str]:
        return [name for name, (flag, _) in armed.items() if not flag[0]]

    arm.fired = fired
    try:
        yield f"memory://{base}/manifest.json", arm
    finally:
        fs.rm(base, recursive=True)


def shard_size(dataset: Path, name: str) -> int:
    return (dataset.parent / name).stat().st_size


# ----------------------------------------------------------------------------------------------------------
# Locations, classification of errors, settings
# ----------------------------------------------------------------------------------------------------------


def test_shard_paths_resolve_under_the_manifest_location():
    assert resolve_location("s3://bucket/ds/manifest.json", "train/a.tar") == "s3://bucket/ds/train/a.tar"
    assert resolve_location("gs://bucket/manifest.json", "train/a.tar") == "gs://bucket/train/a.tar"
    assert resolve_location("https://host/x/ds/manifest.json?sig=a/b", "train/a.tar") == "https://host/x/ds/train/a.tar"
    assert resolve_location("memory://ds/manifest.json", "val/p.parquet") == "memory://ds/val/p.parquet"
    assert resolve_location("s3://bucket/ds/manifest.json", "gs://other/a.tar") == "gs://other/a.tar"


def test_transient_and_permanent_errors_are_told_apart():
    import aiohttp

    def response_error(status):
        return aiohttp.ClientResponseError(request_info=None, history=(), status=status, message="x")

    for exc in (ConnectionResetError(), TimeoutError(), OSError(104, "reset"), response_error(503),
                response_error(429), response_error(500), aiohttp.ClientPayloadError("cut"),
                aiohttp.ServerDisconnectedError()):
        assert is_transient(exc), exc
    for exc in (FileNotFoundError("gone"), PermissionError("no"), response_error(404), response_error(403),
                ValueError("bad tar"), KeyError("x"), RetriesExhausted("already retried")):
        assert not is_transient(exc), exc
    try:  # a reader's own error around a connection reset: the cause decides
        try:
            raise ConnectionResetError(104, "reset")
        except OSError as inner:
            raise ShardReadError("s3://b/x.tar: cannot read shard") from inner
    except ShardReadError as wrapped:
        assert is_transient(wrapped)
    # fsspec's HTTP info() says FileNotFoundError for any failed HEAD+GET: a 503 underneath is transient.
    missing_503, missing_404 = FileNotFoundError("u"), FileNotFoundError("u")
    missing_503.__cause__, missing_404.__cause__ = response_error(503), response_error(404)
    assert is_transient(missing_503) and not is_transient(missing_404)


def test_retry_policy_backs_off_exponentially_and_config_validates():
    policy = RetryPolicy(retries=8, backoff_s=1.0)
    assert [policy.delay(r) for r in range(1, 9)] == [1, 2, 4, 8, 16, 32, 60, 60]
    with pytest.raises(ValueError):
        RetryPolicy(retries=-1)
    with pytest.raises(ValueError):
        RetryPolicy(backoff_s=float("nan"))
    assert DataConfig(retries=5, retry_backoff_s=0.5).retries == 5
    with pytest.raises(ConfigError, match="data.retries"):
        DataConfig(retries=-1)
    with pytest.raises(ConfigError, match="data.retry_backoff_s"):
        DataConfig(retry_backoff_s=-1.0)
    with pytest.raises(ValueError, match="retries"):
        opts(retries=-2)


def test_a_missing_cloud_package_names_the_extra(monkeypatch, tmp_path):
    def no_package(url, **kwargs):
        raise ImportError("Install s3fs to access S3")

    monkeypatch.setattr(fsspec.core, "url_to_fs", no_package)
    monkeypatch.setattr(fsspec, "get_filesystem_class", lambda protocol: no_package(protocol))
    with pytest.raises(ManifestError, match=r"s3://bucket/ds/manifest\.json: .*needs s3fs.*"
                                            r"motion-flow-matching\[remote\]"):
        open_manifest("s3://bucket/ds/manifest.json")
    # A local manifest whose shards are on S3: the loader says so before any worker starts.
    manifest = write_fixture_dataset(tmp_path / "ds", (4, 4))
    edit_manifest(manifest, lambda m: [e.__setitem__("path", "s3://bucket/ds/" + e["path"])
                                       for e in m["splits"]["train"]["shards"]])
    external = open_manifest(manifest, allow_external_shards=True)  # shards elsewhere than the manifest: asked for
    with pytest.raises(RemoteSupportMissing, match=r"pip install 'motion-flow-matching\[remote\]'"):
        MotionLoader(external, "train", opts())
    with pytest.raises(RemoteSupportMissing, match="s3fs"):
        verify_shards(external, "train")


@pytest.mark.skipif(importlib.util.find_spec("s3fs") is not None, reason="s3fs is installed here")
def test_s3_without_s3fs_names_the_extra_for_real():
    with pytest.raises(ManifestError, match=r"needs s3fs.*motion-flow-matching\[remote\]"):
        open_manifest("s3://no-such-bucket/ds/manifest.json")


# ----------------------------------------------------------------------------------------------------------
# HTTP: every record once, in the local order, through a 503 and a connection cut mid-body
# ----------------------------------------------------------------------------------------------------------


@needs_http
@pytest.mark.parametrize("num_workers, check_remote_bytes", [(0, True), (2, True), (0, False)])
def test_http_stream_is_the_local_stream_through_transient_failures(dataset, http_root, caplog, num_workers,
                                                                    check_remote_bytes):
    root, base, server = http_root
    # One 503 at the open of one shard, one connection cut half way through another: while it is downloaded and
    # hashed, before any of its records is used (check_remote_bytes), or after some were yielded (without).
    server.faults = {"/train/shard-00003.tar": [503], "/train/shard-00006.tar": ["cut"]}
    caplog.set_level("WARNING", logger="pipeline.data.locations")
    options = opts(num_workers=num_workers, check_remote_bytes=check_remote_bytes, **FAST)
    local = list(MotionLoader(dataset, "train", opts(num_workers=num_workers)).iter_epoch())
    remote = list(MotionLoader(f"{base}/manifest.json", "train", options).iter_epoch())
    assert_batches_equal(remote, local)
    ids = [i for b in remote for i in b["ids"]]
    assert len(ids) == len(set(ids))
    assert server.faults == {"/train/shard-00003.tar": [], "/train/shard-00006.tar": []}  # both were hit
    if num_workers == 0:  # worker processes log to their own stderr
        assert "shard-00003.tar: transient error while reading the shard (ClientResponseError (HTTP 503)" in caplog.text
        resuming = r" \(resuming after record \d+\)" if not check_remote_bytes else ""
        assert re.search(rf"shard-00006\.tar: transient error while reading the shard{resuming} \(ClientPayloadError",
                         caplog.text)


@needs_http
@pytest.mark.parametrize("backend", ["webdataset", "parquet"])
def test_http_reads_every_record_once_in_local_order(dataset, http_root, backend, caplog):
    root, base, server = http_root
    name = "shard-00002.tar" if backend == "webdataset" else "part-00002.parquet"
    server.faults = {f"/train/{name}": [503, "cut"]}  # while it is verified (hashed)
    caplog.set_level("WARNING", logger="pipeline.data.locations")
    local = list(iter_motions(dataset, "train", backend, verify="off"))
    source = verified_split(f"{base}/manifest.json", "train", backend, retry=RetryPolicy(3, 0.01))
    assert source.report.verified and server.faults[f"/train/{name}"] == []
    assert caplog.text.count("transient error while verifying") == 2
    server.faults = {f"/train/{name}": [503, "cut"]}  # and while it is read
    remote = list(source.iter_motions())
    assert [r.id for r in remote] == [r.id for r in local] == sorted(r.id for r in local)
    assert all(np.array_equal(a.features, b.features) for a, b in zip(remote, local))
    assert server.faults[f"/train/{name}"] == [] and caplog.text.count("transient error while reading") == 2


@needs_http
def test_http_404_fails_strict_naming_the_url_and_is_not_retried(dataset, http_root, caplog):
    root, base, server = http_root
    (root / "train/shard-00004.tar").unlink()
    caplog.set_level("WARNING")
    with pytest.raises(ShardVerificationError,
                       match=rf"{re.escape(base)}/train/shard-00004\.tar: bad shard \(missing"):
        verify_shards(f"{base}/manifest.json", "train", mode="strict", retry=RetryPolicy(3, 5.0))
    report = verify_shards(f"{base}/manifest.json", "train", mode="tolerant", retry=RetryPolicy(3, 5.0))
    assert report.bad_paths == ("train/shard-00004.tar",)
    # Without verification the reader names it too, at once (a 5 s back-off would show).
    loader = MotionLoader(f"{base}/manifest.json", "train", opts(shuffle=False, retries=3, retry_backoff_s=5.0))
    started = time.perf_counter()
    with pytest.raises(ShardReadError, match=rf"{re.escape(base)}/train/shard-00004\.tar: cannot read shard"):
        list(loader.iter_epoch())
    assert time.perf_counter() - started < 4.0 and "transient error" not in caplog.text


@needs_http
def test_http_403_is_permanent_and_named(dataset, http_root, caplog):
    root, base, server = http_root
    server.faults = {"/train/shard-00001.tar": [403] * 5}
    caplog.set_level("WARNING", logger="pipeline.data.locations")
    with pytest.raises(ShardVerificationError, match=rf"{re.escape(base)}/train/shard-00001\.tar: bad shard "
                                                     r"\(unreadable: ClientResponseError \(HTTP 403\)"):
        verify_shards(f"{base}/manifest.json", "train", mode="strict", retry=RetryPolicy(3, 0.01))
    shard = split_shards(open_manifest(f"{base}/manifest.json"), "train")[1]
    with pytest.raises(ShardReadError, match=r"shard-00001\.tar: cannot read shard: ClientResponseError"):
        list(read_shard(shard, np.ones(shard.num_motions, bool), retry=RetryPolicy(3, 0.01)))
    assert server.faults["/train/shard-00001.tar"] == [403] * 3 and "transient error" not in caplog.text


@needs_http
def test_a_shard_that_keeps_failing_gives_up_after_the_retries_naming_it(dataset, http_root, caplog):
    root, base, server = http_root
    server.faults = {"/train/shard-00001.tar": [503] * 20}
    caplog.set_level("WARNING", logger="pipeline.data.locations")
    shard = split_shards(open_manifest(f"{base}/manifest.json"), "train")[1]
    with pytest.raises(ShardReadError, match=rf"{re.escape(base)}/train/shard-00001\.tar: cannot read shard: still "
                                             r"failing after 2 retries"):
        list(read_shard(shard, np.ones(shard.num_motions, bool), retry=RetryPolicy(2, 0.01)))
    assert caplog.text.count("transient error") == 2
    # Verification does not turn an outage into a "bad shard" (tolerant mode would drop its data): it raises.
    server.faults = {"/train/shard-00001.tar": [503] * 20}
    with pytest.raises(RetriesExhausted, match=r"shard-00001\.tar: verifying the shard failed after 2 retries"):
        verify_shards(f"{base}/manifest.json", "train", mode="tolerant", retry=RetryPolicy(2, 0.01), cache=False)


@needs_http
def test_a_remote_manifest_names_shards_only_under_its_own_url(dataset, http_root, tmp_path):
    """Issue 24.7: a manifest fetched over http listing file:///... or an absolute local path read the local file.
    Now every location that does not resolve under the manifest's URL is refused before anything is opened, unless
    allowed; a pipe: command never."""
    root, base, server = http_root
    local = tmp_path / "local" / "shard.tar"  # a local file that would even verify: the shard's own bytes
    local.parent.mkdir()
    shutil.copy(root / "train" / "shard-00001.tar", local)
    port = base.rsplit(":", 1)[1]
    refused = [str(local), local.as_uri(), "../shard.tar", "%2e%2e/shard.tar", "train/%2E%2E/%2E%2E/x.tar",
               "train\\..\\..\\x.tar", f"http://localhost:{port}/train/shard-00001.tar", "s3://bucket/shard.tar"]
    for path in refused:
        edit_manifest(root / "manifest.json", lambda m, path=path: m["splits"]["train"]["shards"][1].__setitem__("path", path))
        server.requests.clear()
        with pytest.raises(ManifestError, match=rf"{re.escape(base)}/manifest\.json: shard path "
                                                rf"{re.escape(repr(path))} .*data\.allow_external_shards=true"):
            verify_shards(f"{base}/manifest.json", "train", mode="tolerant")
        with pytest.raises(ManifestError, match="allow_external_shards"):
            MotionLoader(f"{base}/manifest.json", "train", opts())
        assert {p for _, p in server.requests} == {"/manifest.json"}, path  # no shard was asked for

    # Allowed: the local file is read where the manifest points.
    edit_manifest(root / "manifest.json", lambda m: m["splits"]["train"]["shards"][1].__setitem__("path", str(local)))
    allowed = open_manifest(f"{base}/manifest.json", allow_external_shards=True)
    assert split_shards(allowed, "train")[1].url == str(local)
    assert verify_shards(allowed, "train", mode="strict").verified
    edit_manifest(root / "manifest.json", lambda m: m["splits"]["train"]["shards"][1].__setitem__(
        "path", f"pipe:cat {local}"))
    with pytest.raises(ManifestError, match=r"is a shell command \(pipe:\)"):
        split_shards(open_manifest(f"{base}/manifest.json", allow_external_shards=True), "train")


# ----------------------------------------------------------------------------------------------------------
# memory://: a ConnectionResetError mid-read, exact resume over a remote source
# ----------------------------------------------------------------------------------------------------------


def test_memory_stream_with_a_reset_mid_read_is_the_local_stream(dataset, memory_dataset, caplog):
    url, arm = memory_dataset
    arm("train/shard-00002.tar", shard_size(dataset, "train/shard-00002.tar") // 2)
    arm("train/part-00005.parquet", 0)
    caplog.set_level("WARNING", logger="pipeline.data.locations")
    assert verify_shards(url, "train", mode="strict", retry=RetryPolicy(3, 0.01)).verified  # through a reset
    assert [name.split("/", 2)[2] for name in arm.fired()] == ["train/shard-00002.tar"]
    arm("train/shard-00002.tar", shard_size(dataset, "train/shard-00002.tar") // 2)
    arm("train/shard-00005.tar", 0)
    for backend in ("webdataset", "parquet"):
        local = list(MotionLoader(dataset, "train", opts(backend=backend)).iter_epoch())
        remote = list(MotionLoader(url, "train", opts(backend=backend, **FAST)).iter_epoch())
        assert_batches_equal(remote, local)
    assert len(arm.fired()) == 3 and "ConnectionResetError" in caplog.text


@pytest.mark.parametrize("num_workers", [0, 2])
def test_resume_mid_epoch_over_a_remote_source_with_failures_is_exact(dataset, memory_dataset, num_workers):
    """tests/test_data.py's exact-resume check, reading from memory:// with resets injected in every segment."""
    url, arm = memory_dataset
    kw = dict(num_workers=num_workers)
    probe = MotionLoader(dataset, "train", opts(**kw), rank=1, world_size=2)
    first, second = probe.batches_per_epoch(0), probe.batches_per_epoch(1)
    total = first + second + 3
    expected = take(MotionLoader(dataset, "train", opts(**kw), rank=1, world_size=2).iter_batches(), total)
    cuts = [1, 3, first, first + 2, total]

    def fail_every_shard_once() -> None:  # every shard fails once, half way, in each segment
        for index, _ in enumerate(UNEVEN):
            name = f"train/shard-{index:05d}.tar"
            arm(name, shard_size(dataset, name) // 2)

    got, state = read_in_resumed_segments(
        lambda: MotionLoader(url, "train", opts(**kw, **FAST), rank=1, world_size=2), cuts, probe,
        before_segment=fail_every_shard_once)
    assert_batches_equal(got, expected)
    assert state == MotionLoader(dataset, "train", opts(**kw), rank=1, world_size=2).state_dict() | {
        "epoch": state["epoch"], "batches_in_epoch": state["batches_in_epoch"]}


# ----------------------------------------------------------------------------------------------------------
# The verification cache: an unchanged shard is not hashed again; any change is
# ----------------------------------------------------------------------------------------------------------


@pytest.fixture
def short_racy_window(monkeypatch):
    """Remember files changed 20 ms before they were hashed (2 s by default): tests do not wait."""
    monkeypatch.setattr(data_module, "RACY_S", 0.02)


def counting_reads(monkeypatch) -> list[str]:
    read = []
    for backend, reader in list(data_module._CONTENT_READERS.items()):
        def counted(shard, _reader=reader):
            read.append(shard.path)
            return _reader(shard)
        monkeypatch.setitem(data_module._CONTENT_READERS, backend, counted)
    return read


@pytest.mark.parametrize("backend", ["webdataset", "parquet"])
def test_cache_skips_unchanged_shards_and_catches_any_change(tmp_path, monkeypatch, short_racy_window, backend):
    manifest = write_fixture_dataset(tmp_path / "ds", (3, 4, 5))
    time.sleep(0.05)
    reads = counting_reads(monkeypatch)
    first = verify_shards(manifest, "train", backend=backend)
    assert first.verified and first.num_from_cache == 0 and len(reads) == 3
    assert first.as_dict()["num_from_cache"] == 0
    reads.clear()
    again = verify_shards(manifest, "train", backend=backend)
    assert again.verified and again.num_from_cache == 3 and reads == []
    cache_files = list((tmp_path / "verify-cache").glob("*.json"))
    assert len(cache_files) == 1

    # A same-size corruption with the old mtime put back: ctime still differs, the shard is hashed and refused.
    name = "shard-00001.tar" if backend == "webdataset" else "part-00001.parquet"
    path = tmp_path / "ds/train" / name
    stat = path.stat()
    flip_byte(path)
    os.utime(path, ns=(stat.st_atime_ns, stat.st_mtime_ns))
    assert path.stat().st_mtime_ns == stat.st_mtime_ns and path.stat().st_size == stat.st_size
    with pytest.raises(ShardVerificationError, match=rf"{re.escape(name)}: bad shard \(corrupted"):
        verify_shards(manifest, "train", mode="strict", backend=backend)
    report = verify_shards(manifest, "train", mode="tolerant", backend=backend)
    assert report.bad_paths == (f"train/{name}",) and report.num_from_cache == 2
    with pytest.raises(ShardVerificationError):  # a bad shard is never remembered
        verify_shards(manifest, "train", mode="strict", backend=backend)

    # A count changed in the manifest (same bytes): another manifest entry, so no cached verdict applies.
    fresh = write_fixture_dataset(tmp_path / "ds2", (3, 4))
    time.sleep(0.05)
    verify_shards(fresh, "train", backend=backend)
    key = "shards" if backend == "webdataset" else "parquet"
    edit_manifest(fresh, lambda m: m["splits"]["train"][key][1].__setitem__("num_motions", 3))
    with pytest.raises(ShardVerificationError, match="record count: holds 4 records, manifest says 3"):
        verify_shards(fresh, "train", mode="strict", backend=backend)


def test_cache_off_and_fresh_files_are_hashed_every_time(tmp_path, monkeypatch):
    manifest = write_fixture_dataset(tmp_path / "ds", (3, 4))
    reads = counting_reads(monkeypatch)
    # Written a moment ago (inside the 2 s racy window): not remembered by its times.
    assert verify_shards(manifest, "train").num_from_cache == 0
    assert verify_shards(manifest, "train").num_from_cache == 0 and len(reads) == 4
    monkeypatch.setenv("MFM_VERIFY_CACHE", "off")
    monkeypatch.setattr(data_module, "RACY_S", 0.0)
    verify_shards(manifest, "train")
    assert verify_shards(manifest, "train").num_from_cache == 0 and len(reads) == 8
    assert not (tmp_path / "verify-cache").exists()


def test_a_remote_shard_is_remembered_only_by_a_content_hash(dataset, memory_dataset, monkeypatch,
                                                             short_racy_window):
    """Issue 24, item 2: a URL's metadata other than a content hash (an ETag, a modification time, a version id)
    is the server's word, not the bytes': such shards are hashed on every start. One whose store reports a content
    hash (GCS md5Hash, Content-MD5, the Hub's LFS sha256) is remembered, and read again when the hash changes."""
    url, _ = memory_dataset
    time.sleep(0.05)
    reads = counting_reads(monkeypatch)
    assert verify_shards(url, "train").num_from_cache == 0 and len(reads) == len(UNEVEN)
    assert verify_shards(url, "train").num_from_cache == 0 and len(reads) == 2 * len(UNEVEN)  # "created" only

    real_info = MemoryFileSystem.info

    def info_with_md5(self, path, **kwargs):  # as gcsfs reports an object
        info = real_info(self, path, **kwargs)
        return {**info, "md5Hash": hashlib.md5(self.cat_file(path)).hexdigest()} if info["type"] == "file" else info

    monkeypatch.setattr(MemoryFileSystem, "info", info_with_md5)
    reads.clear()
    assert verify_shards(url, "train").num_from_cache == 0 and len(reads) == len(UNEVEN)
    assert verify_shards(url, "train").num_from_cache == len(UNEVEN) and len(reads) == len(UNEVEN)
    # Replace one object with tampered bytes of the same size: its content hash changes, so it is read again.
    fs = fsspec.filesystem("memory")
    name = url[len("memory://"):].rsplit("/", 1)[0] + "/train/shard-00003.tar"
    content = bytearray(fs.cat(name))
    content[len(content) // 3] ^= 0xFF
    fs.pipe(name, bytes(content))
    with pytest.raises(ShardVerificationError, match=r"memory://.*/train/shard-00003\.tar: bad shard \(corrupted"):
        verify_shards(url, "train", mode="strict")


@needs_http
def test_a_shard_changed_in_place_with_its_old_etag_is_hashed_again_not_trusted(dataset, http_root,
                                                                                short_racy_window):
    """Issue 24, item 2: an nginx-style server derives the ETag from size and mtime, so a shard rewritten in place
    with its old mtime keeps ETag and Last-Modified. It was trusted from the verification cache and a strict run
    trained on the changed bytes. Now a URL known only by such validators is hashed on every start, and an entry an
    earlier version remembered by its ETag is not used."""
    root, base, server = http_root
    old = time.time() - 10  # Last-Modified has a one-second resolution
    for path in root.rglob("*"):
        os.utime(path, (old, old))
    url = f"{base}/manifest.json"
    assert verify_shards(url, "train").verified
    shard = split_shards(open_manifest(url), "train")[3]
    before = fingerprint(shard.url)
    assert dict(before.fields)["ETag"] == nginx_etag(root / shard.path) and not before.identifies_content
    cache = VerificationCache.for_manifest(url)  # what an earlier version wrote: the shard remembered by its ETag
    cache.remember(shard.url, "webdataset", shard.bytes, shard.sha256, shard.num_motions, before,
                   check_shard(shard).record_ids)
    cache.save()

    rewrite_in_place(root / shard.path)
    assert fingerprint(shard.url) == before  # size, ETag and Last-Modified as they were
    server.requests.clear()
    with pytest.raises(ShardVerificationError, match=rf"{re.escape(shard.url)}: bad shard \(corrupted"):
        verify_shards(url, "train", mode="strict")
    assert ("GET", "/" + shard.path) in server.requests  # read, not taken from the cache
    server.requests.clear()
    report = verify_shards(url, "train", mode="tolerant")
    assert report.bad_paths == (shard.path,) and report.num_from_cache == 0
    assert {path for method, path in server.requests if method == "GET" and path.endswith(".tar")} == {
        "/" + s.path for s in split_shards(open_manifest(url), "train")}  # every shard read, every start


def shard_ids(manifest: Path, backend: str, index: int) -> set[str]:
    shard = split_shards(open_manifest(manifest), "train", backend)[index]
    return set(check_shard(shard, backend).record_ids)


@needs_http
@pytest.mark.parametrize("backend, num_workers", [("webdataset", 0), ("webdataset", 2), ("parquet", 0)])
def test_a_shard_changed_on_the_server_after_verification_is_never_used(dataset, http_root, backend, num_workers):
    """Issue 24, item 2: verification passed, then a shard changed on the server keeping size, ETag and
    Last-Modified. The reader hashes a remote shard as it downloads it and compares it with the manifest before it
    parses a record: strict stops with ShardChangedError naming the URL, and no batch before the error holds a
    record of that shard (nothing of it can reach a step, let alone a checkpoint); tolerant leaves its records out
    of their planned batches, counted."""
    root, base, server = http_root
    url = f"{base}/manifest.json"
    index = 3
    name = split_shards(open_manifest(dataset), "train", backend)[index].path
    changed = shard_ids(dataset, backend, index)
    local = list(MotionLoader(dataset, "train", opts(backend=backend, num_workers=num_workers)).iter_epoch())
    assert verify_shards(url, "train", backend=backend).verified
    rewrite_in_place(root / name)

    strict = MotionLoader(url, "train", opts(backend=backend, num_workers=num_workers, **FAST))
    got = []
    with pytest.raises(ShardChangedError, match=rf"{re.escape(base)}/{name}: changed since it was verified.*none "
                                                r"of its records was used"):
        for batch in strict.iter_epoch():
            got.append(batch)
    assert len(got) < len(local) and not changed & {i for b in got for i in b["ids"]}
    assert_batches_equal(got, local[:len(got)])

    tolerant = MotionLoader(url, "train", opts(backend=backend, num_workers=num_workers, tolerate_bad_data=True,
                                                 **FAST))
    remote = list(tolerant.iter_epoch())
    assert [list(b["ids"]) for b in remote] == [[i for i in b["ids"] if i not in changed] for b in local]
    assert tolerant.records_skipped == sum(i in changed for b in local for i in b["ids"]) > 0


def test_manifest_digest_of_the_cache_key_is_the_location(tmp_path):
    """One cache file per manifest location (the file name is a digest of it)."""
    from pipeline.data.shard_cache import VerificationCache

    cache = VerificationCache.for_manifest("s3://bucket/ds/manifest.json", tmp_path)
    assert Path(cache.path).name == hashlib.sha256(b"s3://bucket/ds/manifest.json").hexdigest()[:32] + ".json"
    assert VerificationCache.for_manifest("x", False) is None
