"""Solvers: batched Levenberg-Marquardt / L-BFGS, block-banded normal equations, pose Jacobians of the cost
terms. Imports `costs` and the layers below."""
