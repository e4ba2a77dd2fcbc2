"""Geometry: tet meshes of the objects, rigid tools with analytic SDFs, pose transforms."""

from colgnn_core.geometry.tetmesh import TetMesh, boundary_faces, load_msh, load_npz, surface_edges
from colgnn_core.geometry.tools import TOOL_SHAPES, Tool, make_tool

__all__ = ["TetMesh", "boundary_faces", "load_msh", "load_npz", "surface_edges", "Tool", "TOOL_SHAPES", "make_tool"]
