"""The local shard cache (issue 27, item 6; pipeline/data/download_cache.py, ``data.cache_dir``): a remote shard is
downloaded once, verified (size and sha256) before it becomes an entry, and read from the local copy every later
epoch and run; a truncated or damaged copy is downloaded again; a server serving wrong bytes is an error naming the
URL that leaves nothing in the cache; the size cap evicts the least recently used copies; local data is never copied.
Remote shards come from the local HTTP server of tests/test_data_remote.py, which counts the requests."""

from __future__ import annotations

import hashlib
import io
import json
import logging
import os
import re
import threading
import time
from collections import Counter
from pathlib import Path

import pytest
from conftest import flip_byte as flip_byte_at
from conftest import load_launch_script
from test_data import assert_batches_equal, opts, take
from test_data_remote import (  # noqa: F401  (fixtures: dataset, http_root, _own_verification_cache)
    FAST,
    _own_verification_cache,
    dataset,
    http_root,
    needs_http,
    rewrite_in_place,
)

from pipeline.config import ConfigError, DataConfig
from pipeline.data.download_cache import DownloadMismatch, ShardDownloadCache
from pipeline.data.stream import (
    MotionLoader,
    ShardChangedError,
    ShardVerificationError,
    open_manifest,
    split_shards,
    verified_split,
    verify_shards,
)


def shard_gets(server, suffix: str = ".tar") -> Counter:
    """GET requests per shard path the server answered."""
    return Counter(path for method, path in server.requests if method == "GET" and path.endswith(suffix))


def entries(folder: Path) -> set[str]:
    return {p.name for p in folder.iterdir()} if folder.exists() else set()


def two_epochs(manifest, **kw) -> tuple[list[dict], MotionLoader]:
    loader = MotionLoader(manifest, "train", opts(**kw))
    return take(loader.iter_batches(), 2 * loader.batches_per_epoch()), loader


# ----------------------------------------------------------------------------------------------------------
# One GET per shard, the same records
# ----------------------------------------------------------------------------------------------------------


@needs_http
@pytest.mark.parametrize("backend, num_workers", [("webdataset", 0), ("webdataset", 2), ("parquet", 0)])
def test_two_epochs_and_a_second_run_make_one_get_per_shard(dataset, http_root, tmp_path, backend, num_workers):
    _, base, server = http_root
    url, cache = f"{base}/manifest.json", tmp_path / "shard-cache"
    suffix = ".tar" if backend == "webdataset" else ".parquet"
    shards = split_shards(open_manifest(url), "train", backend)
    local, _ = two_epochs(dataset, backend=backend, num_workers=num_workers)

    # Without the cache every epoch reads every shard over the network again.
    uncached, _ = two_epochs(url, backend=backend, num_workers=num_workers, **FAST)
    assert_batches_equal(uncached, local)
    assert min(shard_gets(server, suffix).values()) >= 2  # (workers may prefetch into a third epoch)
    server.requests.clear()

    # Run 1: verification downloads each shard once into the cache; both epochs read the copies.
    report = verify_shards(url, "train", backend=backend, downloads=ShardDownloadCache(cache))
    assert report.verified and report.num_downloaded == len(shards) and report.num_cache_served == 0
    cached, loader = two_epochs(url, backend=backend, num_workers=num_workers, cache_dir=str(cache), **FAST)
    assert_batches_equal(cached, local)
    assert shard_gets(server, suffix) == {"/" + s.path: 1 for s in shards}
    assert loader.shards_fetched == 0 and loader.shards_from_cache >= len(shards)
    assert entries(cache) == {s.sha256 for s in shards}  # content-addressed, nothing else left behind

    # Run 2: nothing is downloaded again, by verification nor by the loader.
    again = verify_shards(url, "train", backend=backend, downloads=ShardDownloadCache(cache))
    assert again.verified and again.num_downloaded == 0 and again.num_cache_served == len(shards)
    assert again.as_dict()["num_cache_served"] == len(shards)
    rerun, _ = two_epochs(url, backend=backend, num_workers=num_workers, cache_dir=str(cache), **FAST)
    assert_batches_equal(rerun, local)
    assert shard_gets(server, suffix) == {"/" + s.path: 1 for s in shards}


@needs_http
def test_the_loader_alone_fills_the_cache_and_counts_it(dataset, http_root, tmp_path, caplog):
    """Without verification (data.verify=off) the reader downloads a shard the first time it needs it."""
    _, base, server = http_root
    cache = tmp_path / "shard-cache"
    caplog.set_level(logging.INFO, logger="pipeline.data")
    local, _ = two_epochs(dataset)
    cached, loader = two_epochs(f"{base}/manifest.json", cache_dir=str(cache), check_remote_bytes=False, **FAST)
    assert_batches_equal(cached, local)
    gets = shard_gets(server)
    assert set(gets.values()) == {1} and loader.shards_fetched == len(gets)
    assert loader.shards_from_cache > 0  # the second epoch
    assert re.search(r"shard cache .*: \d+ remote shard\(s\) read from it, \d+ downloaded into it so far",
                     caplog.text)
    assert "downloaded into the shard cache" in caplog.text


# ----------------------------------------------------------------------------------------------------------
# Damaged copies, wrong bytes on the server
# ----------------------------------------------------------------------------------------------------------


@needs_http
def test_a_truncated_copy_is_downloaded_again(dataset, http_root, tmp_path, caplog):
    _, base, server = http_root
    url, cache = f"{base}/manifest.json", tmp_path / "shard-cache"
    local, _ = two_epochs(dataset)
    assert verify_shards(url, "train", downloads=ShardDownloadCache(cache)).verified
    shard = split_shards(open_manifest(url), "train")[2]
    copy = cache / shard.sha256
    copy.write_bytes(copy.read_bytes()[: shard.bytes // 2])  # a crash or a user cut it
    server.requests.clear()
    caplog.set_level(logging.WARNING, logger="pipeline.data.download_cache")
    cached, _ = two_epochs(url, cache_dir=str(cache), **FAST)  # no verification: the size check on open
    assert_batches_equal(cached, local)
    assert shard_gets(server) == {"/" + shard.path: 1}
    assert f"holds {shard.bytes // 2} bytes, the manifest says {shard.bytes}" in caplog.text
    assert copy.stat().st_size == shard.bytes and hashlib.sha256(copy.read_bytes()).hexdigest() == shard.sha256


@needs_http
def test_a_copy_damaged_with_its_size_kept_is_caught_by_verification_and_downloaded_again(dataset, http_root,
                                                                                         tmp_path, caplog):
    _, base, server = http_root
    url, cache = f"{base}/manifest.json", tmp_path / "shard-cache"
    assert verify_shards(url, "train", downloads=ShardDownloadCache(cache)).verified
    shard = split_shards(open_manifest(url), "train")[4]
    flip_byte_at(cache / shard.sha256, shard.bytes // 2)
    server.requests.clear()
    caplog.set_level(logging.WARNING, logger="pipeline.data.download_cache")
    report = verify_shards(url, "train", downloads=ShardDownloadCache(cache))
    assert report.verified and report.num_downloaded == 1
    assert shard_gets(server) == {"/" + shard.path: 1}
    assert re.search(rf"{re.escape(shard.url)}: its copy in the shard cache is bad \(corrupted", caplog.text)
    assert hashlib.sha256((cache / shard.sha256).read_bytes()).hexdigest() == shard.sha256
    local = [r.id for r in verified_split(dataset, "train").iter_motions()]
    source = verified_split(url, "train", downloads=ShardDownloadCache(cache))
    assert [r.id for r in source.iter_motions()] == local


@needs_http
@pytest.mark.parametrize("backend", ["webdataset", "parquet"])
def test_a_server_serving_wrong_bytes_is_named_and_nothing_is_kept(dataset, http_root, tmp_path, backend):
    root, base, server = http_root
    url, cache = f"{base}/manifest.json", tmp_path / "shard-cache"
    shard = split_shards(open_manifest(url), "train", backend)[3]
    rewrite_in_place(root / shard.path)  # same size, other bytes

    with pytest.raises(ShardVerificationError, match=rf"{re.escape(shard.url)}: bad shard \(corrupted: the bytes "
                                                     r"downloaded .*nothing was kept in the shard cache"):
        verify_shards(url, "train", backend=backend, downloads=ShardDownloadCache(cache))
    assert shard.sha256 not in entries(cache) and not any(n.endswith(".download") for n in entries(cache))
    report = verify_shards(url, "train", backend=backend, mode="tolerant", downloads=ShardDownloadCache(cache))
    assert report.bad_paths == (shard.path,) and shard.sha256 not in entries(cache)

    loader = MotionLoader(url, "train", opts(backend=backend, cache_dir=str(cache), **FAST))
    with pytest.raises(ShardChangedError, match=rf"{re.escape(shard.url)}: corrupted: the bytes downloaded are "
                                                r".*nothing was kept in the shard cache"):
        list(loader.iter_epoch())
    assert shard.sha256 not in entries(cache) and not any(n.endswith(".download") for n in entries(cache))
    assert len(entries(cache)) == len(split_shards(open_manifest(url), "train", backend)) - 1


# ----------------------------------------------------------------------------------------------------------
# The size cap, concurrent writers, local data
# ----------------------------------------------------------------------------------------------------------


def blob(n: int, size: int = 1000) -> tuple[bytes, str]:
    data = bytes([n]) * size
    return data, hashlib.sha256(data).hexdigest()


def test_the_size_cap_evicts_the_least_recently_used_copies(tmp_path):
    cache = ShardDownloadCache(tmp_path / "c", max_bytes=2500)
    blobs = [blob(n) for n in range(4)]
    for n, (data, sha) in enumerate(blobs[:2]):
        cache.store(f"http://x/{n}", len(data), sha, io.BytesIO(data)).close()
    old = time.time() - 100
    os.utime(cache.entry_path(blobs[0][1]), (old, old))
    os.utime(cache.entry_path(blobs[1][1]), (old - 50, old - 50))
    cache.open_entry("http://x/0", 1000, blobs[0][1]).close()  # used now: the most recent
    cache.store("http://x/2", 1000, blobs[2][1], io.BytesIO(blobs[2][0])).close()
    assert entries(tmp_path / "c") == {blobs[0][1], blobs[2][1]}  # 1, the least recently used, went
    cache.store("http://x/3", 1000, blobs[3][1], io.BytesIO(blobs[3][0])).close()
    assert entries(tmp_path / "c") == {blobs[2][1], blobs[3][1]}
    assert sum(p.stat().st_size for p in (tmp_path / "c").iterdir()) <= 2500
    # No cap: nothing is evicted.
    uncapped = ShardDownloadCache(tmp_path / "u")
    for n, (data, sha) in enumerate(blobs):
        uncapped.store(f"http://x/{n}", len(data), sha, io.BytesIO(data)).close()
    assert len(entries(tmp_path / "u")) == 4


@needs_http
def test_a_capped_cache_stays_under_its_cap_while_training(dataset, http_root, tmp_path):
    _, base, server = http_root
    shards = split_shards(open_manifest(dataset), "train")
    cap = sum(sorted(s.bytes for s in shards)[-3:])  # room for about three shards
    cache = tmp_path / "shard-cache"
    local, _ = two_epochs(dataset)
    cached, _ = two_epochs(f"{base}/manifest.json", cache_dir=str(cache), cache_max_bytes=cap, **FAST)
    assert_batches_equal(cached, local)
    assert 0 < len(entries(cache)) < len(shards) and sum(p.stat().st_size for p in cache.iterdir()) <= cap


def test_a_wrong_download_raises_and_concurrent_writers_of_one_entry_agree(tmp_path):
    cache = ShardDownloadCache(tmp_path)
    data, sha = blob(7, 300_000)
    with pytest.raises(DownloadMismatch, match=r"http://x/s: truncated: the bytes downloaded are 10 bytes"):
        cache.store("http://x/s", len(data), sha, io.BytesIO(data[:10]))
    assert entries(tmp_path) == set()
    with pytest.raises(ValueError, match="is not 64 hexadecimal digits"):
        cache.store("http://x/s", len(data), "../../escape", io.BytesIO(data))
    errors = []

    def write() -> None:
        try:
            cache.store("http://x/s", len(data), sha, io.BytesIO(data)).close()
        except Exception as exc:  # noqa: BLE001
            errors.append(exc)

    threads = [threading.Thread(target=write) for _ in range(4)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert not errors and entries(tmp_path) == {sha}
    assert (tmp_path / sha).read_bytes() == data


def test_local_data_is_never_copied(dataset, tmp_path):
    cache = tmp_path / "shard-cache"
    downloads = ShardDownloadCache(cache)
    assert verify_shards(dataset, "train", downloads=downloads).verified
    batches, loader = two_epochs(dataset, cache_dir=str(cache))
    assert batches and not cache.exists()
    assert downloads.fetched == downloads.served == loader.shards_fetched == loader.shards_from_cache == 0


def test_data_config_validates_the_cache_options(tmp_path):
    config = DataConfig(cache_dir="~/.cache/mfm-shards", cache_max_gb=1.5)
    assert config.cache_max_bytes == 1_500_000_000
    assert DataConfig().cache_dir is None and DataConfig().cache_max_bytes == 0
    with pytest.raises(ConfigError, match="data.cache_max_gb must be a finite number >= 0"):
        DataConfig(cache_dir=str(tmp_path), cache_max_gb=-1.0)
    with pytest.raises(ConfigError, match="data.cache_dir is not set"):
        DataConfig(cache_max_gb=2.0)
    with pytest.raises(ConfigError, match="data.cache_dir must be a folder"):
        DataConfig(cache_dir=" ")
    (tmp_path / "file").write_text("x")
    with pytest.raises(ConfigError, match="exists and is not a folder"):
        DataConfig(cache_dir=str(tmp_path / "file"))


# ----------------------------------------------------------------------------------------------------------
# Training from a URL with data.cache_dir (the README's command)
# ----------------------------------------------------------------------------------------------------------


@needs_http
def test_training_from_a_url_with_a_cache_dir_gets_each_shard_once(http_root, tmp_path):
    """``python launch/train.py --config tiny data.manifest=https://... data.cache_dir=...``: verification downloads
    each shard once; three epochs and a second run read the copies; metrics.jsonl counts them."""
    train_entry = load_launch_script("train")
    _, base, server = http_root
    cache = tmp_path / "shard-cache"
    shards = split_shards(open_manifest(f"{base}/manifest.json"), "train")
    for run in ("run-1", "run-2"):
        overrides = [f"data.manifest={base}/manifest.json", f"train.out_dir={tmp_path / run}", "train.log_every=1",
                     "train.max_steps=40", "train.save_every=40", "data.batch_size=4", "data.window=24",
                     f"data.cache_dir={cache}", "data.cache_max_gb=1", "data.retry_backoff_s=0.01"]
        assert train_entry.main(["--config", "tiny", *overrides]) == 0
        last = json.loads((tmp_path / run / "metrics.jsonl").read_text().splitlines()[-1])
        assert last["epoch"] >= 2 and last["shards_fetched"] == 0 and last["shards_from_cache"] >= 2 * len(shards)
        report = json.loads((tmp_path / run / "shard_report.json").read_text())
        assert report["verified"] and report["num_downloaded"] == (len(shards) if run == "run-1" else 0)
        assert shard_gets(server) == {"/" + s.path: 1 for s in shards}
