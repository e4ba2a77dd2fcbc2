"""colgnn core: collision-aware GNN simulation of soft objects pressed by rigid tools.

Pure Python (numpy, torch, trimesh, ipctk); never imports ROS.
"""

__version__ = "0.1.0"
