"""Turns a validated dataset spec into a deterministic plan: styles, shapes,
style-shape pairs, pose sets and one task per (pair, TailorNet split).

Everything here is a pure function of the spec (and its seed), so a resumed or
distributed run plans exactly the same tasks.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from simulate.body.base import BodyModel

#: TailorNet's four splits: (pair group, pose set) of each.
SPLIT_SOURCES = {"train_train": ("train", "train"), "train_test": ("train", "test"),
                 "test_train": ("test", "train"), "test_test": ("test", "test")}


@dataclass
class Task:
    """One shard: one style-shape pair through the poses of one split (or, with
    ``simulation.poses_per_task``, through one consecutive piece of them)."""

    task_id: str
    split: str
    pair: int
    style_index: int
    shape: np.ndarray
    style_vector: np.ndarray
    pose_ids: np.ndarray
    poses: np.ndarray  # (N, 60) in visiting order (greedy nearest-pose from the canonical pose)


@dataclass
class Plan:
    styles: list  # StyleParams, train styles first then test styles
    style_vectors: np.ndarray  # (n_styles, G)
    shapes: np.ndarray  # (n_shapes, S), train shapes first
    pairs: list[tuple[str, int, int]]  # (group, style index, shape index)
    poses: dict[str, np.ndarray]  # "train"/"test" pose sets (N, 60)
    pruned_poses: np.ndarray
    pruned_reasons: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=str))  # (M,) why each went
    tasks: list[Task] = field(default_factory=list)


def default_pose_joints(garment_type: str) -> str:
    """The joints a garment type's sampled poses move by default: lower for bottoms, all for the
    full-body dress and jumpsuit, upper for tops."""
    if garment_type in ("pants", "shorts", "skirt"):
        return "lower"
    return "all" if garment_type in ("dress", "jumpsuit") else "upper"


def _rng(seed: int, *stream: int) -> np.random.Generator:
    return np.random.default_rng([seed, *stream])


def plan_dataset(spec: dict, body: BodyModel) -> Plan:
    from simulate.garment.style import StyleParams, sample_styles
    from simulate.poses import GARMENT_POSE_JOINTS, PoseSampler, greedy_order, load_pose_file, sample_poses

    seed = int(spec["seed"])
    gtype = spec["garment"]["type"]
    # The spec validates these (simulate.garment.cloth3d, simulate.garment.tightness give the sampling
    # and the shape blend); the dataset's simulation runs one fabric and no tightness offset per run.
    if isinstance(spec["garment"]["fabric"], list):
        raise ValueError(f"spec.garment.fabric is a list ({spec['garment']['fabric']}) but generate-dataset simulates "
                         f"one fabric per run; give one fabric name")
    if spec["garment"].get("tightness") is not None:
        raise ValueError(f"spec.garment.tightness is {spec['garment']['tightness']} but generate-dataset sizes every "
                         f"garment for the neutral shape; remove the field (null)")
    styles = []
    for k, group in enumerate(("train", "test")):
        given = spec["styles"][group]
        if isinstance(given, list):
            styles.append([StyleParams(gtype, s) for s in given])
        else:
            styles.append(sample_styles(gtype, int(given), seed=seed * 1000 + 11 + k))
    n_train_styles = len(styles[0])
    all_styles = styles[0] + styles[1]
    style_vectors = np.array([s.as_array() for s in all_styles], dtype=np.float32)

    shapes = []
    for k, group in enumerate(("train", "test")):
        given = spec["shapes"][group]
        if given == "tailornet9":
            from simulate.garment.shapes import training_shapes

            shapes.append(np.asarray(training_shapes(body)[0], np.float32))
        elif isinstance(given, list):
            arr = np.asarray(given, np.float32)
            if arr.ndim != 2 or arr.shape[1] != body.shape_size:
                raise ValueError(f"spec.shapes.{group} entries must have {body.shape_size} values "
                                 f"({', '.join(body.shape_names)}), got shape {arr.shape}")
            lo, hi = body.shape_ranges[:, 0], body.shape_ranges[:, 1]
            outside = np.argwhere((arr < lo) | (arr > hi))
            if len(outside):
                i, j = (int(v) for v in outside[0])
                raise ValueError(f"spec.shapes.{group}[{i}][{j}] ({body.shape_names[j]}) must be in "
                                 f"[{lo[j]:g}, {hi[j]:g}] for the {body.name} body (got {arr[i, j]:g})")
            shapes.append(arr)
        else:
            from simulate.garment.shapes import sample_test_shapes

            shapes.append(np.asarray(sample_test_shapes(body, int(given), seed=seed * 1000 + 21 + k), np.float32))
    n_train_shapes = len(shapes[0])
    all_shapes = np.concatenate(shapes)

    pairs: list[tuple[str, int, int]] = []
    for k, group in enumerate(("train", "test")):
        s_off = 0 if group == "train" else n_train_styles
        h_off = 0 if group == "train" else n_train_shapes
        candidates = [(s_off + a, h_off + b) for a in range(len(styles[k])) for b in range(len(shapes[k]))]
        want = int(spec["pairs"][group])
        if want > len(candidates):
            raise ValueError(f"spec.pairs.{group} = {want} but only {len(candidates)} {group} style-shape "
                             f"combinations exist ({len(styles[k])} styles x {len(shapes[k])} shapes)")
        pick = _rng(seed, 31 + k).permutation(len(candidates))[:want]
        pairs.extend((group, *candidates[i]) for i in sorted(pick))

    joints = spec["poses"]["joints"] or default_pose_joints(gtype)
    joints = GARMENT_POSE_JOINTS[joints] if isinstance(joints, str) else tuple(joints)
    total = int(spec["poses"]["train_count"]) + int(spec["poses"]["test_count"])
    if spec["poses"]["source"] == "file":
        all_poses = load_pose_file(spec["poses"]["path"])
        if len(all_poses) < total:
            raise ValueError(f"spec.poses: the pose file has {len(all_poses)} poses, fewer than "
                             f"train_count + test_count = {total}")
        all_poses = all_poses[_rng(seed, 41).permutation(len(all_poses))[:total]]
        pruned = np.zeros((0, all_poses.shape[1]), np.float32)
        reasons: list[str] = []
    else:
        sampler = PoseSampler(joints=joints, range_scale=float(spec["poses"]["range_scale"]), base_pose=body.canonical_pose)
        kind = spec["poses"]["joints"] if spec["poses"]["joints"] in ("upper", "lower", "all") else \
            default_pose_joints(gtype)
        min_clearance = spec["poses"]["min_clearance"]
        reasons = []
        all_poses, pruned = sample_poses(body, body.shape_default, total, sampler, _rng(seed, 42),
                                         min_clearance=None if min_clearance is None else float(min_clearance),
                                         clearance_pairs=kind, reasons=reasons)
    pose_sets = {"train": all_poses[: spec["poses"]["train_count"]], "test": all_poses[spec["poses"]["train_count"]:]}

    plan = Plan(all_styles, style_vectors, all_shapes, pairs, pose_sets, pruned, np.array(reasons, dtype=str))
    orders: dict[tuple, np.ndarray] = {}  # pairs given the same poses ("all") share one visiting order
    for split, (group, pose_group) in SPLIT_SOURCES.items():
        count = spec["splits"][split]
        available = len(pose_sets[pose_group])
        if count == "all":
            count = available
        if count == 0:
            continue
        if count > available:
            raise ValueError(f"spec.splits.{split} = {count} but poses.{pose_group}_count is only {available}")
        for p, (g, si, hi) in enumerate(pairs):
            if g != group:
                continue
            ids = np.sort(_rng(seed, 51, p, list(SPLIT_SOURCES).index(split)).permutation(available)[:count])
            key = (pose_group, ids.tobytes())
            if key not in orders:
                orders[key] = greedy_order(pose_sets[pose_group][ids], body.canonical_pose)
            order = orders[key]
            ids = ids[order]
            chunk = spec["simulation"]["poses_per_task"]
            if chunk is None or len(ids) <= chunk:
                plan.tasks.append(Task(f"{split}-p{p:03d}", split, p, si, all_shapes[hi], style_vectors[si], ids,
                                       pose_sets[pose_group][ids]))
                continue
            # consecutive pieces of the visiting order, each its own task (world and shard), so
            # a pair's thousands of poses run in parallel instead of one long world
            for c, start in enumerate(range(0, len(ids), chunk)):
                part = ids[start:start + chunk]
                plan.tasks.append(Task(f"{split}-p{p:03d}-c{c:03d}", split, p, si, all_shapes[hi], style_vectors[si],
                                       part, pose_sets[pose_group][part]))
    return plan
