"""New garments from the GCVAE's latent space (``drape sample RUN --out DIR``): z ~ N(0, I)
(seeded), decoded for a body shape and tightness into offsets and a mask on the common body
mesh, reconstructed as a mesh (masked vertices moved by their offsets, faces of three masked
vertices; the dual topology when the mask covers the bridge between the legs but not the
inner legs, i.e. a skirt-like garment) and written as OBJ, with the body as ``body.obj`` and
every garment on the body in ``samples.png``.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from learn.gcvae.model import GCVAE
from learn.gcvae.registration import reconstruct


@torch.no_grad()
def decode_garments(model: GCVAE, body_vertices: np.ndarray, condition: np.ndarray, z: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Offsets (K, N, 3) [m] and mask probabilities (K, N) of latent codes z (K, Z) for one
    body (N, 3) [m] and its condition (C,)."""
    device = model.offset_mean.device
    k = len(z)
    body = torch.as_tensor(np.asarray(body_vertices, np.float32), device=device).expand(k, -1, -1)
    cond = torch.as_tensor(np.asarray(condition, np.float32), device=device).expand(k, -1)
    out, logits = model.decode(torch.as_tensor(np.asarray(z, np.float32), device=device), cond, body)
    return model.offsets_from(out).cpu().numpy(), torch.sigmoid(logits).cpu().numpy()


def write_obj(path: Path, vertices: np.ndarray, faces: np.ndarray) -> Path:
    """A plain OBJ (vertices [m], 1-based faces), written under a temporary name then renamed."""
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "w") as fh:
        fh.writelines(f"v {x:.6f} {y:.6f} {z:.6f}\n" for x, y, z in vertices)
        fh.writelines(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in faces)
    tmp.replace(path)
    return path


def sample_garments(model: GCVAE, out: str | Path, *, count: int = 4, shape: np.ndarray | None = None,
                    tightness: float | None = None, seed: int = 0, body=None, log=print) -> list[Path]:
    """Draws ``count`` garments for ``shape`` (anny's 6 values; default neutral 0.5) and
    ``tightness`` [m] (default the training mean) and writes ``garment_<k>.obj`` + ``body.obj``."""
    from learn.gcvae.body_mesh import canonical_body_vertices
    from learn.gcvae.train import body_mesh_of
    from simulate.body import load_body_model

    if count < 1:
        raise ValueError(f"--count must be >= 1, got {count}")
    body = load_body_model("anny") if body is None else body
    shape = np.full(body.shape_size, 0.5, np.float32) if shape is None else np.asarray(shape, np.float32).reshape(-1)
    if shape.shape != (body.shape_size,) or not np.all((shape >= 0) & (shape <= 1)):
        raise ValueError(f"--shape must be {body.shape_size} values in [0, 1] ({', '.join(body.shape_names)}), "
                         f"got {shape.tolist()}")
    if tightness is None:
        tightness = float(model.condition_mean[-1])
    if not 0.0 <= tightness <= 0.1:
        raise ValueError(f"--tightness must be a looseness in [0, 0.1] m, got {tightness}")
    mesh = body_mesh_of(model)
    body_v = mesh.vertices(canonical_body_vertices(body, shape))[0]
    z = np.random.default_rng(seed).standard_normal((count, model.latent_size)).astype(np.float32)
    offsets, probability = decode_garments(model, body_v, np.concatenate([shape, [tightness]]), z)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    paths = [write_obj(out / "body.obj", body_v, mesh.faces)]
    meshes, titles = [], []
    for k in range(count):
        mask = probability[k] > 0.5
        topology = mesh.topology_of_mask(mask)
        faces = mesh.dual_faces if topology == "dual" else mesh.faces
        base = mesh.dual_vertices(body_v) if topology == "dual" else body_v
        # Offsets are relative to the standard positions: move them to the topology's base.
        v, f, _ = reconstruct(base, faces, body_v + offsets[k] - base, mask)
        paths.append(write_obj(out / f"garment_{k}.obj", v, f))
        meshes.append((v, f))
        titles.append(f"garment_{k} ({topology})")
        log(f"garment_{k}.obj: {len(v)} vertices, {len(f)} faces, {topology} topology")
    from learn.gcvae.plots import render_samples

    render_samples(body_v, mesh.faces, meshes, out / "samples.png", titles=titles)
    return paths
