"""Tiny static sets and motion datasets in the real file formats for tests and examples, without
garment generation or simulation (motion: :func:`write_synthetic_motion_dataset`). Static sets:
each "garment" is a set of body segments (by type) lifted off the body along its smoothed
normals by the sample's tightness plus a smooth ripple, so offsets, masks, shapes and
topologies are real while a sample costs one body posing (milliseconds).
"""
from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from learn.gcvae.body_mesh import DUAL_TYPES, build_body_mesh, canonical_body_vertices
from learn.gcvae.static_set import FILE_NAME, STYLE_WIDTH, sample_shapes
from simulate.garment import mesh_ops

#: Segments (bone names, by prefix) each synthetic type covers.
SEGMENTS_OF: dict[str, tuple[str, ...]] = {
    "tshirt": ("spine01", "spine02", "spine03", "spine04", "clavicle", "upperarm01", "neck01"),
    "pants": ("spine05", "pelvis", "upperleg", "lowerleg"),
    "skirt": ("spine05", "pelvis", "upperleg01", "upperleg02"),
}


def write_synthetic_static_set(root: str | os.PathLike, body, *, types: tuple[str, ...] = ("tshirt", "pants", "skirt"),
                               count: int = 4, seed: int = 0) -> Path:
    """Writes ``root/static_set.npz`` with ``count`` samples per type (a quarter, at least one,
    in the test split); returns its path."""
    mesh = build_body_mesh(body, subdivisions=0)
    rng = np.random.default_rng(seed)
    rows: dict[str, list] = {k: [] for k in ("type", "shape", "tightness", "style", "split", "body_vertices",
                                             "offsets", "mask", "registration_mm")}
    for ti, garment_type in enumerate(types):
        prefixes = SEGMENTS_OF[garment_type]
        covered = np.array([any(n.startswith(p) for p in prefixes) for n in mesh.segment_names])[mesh.segments]
        shapes = sample_shapes(count, rng, body.shape_size)
        test = np.zeros(count, bool)
        test[rng.permutation(count)[:max(1, count // 4)]] = True
        for k in range(count):
            standard = mesh.vertices(canonical_body_vertices(body, shapes[k]))[0]
            _, faces = mesh.topology(garment_type)
            base = mesh.positions_for(garment_type, standard)
            mask = covered.copy()
            if garment_type in DUAL_TYPES:
                mask &= np.isin(np.arange(len(mask)), np.unique(faces))
                mask &= ~(mesh.inner_leg & ~mesh.bridge_vertices())
            tightness = float(rng.uniform(0.005, 0.05))
            normals = mesh_ops.smooth_normals(base, faces, iterations=5)
            ripple = 0.005 * np.sin(20.0 * base[:, 1] + rng.uniform(0, 2 * np.pi))
            offsets = np.where(mask[:, None], base + normals * (tightness + ripple)[:, None] - standard, 0.0)
            style = np.full(STYLE_WIDTH, np.nan, np.float32)
            style[0] = tightness
            for key, value in (("type", ti), ("shape", shapes[k]), ("tightness", tightness), ("style", style),
                               ("split", int(test[k])), ("body_vertices", standard.astype(np.float32)),
                               ("offsets", offsets.astype(np.float32)), ("mask", mask),
                               ("registration_mm", [0.0, 0.0])):
                rows[key].append(value)
    arrays = {k: np.asarray(v) for k, v in rows.items()}
    arrays["types"] = np.array(types)
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    path = root / FILE_NAME
    tmp = root / f".{FILE_NAME}.{os.getpid()}.tmp.npz"
    meta = {"synthetic": True, "count_per_type": count, "seed": seed}
    np.savez_compressed(tmp, meta=np.array(json.dumps(meta)), **arrays, **mesh.arrays())
    os.replace(tmp, path)
    return path


def write_synthetic_motion_dataset(root: str | os.PathLike, body, *, types: tuple[str, ...] = ("tshirt", "skirt"),
                                   sequences: dict[str, int] | None = None, frames: int = 4, seed: int = 0) -> Path:
    """Writes tiny motion datasets in the real shard format, one per type under ``root/<type>``
    listed in ``root/datasets.json`` (as a multi-type ``drape generate-dataset`` run does), and
    returns ``root``. Without simulation: each "garment" is the type's body segments (on the
    dual topology for skirts, with no body vertex under it as the real skirts have) lifted off the
    canonical body of the sequence's shape by its tightness plus a ripple whose phase follows the
    poses of the frame and of the frame 3 before (a stand-in for dynamics: the unposed drape of a
    frame depends on earlier poses too). Poses are a random walk; ``posed_vertices`` repeat the
    unposed garment (the dynamic set reads only the unposed displacements).
    ``sequences``: split -> sequences per type (default ``{"train_train": 2, "test_test": 1}``)."""
    from data_manifest.manifest import Manifest, collect_provenance
    from data_manifest.schema import template_sha256
    from data_manifest.shard import ShardWriter, shard_path

    sequences = {"train_train": 2, "test_test": 1} if sequences is None else sequences
    mesh = build_body_mesh(body, subdivisions=0)
    anny_index = mesh.interpolation.tocsr().indices  # subdivision 0: body-mesh vertex -> anny vertex
    rng = np.random.default_rng(seed)
    root = Path(root)
    listed = []
    for garment_type in types:
        prefixes = SEGMENTS_OF[garment_type]
        covered = np.array([any(n.startswith(p) for p in prefixes) for n in mesh.segment_names])[mesh.segments]
        _, body_faces = mesh.topology(garment_type)
        dual = garment_type in DUAL_TYPES
        if dual:
            covered &= ~(mesh.inner_leg & ~mesh.bridge_vertices())
        faces = body_faces[covered[body_faces].all(1)]
        used = np.unique(faces)
        remap = np.full(mesh.vertex_count, -1, np.int64)
        remap[used] = np.arange(len(used))
        default = mesh.vertices(canonical_body_vertices(body, body.shape_default))[0]
        base_default = mesh.positions_for(garment_type, default)[used]
        template = {"faces": remap[faces].astype(np.int32), "rest_vertices": base_default.astype(np.float32),
                    "skinning_weights": np.full((len(used), 1), 1.0, np.float32),
                    "body_vertex_index": (np.full(len(used), -1) if dual else anny_index[used]).astype(np.int32)}
        spec = {"name": f"synthetic-motion-{garment_type}", "garment": {"type": garment_type},
                "body": {"backend": "anny", "path": None}, "poses": {"source": "motion"},
                "motion": {"source": "synthetic", "frames": frames}, "seed": seed}
        out = root / garment_type
        task_ids = {split: [f"{split}-p{k:03d}-m00" for k in range(n)] for split, n in sequences.items()}
        manifest = Manifest.create(out, name=spec["name"], spec=spec, template_sha256=template_sha256(template),
                                   precision="float32",
                                   provenance=collect_provenance(device="cpu", seeds={"spec": seed}),
                                   splits=task_ids)
        for split, ids in task_ids.items():
            for task_id in ids:
                shape = sample_shapes(1, rng, body.shape_size)[0]
                tightness = np.array([rng.uniform(0.005, 0.03), rng.uniform(0.0, 0.4)], np.float32)
                standard = mesh.vertices(canonical_body_vertices(body, shape))[0]
                base = mesh.positions_for(garment_type, standard)[used]
                normals = mesh_ops.smooth_normals(mesh.positions_for(garment_type, standard), body_faces,
                                                  iterations=5)[used]
                poses = np.cumsum(rng.normal(0.0, 0.15, (frames, body.pose_size)), 0).astype(np.float32)
                task = {"task_id": task_id, "garment": garment_type, "splits": [split], "seed": seed,
                        "shape": shape, "style": np.array([tightness[0]], np.float32), "tightness": tightness,
                        "motion": "synthetic", "fps": 30.0}
                with ShardWriter(shard_path(out, task_id), template=template, task=task) as writer:
                    for t in range(frames):
                        phase = 4.0 * poses[t, :3].sum() + 8.0 * poses[max(t - 3, 0), 3:6].sum()
                        ripple = 0.01 * np.sin(25.0 * base[:, 1] + phase)
                        unposed = base + normals * (tightness[0] + ripple)[:, None]
                        under = base_default if dual else canonical_body_vertices(body, shape)[0][anny_index[used]]
                        writer.write_frame(unposed, unposed - under, poses[t],
                                           {"penetration_fraction": 0.0}, frame_index=t)
                manifest.add_shard(writer.record)
        manifest.finish()
        manifest.save()
        listed.append({"type": garment_type, "path": garment_type, "complete": True,
                       "frames_kept": manifest.totals["frames_kept"]})
    tmp = root / f".datasets.json.{os.getpid()}.tmp"
    tmp.write_text(json.dumps({"format": "drape-datasets", "name": "synthetic-motion", "datasets": listed}, indent=2))
    os.replace(tmp, root / "datasets.json")
    return root
