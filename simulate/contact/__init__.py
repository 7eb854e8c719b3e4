"""Body contact (signed distance to a Warp mesh per world) and optional cloth self-contact."""

from simulate.contact.body_collider import BodyCollider

__all__ = ["BodyCollider"]
