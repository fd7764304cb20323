"""The data job's online half: streaming shards into training and evaluation batches.

Owns the manifest and shard readers (``stream``: webdataset tar / Parquet, verification, every sample once across
ranks and workers, exact resume), the named pipeline stages (``stages``), shard locations on disk or any fsspec URL
with retries (``locations``) and the verified-shard cache (``shard_cache``). May import only the shared modules
(pipeline.config, pipeline.distributed, pipeline.checkpoint) and mfm; the training, generation and evaluation
packages import it, never the other way round.
"""
