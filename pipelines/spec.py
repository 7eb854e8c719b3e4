"""The dataset spec: a YAML file describing one `generate-dataset` run.

The spec is validated completely before anything runs; each problem names its field
path, the value found and what was expected, e.g.
``spec.poses.train_count must be an integer >= 1 (got 0) in quickstart.yaml``.
Defaults are filled in, and the resolved spec (with defaults) is what the manifest
records and hashes. Schema (every key optional unless marked required)::

    name: str (required)                dataset name
    seed: int = 0                       seeds every RNG of the run
    garment:
      type: tshirt|shirt|pants|shorts|skirt|top|dress|jumpsuit | list (required)   a list of distinct
                                        types makes one ordinary dataset per type, OUT/<type>/, each
                                        the spec with that type (``type_specs``; docs/dataset.md)
      resolution: int = 1500            target garment vertex count
      fabric: cotton|silk|denim|leather | list = cotton   one fabric, or a list to draw one from per
                                        style (seed 004: tshirt, shirt and top only cotton or silk; with
                                        several types, those draw from the list's cotton and silk)
      tightness: null | [lo, hi] | [[lo, hi], [lo, hi]] = null   tightness range (seed 004): one
                                        range for both offsets or one per offset (anny height,
                                        weight; simulate.garment.cloth3d), each within [-0.5, 0.5];
                                        each style-shape pair draws tau, its garment is sized for
                                        shape + tau and the body blends from there to the shape
    body:
      backend: anny|smpl = anny
      path: str | null                  SMPL-family file for backend smpl
    styles:                             garment style parameters (CLOTH3D-like)
      train: int | list[dict]           count to sample, or explicit {param: value} dicts
      test:  int | list[dict] | train   train: the train styles (test pairs of seen styles)
      space: str | null                 style-space .npz: styles are then PCA gammas
      limb_profiles: bool = false       sampled tshirt, shirt, pants and shorts styles also draw the
                                        optional sleeve/leg width profile (taper, widen_at, widen;
                                        seed 004), appended to their style vectors (optional key: absent,
                                        it stays out of the resolved spec)
    shapes:
      train: tailornet9 | int | list[list[float]]   the 9 TailorNet shapes, a sampled count, or explicit
      test:  int | list[list[float]] | train   train: the train shapes (with styles.test: train, test
                                        pairs are unseen combinations of seen styles and shapes, as
                                        TailorNet's; otherwise unseen shapes)
    pairs:                              style-shape pairs (TailorNet: 20 train, 20 test)
      train: int                        drawn from styles.train x shapes.train
      test: int                         drawn from styles.test x shapes.test
      cover: bool = false               true: the train pairs wear every train style and every train
                                        shape at least once (as far as pairs.train allows), the rest
                                        drawn at random; false: all drawn at random, so some styles
                                        may be in no train pair (a test pair wearing one is then an
                                        unseen style to a learner); optional key: absent (false), it
                                        stays out of the resolved spec
    poses:
      source: sampled|file|motion = sampled   motion: sequences at a fixed frame rate (the motion
                                        section; docs/motion.md): the rest of poses and splits are not read
      path: str | null                  .npz with `poses` (N, 60) for source=file
      joints: upper|lower|all|list = garment default
      range_scale: float in (0, 1] = 1.0
      min_clearance: float [m] | null = null   also prune sampled poses whose skin clearance (arm to
                                        torso for tops, between the legs for bottoms) is below this
                                        (simulate.body.clearance); null = only the capsule test
      train_count: int                  poses of the training pose set
      test_count: int                   unseen poses
      regularization_count: int         poses of a third set, apart from train and test: split
                                        ``regularization``, every train pair through all of them
                                        (seed 001's 2k regularization set, held out of training to
                                        catch overfitting; docs/learners/uvimage.md); optional key:
                                        absent (0 poses), it stays out of the resolved spec
    splits:                             poses per pair in each TailorNet split
      train_train: int | all = all      train pairs x train poses
      train_test: int | all = all       train pairs x unseen poses
      test_train: int                   test pairs x a subset of train poses
      test_test: int                    test pairs x a subset of unseen poses
      canonical: all | 0                one frame in the body's canonical pose for every combination
                                        of the dataset's styles and shapes (train and test): split
                                        ``canonical``, the canonical-pose drapes TailorNet's g and
                                        prototype choice learn from (seed 000 Sec. 5.3 simulates all
                                        225 in A-pose); optional key: absent (0), it stays out of the
                                        resolved spec
    simulation:                         what a run changes; the rest of the stepping (damping, explosion
                                        limits, convergence outliers and limit cycles, contact thickness
                                        and detection rates, shape transition, restarts, ...) is the
                                        library's (simulate.quasi_static.SimSettings,
                                        simulate.sequence.SequenceSettings), whose defaults are the
                                        production settings; a spec giving one of them is an error
      solver: vbd|xpbd|mass_spring = xpbd  vbd: vertex block descent, rests at the model's equilibrium
                                        (converged stiffness); xpbd: faster, stretches stiff cloth
      device: auto|cpu|cuda[:N] = auto
      worlds: int = 64                  tasks simulated together (one world each)
      batches: int = 1                  the plan's batches at least (tasks dealt out evenly,
                                        each batch with `worlds` worlds): a Ray run simulates one batch
                                        per GPU at once, so set it to the GPU count or a multiple;
                                        the same spec gives the same shards on any executor
      frame_dt: float [s] = 1/45        the body moves from one pose to the next in one frame
      substeps: int = 15, iterations: int = 5   per frame, per substep
      tolerance: float [m/s] = 0.05     a pose is held until every vertex (but SimSettings.outlier_fraction
                                        of them) is slower, 3 frames in a row
      max_relax_frames: int = 60        frames a pose is held at most
      interpolation_threshold: float [rad] = 0.1   largest joint turn per frame: slerp'ed poses are
                                        inserted between targets farther apart
      poses_per_task: int | null = null split a pair's visiting order into tasks of at most this
                                        many poses (each its own world and shard, starting from the
                                        canonical drape), so long pose lists fill the GPU's worlds
      targets_from_home: bool = false   every target pose is reached from the settled canonical
                                        drape, not from the pose before it, so its rest does not
                                        depend on the visiting order (optional key: absent, it stays
                                        out of the resolved spec)
      contact:
        self_contact: bool = false      cloth-cloth contact: more frames come to rest without the
                                        garment passing through itself, at a higher cost per frame
        primary_bodies: bool = false    each garment vertex meets only its primary collision
                                        body (torso / left arm / right arm for tops, legs for pants;
                                        seed 001 D.6; simulate/body/collision_parts.py): cloth
                                        between an arm and the torso is not pushed by the wrong skin
    filters:
      max_area_shrink: 0.75  max_area_growth: 1.0    a triangle is distorted beyond these (seed 001 D.6)
      max_distorted_fraction: 0.002     share of distorted triangles a kept frame may have
                                        (0 = the seed's "any triangle"; a few triangles at hems and
                                        armpits of our body-derived garments briefly exceed the bounds)
      collision_depth [m]: 0.001
      max_penetration_fraction: 0.01    max_self_intersections: 0  require_converged: true
      max_off_body_fraction: 0.0        share of garment vertices a kept frame may have 0.5 m or
                                        more from their body (part): a garment that slid or fell off
    motion:                             only with poses.source motion (docs/motion.md); each style-shape
                                        pair is simulated through per_pair motions, each frame recorded
      source: procedural|file = procedural
      path: str | list[str] | null      .npz motion file(s) for source=file: `poses` (F, 20, 3)
                                        axis-angle [rad] in POSE_JOINTS order and `fps`
      kinds: list = [walk, arm_raise, torso_twist, squat]   procedural motions, taken in turn
      fps: float = 30                   the dataset's frame rate: 1 / (fps x simulation.frame_dt)
                                        must be a whole number of simulator frames; file motions are
                                        taken every k-th frame to reach it (k whole)
      frames: int | null = 30           recorded frames per motion (file: at most; null = all)
      amplitude: float in (0, 1] = 0.5  share of each joint's room to its limit procedural motions use
      per_pair: int = 1                 motions per style-shape pair
      damping: float [1/s] | null = null  velocity damping during the sequences (null: the library's
                                        quasi-static 20/s, SimSettings.damping); the canonical drapes keep it
    output: {precision: float32|float16, compression: gzip|lzf}
    audit: {samples: int = 4,           kept frames re-solved to their static equilibrium (pipelines/audit.py)
            max_iterations: int = 100}  Newton iterations per audited frame at most (~1 s each on a
                                        7k-vertex garment; a 1.8k t-shirt frame of XPBD at 8
                                        iterations took 60); frames whose reference does not
                                        converge are counted, not measured
"""
from __future__ import annotations

import copy
import difflib
import hashlib
import json
import math
from pathlib import Path
from typing import Any

import yaml

GARMENT_TYPES = ("tshirt", "shirt", "pants", "shorts", "skirt", "top", "dress", "jumpsuit")
FABRIC_NAMES = ("cotton", "silk", "denim", "leather")
TOP_TYPES = ("tshirt", "shirt", "top")
"""Upper-body types: a fabric list may name only cotton and silk for them (seed 004, Sec. 3.3)."""
TOP_FABRICS = ("cotton", "silk")
TIGHTNESS_LIMIT = 0.5
"""Largest |tightness| offset a spec may ask for [anny shape parameter units]."""
SPLITS = ("train_train", "train_test", "test_train", "test_test")

DEFAULTS: dict[str, Any] = {
    "seed": 0,
    "garment": {"resolution": 1500, "fabric": "cotton"},
    "body": {"backend": "anny", "path": None},
    "styles": {"train": 2, "test": 1, "space": None},
    "shapes": {"train": 2, "test": 1},
    "pairs": {"train": 2, "test": 1},
    "poses": {"source": "sampled", "path": None, "joints": None, "range_scale": 1.0, "min_clearance": None, "train_count": 8, "test_count": 4},
    "splits": {"train_train": "all", "train_test": "all", "test_train": 2, "test_test": 2},
    "simulation": {
        "solver": "xpbd", "device": "auto", "worlds": 64, "batches": 1, "frame_dt": 1.0 / 45.0, "substeps": 15, "iterations": 5,
        "tolerance": 0.05, "max_relax_frames": 60, "interpolation_threshold": 0.1, "poses_per_task": None,
        "contact": {"self_contact": False, "primary_bodies": False},
    },
    "filters": {"max_area_shrink": 0.75, "max_area_growth": 1.0, "max_distorted_fraction": 0.002, "collision_depth": 0.001,
                "max_penetration_fraction": 0.01, "max_self_intersections": 0, "require_converged": True,
                "max_off_body_fraction": 0.0},
    "output": {"precision": "float32", "compression": "gzip"},
    "audit": {"samples": 4, "max_iterations": 100},
}


MOTION_DEFAULTS: dict[str, Any] = {"source": "procedural", "path": None,
                                   "kinds": ["walk", "arm_raise", "torso_twist", "squat"], "fps": 15.0, "frames": 30,
                                   "amplitude": 0.5, "per_pair": 1, "damping": None}
"""The ``motion`` section, filled in only when ``poses.source`` is motion (a spec without motions
resolves, and hashes, as it did before the section existed)."""

REQUIRED_KEYS: dict[str, tuple[str, ...]] = {"": ("name",), "garment": ("type",)}
"""Keys a spec must give (they have no default), by section path ("" = top level)."""

OPTIONAL_KEYS: dict[str, tuple[str, ...]] = {"garment": ("tightness",), "styles": ("limb_profiles",),
                                             "pairs": ("cover",), "poses": ("regularization_count",),
                                             "splits": ("canonical",),
                                             "simulation": ("targets_from_home",)}
"""Keys a spec may give that have no default: absent, they stay out of the resolved spec (and its hash)."""

LIBRARY_SETTINGS: dict[str, tuple[str, str]] = {
    "simulation.outlier_fraction": ("SimSettings", "outlier_fraction"),
    "simulation.limit_cycle_window": ("SimSettings", "limit_cycle_window"),
    "simulation.shape_transition_frames": ("SequenceSettings", "shape_transition_frames"),
    "simulation.restart_after_rejects": ("SequenceSettings", "restart_after_rejects"),
    "simulation.contact.thickness": ("SequenceSettings", "contact_thickness"),
    "simulation.contact.self_contact_detect_every": ("SimSettings", "self_contact_detect_every"),
    "simulation.contact.body_contact_detect_every": ("SimSettings", "body_contact_detect_every"),
}
"""Simulation settings that are the library's, not the spec's, by the field path a spec might give
them under: (settings class, field). A spec giving one is told which library default applies."""


def without_library_settings(raw: dict) -> dict:
    """A copy of a spec dict without :data:`LIBRARY_SETTINGS` fields, e.g. a dataset manifest's
    resolved spec that lists them: re-simulating its frames takes the library's settings."""
    out = copy.deepcopy(raw)
    for path in LIBRARY_SETTINGS:
        *parents, leaf = path.split(".")
        node = out
        for part in parents:
            node = node.get(part) if isinstance(node, dict) else None
        if isinstance(node, dict):
            node.pop(leaf, None)
    return out


def library_setting_error(path: str, source: str) -> str:
    """The error for a spec giving :data:`LIBRARY_SETTINGS` ``path``: the library field and its default."""
    from simulate.quasi_static import SimSettings
    from simulate.sequence import SequenceSettings

    cls_name, field = LIBRARY_SETTINGS[path]
    default = getattr({"SimSettings": SimSettings, "SequenceSettings": SequenceSettings}[cls_name](), field)
    return (f"spec.{path} is not a spec field: the library's {cls_name}.{field} ({default!r}) applies "
            f"(in {source})")

MAX_RESOLUTION = 200_000
"""Largest garment.resolution accepted [vertices] (the TailorNet t-shirt has 7.7k)."""


class SpecError(ValueError):
    """A spec problem; the message names the field path, the value and what was expected."""


def nearest_name(name: Any, known: list[str] | tuple[str, ...]) -> str:
    """" (did you mean X?)" for the known name closest to ``name`` (difflib), or ""."""
    close = difflib.get_close_matches(str(name), [str(k) for k in known], n=1, cutoff=0.6)
    return f" (did you mean {close[0]}?)" if close else ""


def _check_structure(raw: dict, defaults: dict, section: str, source: str, errors: list[str]) -> dict:
    """Unknown keys and non-mapping sections at every nesting level, named by their field path.

    Returns a copy of ``raw`` without the offending keys (so value checks can go on and every
    problem is reported at once). A section given as null (e.g. all its lines commented out)
    counts as empty."""
    known = sorted(set(defaults) | set(REQUIRED_KEYS.get(section, ())) | set(OPTIONAL_KEYS.get(section, ())))
    clean: dict = {}
    for key, value in raw.items():
        path = f"{section}.{key}" if section else str(key)
        if key not in known and path in LIBRARY_SETTINGS:
            errors.append(library_setting_error(path, source))
            continue
        if key not in known:
            hint = nearest_name(key, known)
            errors.append(f"spec.{path} is not a known field" + (hint or f"; known fields{' of spec.' + section if section else ''}: "
                                                                 f"{', '.join(known)}") + f" (in {source})")
            continue
        if isinstance(defaults.get(key), dict):
            if value is None:
                value = {}
            if not isinstance(value, dict):
                fields = sorted(set(defaults[key]) | set(REQUIRED_KEYS.get(path, ())))
                errors.append(f"spec.{path} must be a mapping of fields such as {', '.join(fields[:3])}"
                              f" (got {value!r}) in {source}")
                continue
            value = _check_structure(value, defaults[key], path, source, errors)
        clean[key] = value
    return clean


def _merge(defaults: dict, given: dict) -> dict:
    out = copy.deepcopy(defaults)
    for key, value in given.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = _merge(out[key], value)
        else:
            out[key] = value
    return out


class _Checker:
    def __init__(self, spec: dict, source: str) -> None:
        self.spec, self.source, self.errors = spec, source, []

    def get(self, path: str) -> Any:
        node: Any = self.spec
        for part in path.split("."):
            node = node.get(part) if isinstance(node, dict) else None
        return node

    def fail(self, path: str, expected: str, value: Any = None) -> None:
        got = self.get(path) if value is None else value
        self.errors.append(f"spec.{path} must be {expected} (got {got!r}) in {self.source}")

    def integer(self, path: str, minimum: int = 0, *, allow: tuple = (), maximum: int | None = None) -> None:
        v = self.get(path)
        if v in allow and not isinstance(v, bool):
            return
        if isinstance(v, bool) or not isinstance(v, int) or v < minimum or (maximum is not None and v > maximum):
            self.fail(path, f"an integer >= {minimum}" + (f" and <= {maximum}" if maximum is not None else "")
                      + (f" or one of {allow}" if allow else ""))

    def number(self, path: str, lo: float, hi: float | None = None, *, lo_open: bool = False,
               hi_open: bool = False) -> None:
        v = self.get(path)
        ok = (isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
              and (v > lo if lo_open else v >= lo) and (hi is None or (v < hi if hi_open else v <= hi)))
        if not ok:
            self.fail(path, f"a number {'>' if lo_open else '>='} {lo}"
                      + (f" and {'<' if hi_open else '<='} {hi}" if hi is not None else ""))

    def choice(self, path: str, options: tuple) -> None:
        if self.get(path) not in options:
            self.fail(path, f"one of {', '.join(map(str, options))}")


def validate_spec(raw: Any, *, source: str = "<spec>") -> dict[str, Any]:
    """Validates a spec dict and returns it with defaults filled in; raises SpecError listing every problem."""
    if not isinstance(raw, dict):
        raise SpecError(f"the spec in {source} must be a YAML mapping of fields (name, garment, ...) "
                        f"(got {type(raw).__name__})")
    errors: list[str] = []
    motion_given = "motion" in raw
    known = {**DEFAULTS, "motion": MOTION_DEFAULTS}  # (for the names an unknown field is matched against)
    spec = _merge(DEFAULTS, _check_structure({k: v for k, v in raw.items() if k != "motion"}, known, "", source, errors))
    if motion_given or spec["poses"].get("source") == "motion":
        motion = {} if raw.get("motion") is None else raw["motion"]
        if isinstance(motion, dict):
            spec["motion"] = _merge(MOTION_DEFAULTS, _check_structure(motion, MOTION_DEFAULTS, "motion", source, errors))
        else:
            errors.append(f"spec.motion must be a mapping of fields such as fps, frames, kinds (got {motion!r}) in {source}")
    c = _Checker(spec, source)
    c.errors.extend(errors)
    if not isinstance(spec.get("name"), str) or not spec["name"]:
        c.fail("name", "a non-empty string")
    c.integer("seed", 0)
    gtype = spec["garment"].get("type")
    if isinstance(gtype, list):
        _check_type_list(c, gtype)
    else:
        c.choice("garment.type", GARMENT_TYPES)
    c.integer("garment.resolution", 64, maximum=MAX_RESOLUTION)
    _check_fabric(c, spec["garment"].get("fabric"), gtype)
    profiles = spec["styles"].get("limb_profiles")
    if profiles is not None and not isinstance(profiles, bool):
        c.fail("styles.limb_profiles", "true or false")
    _check_tightness(c, spec["garment"].get("tightness"))
    c.choice("body.backend", ("anny", "smpl"))
    if spec["body"]["backend"] == "smpl" and not spec["body"].get("path"):
        c.fail("body.path", "the path of an SMPL-family model file when body.backend is smpl")
    for group in ("train", "test"):
        styles = spec["styles"][group]
        if group == "test" and styles == "train":
            pass  # the train styles: test pairs are unseen combinations of seen styles and shapes
        elif isinstance(styles, list):
            if not styles or not all(isinstance(s, dict) for s in styles):
                c.fail(f"styles.{group}", "a count >= 1 or a non-empty list of {param: value} mappings")
            elif isinstance(gtype, list):
                c.fail(f"styles.{group}", "a count >= 1 when garment.type is a list (explicit style parameters "
                                          "belong to one type)", styles)
            elif spec["garment"].get("type") in GARMENT_TYPES:
                _check_styles(c, f"styles.{group}", styles, spec["garment"]["type"])
        elif group == "test" and isinstance(styles, str):
            c.fail("styles.test", "a count >= 1, a non-empty list of {param: value} mappings or 'train'", styles)
        else:
            c.integer(f"styles.{group}", 1)
        shapes = spec["shapes"][group]
        if isinstance(shapes, list):
            if not shapes or not all(isinstance(s, list) and s and all(
                    isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in s) for s in shapes):
                c.fail(f"shapes.{group}", "a count, 'tailornet9' (train only) or a non-empty list of shape vectors "
                                          "(lists of finite numbers)")
        elif group == "test" and isinstance(shapes, str) and shapes != "train":
            c.fail("shapes.test", "a count >= 1, a non-empty list of shape vectors or 'train'", shapes)
        elif not (group == "train" and shapes == "tailornet9") and not (group == "test" and shapes == "train"):
            c.integer(f"shapes.{group}", 1)
        c.integer(f"pairs.{group}", 0 if group == "test" else 1)
    if not isinstance(spec["pairs"].get("cover", False), bool):
        c.fail("pairs.cover", "true (every train style and shape in a train pair) or false")
    c.choice("poses.source", ("sampled", "file", "motion"))
    if spec["poses"]["source"] == "file" and not spec["poses"].get("path"):
        c.fail("poses.path", "a .npz pose file when poses.source is file")
    joints = spec["poses"]["joints"]
    if joints is not None and not (joints in ("upper", "lower", "all") or (isinstance(joints, list) and joints)):
        c.fail("poses.joints", "upper, lower, all or a list of joint names")
    elif isinstance(joints, list):
        from simulate.body import POSE_JOINTS

        for k, name in enumerate(joints):
            if name not in POSE_JOINTS or name == "pelvis":
                c.fail(f"poses.joints[{k}]", f"a posable joint name{nearest_name(name, POSE_JOINTS)} "
                                            f"(one of {', '.join(j for j in POSE_JOINTS if j != 'pelvis')})", name)
    for key in ("path",):
        value = spec["poses"][key]
        if value is not None and not isinstance(value, str):
            c.fail(f"poses.{key}", "the path of a .npz pose file (a string) or null")
    if spec["body"]["path"] is not None and not isinstance(spec["body"]["path"], str):
        c.fail("body.path", "the path of an SMPL-family model file (a string) or null")
    if spec["styles"]["space"] is not None:
        c.fail("styles.space", "null (generate-dataset samples or takes explicit style parameters; style "
                               "spaces are for drape garment and style-space)")
    c.number("poses.range_scale", 0.0, 1.0, lo_open=True)
    if spec["poses"]["min_clearance"] is not None:
        c.number("poses.min_clearance", 0.0, 0.2)
        if spec["poses"]["source"] in ("file", "motion"):
            c.fail("poses.min_clearance", f"null when poses.source is {spec['poses']['source']} (only sampled poses "
                                          "are pruned)")
    c.integer("poses.train_count", 1)
    c.integer("poses.test_count", 0)
    if "regularization_count" in spec["poses"]:
        c.integer("poses.regularization_count", 0)
        if spec["poses"]["source"] == "motion":
            c.fail("poses.regularization_count", "absent when poses.source is motion (motion datasets split by "
                                                 "style-shape pair)")
    for split in SPLITS:
        c.integer(f"splits.{split}", 0, allow=("all",))
    if "canonical" in spec["splits"]:
        if spec["splits"]["canonical"] not in ("all", 0) or isinstance(spec["splits"]["canonical"], bool):
            c.fail("splits.canonical", "all (one canonical-pose frame per style-shape combination) or 0")
        elif spec["splits"]["canonical"] == "all" and spec["poses"]["source"] == "motion":
            c.fail("splits.canonical", "absent or 0 when poses.source is motion (motion datasets split by "
                                       "style-shape pair)")
    sim = "simulation"
    c.choice(f"{sim}.solver", ("vbd", "xpbd", "mass_spring"))
    device = spec[sim]["device"]
    if not (isinstance(device, str) and (device in ("auto", "cpu", "cuda") or device.startswith("cuda:"))):
        c.fail(f"{sim}.device", "auto, cpu, cuda or cuda:N")
    c.integer(f"{sim}.worlds", 1)
    c.integer(f"{sim}.batches", 1)
    c.number(f"{sim}.frame_dt", 0.0, 1.0, lo_open=True)
    c.integer(f"{sim}.substeps", 1)
    c.integer(f"{sim}.iterations", 1)
    c.number(f"{sim}.tolerance", 0.0, lo_open=True)
    c.integer(f"{sim}.max_relax_frames", 1)
    c.number(f"{sim}.interpolation_threshold", 0.0, 3.2, lo_open=True)
    if spec[sim]["poses_per_task"] is not None:
        c.integer(f"{sim}.poses_per_task", 1)
    if not isinstance(spec[sim].get("targets_from_home", False), bool):
        c.fail(f"{sim}.targets_from_home", "true or false")
    for flag in ("self_contact", "primary_bodies"):
        if not isinstance(spec[sim]["contact"][flag], bool):
            c.fail(f"{sim}.contact.{flag}", "true or false")
    c.number("filters.max_area_shrink", 0.0, 1.0, lo_open=True)
    c.number("filters.max_area_growth", 0.0, lo_open=True)
    c.number("filters.max_distorted_fraction", 0.0, 1.0)
    c.number("filters.collision_depth", 0.0)
    c.number("filters.max_penetration_fraction", 0.0, 1.0)
    c.integer("filters.max_self_intersections", 0)
    c.number("filters.max_off_body_fraction", 0.0, 1.0)
    if not isinstance(spec["filters"]["require_converged"], bool):
        c.fail("filters.require_converged", "true or false")
    c.choice("output.precision", ("float32", "float16"))
    c.choice("output.compression", ("gzip", "lzf"))
    c.integer("audit.samples", 0)
    c.integer("audit.max_iterations", 1)
    if isinstance(spec.get("motion"), dict):
        _check_motion(c, spec, motion_given)
    if spec["pairs"]["test"] == 0 and (spec["splits"]["test_train"] or spec["splits"]["test_test"]):
        spec["splits"]["test_train"] = spec["splits"]["test_test"] = 0
    if c.errors:
        raise SpecError("invalid dataset spec: " + "; ".join(c.errors))
    return spec


def _check_type_list(c: _Checker, types: list) -> None:
    """garment.type as a list: distinct known types, at least one."""
    if not types:
        c.fail("garment.type", f"one of {', '.join(GARMENT_TYPES)} or a non-empty list of them")
        return
    for k, name in enumerate(types):
        if name not in GARMENT_TYPES:
            c.fail(f"garment.type[{k}]", f"one of {', '.join(GARMENT_TYPES)}{nearest_name(name, GARMENT_TYPES)}", name)
    if len(set(map(str, types))) != len(types):
        c.fail("garment.type", "a list without repeated types")


def _check_fabric(c: _Checker, fabric: Any, garment_type: Any) -> None:
    """garment.fabric: one preset name, or a non-empty list of distinct names (upper-body types:
    cotton or silk only; with a list of types, the list must leave the upper-body ones one)."""
    if not isinstance(fabric, list):
        c.choice("garment.fabric", FABRIC_NAMES)
        return
    if not fabric:
        c.fail("garment.fabric", f"one of {', '.join(FABRIC_NAMES)} or a non-empty list of them")
        return
    several = isinstance(garment_type, list)
    for k, name in enumerate(fabric):
        if name not in FABRIC_NAMES:
            c.fail(f"garment.fabric[{k}]", f"one of {', '.join(FABRIC_NAMES)}{nearest_name(name, FABRIC_NAMES)}", name)
        elif not several and garment_type in TOP_TYPES and name not in TOP_FABRICS:
            c.fail(f"garment.fabric[{k}]", f"{' or '.join(TOP_FABRICS)} for a {garment_type} (upper-body garments "
                                           f"are cotton or silk, seed 004)", name)
    if len(set(map(str, fabric))) != len(fabric):
        c.fail("garment.fabric", "a list without repeated fabrics")
    tops = [t for t in garment_type if t in TOP_TYPES] if several else []
    if tops and not set(fabric) & set(TOP_FABRICS):
        c.fail("garment.fabric", f"a list naming {' or '.join(TOP_FABRICS)} for the upper-body types of garment.type "
                                 f"({', '.join(map(str, tops))}; seed 004)")


def type_specs(spec: dict[str, Any]) -> list[tuple[str, dict[str, Any]]]:
    """(type, spec) per garment type of a validated spec: ``[(type, spec)]`` for one type; for a
    list, each type's spec is this one with ``garment.type`` that type, ``name`` ``<name>-<type>``
    and, for upper-body types, a fabric list cut to its cotton and silk (seed 004), validated
    again: an ordinary single-type spec, written to ``OUT/<type>/``."""
    types = spec["garment"]["type"]
    if not isinstance(types, list):
        return [(types, spec)]
    out = []
    for gtype in types:
        sub = copy.deepcopy(spec)
        sub["name"] = f"{spec['name']}-{gtype}"
        sub["garment"]["type"] = gtype
        fabric = sub["garment"]["fabric"]
        if isinstance(fabric, list) and gtype in TOP_TYPES:
            sub["garment"]["fabric"] = [f for f in fabric if f in TOP_FABRICS]
        out.append((gtype, validate_spec(sub, source=f"{spec['name']} ({gtype})")))
    return out


def _check_tightness(c: _Checker, value: Any) -> None:
    """garment.tightness: null, [lo, hi], or [[lo, hi], [lo, hi]] with -0.5 <= lo <= hi <= 0.5."""
    if value is None:
        return

    def is_range(r: Any) -> bool:
        return (isinstance(r, list) and len(r) == 2 and all(
            isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)
            and -TIGHTNESS_LIMIT <= x <= TIGHTNESS_LIMIT for x in r) and r[0] <= r[1])

    ranges = value if isinstance(value, list) and value and isinstance(value[0], list) else [value]
    if len(ranges) not in (1, 2) or not all(is_range(r) for r in ranges):
        c.fail("garment.tightness", f"null, a range [lo, hi] or two ranges [[lo, hi], [lo, hi]] (height, weight) "
                                    f"with -{TIGHTNESS_LIMIT} <= lo <= hi <= {TIGHTNESS_LIMIT}")


def _check_motion(c: _Checker, spec: dict, given: bool) -> None:
    """The ``motion`` section: read only with poses.source motion; its fields, and a frame rate
    that is a whole number of simulator frames."""
    from simulate.motion import MOTION_KINDS

    m = spec["motion"]
    if spec["poses"]["source"] != "motion":
        c.errors.append(f"spec.motion is read only when poses.source is motion (got poses.source "
                        f"{spec['poses']['source']!r}); set poses.source: motion or remove the section (in {c.source})")
        return
    c.choice("motion.source", ("procedural", "file"))
    path = m["path"]
    paths_ok = (isinstance(path, str) and path) or (isinstance(path, list) and path and all(
        isinstance(p, str) and p for p in path))
    if m["source"] == "file" and not paths_ok:
        c.fail("motion.path", "a .npz motion file or a non-empty list of them when motion.source is file")
    elif m["source"] == "procedural" and path is not None:
        c.fail("motion.path", "null when motion.source is procedural (set motion.source: file to read motion files)")
    kinds = m["kinds"]
    if not (isinstance(kinds, list) and kinds):
        c.fail("motion.kinds", f"a non-empty list of motion kinds ({', '.join(MOTION_KINDS)})")
    else:
        for k, name in enumerate(kinds):
            if name not in MOTION_KINDS:
                c.fail(f"motion.kinds[{k}]", f"a motion kind{nearest_name(name, list(MOTION_KINDS))} "
                                             f"(one of {', '.join(MOTION_KINDS)})", name)
    c.number("motion.fps", 0.0, 1000.0, lo_open=True)
    if m["frames"] is None:
        if m["source"] == "procedural":
            c.fail("motion.frames", "an integer >= 1 for procedural motions (null, all frames, is for motion files)")
    else:
        c.integer("motion.frames", 1)
    c.number("motion.amplitude", 0.0, 1.0, lo_open=True)
    c.integer("motion.per_pair", 1)
    if m["damping"] is not None:
        c.number("motion.damping", 0.0, 1000.0)
    fps, dt = m["fps"], spec["simulation"]["frame_dt"]
    if all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v > 0 for v in (fps, dt)):
        steps = 1.0 / (fps * dt)
        if steps < 1.0 - 1e-6 or abs(steps - round(steps)) > 1e-6 * steps:
            c.fail("motion.fps", f"a rate whose frame time 1/fps is a whole number of simulation.frame_dt "
                                 f"({dt:g} s): {1.0 / dt:g}, {0.5 / dt:g}, {1.0 / (3 * dt):g}, ... fps "
                                 f"(1/fps is {steps:.4g} frames)")


def motion_steps(spec: dict) -> int:
    """Simulator frames per motion frame of a validated motion spec: 1 / (motion.fps x frame_dt)."""
    return int(round(1.0 / (float(spec["motion"]["fps"]) * float(spec["simulation"]["frame_dt"]))))


def _check_styles(c: _Checker, path: str, styles: list[dict], garment_type: str) -> None:
    """Explicit style dicts: parameter names of the garment type, finite values in range."""
    from simulate.garment.style import parameter_specs

    params = parameter_specs(garment_type)
    for k, style in enumerate(styles):
        for name, value in style.items():
            where = f"{path}[{k}].{name}"
            if name not in params:
                c.errors.append(f"spec.{where} is not a style parameter of a {garment_type}{nearest_name(name, list(params))}; "
                                f"known: {', '.join(params)} (in {c.source})")
                continue
            lo, hi = params[name][0], params[name][1]
            if (isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value)
                    or not lo <= value <= hi):
                c.fail(where, f"a number >= {lo:g} and <= {hi:g}", value)


def load_spec(path: str | Path) -> dict[str, Any]:
    """Reads and validates a spec file; a bare name like ``quickstart`` means a shipped config."""
    p = Path(path)
    if not p.exists() and not p.suffix:
        p = Path(__file__).parent / "configs" / f"{path}.yaml"
    if not p.is_file():
        shipped = sorted(q.stem for q in (Path(__file__).parent / "configs").glob("*.yaml"))
        raise FileNotFoundError(f"dataset spec not found: {path} (shipped specs: {', '.join(shipped)})")
    try:
        text = p.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise SpecError(f"{p} is not a YAML dataset spec (it is a binary file{', an .npz archive' if p.suffix == '.npz' else ''}; "
                        f"expected a .yaml file such as pipelines/configs/quickstart.yaml)") from None
    try:
        raw = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1} column {mark.column + 1}" if mark is not None else ""
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise SpecError(f"{p.name} is not valid YAML{where}: {problem}") from None
    return validate_spec(raw, source=p.name)


def spec_hash(spec: dict[str, Any]) -> str:
    """sha256 of the resolved spec's canonical JSON."""
    return hashlib.sha256(json.dumps(spec, sort_keys=True, separators=(",", ":"), default=str).encode()).hexdigest()
