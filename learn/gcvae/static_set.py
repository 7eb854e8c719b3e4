"""GCVAE's static set (seed 004, Sec. 5.2: "static samples (in rest pose)"): garments of every
type, style and body shape in the canonical pose, registered on the common body mesh.

A sample draws a type (round robin), a style uniformly within the type's ranges
(:func:`simulate.garment.sample_styles`) and a body shape (every anny parameter uniform in
[0.125, 0.875], age fixed at 0.5: anny's age blends child to elderly bodies, a change of person
class rather than of shape), builds the rest garment on that body (:func:`apply_style`, the
CLOTH3D "outfit fitted to the rest pose for the body shape", no simulation) and registers it.

Conditioning: ``shape`` (anny's 6 phenotype values; anny has no gender flag, its ``gender``
parameter is a continuous blend in [0, 1] and is conditioned on as one of the 6) and
``tightness`` = the style's ``looseness`` [m] (the offset of the garment from the body, the
closest of our style parameters to CLOTH3D's tightness).

File ``DIR/static_set.npz`` (written atomically): ``types`` (T,) names, ``type`` (M,) index,
``shape`` (M, 6), ``tightness`` (M,), ``style`` (M, 4) (the type's parameters in
STYLE_SPECS order, NaN-padded), ``split`` (M,) 0 train / 1 test, ``body_vertices`` (M, N, 3)
[m] (standard topology), ``offsets`` (M, N, 3) [m] relative to them, ``mask`` (M, N) bool,
``registration_mm`` (M, 2) (garment to registered, registered to garment), the body mesh
(``body_*``) and ``meta`` (JSON: settings, seconds).
"""
from __future__ import annotations

import json
import os
import time
from pathlib import Path

import numpy as np

from learn.gcvae.body_mesh import BodyMesh, build_body_mesh, canonical_body_vertices
from learn.gcvae.registration import MAX_OFFSET_M, register, registration_error
from simulate.garment.style import STYLE_SPECS, TAILORNET_TYPES, check_garment_type, sample_styles

FILE_NAME = "static_set.npz"
STYLE_WIDTH = max(len(s) for s in STYLE_SPECS.values())
#: Shape sampling range of every anny parameter but age (the centres of TailorNet-style bins).
SHAPE_RANGE = (0.125, 0.875)
AGE_INDEX, AGE_VALUE = 1, 0.5


def sample_shapes(count: int, rng: np.random.Generator, size: int = 6) -> np.ndarray:
    shapes = rng.uniform(*SHAPE_RANGE, size=(count, size)).astype(np.float32)
    shapes[:, AGE_INDEX] = AGE_VALUE
    return shapes


def build_static_set(out: str | os.PathLike, *, types: tuple[str, ...] = TAILORNET_TYPES, count: int = 160,
                     test_fraction: float = 0.2, seed: int = 0, representation: dict | None = None,
                     body=None, log=print) -> Path:
    """Builds ``count`` samples per type into ``out/static_set.npz`` and returns its path."""
    from simulate.body import load_body_model
    from simulate.garment.templates import apply_style, make_template

    from learn.gcvae.hyperparameters import merged

    types = tuple(check_garment_type(t, field_name="--types") for t in types)
    if not types:
        raise ValueError("--types must name at least one garment type")
    if count < 2:
        raise ValueError(f"--count must be >= 2 samples per type (one train, one test), got {count}")
    if not 0.0 < test_fraction < 1.0:
        raise ValueError(f"--test-fraction must be in (0, 1), got {test_fraction}")
    rep = merged({"representation": representation or {}})["representation"]
    body = load_body_model("anny") if body is None else body
    mesh = build_body_mesh(body, subdivisions=rep["subdivisions"], min_segment_vertices=rep["min_segment_vertices"],
                           inner_leg_cosine=rep["inner_leg_cosine"],
                           dual_smoothing_iterations=rep["dual_smoothing_iterations"])
    rng = np.random.default_rng(seed)
    t0 = time.perf_counter()
    rows: dict[str, list] = {k: [] for k in ("type", "shape", "tightness", "style", "split", "body_vertices",
                                             "offsets", "mask", "registration_mm")}
    for ti, garment_type in enumerate(types):
        template = make_template(garment_type, body)
        styles = sample_styles(garment_type, count, seed=int(rng.integers(2**31)))
        shapes = sample_shapes(count, rng, body.shape_size)
        test = np.zeros(count, bool)
        test[rng.permutation(count)[:max(1, int(round(test_fraction * count)))]] = True
        for k in range(count):
            garment = apply_style(template, styles[k], body, shape=shapes[k]).astype(np.float64)
            standard = mesh.vertices(canonical_body_vertices(body, shapes[k]))[0]
            topology, faces = mesh.topology(garment_type)
            positions = mesh.positions_for(garment_type, standard)
            reg = register(garment, template.faces, positions, faces, rounds=rep["registration_rounds"],
                           max_distance=MAX_OFFSET_M[topology])
            error = registration_error(garment, template.faces, positions, faces, reg)
            offsets = np.where(reg.mask[:, None], positions + reg.offsets - standard, 0.0)
            style = np.full(STYLE_WIDTH, np.nan, np.float32)
            style[:len(styles[k].as_array())] = styles[k].as_array()
            for key, value in (("type", ti), ("shape", shapes[k]), ("tightness", styles[k]["looseness"]),
                               ("style", style), ("split", int(test[k])),
                               ("body_vertices", standard.astype(np.float32)), ("offsets", offsets.astype(np.float32)),
                               ("mask", reg.mask), ("registration_mm", [error["garment_to_registered_mm"],
                                                                       error["registered_to_garment_mm"]])):
                rows[key].append(value)
        done = np.asarray(rows["type"]) == ti
        log(f"{garment_type}: {count} samples, registration {np.mean(np.asarray(rows['registration_mm'])[done, 0]):.2f} mm "
            f"(garment to registered), {time.perf_counter() - t0:.0f} s so far")
    arrays = {k: np.asarray(v) for k, v in rows.items()}
    arrays["type"] = arrays["type"].astype(np.int64)
    arrays["split"] = arrays["split"].astype(np.int64)
    arrays["types"] = np.array(types)
    meta = {"count_per_type": count, "test_fraction": test_fraction, "seed": seed, "representation": rep,
            "body": body.name, "seconds": round(time.perf_counter() - t0, 1)}
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    path = out / FILE_NAME
    tmp = out / f".{FILE_NAME}.{os.getpid()}.tmp.npz"
    np.savez_compressed(tmp, meta=np.array(json.dumps(meta)), **arrays, **mesh.arrays())
    os.replace(tmp, path)
    return path


class StaticSet:
    """A static set read back: every array of the file as numpy, ``mesh`` (BodyMesh), ``meta``."""

    def __init__(self, root: str | os.PathLike) -> None:
        root = Path(root)
        path = root / FILE_NAME if root.is_dir() else root
        if not path.is_file():
            raise FileNotFoundError(f"--data {root}: no {FILE_NAME} (build one with drape static-set --out DIR)")
        with np.load(path, allow_pickle=False) as z:
            self.mesh = BodyMesh.from_arrays(z)
            self.meta = json.loads(str(z["meta"]))
            for key in ("types", "type", "shape", "tightness", "style", "split", "body_vertices", "offsets", "mask",
                        "registration_mm"):
                setattr(self, key, z[key])
        self.types = [str(t) for t in self.types]
        self.path = path

    def __len__(self) -> int:
        return int(len(self.type))

    def indices(self, split: str) -> np.ndarray:
        return split_indices(self.split, split)

    def registration_table(self) -> dict[str, dict[str, float]]:
        """Mean registration errors [mm] per type."""
        return {t: {"garment_to_registered_mm": float(self.registration_mm[self.type == i, 0].mean()),
                    "registered_to_garment_mm": float(self.registration_mm[self.type == i, 1].mean()),
                    "samples": int((self.type == i).sum())}
                for i, t in enumerate(self.types)}


def split_indices(codes: np.ndarray, split: str) -> np.ndarray:
    """Sample indices of ``split`` ("train", "test" or "all") given each sample's split code
    (0 train, 1 test), shape (N,)."""
    if split not in ("train", "test", "all"):
        raise ValueError(f"split must be train, test or all, got {split!r}")
    if split == "all":
        return np.arange(len(codes))
    return np.flatnonzero(codes == (1 if split == "test" else 0))
