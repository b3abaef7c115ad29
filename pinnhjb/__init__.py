"""pinnhjb: physics-informed learning of the infinite-horizon optimal control problem via the finite-horizon
HJB (Fotiadis & Vamvoudakis). See the README and the book for the map from the paper to the modules:

systems (f, g, Q, R, Omega as data) · lq (Riccati ground truth) · pinn (networks, residuals) ·
config / training (Algorithm 1) · gauss_newton (Levenberg-Marquardt, our optimiser) · jacobian (its fast Jacobian) ·
solver (solve, extend = Theorem 2, solve_until, steady-state baseline) · metrics (E, errors, closed loop) ·
storage (checkpoints with provenance).
"""
from . import lq, metrics, systems
from .config import TrainConfig
from .solution import FiniteHorizonSolution, Stage, SteadyStateSolution
from .solver import FiniteHorizonSolver, SteadyStateSolver
from .storage import load, save
from .systems import ControlAffineSystem, get_system

__version__ = "0.1.0"

__all__ = ["systems", "lq", "metrics", "TrainConfig", "FiniteHorizonSolver", "SteadyStateSolver",
           "FiniteHorizonSolution", "SteadyStateSolution", "Stage", "ControlAffineSystem", "get_system",
           "save", "load", "__version__"]
