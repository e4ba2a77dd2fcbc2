"""Collision detection between the deforming object and the rigid tool.

* :mod:`.broad_phase`: SDF culling + swept bounding boxes -> candidate pairs.
* :mod:`.filter`: deforming non-penetration filter (numpy + torch), conservative in floating point.
* :mod:`.narrow_phase`: crossing test, time of impact, depth at t+1 (torch-differentiable depths).
* :mod:`.pipeline`: :class:`CollisionDetector` runs the three stages for a step.
* :mod:`.exact`: ipctk oracle (CCD, intersections) and winding numbers.
* :mod:`.metrics`: crossings per step and penetrations per frame.
* :mod:`.ccd_queries`: ``colgnn ccd-check`` over CCD benchmark query files.
* :mod:`.benchmark`: ``bench_collision`` on a cone_bunny contact step.
"""

from colgnn_core.collision.broad_phase import CandidatePairs, Surface, step_candidates
from colgnn_core.collision.filter import (filter_edge_edge, filter_edge_edge_torch, filter_vertex_face,
                                          filter_vertex_face_torch)
from colgnn_core.collision.narrow_phase import (NarrowResult, edge_edge_depth_torch, edge_edge_narrow,
                                                sdf_depth_torch, vertex_face_depth_torch, vertex_face_narrow)
from colgnn_core.collision.pipeline import CollisionDetector, StepCollisions

__all__ = [
    "CandidatePairs", "Surface", "step_candidates",
    "filter_vertex_face", "filter_edge_edge", "filter_vertex_face_torch", "filter_edge_edge_torch",
    "NarrowResult", "vertex_face_narrow", "edge_edge_narrow", "vertex_face_depth_torch", "edge_edge_depth_torch",
    "sdf_depth_torch", "CollisionDetector", "StepCollisions",
]
