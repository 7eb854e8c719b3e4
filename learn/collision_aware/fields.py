"""The diffused body model of seed 002 (Sec. 4.1): skinning weights W~(p) and shape blendshape
offsets B~s(p, beta) defined at any point p of the canonical space, distilled into small MLPs.

Targets come from :mod:`learn.collision_aware.diffusion` at points around the canonical body
(``beta`` = the body model's default shape, ``pose`` = 0): the diffused body skinning weights, and
the diffused shape offsets ``rest(beta) - rest(beta_0)`` of the shaped rest body, in one of two forms:

- **basis** (``shape_basis`` = C > 0, the default): the seed's linear blendshapes, made for any
  backend. anny's six phenotype parameters reach the vertices through a non-linear blend of its
  136 blendshapes, so its offsets, over sampled shapes, span a linear space of the vertices, of
  which C principal components keep almost all (32: 0.2 mm median on the skin at the data's
  shapes). The field distils the C diffused components, a function of the point alone, and a
  shape's coefficients are the exact projection of the body model's own offsets onto them
  (computed by the body model at run time, cached per shape). SMPL's offsets are linear in its
  betas, and 10 components hold them exactly.
- **conditioned** (``shape_basis`` = 0): one MLP of (point, beta) fitted to the diffused offsets of
  sampled shapes. Its error grows away from the shapes it was fitted to (docs/collision_aware.md).

Pose blendshapes: anny has no pose correctives (``BodyModel._pose_correctives`` is None), so its
diffused pose field B~p is identically zero and there is nothing to distil. The consequence for
the canonical garment: every pose-dependent deformation that linear blend skinning with the
diffused weights does not explain (wrinkles at the elbow, bulges under the arm) stays in the
canonical garment X and the regressor learns it as a function of pose, where with SMPL part of it
would be carried by the body's correctives. A backend with correctives would add a third field
B~p(p, pose) distilled from ``D @ correctives(pose)`` like the shape field; not built here.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from learn.collision_aware.body_samples import points_near_body
from learn.collision_aware.diffusion import DEFAULT_SAMPLES, diffusion_operator
from learn.collision_aware.field_mlp import FieldMLP


class DiffusedBody(nn.Module):
    """Distilled diffused fields of one body model.

    Args:
        joint_count: J, skinning weights per point.
        shape_default: the canonical shape beta_0, (S,).
        shape_scale: scale of each shape parameter for the network input, (S,) (half its range).
        hidden_size, layers, frequencies: of each :class:`FieldMLP`.
        center, scale: region of interest [m] (the canonical body's bounding box).
    """

    def __init__(self, joint_count: int, shape_default: list[float], shape_scale: list[float], *,
                 hidden_size: int = 128, layers: int = 3, frequencies: int = 4,
                 center: list[float] = (0.0, 0.0, 0.0), scale: float = 1.0, shape_basis: int = 0,
                 vertex_count: int = 0, shape_hidden_size: int | None = None, shape_layers: int | None = None,
                 shape_frequencies: int | None = None) -> None:
        super().__init__()
        if len(shape_default) != len(shape_scale):
            raise ValueError(f"shape_default ({len(shape_default)}) and shape_scale ({len(shape_scale)}) differ in length")
        if int(shape_basis) < 0 or (int(shape_basis) > 0 and int(vertex_count) < 1):
            raise ValueError(f"shape_basis must be >= 0 (got {shape_basis}), and a basis needs the body's vertex_count "
                             f"(got {vertex_count})")
        shape_net = {"hidden_size": int(hidden_size if shape_hidden_size is None else shape_hidden_size),
                     "layers": int(layers if shape_layers is None else shape_layers),
                     "frequencies": int(frequencies if shape_frequencies is None else shape_frequencies)}
        self.config: dict[str, Any] = {
            "joint_count": int(joint_count), "shape_default": [float(x) for x in shape_default],
            "shape_scale": [float(x) for x in shape_scale], "hidden_size": int(hidden_size), "layers": int(layers),
            "frequencies": int(frequencies), "center": [float(c) for c in center], "scale": float(scale),
            "shape_basis": int(shape_basis), "vertex_count": int(vertex_count) if int(shape_basis) else 0,
            "shape_hidden_size": shape_net["hidden_size"], "shape_layers": shape_net["layers"],
            "shape_frequencies": shape_net["frequencies"],
        }
        region = dict(center=center, scale=scale)
        self.weights_net = FieldMLP(int(joint_count), hidden_size=hidden_size, layers=layers, frequencies=frequencies,
                                    **region)
        basis = int(shape_basis)
        if basis:  # C diffused components [m] (at one typical coefficient), a function of the point alone
            self.shape_net = FieldMLP(3 * basis, **shape_net, **region)
        else:
            self.shape_net = FieldMLP(3, extra_features=len(shape_default), **shape_net, **region)
        self.register_buffer("shape_default", torch.tensor(self.config["shape_default"], dtype=torch.float32))
        self.register_buffer("shape_scale", torch.tensor(self.config["shape_scale"], dtype=torch.float32))
        vertices = int(vertex_count) if basis else 0
        # the basis: orthonormal components (C, Vb, 3) of the body's shape offsets, each component's
        # typical coefficient [m] (C,), and the canonical rest body [m] (Vb, 3) the offsets are from
        self.register_buffer("basis_vectors", torch.zeros(basis, vertices, 3))
        self.register_buffer("basis_scale", torch.ones(basis))
        self.register_buffer("basis_rest", torch.zeros(vertices, 3))
        self._body: Any = None
        self._coefficients: dict[bytes, torch.Tensor] = {}

    def _load_from_state_dict(self, state_dict: dict[str, Any], prefix: str, *args: Any, **kwargs: Any) -> None:
        self._coefficients.clear()  # a new basis: the kept coefficients are of the old one
        if not self.basis_size:  # a conditioned field saved before the basis buffers existed: they are empty
            for name in ("basis_vectors", "basis_scale", "basis_rest"):
                state_dict.setdefault(prefix + name, getattr(self, name))
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    @property
    def shape_size(self) -> int:
        return len(self.config["shape_default"])

    @property
    def basis_size(self) -> int:
        """C, the shape basis's components (0: the conditioned shape field)."""
        return int(self.config["shape_basis"])

    def set_shape_basis(self, vectors: np.ndarray, scale: np.ndarray, rest: np.ndarray) -> None:
        """The basis of :func:`shape_basis`: orthonormal ``vectors`` (C, Vb, 3), ``scale`` [m]
        (C,), the canonical rest vertices ``rest`` [m] (Vb, 3)."""
        for name, value, buffer in (("vectors", vectors, self.basis_vectors), ("scale", scale, self.basis_scale),
                                    ("rest", rest, self.basis_rest)):
            if tuple(np.shape(value)) != tuple(buffer.shape):
                raise ValueError(f"shape basis {name} must have shape {tuple(buffer.shape)}, got {tuple(np.shape(value))}")
            buffer.copy_(torch.as_tensor(np.asarray(value, np.float32)))
        self._coefficients.clear()

    def use_body(self, body: Any) -> "DiffusedBody":
        """The body model whose shaped rest vertices give the basis coefficients (a basis field
        needs it; the conditioned field ignores it). Returns ``self``."""
        self._body = body
        self._coefficients.clear()
        return self

    def shape_coefficients(self, shape: torch.Tensor) -> torch.Tensor:
        """Basis coefficients (B, C) of shapes (B, S): ``<rest(beta) - rest(beta_0), vector_c> /
        scale_c``, by the body model (each distinct shape once, then kept)."""
        if self._body is None:
            raise RuntimeError("this shape field is linear in the body's own shape offsets: give it the body model "
                               "with use_body(body) first")
        rows = shape.detach().to("cpu", torch.float32).contiguous()
        keys = [row.numpy().tobytes() for row in rows]
        missing = sorted({k for k in keys if k not in self._coefficients})
        if missing:
            todo = torch.as_tensor(np.stack([np.frombuffer(k, np.float32) for k in missing]))
            with torch.no_grad():
                shaped, _ = self._body.rest_torch(todo)
                offsets = shaped.to(self.basis_vectors.device, torch.float32) - self.basis_rest  # (U, Vb, 3)
                coefficients = torch.einsum("uvd,cvd->uc", offsets, self.basis_vectors) / self.basis_scale
            self._coefficients.update(zip(missing, coefficients))
        return torch.stack([self._coefficients[k] for k in keys]).to(shape.device)

    def skinning_weights(self, points: torch.Tensor) -> torch.Tensor:
        """W~(p): points [m] (..., 3) -> weights (..., J), non-negative, summing to 1."""
        return torch.softmax(self.weights_net(points), dim=-1)

    def shape_offset(self, points: torch.Tensor, shape: torch.Tensor) -> torch.Tensor:
        """B~s(p, beta): points [m] (B, N, 3), shape (B, S) -> offsets [m] (B, N, 3); zero at beta_0."""
        if shape.ndim != 2 or shape.shape[-1] != self.shape_size:
            raise ValueError(f"shape must have shape (B, {self.shape_size}), got {tuple(shape.shape)}")
        if self.basis_size:
            components = self.shape_net(points).unflatten(-1, (self.basis_size, 3))  # (B, N, C, 3)
            return torch.einsum("bc,bncd->bnd", self.shape_coefficients(shape).to(components.dtype), components)
        code = ((shape - self.shape_default) / self.shape_scale)[:, None, :]  # (B, 1, S)
        neutral = torch.zeros_like(code)
        return self.shape_net(points, code) - self.shape_net(points, neutral)


@dataclass
class FieldTargets:
    """Distillation data: points [m] (N, 3); diffused skinning weights (N, J); shapes (K, S), the
    last ``data_count`` of them the data's. The conditioned field's targets: diffused shape offsets
    [m] (K, N, 3) of each shape. The basis field's: the basis of :func:`shape_basis` (``basis``
    (C, Vb, 3), ``basis_scale`` [m] (C,), the canonical rest body ``basis_rest`` [m] (Vb, 3) the
    offsets are from) and its diffused components at the points times their
    scale, ``components`` [m] (N, C, 3); ``offsets`` is then empty (0, N, 3)."""

    points: np.ndarray
    weights: np.ndarray
    shapes: np.ndarray
    offsets: np.ndarray
    data_count: int = 0
    basis: np.ndarray | None = None
    basis_scale: np.ndarray | None = None
    basis_rest: np.ndarray | None = None
    components: np.ndarray | None = None


def shape_basis(offsets: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray]:
    """The principal components of the body's shape offsets: ``offsets`` [m] (K, Vb, 3) of K
    shapes -> orthonormal vectors (C, Vb, 3) and each one's root-mean-square coefficient over
    the K shapes [m] (C,), C = ``count``; an error where the offsets span fewer dimensions. Not
    centred: the offsets are zero at the default shape, and so is every coefficient."""
    flat = np.asarray(offsets, np.float64).reshape(len(offsets), -1)
    _, singular, vectors = np.linalg.svd(flat, full_matrices=False)
    keep = min(int(count), int((singular > singular[0] * 1e-9).sum()))
    if keep < int(count):
        raise ValueError(f"fields.shape_basis {count}: the {len(offsets)} sampled shapes' offsets span only {keep} "
                         f"dimensions; sample more shapes (fields.shapes) or use a smaller basis")
    return (vectors[:keep].reshape(keep, -1, 3).astype(np.float32),
            (singular[:keep] / np.sqrt(len(flat))).astype(np.float32))


def canonical_body(body: Any) -> np.ndarray:
    """Rest vertices [m] of the canonical body (default shape, pose 0), (Vb, 3)."""
    vertices, _ = body.rest(np.asarray(body.shape_default, np.float32))
    return vertices[0]


def field_targets(body: Any, *, point_count: int = 20000, shape_count: int = 32, samples: int = DEFAULT_SAMPLES,
                  spread: float = 1.0, extra_points: np.ndarray | None = None, extra_shapes: np.ndarray | None = None,
                  basis: int = 0, seed: int = 0, warp_device: str | None = None) -> FieldTargets:
    """Diffused skinning weights and shape offsets at points around the canonical body.

    ``extra_points`` [m] (M, 3) (e.g. the garment template) are added to the sampled points;
    ``shape_count`` shapes are drawn uniformly within the body model's shape ranges, and
    ``extra_shapes`` (E, S) (e.g. the training data's) added to them. ``basis`` = C > 0: the
    targets of the basis field, the C principal components of those shapes' offsets, diffused.
    """
    rest = canonical_body(body)
    points = points_near_body(rest, body.faces, point_count, seed=seed)
    if extra_points is not None:
        points = np.concatenate([points, np.asarray(extra_points, np.float32).reshape(-1, 3)])
    operator = diffusion_operator(points, rest, body.faces, samples=samples, spread=spread, seed=seed + 1,
                                  device=warp_device)  # (N, Vb)
    weights = operator @ np.asarray(body.skinning_weights, np.float64)  # (N, J)
    rng = np.random.default_rng(seed + 2)
    ranges = np.asarray(body.shape_ranges, np.float64)
    shapes = rng.uniform(ranges[:, 0], ranges[:, 1], size=(shape_count, ranges.shape[0])).astype(np.float32)
    if extra_shapes is not None and len(extra_shapes):
        shapes = np.concatenate([shapes, np.asarray(extra_shapes, np.float32).reshape(-1, ranges.shape[0])])
    shaped = np.concatenate([body.rest(shapes[k:k + 64])[0] for k in range(0, len(shapes), 64)])  # (K, Vb, 3)
    data_count = len(shapes) - shape_count
    if basis:
        vectors, scale = shape_basis(shaped.astype(np.float64) - rest, basis)
        components = np.stack([operator @ (vectors[c].astype(np.float64) * scale[c]) for c in range(len(scale))], 1)
        return FieldTargets(points.astype(np.float32), weights.astype(np.float32), shapes,
                            np.zeros((0, len(points), 3), np.float32), data_count=data_count, basis=vectors,
                            basis_scale=scale, basis_rest=rest.astype(np.float32),
                            components=components.astype(np.float32))
    offsets = np.stack([operator @ (shaped[k].astype(np.float64) - rest) for k in range(len(shapes))])  # (K, N, 3)
    return FieldTargets(points.astype(np.float32), weights.astype(np.float32), shapes, offsets.astype(np.float32),
                        data_count=data_count)


@torch.no_grad()
def shape_field_error(fields: DiffusedBody, body: Any, shapes: np.ndarray, vertex_index: np.ndarray | None = None
                      ) -> dict[str, float]:
    """How far the shape field puts the body's own skin: canonical body vertices (those of
    ``vertex_index``, e.g. the ones under the garment; default all) moved by the field's offsets
    for each of ``shapes`` (K, S), against the body model's shaped rest vertices. Median, p99 and
    max over vertices and shapes [mm]. A garment point on the skin is posed this far off, so the
    collision terms' margin (``epsilon_m``) has to cover it."""
    shapes = np.asarray(shapes, np.float32).reshape(-1, len(body.shape_ranges))
    if getattr(fields, "basis_size", 0):
        fields.use_body(body)
    rest = canonical_body(body).astype(np.float32)
    index = np.arange(rest.shape[0]) if vertex_index is None else np.asarray(vertex_index)
    device = next(fields.parameters()).device
    points = torch.as_tensor(rest[index], device=device)[None].expand(len(shapes), -1, -1).contiguous()
    moved = (points + fields.shape_offset(points, torch.as_tensor(shapes, device=device))).cpu().numpy()
    truth, _ = body.rest(shapes)
    error = np.linalg.norm(moved - truth[:, index], axis=-1) * 1e3
    return {"shapes": int(len(shapes)), "median_mm": float(np.median(error)),
            "p99_mm": float(np.percentile(error, 99)), "max_mm": float(error.max())}


def new_diffused_body(body: Any, *, hidden_size: int, layers: int, frequencies: int, shape_basis: int = 0,
                      shape_hidden_size: int | None = None, shape_layers: int | None = None,
                      shape_frequencies: int | None = None) -> DiffusedBody:
    """Untrained fields sized and scaled for ``body``'s canonical rest mesh (a basis field: its
    basis still to be set, :meth:`DiffusedBody.set_shape_basis`), using ``body``."""
    rest = canonical_body(body)
    low, high = rest.min(0), rest.max(0)
    ranges = np.asarray(body.shape_ranges, np.float64)
    return DiffusedBody(body.joint_count, np.asarray(body.shape_default).tolist(),
                        np.maximum(0.5 * (ranges[:, 1] - ranges[:, 0]), 1e-6).tolist(), hidden_size=hidden_size,
                        layers=layers, frequencies=frequencies, center=(0.5 * (low + high)).tolist(),
                        scale=float(0.5 * (high - low).max()) + 0.2, shape_basis=shape_basis,
                        vertex_count=rest.shape[0], shape_hidden_size=shape_hidden_size, shape_layers=shape_layers,
                        shape_frequencies=shape_frequencies).use_body(body)


def draw_shapes(count: int, random_count: int, data_count: int, share: float, generator: torch.Generator
                ) -> torch.Tensor:
    """``count`` shape indices (count,) into ``random_count`` random shapes followed by
    ``data_count`` data shapes: a data shape with probability ``share`` (0: every shape alike)."""
    if share <= 0.0 or data_count == 0:
        return torch.randint(random_count + data_count, (count,), generator=generator)
    data = random_count + torch.randint(data_count, (count,), generator=generator)
    if random_count == 0:
        return data
    random = torch.randint(random_count, (count,), generator=generator)
    return torch.where(torch.rand(count, generator=generator) < share, data, random)


def fit_fields(fields: DiffusedBody, targets: FieldTargets, *, run_dir: str | Path,
               hyperparameters: dict[str, Any], fingerprint: Any = None, device: str = "cpu", seed: int = 0,
               progress: bool = True) -> DiffusedBody:
    """Distil ``targets`` into ``fields`` (stage ``fields``): per batch of points, L1 of the
    weights (summed over joints) plus, for the basis field, L1 of its diffused components [m]
    (summed over components and axes; the basis is set from the targets first), or, for the
    conditioned field, L1 of the shape offset [m] for one random shape per point, drawn from the
    data's shapes with probability ``hyperparameters["data_share"]`` (default 0: every shape
    alike) where the targets have some."""
    from learn import distributed
    from learn.tailornet.train import run_epochs

    points = torch.as_tensor(targets.points, device=device)
    weights = torch.as_tensor(targets.weights, device=device)
    shapes = torch.as_tensor(targets.shapes, device=device)
    offsets = torch.as_tensor(targets.offsets, device=device)
    count = points.shape[0]
    batch_size = int(hyperparameters["batch_size"])
    data_count = int(targets.data_count)
    share = float(hyperparameters.get("data_share", 0.0)) if data_count else 0.0
    random_count = shapes.shape[0] - data_count
    basis = fields.basis_size
    if basis:
        if targets.components is None or targets.components.shape[1] != basis:
            raise ValueError(f"a basis field of {basis} components needs field_targets(..., basis={basis})")
        fields.set_shape_basis(targets.basis, targets.basis_scale, targets.basis_rest)
        components = torch.as_tensor(targets.components, device=device).flatten(1)  # (N, 3 C)

    def epoch_fn(net: DiffusedBody, optimizer: torch.optim.Optimizer, generator: torch.Generator) -> float:
        order = torch.randperm(count, generator=generator).to(device)
        which = draw_shapes(count, random_count, data_count, share, generator).to(device)
        total = torch.zeros((), device=device)
        for begin in range(0, count, batch_size):
            batch = distributed.shard(order[begin:begin + batch_size])  # this rank's points (all in one process)
            k = distributed.shard(which[begin:begin + batch_size])
            p = points[batch][None]  # (1, b, 3)
            weight_loss = (net.skinning_weights(p)[0] - weights[batch]).abs().sum(-1).mean()
            if basis:
                offset_loss = (net.shape_net(p[0]) - components[batch]).abs().sum(-1).mean()
            else:
                predicted = net.shape_offset(p.transpose(0, 1), shapes[k])[:, 0]  # (b, 3): one shape per point
                offset_loss = (predicted - offsets[k, batch]).abs().sum(-1).mean()
            loss = weight_loss + offset_loss
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
            total += loss.detach() * batch.numel()
        return float(total) / count

    return run_epochs("fields", fields, epoch_fn, run_dir=run_dir, hyperparameters=hyperparameters,
                      fingerprint=fingerprint, device=device, seed=seed, progress=progress,
                      loss_name="l1")  # weights (no unit) plus offsets [m]
