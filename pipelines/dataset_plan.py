"""Turns a validated dataset spec into a deterministic plan: styles, shapes,
style-shape pairs, pose sets and one task per (pair, TailorNet split), or, with
``poses.source: motion``, one task per (pair, motion) (:func:`plan_motions`); the fabric of
each style (a ``garment.fabric`` list: one drawn per style) and the tightness of each pair
(``garment.tightness``: the garment sized for shape + tau, :func:`attach_garments`).

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
#: Seed 001's regularization split (``poses.regularization_count``): train pairs x the regularization
#: pose set, every pose of it.
REGULARIZATION_SPLIT = "regularization"
#: The canonical-pose split (``splits.canonical: all``): one frame of every style-shape combination in
#: the body's canonical pose, TailorNet's A-pose drapes (seed 000, Sec. 4.4 and 5.3).
CANONICAL_SPLIT = "canonical"


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
    pose_ids: np.ndarray  # (N,) index into the split's pose set; a motion's frame numbers
    poses: np.ndarray  # (N, 60) in visiting order (greedy nearest-pose from the canonical pose); a motion's frames
    motion_steps: int = 0  # simulator frames per motion frame (0: held targets; see SequenceTask)
    motion: str = ""  # the motion's name (a kind or a file name), "" for held targets
    fabric: str = "cotton"  # the style's fabric preset
    garment_index: int = -1  # row of the context's garments (rest geometry, canonical drape): see Plan.garments
    tightness: np.ndarray | None = None  # (2,) the pair's tightness offsets (height, weight); None: no tightness
    start_shape: np.ndarray | None = None  # (S,) shape + tightness the garment is sized for (the shape
    #                                        transition starts there); None: the neutral shape


@dataclass
class Plan:
    styles: list  # StyleParams, train styles first then test styles
    style_vectors: np.ndarray  # (n_styles, G)
    shapes: np.ndarray  # (n_shapes, S), train shapes first
    pairs: list[tuple[str, int, int]]  # (group, style index, shape index)
    poses: dict[str, np.ndarray]  # "train"/"test" (and "regularization", "canonical") pose sets (N, 60)
    pruned_poses: np.ndarray
    pruned_reasons: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=str))  # (M,) why each went
    tasks: list[Task] = field(default_factory=list)
    fabrics: list[str] = field(default_factory=list)  # fabric preset per style
    tightness: np.ndarray | None = None  # (n_pairs, 2) tightness offsets per pair; None: no tightness
    garments: list[tuple[int, np.ndarray | None]] = field(default_factory=list)
    """The garments to prepare (rest geometry, canonical drape), one per ``Task.garment_index``: (style
    index, shape it is sized and draped on, None: the neutral shape). Without tightness one per style
    on the neutral shape; with it one per pair, sized for the pair's shape + tau."""


def _rng(seed: int, *stream: int) -> np.random.Generator:
    return np.random.default_rng([seed, *stream])


def plan_dataset(spec: dict, body: BodyModel) -> Plan:
    from simulate.garment.style import StyleParams, sample_styles
    from simulate.poses import greedy_order, load_pose_file, sample_poses, spec_pose_sampling

    seed = int(spec["seed"])
    gtype = spec["garment"]["type"]
    if isinstance(gtype, list):
        raise ValueError(f"spec.garment.type is a list ({gtype}): plan each type's spec (pipelines.spec.type_specs)")
    styles = []
    profiles = bool(spec["styles"].get("limb_profiles", False))
    # "train" for a test group: the test pairs take the train styles (shapes), so they are unseen
    # combinations of seen styles and shapes, as TailorNet's test pairs (seed 000, section 5.3)
    test_styles_seen, test_shapes_seen = spec["styles"]["test"] == "train", spec["shapes"]["test"] == "train"
    for k, group in enumerate(("train", "test")):
        given = spec["styles"][group]
        if group == "test" and test_styles_seen:
            styles.append([])
        elif isinstance(given, list):
            styles.append([StyleParams(gtype, s) for s in given])
        else:
            styles.append(sample_styles(gtype, int(given), seed=seed * 1000 + 11 + k, optional=profiles))
    n_train_styles = len(styles[0])
    all_styles = styles[0] + styles[1]
    # styles that give the width profile carry it in their vectors, every style of the dataset alike
    optional = any(s.uses_optional() for s in all_styles)
    style_vectors = np.array([s.as_array(optional=optional) for s in all_styles], dtype=np.float32)

    shapes = []
    for k, group in enumerate(("train", "test")):
        given = spec["shapes"][group]
        if group == "test" and test_shapes_seen:
            shapes.append(np.zeros((0, body.shape_size), np.float32))
        elif given == "tailornet9":
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
        seen_styles = group == "train" or test_styles_seen
        seen_shapes = group == "train" or test_shapes_seen
        s_off, s_count = (0, n_train_styles) if seen_styles else (n_train_styles, len(styles[1]))
        h_off, h_count = (0, n_train_shapes) if seen_shapes else (n_train_shapes, len(shapes[1]))
        taken = {(si, hi) for _, si, hi in pairs}  # a test pair of seen styles and shapes is no train pair
        candidates = [(s_off + a, h_off + b) for a in range(s_count) for b in range(h_count)
                      if (s_off + a, h_off + b) not in taken]
        want = int(spec["pairs"][group])
        if want > len(candidates):
            raise ValueError(f"spec.pairs.{group} = {want} but only {len(candidates)} {group} style-shape "
                             f"combinations exist ({s_count} styles x {h_count} shapes"
                             + (f", less the {len(taken)} train pairs)" if taken and seen_styles and seen_shapes else ")"))
        if group == "train" and spec["pairs"].get("cover", False):
            pick = covering_pick(candidates, s_count, h_count, want, _rng(seed, 31 + k))
        else:
            pick = _rng(seed, 31 + k).permutation(len(candidates))[:want]
        pairs.extend((group, *candidates[i]) for i in sorted(pick))

    if spec["poses"]["source"] == "motion":
        return attach_garments(spec, body, plan_motions(spec, body, Plan(all_styles, style_vectors, all_shapes, pairs, {},
                                                                         np.zeros((0, body.pose_size), np.float32))))
    n_train, n_test = int(spec["poses"]["train_count"]), int(spec["poses"]["test_count"])
    n_regularization = int(spec["poses"].get("regularization_count", 0))
    total = n_train + n_test + n_regularization
    if spec["poses"]["source"] == "file":
        all_poses = load_pose_file(spec["poses"]["path"])
        if len(all_poses) < total:
            raise ValueError(f"spec.poses: the pose file has {len(all_poses)} poses, fewer than "
                             f"train_count + test_count{' + regularization_count' if n_regularization else ''} = {total}")
        all_poses = all_poses[_rng(seed, 41).permutation(len(all_poses))[:total]]
        pruned = np.zeros((0, all_poses.shape[1]), np.float32)
        reasons: list[str] = []
    else:
        sampler, pruning = spec_pose_sampling(spec["poses"], gtype, body)
        reasons = []
        all_poses, pruned = sample_poses(body, body.shape_default, total, sampler, _rng(seed, 42), reasons=reasons,
                                         **pruning)
    # regularization poses come after train and test, so a spec without them samples as before
    pose_sets = {"train": all_poses[:n_train], "test": all_poses[n_train:n_train + n_test]}
    sources, counts = dict(SPLIT_SOURCES), dict(spec["splits"])
    if n_regularization:
        pose_sets[REGULARIZATION_SPLIT] = all_poses[n_train + n_test:]
        sources[REGULARIZATION_SPLIT] = ("train", REGULARIZATION_SPLIT)
        counts[REGULARIZATION_SPLIT] = "all"

    plan = Plan(all_styles, style_vectors, all_shapes, pairs, pose_sets, pruned, np.array(reasons, dtype=str))
    orders: dict[tuple, np.ndarray] = {}  # pairs given the same poses ("all") share one visiting order
    for split, (group, pose_group) in sources.items():
        count = counts[split]
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
            ids = np.sort(_rng(seed, 51, p, list(sources).index(split)).permutation(available)[:count])
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
    if spec["splits"].get("canonical", 0) == "all":
        add_canonical_tasks(plan, np.asarray(body.canonical_pose, np.float32))
    return attach_garments(spec, body, plan)


def covering_pick(candidates: list[tuple[int, int]], s_count: int, h_count: int, want: int,
                  rng: np.random.Generator) -> np.ndarray:
    """``want`` indices into ``candidates`` (every (style, shape) of ``s_count`` styles x ``h_count``
    shapes, style-major, offsets aside) such that every style and every shape is in one of them
    where ``want >= max(s_count, h_count)`` (else as many as ``want`` reach): the k-th of the first
    max(s_count, h_count) pairs takes the k-th style and the k-th shape of two seeded permutations
    (each cycled), the rest are drawn at random from the combinations left (``pairs.cover``)."""
    styles, shapes = rng.permutation(s_count), rng.permutation(h_count)
    first = [int(styles[k % s_count]) * h_count + int(shapes[k % h_count])
             for k in range(min(want, max(s_count, h_count)))]
    rest = np.setdiff1d(np.arange(len(candidates)), first)
    return np.concatenate([np.asarray(first, np.int64), rng.permutation(rest)[:want - len(first)]]).astype(np.int64)


def add_canonical_tasks(plan: Plan, canonical_pose: np.ndarray) -> None:
    """Split ``canonical`` (``splits.canonical: all``): one task per combination of the plan's styles
    and shapes, its one target the canonical pose (P,). A combination that is a train or test pair
    keeps that pair's index; the others become pairs of group ``canonical``, appended after them, so
    the train and test tasks (and their seeded draws) are those of the spec without the split."""
    index = {(si, hi): p for p, (_, si, hi) in enumerate(plan.pairs)}
    plan.poses[CANONICAL_SPLIT] = canonical_pose[None].copy()
    for si in range(len(plan.styles)):
        for hi in range(len(plan.shapes)):
            if (si, hi) not in index:
                index[si, hi] = len(plan.pairs)
                plan.pairs.append((CANONICAL_SPLIT, si, hi))
            p = index[si, hi]
            plan.tasks.append(Task(f"{CANONICAL_SPLIT}-p{p:03d}", CANONICAL_SPLIT, p, si, plan.shapes[hi],
                                   plan.style_vectors[si], np.zeros(1, np.int64), canonical_pose[None].copy()))


def attach_garments(spec: dict, body: BodyModel, plan: Plan) -> Plan:
    """Fabrics, tightness and garments of a plan (seed 004, Sec. 3.2-3.3), set on every task.

    ``garment.fabric``: one name for every style, or a list: each style draws one
    (``simulate.garment.cloth3d.sample_fabrics``, seeded by (seed, 71); upper-body types only
    cotton or silk). ``garment.tightness``: each pair draws tau uniformly from the range(s)
    (``simulate.garment.tightness.sample_tightness``, seeded by (seed, 81)); its garment is sized
    for the pair's shape + tau (``sized_shape``), draped there, and its tasks start on that shape
    (``Task.start_shape``). Without tightness a style's garment serves every pair of the style."""
    from simulate.garment.cloth3d import sample_fabrics
    from simulate.garment.tightness import sample_tightness, sized_shape

    seed, gtype, fabric = int(spec["seed"]), spec["garment"]["type"], spec["garment"]["fabric"]
    if isinstance(fabric, list):
        plan.fabrics = sample_fabrics(gtype, len(plan.styles), fabrics=fabric, seed=seed * 1000 + 71)
    else:
        plan.fabrics = [fabric] * len(plan.styles)
    ranges = spec["garment"].get("tightness")
    shapes_of = {}
    if ranges is None:
        plan.garments = [(k, None) for k in range(len(plan.styles))]
    else:
        ranges = ranges if isinstance(ranges[0], list) else [ranges, ranges]
        plan.tightness = sample_tightness(len(plan.pairs), seed=seed * 1000 + 81, tightness_range=ranges)
        plan.garments = []
        for p, (_, si, hi) in enumerate(plan.pairs):
            shapes_of[p] = sized_shape(body, plan.shapes[hi], plan.tightness[p])
            plan.garments.append((si, shapes_of[p]))
    for t in plan.tasks:
        t.fabric = plan.fabrics[t.style_index]
        if plan.tightness is None:
            t.garment_index = t.style_index
        else:
            t.garment_index, t.tightness, t.start_shape = t.pair, plan.tightness[t.pair], shapes_of[t.pair]
    return plan


def load_motions(spec: dict) -> list:
    """The motion files of a motion spec with ``motion.source: file``, each at ``motion.fps``
    (``simulate.motion.Motion``; [] for procedural motions). Raises ValueError (FileNotFoundError)
    naming ``motion.path`` (``motion.path[k]``), the file, the value and what was expected."""
    from simulate.motion import load_motion

    m = spec["motion"]
    if m["source"] != "file":
        return []
    paths = [m["path"]] if isinstance(m["path"], str) else list(m["path"])
    fields = ["motion.path"] if isinstance(m["path"], str) else [f"motion.path[{k}]" for k in range(len(paths))]
    return [load_motion(path, field=field).at_rate(float(m["fps"]), field="motion.fps")
            for path, field in zip(paths, fields)]


#: The TailorNet split of a motion task by its pair's group: train pairs' sequences train, test
#: pairs' (unseen styles and shapes, their own motions) test.
MOTION_SPLITS = {"train": "train_train", "test": "test_test"}


def plan_motions(spec: dict, body: BodyModel, plan: Plan) -> Plan:
    """The tasks of a motion spec: per style-shape pair ``motion.per_pair`` motions, task ``s`` of
    pair ``p`` taking motion number ``n = p * per_pair + s``: file motions in turn (``motion.path``,
    each at ``motion.fps``, its first ``motion.frames``), or a procedural motion of kind
    ``motion.kinds[n % len(kinds)]`` seeded by (seed, p, s). With ``simulation.poses_per_task`` a
    motion is split into consecutive pieces, each its own task starting from the canonical drape
    (CLOTH3D simulates its 300-frame splits the same way). Task ids: ``<split>-p<pair>-m<s>``
    (``-c<piece>`` for pieces); ``pose_ids`` are the frames' numbers in the motion."""
    from pipelines.spec import motion_steps
    from simulate.motion import procedural_motion

    m = spec["motion"]
    seed, fps, frames = int(spec["seed"]), float(m["fps"]), m["frames"]
    steps = motion_steps(spec)
    files = load_motions(spec)
    canonical = np.asarray(body.canonical_pose, np.float32)
    chunk = spec["simulation"]["poses_per_task"]
    for p, (group, si, hi) in enumerate(plan.pairs):
        split = MOTION_SPLITS[group]
        for s in range(int(m["per_pair"])):
            n = p * int(m["per_pair"]) + s
            if files:
                motion = files[n % len(files)]
                poses = motion.poses if frames is None else motion.poses[:int(frames)]
            else:
                kind = m["kinds"][n % len(m["kinds"])]
                motion = procedural_motion(kind, int(frames), fps, _rng(seed, 61, p, s), amplitude=float(m["amplitude"]),
                                           base_pose=canonical)
                poses = motion.poses
            base = f"{split}-p{p:03d}-m{s:02d}"
            starts = [0] if chunk is None or len(poses) <= chunk else list(range(0, len(poses), int(chunk)))
            for c, start in enumerate(starts):
                stop = len(poses) if len(starts) == 1 else start + int(chunk)
                ids = np.arange(start, min(stop, len(poses)))
                plan.tasks.append(Task(base if len(starts) == 1 else f"{base}-c{c:03d}", split, p, si, plan.shapes[hi],
                                       plan.style_vectors[si], ids, np.asarray(poses[ids], np.float32),
                                       motion_steps=steps, motion=motion.name))
    return plan
