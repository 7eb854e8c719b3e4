"""The UV-image learner as one module: features -> offsets of the cloth pixels -> garment.

``forward(pose, shape, style)`` returns unposed displacements (B, V, 3) [m] like every
learner (ARCHITECTURE.md), so the shared evaluation harness, ``drape evaluate`` and
``drape predict`` treat it like TailorNet: the garment is built posed (embedded points
plus offsets in the posed body's tangent frames) and unposed by the garment's inverse
skinning (TailorNet Eq. 5's W^-1, what the dataset's ``unposed_displacements`` are),
minus the unposed body under each vertex; skinning it again gives the posed garment
back. ``posed`` gives the posed garment directly.

The body model is attached, not owned (:meth:`attach_body`): anything with
``pose_torch(shape, pose)`` returning ``vertices`` (B, Vb, 3), ``skinning_transforms``
(B, J, 4, 4) and ``rest_vertices`` (B, Vb, 3), e.g. a ``simulate.body`` model.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import torch
from torch import nn

from learn.common.normals import vertex_normals
from learn.uvimage.decoder import ImageDecoder
from learn.uvimage.features import PoseFeatures
from learn.uvimage.frames import BodyEmbedding
from learn.uvimage.pca import PCADecoder
from learn.uvimage.pixels import ClothPixels

#: Arrays a learner is built from (saved with its checkpoint), see :func:`layout_arrays`.
LAYOUT_KEYS = ("faces", "face_uv", "face_panel", "body_faces", "body_face", "body_bary", "tangent_coefficients",
               "skinning_weights", "body_vertex_index")
KINDS = ("image", "pca")


class UVImageLearner(nn.Module):
    """Seed 001's learner: the whole-image decoder (``kind="image"``) or the fully
    connected 128-PC variant (``kind="pca"``).

    Args:
        layout: arrays of :data:`LAYOUT_KEYS` (numpy or torch): garment faces (F, 3),
            face_uv (F, 3, 2), face_panel (F,), body faces (Fb, 3), body_face (V,),
            body_bary (V, 3), tangent_coefficients (K, 2), garment skinning_weights (V, J),
            body_vertex_index (V,).
        features: the network input (:class:`PoseFeatures`).
        kind: "image" or "pca"; image_size, padding: cloth images [px];
        start_channels: the image decoder's 8 x 8 channels; components, hidden: the PCA variant's.
        style_components: G, the dataset's style size (recorded for ``drape predict``).
    """

    def __init__(self, layout: Mapping[str, Any], features: PoseFeatures, *, kind: str = "image", image_size: int = 256,
                 padding: int = 4, start_channels: int = 384, components: int = 128, hidden: int = 256,
                 style_components: int = 0) -> None:
        super().__init__()
        if kind not in KINDS:
            raise ValueError(f"kind must be one of {KINDS}, got {kind!r}")
        missing = [k for k in LAYOUT_KEYS if k not in layout]
        if missing:
            raise ValueError(f"layout lacks {missing}; expected keys {list(LAYOUT_KEYS)}")
        arrays = {k: np.asarray(v.cpu() if isinstance(v, torch.Tensor) else v) for k, v in layout.items()}
        faces = arrays["faces"].astype(np.int64)
        vertex_count = len(arrays["body_face"])
        self.kind = kind
        self.features = features
        self.pixels = ClothPixels(faces, arrays["face_uv"], arrays["face_panel"], vertex_count, size=image_size,
                                  padding=padding)
        self.embedding = BodyEmbedding(arrays["body_faces"], arrays["body_face"], arrays["body_bary"],
                                       self.pixels.pixel_vertex.numpy(), arrays["tangent_coefficients"])
        if kind == "image":
            self.network: nn.Module = ImageDecoder(features.size, self.pixels.channels, size=image_size,
                                                   start_channels=start_channels)
        else:
            self.network = PCADecoder(features.size, self.pixels.pixel_count, components=components, hidden=hidden)
        self.register_buffer("faces", torch.as_tensor(faces))
        self.register_buffer("skinning_weights", torch.as_tensor(arrays["skinning_weights"], dtype=torch.float32))
        self.register_buffer("body_vertex_index", torch.as_tensor(arrays["body_vertex_index"], dtype=torch.int64))
        self.vertex_count = vertex_count
        #: the layout arrays (numpy) this learner was built from, saved with it
        self.layout = {k: arrays[k] for k in LAYOUT_KEYS}
        self.config = {"kind": kind, "image_size": int(image_size), "padding": int(padding),
                       "start_channels": int(start_channels), "components": int(components), "hidden": int(hidden),
                       "style_components": int(style_components), "features": features.config(),
                       "vertex_count": vertex_count, "pixel_count": self.pixels.pixel_count}
        self._body = None
        self._bodies: dict[str, Any] = {}

    # ---------------------------------------------------------------- body
    def attach_body(self, body: Any) -> "UVImageLearner":
        """Sets the body model that poses the embedding (see the module docstring)."""
        self._body, self._bodies = body, {}
        return self

    def pose_body(self, pose: torch.Tensor, shape: torch.Tensor):
        """The attached body posed on ``pose``'s device: ``vertices`` (B, Vb, 3) [m] etc."""
        if self._body is None:
            raise ValueError("no body model attached: call attach_body(body) (load_uvimage does it)")
        key = str(pose.device)
        if key not in self._bodies:
            on = getattr(self._body, "on_device", None)
            self._bodies[key] = on(pose.device) if on is not None else self._body
        return self._bodies[key].pose_torch(shape, pose)

    # ---------------------------------------------------------------- prediction
    def images(self, features: torch.Tensor) -> torch.Tensor:
        """Cloth images (B, 3 P, H, W) [m] of the image decoder."""
        if self.kind != "image":
            raise ValueError("images() is the image decoder's; this learner predicts PCA coefficients")
        return self.network(features)

    def local_offsets(self, features: torch.Tensor) -> torch.Tensor:
        """Cloth-pixel offsets (du, dv, dn) (B, K, 3) [m] from network features (B, N)."""
        if self.kind == "image":
            return self.pixels.sample(self.network(features))
        return self.network(features)

    def garment(self, local: torch.Tensor, body_vertices: torch.Tensor) -> torch.Tensor:
        """Posed garment (B, V, 3) [m] from offsets (B, K, 3) on posed bodies (B, Vb, 3)."""
        points, frames = self.embedding(body_vertices)
        return self.embedding.to_world(local, points, frames, self.pixels.pixel_weight)

    def posed(self, pose: torch.Tensor, shape: torch.Tensor, style: torch.Tensor) -> torch.Tensor:
        """Posed garment (B, V, 3) [m] (body root at the origin)."""
        body = self.pose_body(pose, shape)
        return self.garment(self.local_offsets(self.features(pose, shape, style)), body.vertices.to(pose.device))

    def forward(self, pose: torch.Tensor, shape: torch.Tensor, style: torch.Tensor) -> torch.Tensor:
        """Unposed displacements (B, V, 3) [m]: W^-1(posed garment) - unposed body under each vertex."""
        from simulate.body.kinematics import inverse_lbs

        body = self.pose_body(pose, shape)
        posed = self.garment(self.local_offsets(self.features(pose, shape, style)), body.vertices.to(pose.device))
        unposed = inverse_lbs(posed, self.skinning_weights.to(posed.dtype), body.skinning_transforms.to(posed))
        return unposed - body.rest_vertices.to(posed)[:, self.body_vertex_index]

    def normals(self, vertices: torch.Tensor) -> torch.Tensor:
        """Unit vertex normals (B, V, 3) of garments (B, V, 3)."""
        return vertex_normals(vertices, self.faces)

    def decoder_only(self) -> nn.Module:
        """features + network alone, ``(pose, shape, style) -> network output``: what the
        seed times (no body posing, no sampling)."""
        return _DecoderOnly(self)


class _DecoderOnly(nn.Module):
    def __init__(self, learner: UVImageLearner) -> None:
        super().__init__()
        self.learner = learner

    def forward(self, pose: torch.Tensor, shape: torch.Tensor, style: torch.Tensor) -> torch.Tensor:
        return self.learner.network(self.learner.features(pose, shape, style))


def layout_arrays(template: Any, body_rest_vertices: np.ndarray, body_faces: np.ndarray, *, image_size: int = 256,
                  padding: int = 4) -> dict[str, np.ndarray]:
    """The :data:`LAYOUT_KEYS` arrays of a ``GarmentTemplate`` embedded in the body whose
    rest (neutral shape, rest pose) vertices are ``body_rest_vertices`` (Vb, 3) [m]."""
    from learn.uvimage.frames import embedding_for

    pixels = ClothPixels(template.faces, template.face_uv, template.face_panel, template.vertex_count,
                         size=image_size, padding=padding)
    embedding = embedding_for(pixels, template.faces, body_rest_vertices, body_faces, template.body_face,
                              template.body_bary)
    return {"faces": np.asarray(template.faces, np.int64), "face_uv": np.asarray(template.face_uv, np.float32),
            "face_panel": np.asarray(template.face_panel, np.int64), "body_faces": np.asarray(body_faces, np.int64),
            "body_face": np.asarray(template.body_face, np.int64), "body_bary": np.asarray(template.body_bary, np.float32),
            "tangent_coefficients": embedding.coefficients.numpy(),
            "skinning_weights": np.asarray(template.skinning_weights, np.float32),
            "body_vertex_index": np.asarray(template.body_vertex_index, np.int64)}
