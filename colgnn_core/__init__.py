"""colgnn core: collision-aware GNN simulation of soft objects pressed by rigid tools.

Pure Python (numpy, torch, trimesh, ipctk); never imports ROS.
"""

from pathlib import Path

from colgnn_core.jit_cache import use_source_keyed_cache

__version__ = "0.1.0"

# Before any module imports numba: its kernel cache is keyed by these sources (jit_cache explains why).
use_source_keyed_cache(Path(__file__).resolve().parent)
