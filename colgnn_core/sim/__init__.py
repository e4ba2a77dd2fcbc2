"""Ground truth: stable Neo-Hookean elasticity, the IPC time stepper on ipctk, dataset generation.

Heavy modules are imported on use, so ``import colgnn_core.sim`` stays cheap.
"""

from colgnn_core.sim.elasticity import StableNeoHookean, lumped_mass
from colgnn_core.sim.ipc import IPCSimulator, StepStats


def __getattr__(name):
    if name in ("simulate_sequence", "generate_dataset", "parse_shard"):
        from colgnn_core.sim import dataset

        return getattr(dataset, name)
    if name in ("bench_ipc", "estimate_generation_s", "mesh_counts"):
        from colgnn_core.sim import benchmark

        return getattr(benchmark, name)
    raise AttributeError(name)


__all__ = [
    "IPCSimulator",
    "StableNeoHookean",
    "StepStats",
    "lumped_mass",
    "simulate_sequence",
    "generate_dataset",
    "parse_shard",
    "bench_ipc",
    "estimate_generation_s",
    "mesh_counts",
]
