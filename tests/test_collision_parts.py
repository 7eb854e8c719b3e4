"""Primary collision bodies (seed 001 D.6): each cloth vertex meets only its own body part."""

from __future__ import annotations

import numpy as np
import pytest

from simulate.body.collision_parts import COLLISION_PART_NAMES, collision_parts
from simulate.cloth import ClothBuilder, Features
from simulate.quasi_static import QuasiStaticSimulator
from simulate.scenes import grid_cloth, icosphere
from simulate.contact import BodyCollider
from unit_sim import unit_settings

TORSO_R = 0.15
ARM_R = 0.06
ARM_CENTER = np.array([0.0, TORSO_R - 0.03, 0.0])  # the arm pokes 3 cm out of the torso's top


def _two_part_body():
    tv, tf = icosphere(TORSO_R, subdivisions=4)
    av, af = icosphere(ARM_R, subdivisions=3)
    verts = np.concatenate([tv, av + ARM_CENTER])
    faces = np.concatenate([tf, af + len(tv)])
    groups = [np.arange(len(tf)), np.arange(len(tf), len(tf) + len(af))]
    return verts, faces, groups


def test_collider_measures_each_point_against_its_part() -> None:
    verts, faces, groups = _two_part_body()
    collider = BodyCollider(verts, faces, device="cpu", face_groups=groups)
    # inside the arm, outside the torso; and inside both
    probe = np.array([[0.0, TORSO_R + 0.02, 0.0], [0.0, TORSO_R - 0.05, 0.0]])
    world = np.zeros(2, np.int32)
    whole = collider.signed_distance(probe, world)
    torso = collider.signed_distance(probe, world, point_part=np.zeros(2, np.int32))
    arm = collider.signed_distance(probe, world, point_part=np.ones(2, np.int32))
    assert whole[0] < -0.008 and torso[0] == pytest.approx(0.02, abs=2e-3) and arm[0] < -0.008
    assert torso[1] < -0.04 and arm[1] < -0.01
    with pytest.raises(ValueError, match="face_groups\\[1\\]"):
        BodyCollider(verts, faces, device="cpu", face_groups=[groups[0], np.array([len(faces)])])


@pytest.mark.parametrize("solver", ["xpbd", "vbd"])
@pytest.mark.parametrize("parts", [False, True], ids=["whole-body", "primary-parts"])
def test_cloth_meets_only_its_primary_part(solver: str, parts: bool) -> None:
    """A torso cloth dropped on the torso where an arm's skin pokes out of it: with primary parts it
    rests on the torso through the arm (the skins interpenetrate, the cloth is not pushed off by the
    wrong one); against the whole body it drapes over the arm."""
    verts, faces, groups = _two_part_body()
    cloth_v, cloth_f = grid_cloth(13, 13, 0.16, 0.16, plane="xz", origin=(-0.08, TORSO_R + 0.06, -0.08))
    builder = ClothBuilder()
    builder.add_garment(cloth_v, cloth_f, fabric="cotton", body_part=np.zeros(len(cloth_v), np.int32) if parts else None)
    model = builder.finalize("cpu", features=Features(friction=False))
    collider = BodyCollider(verts, faces, device="cpu", face_groups=groups if parts else None)
    sim = QuasiStaticSimulator(model, collider, solver=solver,
                               settings=unit_settings(substeps=5, iterations=10, damping=5.0))
    for _ in range(40):
        sim.step_frame()
    q = sim.positions()
    world = np.zeros(len(q), np.int32)
    probe = BodyCollider(verts, faces, device="cpu", face_groups=groups)
    sd_torso = probe.signed_distance(q, world, point_part=np.zeros(len(q), np.int32))
    sd_arm = probe.signed_distance(q, world, point_part=np.ones(len(q), np.int32))
    assert np.isfinite(q).all()
    assert sd_torso.min() > -1e-3, f"a cloth vertex {-sd_torso.min() * 1e3:.1f} mm inside the torso"
    top = q[np.argmax(q[:, 1])]
    if parts:
        # the cloth's top rests on the torso, inside the arm
        assert sd_arm.min() < -0.02, f"the cloth did not pass into the arm (deepest {sd_arm.min() * 1e3:.1f} mm)"
        assert top[1] < TORSO_R + 0.01, f"the cloth's top is at {top[1]:.3f} m: it rests on the arm"
    else:
        assert sd_arm.min() > -1e-3, f"a cloth vertex {-sd_arm.min() * 1e3:.1f} mm inside the arm"
        assert top[1] > ARM_CENTER[1] + ARM_R, f"the cloth's top is at {top[1]:.3f} m: it does not cover the arm"


def test_builder_checks_body_part() -> None:
    cloth_v, cloth_f = grid_cloth(3, 3, 0.1, 0.1)
    builder = ClothBuilder()
    with pytest.raises(ValueError, match="body_part"):
        builder.add_garment(cloth_v, cloth_f, body_part=np.zeros(len(cloth_v) + 1, np.int32))
    with pytest.raises(ValueError, match="body_part"):
        builder.add_garment(cloth_v, cloth_f, body_part=np.full(len(cloth_v), -1))


def test_anny_parts_for_a_tshirt(anny_body) -> None:
    from simulate.garment.templates import make_template

    parts = collision_parts(anny_body, "tshirt")
    assert parts.names == ("torso", "left_arm", "right_arm")
    rest = np.asarray(anny_body.rest(anny_body.shape_default)[0]).reshape(-1, 3)
    left = parts.vertex_part == 1
    right = parts.vertex_part == 2
    assert left.sum() > 100 and right.sum() > 100
    assert (rest[left, 0] > 0).all() and (rest[right, 0] < 0).all()
    faces = anny_body.faces
    covered = np.zeros(len(faces), bool)
    for g in parts.face_groups:
        covered[g] = True
    assert covered.all(), "every body face belongs to some part"
    # the parts overlap around the shoulder, and an arm's mesh never reaches the other arm
    assert len(np.intersect1d(parts.face_groups[0], parts.face_groups[1])) > 20
    assert not np.intersect1d(parts.face_groups[1], parts.face_groups[2]).size
    assert not (parts.vertex_part[faces[parts.face_groups[1]]] == 2).any()
    template = make_template("tshirt", anny_body, resolution=500)
    posed = anny_body.pose(anny_body.shape_default, anny_body.canonical_pose).vertices
    garment = parts.garment_vertex_parts(template.vertices, np.asarray(posed).reshape(-1, 3))
    # the sleeve ends meet the arms, the hem meets the torso
    assert (garment[template.boundary("hem")] == 0).all() and (garment[template.boundary("neck")] == 0).all()
    assert (garment[template.boundary("left_sleeve")] == 1).all()
    assert (garment[template.boundary("right_sleeve")] == 2).all()
    assert set(np.unique(garment)) == {0, 1, 2}
    assert COLLISION_PART_NAMES[0] == "torso"


def test_quality_meter_measures_penetration_against_the_vertex_part() -> None:
    from simulate.quality import QualityMeter

    verts, faces, groups = _two_part_body()
    cloth_v, cloth_f = grid_cloth(3, 3, 0.02, 0.02, plane="xz", origin=(-0.01, TORSO_R + 0.02, -0.01))  # in the arm
    whole = QualityMeter(cloth_f, cloth_v, faces, len(verts))
    torso = QualityMeter(cloth_f, cloth_v, faces, len(verts), body_face_groups=groups,
                         garment_part=np.zeros(len(cloth_v), np.int32))
    arm = QualityMeter(cloth_f, cloth_v, faces, len(verts), body_face_groups=groups,
                       garment_part=np.ones(len(cloth_v), np.int32))
    assert whole.measure(cloth_v, verts)["penetration_fraction"] == 1.0
    assert torso.measure(cloth_v, verts)["penetration_fraction"] == 0.0
    assert arm.measure(cloth_v, verts)["penetration_fraction"] == 1.0
    d = torso.signed_distances(cloth_v[None], verts[None])[0]
    assert np.allclose(d, 0.02, atol=2e-3), d
    with pytest.raises(ValueError, match="garment_part"):
        QualityMeter(cloth_f, cloth_v, faces, len(verts), body_face_groups=groups, garment_part=np.full(len(cloth_v), 2))
