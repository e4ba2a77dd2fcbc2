"""The object-tool graph the learned simulator runs on.

Nodes: the object's graph nodes (every tet vertex, or only the surface vertices
when the scene sets ``model.surface_only``) first, then the tool's surface
vertices. Node features: velocity and a one-hot node type (object, tool, and
pinned when the scene pins vertices). Object velocity is ``x_t - x_{t-1}``;
tool nodes carry their known displacement to t+1, ``y_{t+1} - y_t``.

Edge sets:

* ``mesh``: object mesh edges (tet edges, or surface edges when surface-only),
  both directions; features ``[x_s - x_r, |x_s - x_r|, X_s - X_r, |X_s - X_r|]``
  (world displacement at t, rest displacement).
* ``world``: tool node <-> object node pairs closer than ``r_W``, both
  directions; features ``[p_s - p_r, |p_s - p_r|]``. As in the paper, the tool
  is placed at t+1 (the combined mesh (M_X^t, M_Y^{t+1})), so a world edge says
  where the tool *will* be relative to the object node.

World edges are found with a KD-tree after SDF culling: an object node with
``|sdf(x)| > r_W + max_v |sdf(v)|`` (v the tool's vertices) cannot be within
r_W of any tool vertex, because the SDF is 1-Lipschitz. Zero world edges (tool
far away) give empty edge sets, which the model handles.

Times are frames; positions metres (float64 in, float64 features out; the
model casts after normalising).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
import torch
from scipy.spatial import cKDTree

from colgnn_core.learn.core_model import EdgeSet

NODE_OBJECT, NODE_TOOL, NODE_PINNED = 0, 1, 2
MESH_EDGE_FEATURES = 8
WORLD_EDGE_FEATURES = 4
SdfFn = Callable[[np.ndarray, np.ndarray], np.ndarray]  # (points [K,3] world, pose [7]) -> [K] metres


@dataclass(frozen=True, eq=False)
class GraphTemplate:
    """The per-scene constant part of the graph (topology, rest geometry, node types).

    Index spaces: "mesh ids" index the scene's tet mesh vertices [N_mesh];
    "graph ids" index the object graph nodes [N] (tool nodes follow at N..N+M-1).
    """

    object_nodes: np.ndarray        # [N] int64 mesh ids of the object graph nodes (sorted)
    rest: torch.Tensor              # [N,3] float64 rest positions of the object graph nodes
    mesh_senders: torch.Tensor      # [E] int64 graph ids, each undirected edge in both directions
    mesh_receivers: torch.Tensor    # [E] int64
    mesh_rest_features: torch.Tensor  # [E,4] float64 rest displacement (sender - receiver) and its norm
    surface_faces: np.ndarray       # [F,3] int64 surface triangles in graph ids (outward)
    surface_edges: np.ndarray       # [H,2] int64 unique surface edges in graph ids
    pinned: torch.Tensor            # [N] bool, object nodes held fixed
    num_node_types: int             # 2 (object, tool) or 3 (+ pinned)
    node_one_hot: torch.Tensor      # [N+M, num_node_types] float64
    num_tool_nodes: int             # M
    world_radius: float             # r_W (m)
    surface_only: bool
    tool_sdf: SdfFn | None = None   # for culling; None = no culling
    sdf_margin: float = 0.0         # max |sdf| over the tool's own vertices (tessellation error)
    mesh_rest_vertices: np.ndarray | None = None  # [N_mesh,3] all rest vertices (for lift_to_mesh)
    interior_ids: np.ndarray | None = None        # [I] mesh ids not in the graph (surface-only)
    interior_neighbours: np.ndarray | None = None  # [I,k] graph ids used to interpolate them
    interior_weights: np.ndarray | None = None     # [I,k] inverse-distance weights, rows sum to 1

    @property
    def num_object_nodes(self) -> int:
        return int(self.object_nodes.shape[0])

    @property
    def node_feature_size(self) -> int:
        return 3 + self.num_node_types


@dataclass(frozen=True, eq=False)
class GraphInputs:
    """Raw (unnormalised) graph features for one frame. Object nodes first, then tool nodes."""

    node_features: torch.Tensor     # [N+M, 3+T]: velocity (m/frame), one-hot node type
    mesh: EdgeSet                   # features [E,8]
    world: EdgeSet                  # features [2W,4]; first W edges tool->object, then object->tool
    num_object_nodes: int
    coarse: EdgeSet | None = None   # features [Ec,8] between cluster centres (models with a coarse level)
    # Edge sets ("mesh", "coarse") whose features are the network's normalised, encoded latents already [E,latent]:
    # a quasi-static model's graph lies on the settled rest, so at inference they are the same every step
    # (learn.model.Simulator.static_edges). The normalisers and encoders skip them.
    encoded: tuple[str, ...] = ()

    @property
    def num_world_pairs(self) -> int:
        return int(self.world.senders.shape[0]) // 2


def tet_edges(tets: np.ndarray) -> np.ndarray:
    """Unique undirected edges [E,2] (i<j) of tets [K,4]."""
    tets = np.asarray(tets, dtype=np.int64)
    pairs = tets[:, [[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]]].reshape(-1, 2)
    return np.unique(np.sort(pairs, axis=1), axis=0)


def face_edges(faces: np.ndarray) -> np.ndarray:
    """Unique undirected edges [E,2] (i<j) of triangles [F,3]."""
    faces = np.asarray(faces, dtype=np.int64)
    pairs = faces[:, [[0, 1], [1, 2], [2, 0]]].reshape(-1, 2)
    return np.unique(np.sort(pairs, axis=1), axis=0)


def make_template(rest_vertices: np.ndarray, tets: np.ndarray, faces: np.ndarray, *, num_tool_nodes: int,
                  world_radius: float, surface_only: bool = False, pinned: np.ndarray | None = None,
                  tool_sdf: SdfFn | None = None, sdf_margin: float = 0.0, interior_k: int = 4) -> GraphTemplate:
    """Build the constant graph part from arrays.

    Args:
        rest_vertices: [N_mesh,3] rest positions (m).
        tets: [K,4] tets (mesh ids); faces: [F,3] boundary triangles (mesh ids).
        num_tool_nodes: M, the tool's surface vertex count.
        world_radius: r_W (m) for world edges.
        surface_only: graph nodes = surface vertices with surface edges, else all vertices with tet edges.
        pinned: optional mesh ids (or a [N_mesh] bool mask) of vertices held fixed.
        tool_sdf, sdf_margin: SDF for culling and the tool vertices' max |SDF| (see module docstring).
        interior_k: neighbours used by :func:`lift_to_mesh` for interior vertices (surface-only).
    """
    rest_vertices = np.asarray(rest_vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    n_mesh = rest_vertices.shape[0]
    if not (world_radius > 0):
        raise ValueError(f"world_radius must be > 0, got {world_radius}")
    if surface_only:
        nodes = np.unique(faces)
        edges_mesh = face_edges(faces)
    else:
        nodes = np.arange(n_mesh, dtype=np.int64)
        edges_mesh = tet_edges(tets)
    to_graph = np.full(n_mesh, -1, dtype=np.int64)
    to_graph[nodes] = np.arange(nodes.shape[0])
    edges = to_graph[edges_mesh]
    senders = np.concatenate([edges[:, 0], edges[:, 1]])
    receivers = np.concatenate([edges[:, 1], edges[:, 0]])
    rest = rest_vertices[nodes]
    d_rest = rest[senders] - rest[receivers]
    rest_feat = np.concatenate([d_rest, np.linalg.norm(d_rest, axis=1, keepdims=True)], axis=1)

    pinned_mask = np.zeros(n_mesh, dtype=bool)
    if pinned is not None:
        pinned = np.asarray(pinned)
        if pinned.dtype == bool:
            pinned_mask[:] = pinned
        else:
            pinned_mask[pinned.astype(np.int64)] = True
    pinned_graph = pinned_mask[nodes]
    num_types = 3 if pinned_graph.any() else 2
    node_type = np.concatenate([np.where(pinned_graph, NODE_PINNED, NODE_OBJECT),
                                np.full(num_tool_nodes, NODE_TOOL)])
    one_hot = np.eye(num_types)[node_type]

    interior = interior_nbrs = interior_w = None
    if surface_only and nodes.shape[0] < n_mesh:
        interior = np.flatnonzero(to_graph < 0)
        k = min(interior_k, nodes.shape[0])
        dist, nbr = cKDTree(rest).query(rest_vertices[interior], k=k)
        dist, nbr = dist.reshape(len(interior), k), nbr.reshape(len(interior), k)
        w = 1.0 / np.maximum(dist, 1e-12)
        interior_w = w / w.sum(axis=1, keepdims=True)
        interior_nbrs = nbr.astype(np.int64)

    return GraphTemplate(
        object_nodes=nodes,
        rest=torch.from_numpy(rest),
        mesh_senders=torch.from_numpy(senders),
        mesh_receivers=torch.from_numpy(receivers),
        mesh_rest_features=torch.from_numpy(rest_feat),
        surface_faces=to_graph[faces],
        surface_edges=to_graph[face_edges(faces)],
        pinned=torch.from_numpy(pinned_graph),
        num_node_types=num_types,
        node_one_hot=torch.from_numpy(one_hot),
        num_tool_nodes=int(num_tool_nodes),
        world_radius=float(world_radius),
        surface_only=bool(surface_only),
        tool_sdf=tool_sdf,
        sdf_margin=float(sdf_margin),
        mesh_rest_vertices=rest_vertices,
        interior_ids=interior,
        interior_neighbours=interior_nbrs,
        interior_weights=interior_w,
    )


def template_from_scene(scene, surface_only: bool | None = None, world_radius: float | None = None) -> GraphTemplate:
    """:func:`make_template` for a :class:`colgnn_core.scenes.Scene` (its ``model`` table gives the defaults)."""
    if surface_only is None:
        surface_only = bool(scene.model.get("surface_only", False))
    if world_radius is None:
        world_radius = float(scene.model["world_radius"])
    tool = scene.tool
    margin = float(np.abs(tool.sdf_local(np.asarray(tool.vertices, dtype=np.float64))).max())
    mesh = scene.object
    return make_template(mesh.vertices, mesh.tets, mesh.faces, num_tool_nodes=tool.vertices.shape[0],
                         world_radius=world_radius, surface_only=surface_only,
                         pinned=getattr(scene, "pinned", None), tool_sdf=tool.sdf, sdf_margin=margin)


def find_world_edges(object_pos: np.ndarray, tool_pos: np.ndarray, radius: float, sdf: SdfFn | None = None,
                     pose: np.ndarray | None = None, margin: float = 0.0, sdf_values: np.ndarray | None = None
                     ) -> tuple[np.ndarray, np.ndarray]:
    """All (object node, tool node) pairs with ``|x_i - y_j| <= radius``.

    Object nodes whose ``|sdf(x, pose)|`` exceeds ``radius + margin`` are culled
    first (exact when ``margin`` bounds the tool vertices' |sdf|). ``sdf_values`` [N] (m): those SDF values where the
    caller has them already.

    Returns:
        ``(object_ids [W], tool_ids [W])`` int64, sorted by object id then tool id.
    """
    empty = np.zeros(0, dtype=np.int64)
    if object_pos.shape[0] == 0 or tool_pos.shape[0] == 0:
        return empty, empty
    if sdf_values is None and sdf is not None and pose is not None:
        sdf_values = sdf(object_pos, pose)
    if sdf_values is not None:
        candidates = np.flatnonzero(np.abs(sdf_values) <= radius + margin)
        if candidates.size == 0:
            return empty, empty
        pts = object_pos[candidates]
    else:
        candidates, pts = None, object_pos
    pairs = cKDTree(pts).sparse_distance_matrix(cKDTree(tool_pos), radius, output_type="ndarray")
    obj = pairs["i"].astype(np.int64)
    tool = pairs["j"].astype(np.int64)
    if candidates is not None:
        obj = candidates[obj]
    order = np.lexsort((tool, obj))
    return obj[order], tool[order]


def mesh_edge_set(template: GraphTemplate, x_t: torch.Tensor) -> EdgeSet:
    """Mesh edge features [E,8] at object graph-node positions ``x_t`` [N,3] (m): ``[x_s - x_r, |x_s - x_r|, rest,
    |rest|]``."""
    s, r = template.mesh_senders, template.mesh_receivers
    d = x_t[s] - x_t[r]
    feats = torch.cat([d, torch.linalg.vector_norm(d, dim=1, keepdim=True),
                       template.mesh_rest_features.to(x_t.dtype)], dim=1)
    return EdgeSet(feats, s, r)


def build_graph(template: GraphTemplate, x_t: torch.Tensor, x_prev: torch.Tensor, tool_t: torch.Tensor,
                tool_next: torch.Tensor, pose_next: np.ndarray | None = None, mesh: EdgeSet | None = None,
                node_sdf: np.ndarray | None = None) -> GraphInputs:
    """Graph features for predicting t -> t+1.

    Args:
        x_t, x_prev: [N,3] object graph-node positions at t and t-1 (m).
        tool_t, tool_next: [M,3] tool surface vertices (world) at t and t+1 (m).
        pose_next: [7] tool pose at t+1, used only for SDF culling (None: no culling).
        mesh: the mesh edge set to use (default :func:`mesh_edge_set` at ``x_t``).
        node_sdf: [N] the tool's SDF at ``x_t`` and ``pose_next`` (m), where the caller has it (else computed).
    """
    n, m = x_t.shape[0], tool_next.shape[0]
    if n != template.num_object_nodes or m != template.num_tool_nodes:
        raise ValueError(f"graph expects {template.num_object_nodes} object and {template.num_tool_nodes} tool nodes,"
                         f" got {n} and {m}")
    dtype = x_t.dtype
    velocity = torch.cat([x_t - x_prev, tool_next - tool_t], dim=0)
    node_features = torch.cat([velocity, template.node_one_hot.to(dtype)], dim=1)

    if mesh is None:
        mesh = mesh_edge_set(template, x_t)

    obj_np = x_t.detach().cpu().numpy()
    tool_np = tool_next.detach().cpu().numpy()
    obj_ids, tool_ids = find_world_edges(obj_np, tool_np, template.world_radius, template.tool_sdf, pose_next,
                                         template.sdf_margin, node_sdf)
    obj_ids_t = torch.from_numpy(obj_ids)
    tool_ids_t = torch.from_numpy(tool_ids) + n  # tool nodes follow the object nodes
    w_send = torch.cat([tool_ids_t, obj_ids_t])
    w_recv = torch.cat([obj_ids_t, tool_ids_t])
    pos = torch.cat([x_t, tool_next], dim=0)
    dw = pos[w_send] - pos[w_recv]
    world_feat = torch.cat([dw, torch.linalg.vector_norm(dw, dim=1, keepdim=True)], dim=1)
    return GraphInputs(node_features, mesh, EdgeSet(world_feat, w_send, w_recv), n)


def lift_to_mesh(template: GraphTemplate, x_graph: np.ndarray, rest: np.ndarray | None = None) -> np.ndarray:
    """Object graph-node positions [N,3] -> every mesh vertex [N_mesh,3].

    With all vertices in the graph this is a reorder. Surface-only: interior
    vertices get the inverse-distance-weighted rest-frame displacement of their
    ``k`` nearest surface nodes (only interior vertices move this way; they are
    not part of any contact or output face). ``rest`` [N_mesh,3]: the rest shape the displacements refer to
    (default the template's, the mesh file's; the runtime passes the settled rest).
    """
    x_graph = np.asarray(x_graph)
    rest_all = template.mesh_rest_vertices if rest is None else np.asarray(rest)
    out = np.empty((rest_all.shape[0], 3), dtype=x_graph.dtype)
    out[template.object_nodes] = x_graph
    if template.interior_ids is not None:
        disp = x_graph - rest_all[template.object_nodes]
        out[template.interior_ids] = rest_all[template.interior_ids] + np.einsum(
            "ik,ikc->ic", template.interior_weights, disp[template.interior_neighbours])
    return out


@dataclass(frozen=True, eq=False)
class CoarseTemplate:
    """The constant part of a coarse level: clusters of the object graph nodes and the edges between them.

    Clusters: ``K`` centres by farthest-point sampling of the rest nodes, each node in the cluster of its
    nearest centre. Two clusters are joined when a mesh edge joins them, so coarse edges follow the surface
    (never across a gap between two parts of the object, e.g. a bunny's ears).
    """

    assign: torch.Tensor           # [N] int64 cluster of each object graph node
    inverse_counts: torch.Tensor   # [K,1] float64 1 / cluster size
    senders: torch.Tensor          # [Ec] int64 cluster ids, both directions
    receivers: torch.Tensor        # [Ec] int64
    rest_features: torch.Tensor    # [Ec,4] float64 rest displacement between cluster centres and its norm

    @property
    def num_clusters(self) -> int:
        return int(self.inverse_counts.shape[0])


def farthest_points(points: np.ndarray, k: int) -> np.ndarray:
    """Indices [k] of ``k`` points of [N,3] picked by farthest-point sampling, starting at the point farthest from
    the centroid (deterministic)."""
    k = min(int(k), points.shape[0])
    chosen = np.empty(k, dtype=np.int64)
    chosen[0] = int(np.argmax(np.linalg.norm(points - points.mean(0), axis=1)))
    dist = np.linalg.norm(points - points[chosen[0]], axis=1)
    for i in range(1, k):
        chosen[i] = int(np.argmax(dist))
        dist = np.minimum(dist, np.linalg.norm(points - points[chosen[i]], axis=1))
    return chosen


def coarse_template(template: GraphTemplate, num_clusters: int) -> CoarseTemplate:
    """A :class:`CoarseTemplate` with ``num_clusters`` clusters over ``template``'s object nodes."""
    rest = template.rest.numpy()
    centres = farthest_points(rest, num_clusters)
    _, assign = cKDTree(rest[centres]).query(rest)
    assign = assign.astype(np.int64)
    k = centres.shape[0]
    counts = np.bincount(assign, minlength=k).astype(np.float64)
    pairs = np.stack([assign[template.mesh_senders.numpy()], assign[template.mesh_receivers.numpy()]], axis=1)
    pairs = np.unique(pairs[pairs[:, 0] != pairs[:, 1]], axis=0)  # mesh edges come in both directions already
    mean_rest = np.zeros((k, 3))
    np.add.at(mean_rest, assign, rest)
    mean_rest /= counts[:, None]
    d = mean_rest[pairs[:, 0]] - mean_rest[pairs[:, 1]]
    return CoarseTemplate(
        assign=torch.from_numpy(assign),
        inverse_counts=torch.from_numpy(1.0 / counts[:, None]),
        senders=torch.from_numpy(pairs[:, 0].copy()),
        receivers=torch.from_numpy(pairs[:, 1].copy()),
        rest_features=torch.from_numpy(np.concatenate([d, np.linalg.norm(d, axis=1, keepdims=True)], axis=1)),
    )


def coarse_edges(coarse: CoarseTemplate, x_t: torch.Tensor) -> EdgeSet:
    """Coarse edge features [Ec,8] at positions ``x_t`` [N,3]: ``[c_s - c_r, |c_s - c_r|, rest, |rest|]`` with
    ``c`` the cluster centres (mean node positions), as the mesh edges' features."""
    centres = x_t.new_zeros((coarse.num_clusters, 3)).index_add_(0, coarse.assign, x_t)
    centres = centres * coarse.inverse_counts.to(x_t.dtype)
    d = centres[coarse.senders] - centres[coarse.receivers]
    feats = torch.cat([d, torch.linalg.vector_norm(d, dim=1, keepdim=True), coarse.rest_features.to(x_t.dtype)],
                      dim=1)
    return EdgeSet(feats, coarse.senders, coarse.receivers)
