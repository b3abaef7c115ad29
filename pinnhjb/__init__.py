"""pinnhjb: physics-informed learning of the infinite-horizon optimal control problem via the finite-horizon
HJB (Fotiadis & Vamvoudakis). See the README and the book for the map from the paper to the modules:

* systems: f, g, Q, R, Omega as data; lq: the Riccati ground truth; pinn: the networks.
* residuals: the PDE forms (F_e, F_b, F_in, E_e), registered by name.
* optimizers: Adam, LBFGS, LevenbergMarquardt, the phases of a recipe, registered by name; gauss_newton: the
  Levenberg-Marquardt step; jacobian: its fast Jacobian.
* config, training: Algorithm 1; solver: solve, extend (Theorem 2), solve_until, the steady-state baseline.
* solution, metrics: the results, E, errors, closed loop; storage: checkpoints with provenance.
* paper: what belongs to the paper (its cases, the reproduction, the Theorem 3 demonstration, the chapters'
  loaders).
"""

import importlib as _importlib

from . import lq, metrics, optimizers, parametric, residuals, systems
from .config import TrainConfig
from .gauss_newton import DivergenceError
from .optimizers import LBFGS, Adam, LevenbergMarquardt
from .parametric import ParametricFamily, WeightFamily
from .solution import AveragedSolution, FiniteHorizonSolution, Stage, SteadyStateSolution
from .solver import FiniteHorizonSolver, SteadyStateSolver
from .storage import CheckpointError, load, save
from .systems import ControlAffineSystem, get_system

__version__ = "0.1.0"

__all__ = [
    "systems",
    "lq",
    "metrics",
    "residuals",
    "optimizers",
    "parametric",
    "reference",
    "TrainConfig",
    "Adam",
    "LBFGS",
    "LevenbergMarquardt",
    "FiniteHorizonSolver",
    "SteadyStateSolver",
    "FiniteHorizonSolution",
    "SteadyStateSolution",
    "AveragedSolution",
    "Stage",
    "ControlAffineSystem",
    "get_system",
    "ParametricFamily",
    "WeightFamily",
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
