"""Parametric human bodies: the :class:`BodyModel` interface and its backends.

``load_body_model("anny")`` (default, offline, Apache-2.0) or
``load_body_model("smpl", path="SMPL_NEUTRAL.npz")`` for users who hold an SMPL-family
licence. Both return a :class:`BodyModel` with the same pose convention.
"""
from __future__ import annotations

from simulate.body.base import JOINT_LIMITS, PARTS, POSE_JOINTS, POSE_SIZE, BodyModel, PosedBody
from simulate.body.kinematics import inverse_lbs as inverse_lbs_torch
from simulate.body.kinematics import lbs as lbs_torch
from simulate.body.skinning import inverse_lbs, lbs

BACKENDS = ("anny", "smpl")


def load_body_model(name: str = "anny", *, path: str | None = None, device: str = "cpu", **kwargs) -> BodyModel:
    """Loads a body model by backend name.

    Args:
        name: "anny" (default) or "smpl" (SMPL, SMPL-H or SMPL-X model file).
        path: model file, required for "smpl" (.npz or .pkl).
        device: torch device for the backend's tensors.
    """
    if name == "anny":
        if path is not None:
            raise ValueError("body.path is only used by the 'smpl' backend; anny ships its own data")
        return _load_anny(device)
    if name == "smpl":
        from simulate.body.smpl_backend import SMPLBody

        if path is None:
            raise ValueError("body backend 'smpl' needs body.path: an SMPL/SMPL-H/SMPL-X model file (.npz or .pkl)")
        return SMPLBody(path, device=device, **kwargs)
    raise ValueError(f"unknown body backend {name!r}; expected one of {', '.join(BACKENDS)}")


def _load_anny(device: str) -> BodyModel:
    from simulate.body.anny_backend import anny_on

    return anny_on(device)


__all__ = [
    "BodyModel", "PosedBody", "POSE_JOINTS", "POSE_SIZE", "JOINT_LIMITS", "PARTS", "load_body_model",
    "lbs", "inverse_lbs", "lbs_torch", "inverse_lbs_torch",
]
