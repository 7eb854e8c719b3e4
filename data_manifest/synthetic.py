"""Tiny synthetic datasets in the real on-disk format, for tests and examples.

The garment is an open tube (a skirt-like cylinder) around a body root; frames sway it with
the pose. No physics: the point is exercising the shard/manifest/reader contract quickly.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from .manifest import Manifest, collect_provenance
from .schema import template_sha256
from .shard import ShardWriter, shard_path

POSE_SIZE = 6
SHAPE_SIZE = 4
STYLE_SIZE = 2
JOINT_COUNT = 3


def tube_template(*, rings: int = 5, segments: int = 10, radius_m: float = 0.18, height_m: float = 0.6,
                  with_uv: bool = True) -> dict[str, np.ndarray]:
    """Open cylinder garment template: ``rings * segments`` vertices (50 by default) [m],
    centred on the origin, axis along y, with skinning weights over ``JOINT_COUNT`` joints."""
    angles = np.linspace(0.0, 2.0 * np.pi, segments, endpoint=False)
    heights = np.linspace(height_m / 2, -height_m / 2, rings)
    ring, seg = np.meshgrid(np.arange(rings), np.arange(segments), indexing="ij")
    vertices = np.stack([radius_m * np.cos(angles[seg]), heights[ring], radius_m * np.sin(angles[seg])], axis=-1)
    vertices = vertices.reshape(-1, 3)
    faces = []
    for r in range(rings - 1):
        for s in range(segments):
            a, b = r * segments + s, r * segments + (s + 1) % segments
            c, d = a + segments, b + segments
            faces += [(a, c, b), (b, c, d)]
    height01 = (ring.reshape(-1) / max(1, rings - 1)).astype(np.float64)
    weights = np.stack([1.0 - height01, 0.5 * height01, 0.5 * height01], axis=1)
    template = {
        "faces": np.asarray(faces, dtype=np.int32),
        "rest_vertices": vertices.astype(np.float32),
        "skinning_weights": (weights / weights.sum(axis=1, keepdims=True)).astype(np.float32),
        "body_vertex_index": np.where(np.arange(vertices.shape[0]) % 3 == 0, np.arange(vertices.shape[0]), -1)
        .astype(np.int32),
    }
    if with_uv:
        template["uv"] = np.stack([seg.reshape(-1) / segments, height01], axis=1).astype(np.float32)
    return template


def synthetic_frame(template: dict[str, np.ndarray], rng: np.random.Generator, *,
                    translation_m: np.ndarray) -> dict[str, Any]:
    """One fake frame: posed vertices [m] (V, 3), displacements [m] (V, 3), pose [rad] (P,),
    quality metrics, body translation [m] (3,)."""
    rest = template["rest_vertices"].astype(np.float64)
    pose = rng.uniform(-0.5, 0.5, POSE_SIZE)
    sway = np.array([np.sin(pose[0]), 0.0, np.sin(pose[1])]) * 0.1
    displacement = 0.01 * rng.standard_normal(rest.shape)
    posed = rest + displacement + sway * (0.5 - rest[:, 1:2]) + translation_m
    return {
        "posed_vertices": posed,
        "unposed_displacements": displacement,
        "pose": pose,
        "quality": {"penetration_fraction": float(rng.uniform(0, 0.01)), "max_area_change": float(rng.uniform(0, 0.5))},
        "body_translation": translation_m,
    }


def write_synthetic_dataset(
    root: str | os.PathLike[str],
    *,
    splits: dict[str, int] | None = None,
    frames_per_task: int = 4,
    precision: str = "float32",
    compression: str = "gzip",
    seed: int = 0,
    name: str = "synthetic",
) -> Manifest:
    """Write a complete tiny dataset (shards + manifest) under ``root`` and return its
    manifest. ``splits``: split -> number of tasks (default ``{"train": 2, "test": 1}``).
    Every task drops one frame as ``nan`` (logged in its ``dropped`` group at frame index 1)
    and keeps ``frames_per_task``. Deterministic for a given ``seed``."""
    splits = {"train": 2, "test": 1} if splits is None else splits
    root = Path(root)
    rng = np.random.default_rng(seed)
    template = tube_template()
    spec = {"name": name, "garment": "tube", "splits": splits, "frames_per_task": frames_per_task,
            "precision": precision, "seed": seed}
    manifest = Manifest.create(
        root, name=name, spec=spec, template_sha256=template_sha256(template), precision=precision,
        provenance=collect_provenance(device="cpu", seeds={"spec": seed}),
        splits={split: [f"{split}-{k:03d}" for k in range(count)] for split, count in splits.items()},
    )
    for split, count in splits.items():
        for k in range(count):
            task_id = f"{split}-{k:03d}"
            task = {"task_id": task_id, "garment": "tube", "splits": [split], "seed": seed * 1000 + k,
                    "shape": rng.normal(size=SHAPE_SIZE), "style": rng.normal(size=STYLE_SIZE)}
            translation = np.array([rng.uniform(-2, 2), 1.0, rng.uniform(-2, 2)])
            with ShardWriter(shard_path(root, task_id), template=template, task=task, precision=precision,
                             compression=compression) as writer:
                for frame in range(frames_per_task):
                    writer.write_frame(**synthetic_frame(template, rng, translation_m=translation),
                                       frame_index=2 * frame)
                writer.record_dropped("nan", frame_index=1, pose=rng.uniform(-0.5, 0.5, POSE_SIZE))
                writer.timings["simulate_s"] = 0.5
            manifest.add_shard(writer.record)
            manifest.save()
    manifest.finish()
    manifest.save()
    return manifest
