"""Differentiable 2D MLS-MPM for shape-morphing animation (M. Xu, 2020), with hand-written reverse kernels."""
from .config import ConfigError, SimConfig
from .losses import ColorLoss, LossError, MassLoss, PositionLoss
from .simulator import SimulationError, Simulator

__all__ = ["SimConfig", "ConfigError", "Simulator", "SimulationError", "PositionLoss", "MassLoss", "ColorLoss",
           "LossError"]
