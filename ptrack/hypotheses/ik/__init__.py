"""Inverse kinematics for interpretation-tree leaves: a chain's joint positions -> joint angles.

    plan = ik_plan(sk, chain)                     # "limb", "swing" or "iterative"
    res = chain_ik(plan, q, tree.positions, mode="prune")   # q (N, D), positions (N, L, n+1, 3)
    res.angles, res.q                             # (N, L, M) solved dofs; (N, L, D) full poses

One idea a module:

- `plan`: `ik_plan` (which solver a chain takes, from the skeleton) and the plan's constants as tensors.
- `closed_form`: the "limb" (root -> ball -> hinge) and "swing" (a ball per link) closed forms
  (Sminchisescu & Triggs 2003, section 3.1).
- `iterative`: the Levenberg-Marquardt fit for chains with no closed form (URDF models, other ASF
  chains; `ik_plan(..., closed_form=False)`), and the refinement of closed-form leaves that miss.
- `kinematics`: forward kinematics (and the fit's Jacobian) along a chain, struct-of-arrays.
- `angles`: both Euler solutions of a rotation, angles in the limits' windows, the pick among them.
- `solve`: `chain_ik`, `product_ik` and their `IKResult`.

Angles are returned in the limits' 2 pi window (as `ptrack.body.limits.wrap_to_limits`; unlimited
angles in [-pi, pi)). Leaves whose angles still break the limits are flagged for `mode="prune"`, or
clamped into them and re-run through the chain's forward kinematics (closed forms) or solved again
within them (iterative) for `mode="project"`. The chain's root must stay where q's forward kinematics
puts it; bone lengths are the model's (`sk.lengths`). Joints past the chain's end (hand, foot) follow
through q's own angles below it. `ik_plan` raises `ClosedFormUnavailable` only when no dof moves the
chain.

Layout: the solvers work on struct-of-arrays tensors (`ptrack.hypotheses.jumps`), hypotheses last; inputs
and outputs are ordinary batch-first tensors. Shapes: `N` hypotheses (any leading batch dims), `L`
leaves, `D` dofs, `M` solved dofs, n links.
"""

from ptrack.hypotheses.ik.angles import euler_zyx_solutions
from ptrack.hypotheses.ik.plan import ChainIK, ClosedFormUnavailable, ik_plan
from ptrack.hypotheses.ik.solve import MODES, IKResult, chain_ik, product_ik

__all__ = [
    "MODES",
    "ChainIK",
    "ClosedFormUnavailable",
    "IKResult",
    "chain_ik",
    "euler_zyx_solutions",
    "ik_plan",
    "product_ik",
]
