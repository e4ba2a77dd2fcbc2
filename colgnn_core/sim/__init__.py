"""Ground truth: stable Neo-Hookean elasticity, the IPC time stepper on ipctk, dataset generation."""

from colgnn_core.sim.dataset import generate_dataset, parse_shard, simulate_sequence
from colgnn_core.sim.elasticity import StableNeoHookean, lumped_mass
from colgnn_core.sim.ipc import IPCSimulator, StepStats

__all__ = [
    "IPCSimulator",
    "StableNeoHookean",
    "StepStats",
    "lumped_mass",
    "simulate_sequence",
    "generate_dataset",
    "parse_shard",
]
