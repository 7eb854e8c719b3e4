"""A tiny anny-bodied dataset in the real on-disk format, for the collision-aware learner's tests.

The garment is a band of the canonical anny torso lifted off the skin along the vertex normals;
each frame displaces it outward by a pose-dependent ripple (always >= 4 mm off the body) in the
unposed space and skins it with the body's weights, so the unposed displacements are exact and
the posed garments clear the posed body. No physics: seconds to write, the body model is real.

With ``motion_fps`` the dataset is a motion dataset (spec ``poses.source: motion``, docs/motion.md):
each task is one sequence of frames ``1 / motion_fps`` apart, its poses a smooth sinusoid of the
moving entries, and the ripple follows a lagged copy of spine1's angle (an exponential average
over the frames so far), so a frame's garment depends on the motion before it. The shards store
the garment velocities (finite differences) and the body's root joint, as motion shards do.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from data_manifest.manifest import Manifest, collect_provenance
from data_manifest.schema import template_sha256
from data_manifest.shard import ShardWriter, shard_path

#: Pose entries the frames vary (spine1 x, spine2 z, left/right shoulder z), [rad] ranges +-0.3.
MOVING_POSE = (9, 20, 44, 47)
BAND_Y_M = (0.12, 0.22)  # height band of the torso in the canonical body [m]


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    n = np.zeros_like(vertices)
    fn = np.cross(vertices[faces[:, 1]] - vertices[faces[:, 0]], vertices[faces[:, 2]] - vertices[faces[:, 0]])
    for k in range(3):
        np.add.at(n, faces[:, k], fn)
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)


def torso_band_template(body) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Garment template (faces, rest_vertices, skinning_weights, body_vertex_index) and the
    rest-space vertex normals of its body vertices."""
    rest = body.rest(body.shape_default)[0][0].astype(np.float64)
    normals = vertex_normals(rest, body.faces)
    torso = body.part_vertex_mask(["torso"]) & (rest[:, 1] > BAND_Y_M[0]) & (rest[:, 1] < BAND_Y_M[1])
    faces = body.faces[torso[body.faces].all(axis=1)]
    used = np.unique(faces)
    remap = -np.ones(rest.shape[0], np.int64)
    remap[used] = np.arange(used.size)
    template = {
        "faces": remap[faces].astype(np.int32),
        "rest_vertices": (rest[used] + 0.008 * normals[used]).astype(np.float32),
        "skinning_weights": body.skinning_weights[used].astype(np.float32),
        "body_vertex_index": used.astype(np.int32),
    }
    return template, normals[used]


#: Share of the distance to spine1's current angle the lagged angle of motion datasets closes per frame.
LAG_RATE = 0.3


def write_band_dataset(root: str | Path, body, *, splits: dict[str, int], frames_per_task: int = 4,
                       seed: int = 0, motion_fps: float | None = None) -> Manifest:
    """Write the dataset: ``splits`` maps split name -> tasks (one random shape and style each)."""
    import torch

    from simulate.body import lbs_torch

    root = Path(root)
    rng = np.random.default_rng(seed)
    template, normals = torso_band_template(body)
    index = template["body_vertex_index"].astype(np.int64)
    y = template["rest_vertices"][:, 1].astype(np.float64)
    spec = {"name": "band", "garment": "band", "body": {"backend": "anny", "path": None}, "splits": splits}
    if motion_fps is not None:
        spec.update(poses={"source": "motion"}, motion={"source": "procedural", "fps": float(motion_fps)})
    manifest = Manifest.create(root, name="band", spec=spec, template_sha256=template_sha256(template),
                               precision="float32", provenance=collect_provenance(device="cpu", seeds={"spec": seed}),
                               splits={s: [f"{s}-{k:03d}" for k in range(n)] for s, n in splits.items()})
    for split, count in splits.items():
        for k in range(count):
            task_id = f"{split}-{k:03d}"
            shape = np.clip(body.shape_default + rng.uniform(-0.15, 0.15, body.shape_size), 0, 1).astype(np.float32)
            style = rng.uniform(-1, 1, 2).astype(np.float32)
            rest_body = body.rest(shape)[0][0].astype(np.float64)[index]
            task = {"task_id": task_id, "garment": "band", "splits": [split], "seed": seed, "shape": shape, "style": style}
            if motion_fps is not None:
                task.update(motion="sine", fps=float(motion_fps))
                frequency, phase = rng.uniform(1.0, 2.0), rng.uniform(0, 2 * np.pi, len(MOVING_POSE))
            lagged, previous = None, None
            with ShardWriter(shard_path(root, task_id), template=template, task=task, precision="float32",
                             compression="gzip") as writer:
                for frame in range(frames_per_task):
                    pose = np.zeros(body.pose_size, np.float32)
                    if motion_fps is None:
                        pose[list(MOVING_POSE)] = rng.uniform(-0.3, 0.3, len(MOVING_POSE))
                        driver = pose[MOVING_POSE[0]]
                    else:
                        pose[list(MOVING_POSE)] = 0.3 * np.sin(2 * np.pi * frequency * frame / motion_fps + phase)
                        lagged = pose[MOVING_POSE[0]] if lagged is None else lagged + LAG_RATE * (pose[MOVING_POSE[0]] - lagged)
                        driver = lagged
                    ripple = 0.006 + 0.002 * (1 + np.sin(40 * y + 3 * driver + style[0]))
                    displacement = (0.008 + ripple)[:, None] * normals  # (V, 3), >= 14 mm outward
                    posed_body = body.pose_torch(shape, pose)
                    posed = lbs_torch(torch.as_tensor(rest_body + displacement, dtype=torch.float32)[None],
                                      torch.as_tensor(template["skinning_weights"]), posed_body.skinning_transforms)[0].numpy()
                    motion = {}
                    if motion_fps is not None:
                        velocity = np.zeros_like(posed) if previous is None else (posed - previous) * motion_fps
                        root_joint = posed_body.joints[0, int(body.pose_joint_indices[0])].numpy()  # the pelvis
                        motion = {"velocities": velocity, "root_joint": root_joint}
                        previous = posed
                    writer.write_frame(posed, displacement, pose, {"penetration_fraction": 0.0}, frame_index=frame,
                                       **motion)
            manifest.add_shard(writer.record)
            manifest.save()
    manifest.finish()
    manifest.save()
    return manifest


def write_tiny_config(path: Path, **regressor) -> str:
    """A ``drape train collision-aware --config`` of small networks and few samples (seconds per
    stage on a CPU) at ``path``; ``regressor`` adds regressor options. Returns the path."""
    import yaml

    small = {"hidden_size": 16, "layers": 1, "frequencies": 1, "batch_size": 512, "lr": 3e-3}
    Path(path).write_text(yaml.safe_dump({
        "fields": {**small, "points": 500, "shapes": 2, "samples": 4, "shape_basis": 2, "shape_hidden_size": 16,
                   "shape_layers": 1, "shape_frequencies": 1},
        "sdf": {**small, "points": 1000, "voxel_m": 0.03},  # a grid SDF (the default kind) of 3 cm voxels
        "projection": {"steps": 3},
        "vae": {"hidden_size": 16, "batch_size": 4},
        "regressor": {"hidden_size": 16, "batch_size": 4, **regressor},
    }))
    return str(path)
