"""Static balance (`ptrack.body.balance`): the centre of mass, the foot it stands on, a lean that takes the
centre of mass off that foot, and its place in the kjs tracker's frame cost (only with a known up axis)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest
import torch

from ptrack.body.balance import Balance
from ptrack.body.skeleton import Skeleton, load_amc
from ptrack.body.subject import add_landmark_joints, floor_points, scale_to_height, standing_height
from ptrack.errors import InputError
from ptrack.estimators.kjs import KJS
from ptrack.estimators.kjs.model import frame_evidence, make_setup
from ptrack.pipeline.config import load_config
from ptrack.pipeline.run import prepare
from ptrack.problem import Floor

REPO = Path(__file__).resolve().parents[1]
HEIGHT = 1.72


@pytest.fixture(scope="module")
def body() -> Skeleton:
    return add_landmark_joints(scale_to_height(Skeleton.from_asf(REPO / "ptrack" / "data" / "10.asf"), HEIGHT), HEIGHT)


def _pose(sk: Skeleton, **angles_deg: float) -> torch.Tensor:
    q = torch.zeros(sk.num_dofs, dtype=torch.float64)
    for name, deg in angles_deg.items():
        q[sk.dof_names.index(name.replace("_", "."))] = torch.deg2rad(torch.tensor(deg, dtype=torch.float64))
    return q


def test_centre_of_mass_is_a_mass_weighted_mean(body):
    """Standing at rest the centre of mass lies between the hips and the neck, near the body's midline; moving
    the whole body moves it by as much (a weighted mean of points)."""
    sk = body
    b = Balance.for_skeleton(sk, 0.1)
    j = sk.forward_kinematics(_pose(sk))
    com = b.centre_of_mass(j)
    hips = j[[sk.joint_index("lhipjoint"), sk.joint_index("rhipjoint")]].mean(0)
    neck = j[sk.joint_index("lowerneck")]
    assert hips[1] - 0.05 < com[1] < neck[1]
    assert abs(float(com[0])) < 0.03
    shift = torch.tensor([0.3, -0.2, 1.1], dtype=torch.float64)
    assert torch.allclose(b.centre_of_mass(j + shift), com + shift, atol=1e-12)
    assert float(b.distance(j + shift)) == pytest.approx(float(b.distance(j)), abs=1e-12)


def test_a_lean_over_the_feet_costs_more(body):
    """From a real standing pose (the bundled kick's first frame, its own skeleton) leaning the trunk over
    straight legs moves the centre of mass off the feet: forward the distance and the cost grow with the lean,
    and a lean as far back costs more than standing too."""
    sk = Skeleton.from_asf(REPO / "ptrack" / "data" / "10.asf")
    sk = add_landmark_joints(sk, standing_height(sk))
    b = Balance.for_skeleton(sk, 0.1)
    stand = load_amc(REPO / "ptrack" / "data" / "10_02.amc", sk).q[0].double()
    lean = sk.dof_names.index("lowerback.rx")

    def leaned(deg: float) -> torch.Tensor:
        q = stand.clone()
        q[lean] += torch.deg2rad(torch.tensor(deg, dtype=torch.float64))
        return q

    upright = float(b.distance(sk.forward_kinematics(stand)))
    assert upright < 0.1  # standing: within a hand's width of the support
    prev = upright
    for deg in (15.0, 30.0, 45.0):
        d = float(b.distance(sk.forward_kinematics(leaned(deg))))
        assert d > prev
        prev = d
    assert float(b.distance(sk.forward_kinematics(leaned(-60.0)))) > upright
    energies = b.energy(sk.forward_kinematics(torch.stack([stand, leaned(30.0)])))
    assert energies.shape == (2,)
    assert float(energies[1]) > float(energies[0]) + 0.5


def test_the_lower_foot_carries_the_body(body):
    """With one thigh raised the support is the other foot's points: the standing foot's mean."""
    sk = body
    b = Balance.for_skeleton(sk, 0.1)
    j = sk.forward_kinematics(_pose(sk, lfemur_rx=-60.0, ltibia_rx=60.0))  # the left knee up in front
    right = j[b.feet[1]].mean(0)
    raised = float(j[b.feet[0], 1].min() - j[b.feet[1], 1].min())
    assert raised > 0.15
    assert torch.allclose(b.support(j), right, atol=5e-3)  # the raised foot keeps exp(-raised / 0.03) of a share
    both = sk.forward_kinematics(_pose(sk))  # both feet down, within millimetres of one height: both carry it
    left, right = both[b.feet[0]].mean(0), both[b.feet[1]].mean(0)
    x = float(b.support(both)[0])
    assert float(right[0]) + 0.2 < x < float(left[0]) - 0.2


def test_needs_cmu_joints():
    """A skeleton without the CMU joints the centre of mass reads gets one error; a bad scale too."""
    bare = Skeleton.from_asf(REPO / "ptrack" / "data" / "10.asf")
    Balance.for_skeleton(bare, 0.1)  # a plain CMU skeleton has the ankles and toes: enough foot points
    renamed = dataclasses.replace(bare, joint_names=tuple(n.replace("femur", "thigh") for n in bare.joint_names))
    with pytest.raises(InputError, match="lfemur"):
        Balance.for_skeleton(renamed, 0.1)
    with pytest.raises(InputError, match="sigma"):
        Balance.for_skeleton(bare, 0.0)


def test_frame_evidence_adds_the_balance_only_with_a_floor():
    """`kjs.balance_weight` w: with a floor whose up axis came with the camera each mode's frame cost gains w times
    the balance cost of its joints; without a floor, with a floor fitted under the person's feet, or with w = 0
    (the default of configs/kjs.yaml), nothing changes."""
    base = load_config(REPO / "configs" / "kjs.yaml", ["data.stop=12", "progress=false"])
    assert base.kjs.balance_weight == 0
    prep = prepare(base)
    cfg = load_config(REPO / "configs" / "kjs.yaml", ["data.stop=12", "progress=false", "kjs.balance_weight=40"])
    assert make_setup(prep.problem, cfg, KJS).balance is None  # no floor: up is not known
    sk = prep.problem.skeleton
    joints, clearance = floor_points(add_landmark_joints(sk, HEIGHT), HEIGHT)
    joints = tuple(i for i in joints if i < sk.num_joints)
    problem = dataclasses.replace(prep.problem, floor=Floor(-1.0, joints, clearance))
    plain = make_setup(problem, base, KJS)
    s = make_setup(problem, cfg, KJS)
    assert plain.balance is None and s.balance is not None
    guessed = dataclasses.replace(problem, floor=dataclasses.replace(problem.floor, up_given=False))
    assert make_setup(guessed, cfg, KJS).balance is None  # a floor fitted under the feet: up is a guess
    q = prep.gt_q[:3].to(prep.problem.observations.keypoints)
    t = torch.arange(3)
    expected = frame_evidence(plain, t, q) + 40 * s.balance.energy(sk.forward_kinematics(q))
    assert torch.allclose(frame_evidence(s, t, q), expected, rtol=1e-5, atol=1e-3)


@pytest.mark.parametrize("value", ["-1", ".nan"])
def test_bad_settings(value):
    from ptrack.pipeline.config import load_config as load

    with pytest.raises(InputError, match=r"kjs\.balance_weight"):
        load(REPO / "configs" / "kjs.yaml", [f"kjs.balance_weight={value}"])
    with pytest.raises(InputError, match=r"kjs\.balance_sigma_m"):
        load(REPO / "configs" / "kjs.yaml", [f"kjs.balance_sigma_m={value}"])
