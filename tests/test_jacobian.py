"""pinnhjb.jacobian.residual_jacobian on its own: shapes and refused input (the residual forms' Jacobians against
torch.func's vmap(jacrev(...)) are in test_residuals.py)."""

from __future__ import annotations

import pytest
import torch

from pinnhjb.gauss_newton import FlatParameters
from pinnhjb.jacobian import residual_jacobian
from pinnhjb.pinn import MLP


def test_bad_input_is_refused():
    net = MLP(3, width=4, depth=1).double()
    theta = FlatParameters(net).get()
    z, dz = torch.zeros(6, 3, dtype=torch.float64), torch.zeros(6, 2, 3, dtype=torch.float64)
    ok = lambda out, dout: out  # noqa: E731
    with pytest.raises(ValueError, match="need z"):
        residual_jacobian(net, theta, z, dz[:, :, :2], ok)
    with pytest.raises(ValueError, match="weights"):
        residual_jacobian(net, theta[:-1], z, dz, ok)
    with pytest.raises(ValueError, match="blocks"):
        residual_jacobian(net, theta, z, dz, ok, copies=4)
    with pytest.raises(ValueError, match="expected"):
        residual_jacobian(net, theta, z, dz, ok, copies=2)  # 6 rows in two blocks feed 3 residuals, not 6
    r, J = residual_jacobian(net, theta, z, dz, lambda out, dout: out[:3] + out[3:], copies=2)
    assert r.shape == (3,) and J.shape == (3, theta.numel())
