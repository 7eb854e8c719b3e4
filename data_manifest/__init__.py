"""The on-disk contract of drape datasets: shard layout, manifest schema, writer, reader,
validator and exporters. See ``schema`` for the layout and ``reader.DatasetReader`` for the
training-side API."""

from .manifest import Manifest, collect_provenance, merge_manifests
from .reader import DatasetReader
from .schema import (
    SCHEMA_VERSION,
    CorruptShardError,
    DatasetError,
    ManifestSchemaError,
    MissingShardError,
    template_sha256,
)
from .shard import ShardRecord, ShardWriter, ShardWriterSet, remove_orphan_temporaries, shard_path
from .validate import Report, info, validate_dataset

__all__ = [
    "SCHEMA_VERSION",
    "CorruptShardError",
    "DatasetError",
    "DatasetReader",
    "Manifest",
    "ManifestSchemaError",
    "MissingShardError",
    "Report",
    "ShardRecord",
    "ShardWriter",
    "ShardWriterSet",
    "collect_provenance",
    "info",
    "merge_manifests",
    "remove_orphan_temporaries",
    "shard_path",
    "template_sha256",
    "validate_dataset",
]
