"""What belongs to the paper, not to the method: its simulations and settings (:mod:`.cases`)."""
from .cases import CASES, Case, cases

__all__ = ["CASES", "Case", "cases"]
