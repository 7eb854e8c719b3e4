"""GCVAE's dynamic set (seed 004, Sec. 4.2 "DVAE", Table 4): the frames of simulated motion
sequences written as offsets and a mask on the common body mesh, each conditioned on the body
shape, the tightness and the poses of several frames of its sequence.

Source: a ``drape generate-dataset`` directory whose spec has ``poses.source: motion`` (one
garment type), or a directory of several such datasets listed in ``datasets.json`` (a
multi-type spec such as ``pipelines/configs/cloth3d-mini.yaml``). A sequence is one shard (one
task: a style-shape pair and a motion); its frames are ordered by ``frame_index``, the frame's
index in the motion (dropped frames leave gaps).

Per sequence:

1. The unposed garment of every kept frame (the dataset's ``unposed_displacements``: inverse
   skinning minus the rest body under each garment vertex, added back onto that rest body; the
   template's rest vertices where a garment vertex has no body vertex) lies in the canonical pose
   of the body mesh, so the seed's pose-invariant offsets ``K^-1(G_t) - B`` need no further
   transform.
2. The first kept frame's unposed garment is registered on the body mesh of the sequence's shape
   (:func:`learn.gcvae.registration.register`, the type's topology): the mask, and for every
   masked vertex the garment point it lands on (face, barycentrics). The seed registers once per
   sequence too; the mask is the sequence's.
3. Each frame's offsets are the same garment points on that frame's unposed garment minus the
   standard body positions.

A sequence whose registration covers no body vertex or misses its garment by more than
``MAX_REGISTRATION_MM`` on average is skipped (a garment the simulation let slide off the body)
and listed in ``skipped``.

Conditioning of a frame ``t`` (seed: shape, tightness and the poses of T frames): the body
``shape`` (S), the pair's ``tightness`` (the CLOTH3D (height, weight) offsets, when every
dataset stores it) and the poses (60 values each) of the frames ``t - (T-1) s, ..., t - s, t``
(``dynamic.frames`` T, ``dynamic.frame_stride`` s; the seed: 4 frames every 3). A wanted frame
that was dropped or lies before the sequence's first kept frame takes the nearest kept frame
before it (else the first kept frame).

Frames of the datasets' train splits (``train_train``, ``train``) have split 0, of their test
splits (``test_test``, ``test``, ``train_test``, ``test_train``: every split whose name does
not start with ``train_train``/``train``) split 1.
"""
from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import numpy as np

from learn.gcvae.body_mesh import BodyMesh, build_body_mesh, canonical_body_vertices
from learn.gcvae.registration import MAX_OFFSET_M, register, registration_error
from learn.gcvae.static_set import split_indices
from simulate.garment import mesh_ops

DATASETS_FILE = "datasets.json"
MANIFEST_FILE = "manifest.json"
TRAIN_SPLITS = ("train_train", "train")
#: A sequence whose first frame's garment lies farther than this from its registered surface on
#: average [mm], or covers no body vertex, is not a garment worn on the body (e.g. one the
#: simulation let fall): it is skipped and counted in ``skipped``.
MAX_REGISTRATION_MM = 50.0


def is_motion_source(root: str | os.PathLike) -> bool:
    """Whether ``root`` is a dataset directory (``manifest.json``) or a directory of datasets
    (``datasets.json``), as opposed to a ``drape static-set`` directory."""
    root = Path(root)
    return root.is_dir() and ((root / MANIFEST_FILE).is_file() or (root / DATASETS_FILE).is_file())


def dataset_dirs(root: str | os.PathLike) -> list[Path]:
    """The dataset directories of ``root``: those ``datasets.json`` lists, or ``root`` itself."""
    root = Path(root)
    if (root / DATASETS_FILE).is_file():
        index = json.loads((root / DATASETS_FILE).read_text())
        dirs = [root / d["path"] for d in index.get("datasets", [])]
        if not dirs:
            raise ValueError(f"--data {root}: {DATASETS_FILE} lists no datasets")
        return dirs
    if (root / MANIFEST_FILE).is_file():
        return [root]
    raise FileNotFoundError(f"--data {root}: no {MANIFEST_FILE} or {DATASETS_FILE} (a drape generate-dataset "
                            f"directory with poses.source: motion)")


def context_frames(frame_index: np.ndarray, frames: int, stride: int) -> np.ndarray:
    """Rows (F, T) into a sequence's kept frames (``frame_index`` (F,), increasing): for each
    frame t the kept frames at t - (T-1) s, ..., t (oldest first), each the nearest kept frame
    at or before the wanted index, else the first kept frame."""
    fi = np.asarray(frame_index, np.int64)
    wanted = fi[:, None] - stride * np.arange(frames - 1, -1, -1)[None, :]
    return np.clip(np.searchsorted(fi, wanted, side="right") - 1, 0, len(fi) - 1)


def _correspondence(rest_garment: np.ndarray, faces: np.ndarray, positions: np.ndarray, body_faces: np.ndarray,
                    topology: str, rounds: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[float]]:
    """Mask (N,), garment face (K,) and barycentrics (K, 3) of the K masked vertices, and the
    registration errors [mm] (garment to registered surface, registered to garment)."""
    reg = register(rest_garment, faces, positions, body_faces, rounds=rounds, max_distance=MAX_OFFSET_M[topology])
    e = registration_error(rest_garment, faces, positions, body_faces, reg)
    error = [e["garment_to_registered_mm"], e["registered_to_garment_mm"]]
    points = positions[reg.mask] + reg.offsets[reg.mask]
    _, face, bary, _ = mesh_ops.ClosestPointQuery(rest_garment, faces).query(points)
    return reg.mask, np.asarray(face, np.int64), np.asarray(bary, np.float64), error


class DynamicSet:
    """The frames of motion datasets as offsets and masks on the common body mesh.

    Attributes (M frames, N body-mesh vertices, C condition values): ``types`` names, ``type``
    (M,), ``sequence`` (M,) sequence id, ``frame_index`` (M,), ``split`` (M,) 0 train / 1 test,
    ``body_vertices`` (M, N, 3) [m] (standard topology, canonical pose), ``offsets`` (M, N, 3) [m],
    ``mask`` (M, N) bool, ``condition`` (M, C) float32, ``registration_mm`` (M, 2) (the
    registration error of the sequence's first frame: garment to registered, registered to garment),
    ``mesh`` (BodyMesh), ``layout`` (names and sizes of the condition's parts).
    """

    def __init__(self, root: str | os.PathLike, *, frames: int = 4, frame_stride: int = 3,
                 representation: dict | None = None, body=None, log=None) -> None:
        from data_manifest.reader import DatasetReader
        from simulate.body import load_body_model

        from learn.gcvae.hyperparameters import merged

        if int(frames) < 1:
            raise ValueError(f"dynamic.frames must be >= 1, got {frames}")
        if int(frame_stride) < 1:
            raise ValueError(f"dynamic.frame_stride must be >= 1, got {frame_stride}")
        self.frames, self.frame_stride = int(frames), int(frame_stride)
        rep = merged({"representation": representation or {}})["representation"]
        self.root = Path(root)
        dirs = dataset_dirs(root)
        readers = [DatasetReader(d) for d in dirs]
        for d, r in zip(dirs, readers):
            source = (r.manifest.spec.get("poses") or {}).get("source")
            if source != "motion":
                raise ValueError(f"--data {d}: poses.source is {source!r}; the dynamic gcvae (--dynamic) needs "
                                 f"motion sequences (a dataset generated with poses.source: motion)")
        backends = {(r.manifest.spec.get("body") or {}).get("backend", "anny") for r in readers}
        if backends != {"anny"}:
            raise ValueError(f"--data {root}: body backend {sorted(backends)}; the gcvae body mesh is anny's")
        body = load_body_model("anny") if body is None else body
        self.mesh: BodyMesh = build_body_mesh(
            body, subdivisions=rep["subdivisions"], min_segment_vertices=rep["min_segment_vertices"],
            inner_leg_cosine=rep["inner_leg_cosine"], dual_smoothing_iterations=rep["dual_smoothing_iterations"])
        with_tightness = True
        self.skipped: list[dict] = []
        self.types: list[str] = []
        rows: dict[str, list] = {k: [] for k in ("type", "sequence", "frame_index", "split", "seq_body", "offsets",
                                                 "seq_mask", "shape", "tightness", "poses", "registration_mm")}
        h = hashlib.sha256()
        sequence = 0
        for d, reader in zip(dirs, readers):
            h.update((d / MANIFEST_FILE).read_bytes())
            gtype = str(reader.manifest.spec["garment"]["type"])
            template = reader.template
            faces = np.asarray(template["faces"], np.int64)
            bvi = np.asarray(template["body_vertex_index"], np.int64)
            rest = np.asarray(template["rest_vertices"], np.float64)
            topology, body_faces = self.mesh.topology(gtype)
            for split in reader.splits:
                is_test = 0 if split in TRAIN_SPLITS else 1
                for task_id in reader.splits[split]:
                    if reader.num_frames(split) == 0:
                        continue
                    a = reader.load_task(task_id)
                    if len(a["frame_index"]) == 0:
                        continue
                    order = np.argsort(a["frame_index"], kind="stable")
                    shape = a["shape"][0].astype(np.float32)
                    anny = canonical_body_vertices(body, shape)[0]
                    base = np.where((bvi >= 0)[:, None], anny[np.clip(bvi, 0, None)], rest)
                    garments = base[None] + a["unposed_displacements"][order].astype(np.float64)  # (F, V, 3)
                    standard = self.mesh.vertices(anny)
                    positions = self.mesh.positions_for(gtype, standard)
                    mask, face, bary, error = _correspondence(garments[0], faces, positions, body_faces, topology,
                                                              rep["registration_rounds"])
                    if not mask.any() or not error[0] <= MAX_REGISTRATION_MM:
                        self.skipped.append({"type": gtype, "task_id": task_id, "registration_mm": error[0]})
                        if log is not None:
                            log(f"{gtype} {task_id}: skipped, its garment is not on the body (registration "
                                f"{error[0]:.1f} mm, {int(mask.sum())} vertices covered)")
                        continue
                    if gtype not in self.types:
                        self.types.append(gtype)
                    ti = self.types.index(gtype)
                    tri = faces[face]  # (K, 3)
                    points = np.einsum("kc,fkcd->fkd", bary, garments[:, tri])  # (F, K, 3)
                    offsets = np.zeros((len(order), self.mesh.vertex_count, 3), np.float32)
                    offsets[:, mask] = points - standard[mask][None]
                    fi = a["frame_index"][order]
                    ctx = context_frames(fi, self.frames, self.frame_stride)
                    poses = a["pose"][order][ctx].reshape(len(order), -1)
                    if "tightness" in a:
                        tight = np.repeat(a["tightness"][:1], len(order), 0)
                    else:
                        with_tightness, tight = False, np.zeros((len(order), 0), np.float32)
                    for key, value in (("type", np.full(len(order), ti)), ("sequence", np.full(len(order), sequence)),
                                       ("frame_index", fi), ("split", np.full(len(order), is_test)),
                                       ("offsets", offsets), ("shape", np.repeat(shape[None], len(order), 0)),
                                       ("tightness", tight), ("poses", poses),
                                       ("registration_mm", np.tile(error, (len(order), 1)))):
                        rows[key].append(value)
                    rows["seq_body"].append(standard.astype(np.float32))
                    rows["seq_mask"].append(mask)
                    if log is not None:
                        log(f"{gtype} {task_id}: {len(order)} frames, registration {error[0]:.2f} mm")
                    sequence += 1
            reader.close()
        if sequence == 0:
            raise ValueError(f"--data {root}: no sequence with kept frames of a garment on the body "
                             f"({len(self.skipped)} skipped)")
        cat = {k: np.concatenate(v) for k, v in rows.items() if k not in ("seq_body", "seq_mask")}
        self.type = cat["type"].astype(np.int64)
        self.sequence = cat["sequence"].astype(np.int64)
        self.frame_index = cat["frame_index"].astype(np.int64)
        self.split = cat["split"].astype(np.int64)
        self.offsets = cat["offsets"]
        self.body_vertices = np.stack(rows["seq_body"])[self.sequence]
        self.mask = np.stack(rows["seq_mask"])[self.sequence]
        self.shape = cat["shape"]
        tightness = cat["tightness"] if with_tightness else np.zeros((len(self.type), 0), np.float32)
        self.condition = np.concatenate([self.shape, tightness, cat["poses"]], 1).astype(np.float32)
        self.layout = {"shape": int(self.shape.shape[1]), "tightness": int(tightness.shape[1]),
                       "pose": int(cat["poses"].shape[1] // self.frames), "frames": self.frames,
                       "frame_stride": self.frame_stride}
        self.registration_mm = cat["registration_mm"]
        self.sha256 = h.hexdigest()
        self.path = self.root

    def __len__(self) -> int:
        return int(len(self.type))

    def indices(self, split: str) -> np.ndarray:
        return split_indices(self.split, split)

    def registration_table(self) -> dict[str, dict[str, float]]:
        """Mean registration error [mm] per type over its sequences."""
        out = {}
        for i, t in enumerate(self.types):
            _, first = np.unique(self.sequence[self.type == i], return_index=True)
            errors = self.registration_mm[self.type == i][first]
            out[t] = {"garment_to_registered_mm": float(errors[:, 0].mean()),
                      "registered_to_garment_mm": float(errors[:, 1].mean()), "sequences": int(len(first)),
                      "frames": int((self.type == i).sum())}
        return out
