"""pinnhjb: physics-informed learning of the infinite-horizon optimal control problem via the finite-horizon
HJB (Fotiadis & Vamvoudakis). See the README and the book for the map from the paper to the modules:

systems (f, g, Q, R, Omega as data) · lq (Riccati ground truth) · pinn (networks) · residuals (the PDE forms
F_e, F_b, F_in, E_e, registered by name) · config / training (Algorithm 1) · gauss_newton (Levenberg-Marquardt,
our optimiser) · jacobian (its fast Jacobian) · solver (solve, extend = Theorem 2, solve_until, steady-state
baseline) · metrics (E, errors, closed loop) · storage (checkpoints with provenance). What belongs to the paper
(its cases, the reproduction, the Theorem 3 demonstration, the chapters' loaders) is in the subpackage paper.
"""

import importlib as _importlib

from . import lq, metrics, residuals, systems
from .config import TrainConfig
from .gauss_newton import DivergenceError
from .solution import FiniteHorizonSolution, Stage, SteadyStateSolution
from .solver import FiniteHorizonSolver, SteadyStateSolver
from .storage import CheckpointError, load, save
from .systems import ControlAffineSystem, get_system

__version__ = "0.1.0"

__all__ = [
    "systems",
    "lq",
    "metrics",
    "residuals",
    "reference",
    "TrainConfig",
    "FiniteHorizonSolver",
    "SteadyStateSolver",
    "FiniteHorizonSolution",
    "SteadyStateSolution",
    "Stage",
    "ControlAffineSystem",
    "get_system",
    "save",
    "load",
    "CheckpointError",
    "DivergenceError",
    "__version__",
]

# Submodules imported on first use (``ph.reference`` works after ``import pinnhjb``), so that importing the
# package stays cheap: the reference solver, the paper's reproduction, the plots and widgets.
_LAZY = (
    "reference",
    "paper",
    "plots",
    "widgets",
    "gauss_newton",
    "jacobian",
    "pinn",
    "training",
    "solver",
    "solution",
    "storage",
    "config",
    "cli",
)


def __getattr__(name):
    if name in _LAZY:
        return _importlib.import_module(f".{name}", __name__)
    raise AttributeError(f"module 'pinnhjb' has no attribute {name!r}")
