"""Pose hypotheses: samplers, interpretation trees of depth flips (jumps), closed-form and iterative IK,
Gaussian mixtures of modes, flip branches. Imports `optim` and the layers below."""
