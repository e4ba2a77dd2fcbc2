"""The learned simulator: graph -> normalised features -> GNN -> acceleration -> x_{t+1}.

``Simulator`` is the same module for every variant (full, baseline,
no-compact); only the losses the training loop adds differ.

* Inputs are normalised with online normalizers (node features, one per edge
  set); the network predicts the *normalised* acceleration of the object nodes,
  which is de-normalised and integrated second-order:
  ``x_{t+1} = 2 x_t - x_{t-1} + a``. Pinned nodes stay at ``x_t``.
* Training noise (MGN): Gaussian noise of std ``noise_std`` (m) is added to
  ``x_t`` of free object nodes; the target position is moved by
  ``(1 - noise_gamma) * noise``, so the target acceleration asks the network to
  undo a fraction of the corruption (gamma = 0.1 as in MGN's cloth model).
* Positions stay float64 end to end (graph features, integration); the network
  itself runs in float32 after normalisation.
"""

from __future__ import annotations

import warnings
from dataclasses import asdict, dataclass, fields, replace

import numpy as np
import torch
from scipy.spatial import cKDTree
from torch import nn

from colgnn_core.errors import InputError
from colgnn_core.geometry.tetmesh import vertex_normals
from colgnn_core.geometry.transforms import quat_to_matrix
from colgnn_core.learn.core_model import EdgeSet, EncodeProcessDecode, MultiGraph, Pooling, make_mlp
from colgnn_core.learn.graph import (MESH_EDGE_FEATURES, WORLD_EDGE_FEATURES, GraphInputs, GraphTemplate,
                                     build_graph, coarse_edges, coarse_template, mesh_edge_set)
from colgnn_core.learn.normalizer import Normalizer
from colgnn_core.sim.tip_prior import KAPPA

EDGE_SETS = {"mesh": MESH_EDGE_FEATURES, "world": WORLD_EDGE_FEATURES}


@dataclass
class ModelConfig:
    """Model hyper-parameters. Sizes come from the scene's ``[model]`` table; noise is a training setting."""

    latent: int = 128
    message_passing_steps: int = 15
    mlp_layers: int = 2
    world_radius: float = 0.01        # r_W (m)
    surface_only: bool = False
    noise_std: float = 0.0            # training noise on x_t (m)
    noise_gamma: float = 0.1          # fraction of the noise the target does NOT follow back
    order: int = 2                    # what the network gives: 2 the acceleration (MGN), 1 the velocity
                                      # x_{t+1} - x_t, 0 the displacement from rest x_{t+1} - X (quasi-static)
    rest_feature: bool = False        # node feature: displacement from the rest shape x_t - X (0 for tool nodes)
    coarse_nodes: int = 0             # clusters of a coarse level (0: none)
    coarse_steps: int = 0             # message-passing steps on the coarse level
    quasi_static: bool = False        # order 0 only: the graph is built on the settled rest, not on x_t, and every
                                      # object node also sees the tool (TOOL_FEATURES): the shape is a function of
                                      # the tool's pose and motion, so a rollout cannot drift or tear
    global_modes: int = 0             # order 0 only: K whole-object displacement modes (PCA of the training
                                      # displacements); a graph-level head reads the pooled latents and adds
                                      # sum_k c_k * mode_k to every node's output, so a press can bend the whole
                                      # object at once instead of through hop-limited messages (0: none)
    contact_depth: bool = False       # quasi_static only: every node also sees how deep the tool reaches under the
                                      # settled rest's surface, measured from the tool's side (CONTACT_FEATURES);
                                      # a sharp tool (cone, blade) between the nodes is otherwise nearly invisible
    tip_prior: bool = False           # quasi_static only: a linear-elastic physics prior (sim.tip_prior: the sharp
                                      # tool's tip carries a surface point) is added to the output and given to
                                      # every node (PRIOR_FEATURES); the network learns the remainder
    side_contact: bool = False        # tip_prior only: the cone's side also holds every face it reaches outside it
                                      # (sim.tip_prior.TipSidePrior: a pocket as wide as the cone)
    tip_kappa: float = KAPPA          # tip_prior only: the carried point stays within tip_kappa x the tip's depth
                                      # of the point where the axis leaves the rest shape (sim.tip_prior's slide
                                      # rule); checkpoints from before this option used the default
    contact_prior: bool = False       # quasi_static only: the same with sim.contact_prior (a frictionless smooth
                                      # tool holds every face it reaches on its surface)
    edge_prior: bool = False          # quasi_static only: the same with sim.edge_prior (a blade's edge carries the
                                      # rest surface above it, free to slide along the edge)
    prior_mesh: str = ""              # the prior's mesh: "" the scene's own; a resolution ("ci") solves it on the
                                      # scene's mesh there and carries it onto the graph's nodes (sim.coarse_prior;
                                      # the full banana's contact prior: 280 ms a step on a long contact, at ci 1 ms)
    prior_compliance: str = ""        # contact_prior or edge_prior only: "" exact; "modal" keeps the prior on the
                                      # scene's own mesh in real time (sim.compliance: 5-9 ms a step in contact
                                      # on the full banana, where the exact one takes 60-1,000 ms);
                                      # "modal_response" reads the response from it too (sim.prior.COMPLIANCES)
    prior_input: bool = True          # a model with a physics prior: its nodes see the prior (PRIOR_FEATURES).
                                      # False: the prior is only added to the output, so the network does not wait
                                      # for it and the stepper solves it beside the network (runtime.prior_worker)

    @property
    def prior_kind(self) -> str | None:
        """The physics prior the output is added to (a key of sim.prior.PRIORS), or None."""
        if self.tip_prior:
            return "tip_side" if self.side_contact else "tip"
        if self.edge_prior:
            return "edge"
        return "contact" if self.contact_prior else None

    @property
    def prior_options(self) -> dict:
        """Keyword arguments of sim.prior.physics_prior for this model's prior (empty: the prior's defaults)."""
        return {"kappa": float(self.tip_kappa)} if self.tip_prior and self.tip_kappa != KAPPA else {}

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "ModelConfig":
        names = {f.name for f in fields(cls)}
        unknown = set(d) - names
        if unknown:
            raise InputError(f"unknown model config keys: {', '.join(sorted(unknown))}")
        return cls(**d)

    @classmethod
    def from_scene(cls, scene, **overrides) -> "ModelConfig":
        """Take the known keys of ``scene.model`` (others, e.g. contact_tests, are not model settings)."""
        names = {f.name for f in fields(cls)}
        values = {k: v for k, v in dict(scene.model).items() if k in names}
        values.update(overrides)
        return cls.from_dict(values)


@dataclass(frozen=True, eq=False)
class Frame:
    """Inputs for one prediction t -> t+1 (torch float64, metres; ``pose_next`` numpy [7] or None)."""

    x_prev: torch.Tensor     # [N,3] object graph nodes at t-1
    x_t: torch.Tensor        # [N,3] at t
    tool_t: torch.Tensor     # [M,3] tool vertices (world) at t
    tool_next: torch.Tensor  # [M,3] at t+1
    pose_next: np.ndarray | None = None  # [7] tool pose at t+1 (SDF culling, collision losses)
    prior: torch.Tensor | None = None    # [N,3] the physics prior's displacement at t+1 (m; models with a prior)


def frame_from_sequence(template: GraphTemplate, object_positions: np.ndarray, tool_positions: np.ndarray,
                        tool_poses: np.ndarray, t: int, priors: np.ndarray | None = None) -> tuple[Frame, torch.Tensor]:
    """The transition t -> t+1 of a sequence (arrays as in :class:`colgnn_core.io.Sequence`).

    ``object_positions`` [T,N_mesh,3] holds every mesh vertex; the graph's nodes
    are picked with ``template.object_nodes``. At t = 0 the object starts at
    rest (x_{-1} = x_0). ``priors`` [T,N,3]: the physics prior along the sequence (its frame t+1 goes into the
    frame). Returns ``(frame, x_next [N,3])``, float64 tensors.
    """
    if not 0 <= t < object_positions.shape[0] - 1:
        raise ValueError(f"t={t} outside [0, {object_positions.shape[0] - 1})")
    nodes = template.object_nodes
    pos = lambda a: torch.from_numpy(np.ascontiguousarray(a, dtype=np.float64))
    x_t = pos(object_positions[t, nodes])
    x_prev = pos(object_positions[t - 1, nodes]) if t > 0 else x_t
    frame = Frame(x_prev, x_t, pos(tool_positions[t]), pos(tool_positions[t + 1]), np.asarray(tool_poses[t + 1]),
                  None if priors is None else pos(priors[t + 1]))
    return frame, pos(object_positions[t + 1, nodes])


TOOL_FEATURES = 20  # per-node tool features of a quasi-static model (see tool_features)


def tool_features(template: GraphTemplate, rest: torch.Tensor, tool_t: torch.Tensor, tool_next: torch.Tensor,
                  pose_next: np.ndarray | None, sdf: np.ndarray | None = None) -> torch.Tensor:
    """What every object node of a quasi-static model knows about the tool, whatever its hop distance [N+M,20].

    Per object node (rest position X, tool pose (p, R) at t+1, metres): ``X - p`` (3), ``R^T (X - p)`` (3, the
    node in the tool's frame), the tool's signed distance at X (1; inside the tool < 0: how deep the tool has
    pushed into the rest shape there), the tool's motion t -> t+1 (3, centroid of its vertices), its axis
    ``R e_z`` (3), X itself (3: where on the object the node is, which sets how stiff the response is), and the
    contact seen from the node: ``X - c`` (3) and the depth ``-min sdf`` (1), with c the rest node deepest in the
    tool (the nearest one when none is inside). These last four give a node many hops from the tool how deep and
    where the press is, which the local world edges cannot. Tool nodes get zeros. Without a pose (``pose_next``
    None) the tool's centroid and identity orientation stand in. ``sdf`` [N] (m): :func:`rest_sdf`, where the caller
    has it.
    """
    dtype = rest.dtype
    motion = (tool_next - tool_t).mean(0)
    if pose_next is None:
        origin, rot = tool_next.mean(0), torch.eye(3, dtype=dtype)
    else:
        pose = np.asarray(pose_next, dtype=np.float64)
        origin = torch.as_tensor(pose[:3], dtype=dtype)
        rot = torch.as_tensor(quat_to_matrix(pose[3:]), dtype=dtype)
    d = rest - origin
    if sdf is None:
        sdf = rest_sdf(template, rest, pose_next)
    sdf = torch.linalg.vector_norm(d, dim=1) if sdf is None else torch.as_tensor(sdf, dtype=dtype)
    n = rest.shape[0]
    deepest = int(torch.argmin(sdf))
    obj = torch.cat([d, d @ rot, sdf[:, None], motion.expand(n, 3), rot[:, 2].expand(n, 3), rest,
                     rest - rest[deepest], (-sdf[deepest]).expand(n, 1)], dim=1)
    return torch.cat([obj, rest.new_zeros((template.num_tool_nodes, TOOL_FEATURES))], dim=0)


def rest_sdf(template: GraphTemplate, rest: torch.Tensor, pose_next: np.ndarray | None) -> np.ndarray | None:
    """The tool's SDF [N] (m) at the rest nodes ``rest`` [N,3] for the pose ``pose_next``; None without a tool SDF or
    a pose. One evaluation serves the world edges' culling and :func:`tool_features`."""
    if template.tool_sdf is None or pose_next is None:
        return None
    return template.tool_sdf(rest.detach().cpu().numpy(), np.asarray(pose_next))


CONTACT_FEATURES = 4  # per-node tool-side penetration features of a model with contact_depth (see RestSurface)


class RestSurface:
    """The settled rest's surface, seen from the tool: how deep the tool reaches under it.

    Why: :func:`tool_features` measures the tool's SDF at the rest *nodes*. A sharp tool (the cone's tip, a blade's
    edge) pushes on face interiors between nodes, so those read a few millimetres while the tool is 2 cm deep
    (measured on ``cone_bunny``: -min sdf 2.3 mm at a 25 mm dent). Here each tool vertex is measured against the
    nearest surface node instead: its depth below that node's tangent plane.
    """

    def __init__(self, rest: np.ndarray, faces: np.ndarray):
        """``rest`` [N,3] graph-node rest positions (m), ``faces`` [F,3] outward surface triangles in graph ids."""
        rest = np.asarray(rest, dtype=np.float64)
        ids = np.unique(faces)
        self.points = rest[ids]
        self.normals = vertex_normals(rest, faces)[ids]
        self.tree = cKDTree(self.points)
        f = np.asarray(faces)
        self.edge = float(np.linalg.norm(rest[f] - rest[np.roll(f, 1, axis=1)], axis=2).mean())

    def penetration(self, tool: np.ndarray) -> tuple[float, np.ndarray]:
        """``(depth, point)``: how far the deepest of the tool's vertices [M,3] lies under the rest surface (m; < 0:
        the gap to the nearest one) and that vertex [3].

        A vertex counts as under the surface when its offset to the nearest surface node points mostly along that
        node's outward normal (the 0.7, less one mean edge for the node spacing); one beside a convex part or far
        away does not, and then the depth is minus the distance to the nearest node."""
        tool = np.asarray(tool, dtype=np.float64)
        dist, j = self.tree.query(tool)
        below = np.einsum("ij,ij->i", self.points[j] - tool, self.normals[j])
        under = below >= 0.7 * dist - self.edge
        if under.any():
            k = int(np.argmax(np.where(under, below, -np.inf)))
            return float(below[k]), tool[k]
        k = int(np.argmin(dist))
        return -float(dist[k]), tool[k]


def contact_features(surface: RestSurface, rest: torch.Tensor, tool_next: torch.Tensor,
                     num_tool_nodes: int) -> torch.Tensor:
    """[N+M, CONTACT_FEATURES]: per object node ``X - q`` (3) and the depth (1) of the tool's deepest vertex q
    under the rest surface at t+1 (:meth:`RestSurface.penetration`); tool nodes get zeros."""
    depth, point = surface.penetration(tool_next.detach().cpu().numpy())
    q = torch.as_tensor(point, dtype=rest.dtype)
    obj = torch.cat([rest - q, rest.new_full((rest.shape[0], 1), depth)], dim=1)
    return torch.cat([obj, rest.new_zeros((num_tool_nodes, CONTACT_FEATURES))], dim=0)


PRIOR_FEATURES = 4  # per-node features of a model with a physics prior: the prior's displacement (3) and its length (1)


def prior_features(prior: torch.Tensor, num_tool_nodes: int) -> torch.Tensor:
    """[N+M, PRIOR_FEATURES]: per object node the prior's displacement ``prior`` [N,3] (m) and its length; tool
    nodes get zeros."""
    obj = torch.cat([prior, torch.linalg.vector_norm(prior, dim=1, keepdim=True)], dim=1)
    return torch.cat([obj, prior.new_zeros((num_tool_nodes, PRIOR_FEATURES))], dim=0)


@dataclass
class TrainingOutputs:
    """What the losses need from one training frame (object nodes only)."""

    pred_norm: torch.Tensor        # [N,3] network output (normalised acceleration)
    target_norm: torch.Tensor      # [N,3] normalised target acceleration (noise-corrected)
    loss_mask: torch.Tensor        # [N] bool, free (non-pinned) object nodes
    latents: torch.Tensor          # [N,latent] final processor latents (KL term)
    x_t: torch.Tensor              # [N,3] input positions at t (with noise) float64
    x_next_pred: torch.Tensor      # [N,3] predicted positions at t+1, float64, differentiable
    x_next_random: torch.Tensor | None  # [N,3] positions decoded from z ~ N(0,I) (L_compact), or None
    graph: GraphInputs


class Simulator(nn.Module):
    """Learned simulator for one scene's object mesh and tool."""

    def __init__(self, template: GraphTemplate, config: ModelConfig):
        super().__init__()
        self.template = template
        self.config = config
        if config.order not in (0, 1, 2):
            raise InputError(f"model order must be 0, 1 or 2, got {config.order}")
        if (config.coarse_nodes > 0) != (config.coarse_steps > 0):
            raise InputError("coarse_nodes and coarse_steps must both be > 0 (a coarse level) or both 0")
        if config.quasi_static and config.order != 0:
            raise InputError("quasi_static needs order 0 (the output is the displacement from the settled rest)")
        if config.contact_depth and not config.quasi_static:
            raise InputError("contact_depth needs quasi_static (the depth is measured under the settled rest)")
        if sum((config.tip_prior, config.contact_prior, config.edge_prior)) > 1:
            raise InputError("tip_prior, contact_prior and edge_prior exclude each other: a model adds one physics "
                             "prior")
        if not (np.isfinite(config.tip_kappa) and config.tip_kappa >= 0):
            raise InputError(f"tip_kappa must be a finite number >= 0, got {config.tip_kappa}")
        if config.tip_kappa != KAPPA and not config.tip_prior:
            raise InputError("tip_kappa needs tip_prior (it is the tip prior's slide rule)")
        if config.side_contact and not config.tip_prior:
            raise InputError("side_contact needs tip_prior (it widens the sharp tip's pocket to the cone)")
        if config.prior_mesh and not config.prior_kind:
            raise InputError("prior_mesh needs a physics prior (contact_prior, edge_prior or tip_prior): it says "
                             "where that prior is solved")
        if config.prior_compliance and (not (config.contact_prior or config.edge_prior) or config.prior_mesh):
            raise InputError("prior_compliance needs contact_prior or edge_prior on the scene's own mesh (no "
                             "prior_mesh): it says how that prior reads the fine mesh's compliance")
        if not config.prior_input and not config.prior_kind:
            raise InputError("prior_input false needs a physics prior (contact_prior, edge_prior or tip_prior): it "
                             "says that the prior is added to the output without being a node feature")
        if config.prior_kind and not config.quasi_static:
            raise InputError(f"{config.prior_kind}_prior needs quasi_static (the prior is a displacement from the "
                             "settled rest)")
        if config.global_modes < 0 or (config.global_modes and config.order != 0):
            raise InputError("global_modes needs order 0 (the modes are displacements from the settled rest) "
                             f"and must be >= 0, got {config.global_modes} with order {config.order}")
        node_in = (template.node_feature_size + (3 if config.rest_feature else 0)
                   + (TOOL_FEATURES if config.quasi_static else 0) + (CONTACT_FEATURES if config.contact_depth else 0)
                   + (PRIOR_FEATURES if config.prior_kind and config.prior_input else 0))
        self.coarse = coarse_template(template, config.coarse_nodes) if config.coarse_nodes else None
        self.node_normalizer = Normalizer(node_in)
        edge_sets = dict(EDGE_SETS, **({"coarse": MESH_EDGE_FEATURES} if self.coarse is not None else {}))
        self.edge_normalizers = nn.ModuleDict({name: Normalizer(size) for name, size in edge_sets.items()})
        self.output_normalizer = Normalizer(3)
        if self.has_settled_rest:
            # The settled rest [N,3] (frame 0 of the training data: the object under gravity), stored with the
            # weights: the quasi-static output and the rest feature are displacements from it, not from the mesh
            # file (whose sag under gravity would otherwise dominate both).
            self.register_buffer("settled_rest", template.rest.clone())
        self.core = EncodeProcessDecode(node_in, EDGE_SETS, 3, latent=config.latent,
                                        message_passing_steps=config.message_passing_steps,
                                        mlp_layers=config.mlp_layers, coarse_edge_in=MESH_EDGE_FEATURES,
                                        coarse_steps=config.coarse_steps)
        self.global_head = None
        if config.global_modes:
            # [K,N,3] metres per unit coefficient (set from the training data by set_global_modes). The head sees
            # the mean and the max of the object latents; it is one small MLP per step, whatever N is.
            self.register_buffer("global_modes",
                                 torch.zeros((config.global_modes, template.rest.shape[0], 3), dtype=torch.float64))
            self.global_head = make_mlp(2 * config.latent, 4 * config.latent, config.global_modes,
                                        max(2, config.mlp_layers), layer_norm=False)

    # -- pieces -----------------------------------------------------------------------------------------------
    @property
    def has_settled_rest(self) -> bool:
        return self.config.order == 0 or self.config.rest_feature

    def set_settled_rest(self, rest_graph) -> None:
        """Set the settled rest [N,3] (m) that order-0 outputs and the rest feature refer to."""
        rest = torch.as_tensor(rest_graph, dtype=torch.float64)
        if rest.shape != self.settled_rest.shape:
            raise InputError(f"settled rest must be {tuple(self.settled_rest.shape)}, got {tuple(rest.shape)}")
        self.settled_rest.copy_(rest)

    def set_global_modes(self, displacements) -> float:
        """Fit the K global modes to training displacements from the settled rest [F,N,3] (m, F frames).

        The modes are the leading right singular vectors of the [F,3N] displacement matrix (not centred: rest is
        the natural origin), each scaled by its RMS coefficient over the frames, so the head's outputs are O(1).
        Returns the fraction of the displacements' squared norm that the K modes keep."""
        u = torch.as_tensor(displacements, dtype=torch.float64)
        k, n = self.config.global_modes, self.global_modes.shape[1]
        if u.ndim != 3 or u.shape[1:] != (n, 3):
            raise InputError(f"global-mode displacements must be [F,{n},3], got {tuple(u.shape)}")
        flat = u.reshape(u.shape[0], -1)
        _, s, vt = torch.linalg.svd(flat, full_matrices=False)
        kept = min(k, s.shape[0])
        modes = torch.zeros_like(self.global_modes)
        modes[:kept] = (vt[:kept] * (s[:kept, None] / max(u.shape[0], 1) ** 0.5)).reshape(kept, n, 3)
        self.global_modes.copy_(modes)
        total = float((s ** 2).sum())
        return float((s[:kept] ** 2).sum()) / total if total > 0 else 1.0

    def rest_surface(self) -> RestSurface:
        """The settled rest's :class:`RestSurface`, rebuilt whenever the settled rest changed (loading a checkpoint
        replaces the buffer without calling :meth:`set_settled_rest`)."""
        cached = self.__dict__.get("_rest_surface")
        if cached is None or not torch.equal(cached[0], self.settled_rest):
            rest = self.settled_rest.detach().clone()
            cached = (rest, RestSurface(rest.numpy(), self.template.surface_faces))
            self.__dict__["_rest_surface"] = cached
        return cached[1]

    def build_graph(self, frame: Frame) -> GraphInputs:
        if self.config.quasi_static:
            return self._quasi_static_graph(frame)
        g = build_graph(self.template, frame.x_t, frame.x_prev, frame.tool_t, frame.tool_next, frame.pose_next)
        if self.config.rest_feature:
            rest = torch.cat([frame.x_t - self.settled_rest.to(frame.x_t.dtype),
                              frame.x_t.new_zeros((self.template.num_tool_nodes, 3))], dim=0)
            g = replace(g, node_features=torch.cat([g.node_features[:, :3], rest, g.node_features[:, 3:]], dim=1))
        if self.coarse is not None:
            g = replace(g, coarse=coarse_edges(self.coarse, frame.x_t))
        return g

    def static_edges(self) -> dict[str, EdgeSet] | None:
        """The normalised, encoded edge sets of a quasi-static graph that do not change from step to step: the mesh
        edges (and the coarse ones), which lie on the settled rest. For inference (no gradient) only; None
        otherwise.

        Computed once, then reused while the settled rest, the edge normalisers and those encoders are the same
        tensors at the same in-place versions (the key), so a training step, accumulated statistics or loaded
        weights are never served a stale entry. Saves the mesh edges' features, normalisation and encoder MLP on
        every step (a few ms at full resolution)."""
        if not self.config.quasi_static or torch.is_grad_enabled():
            return None
        tensors = [self.settled_rest, *self.edge_normalizers.buffers(), *self.core.edge_encoders["mesh"].parameters()]
        if self.core.coarse is not None:
            tensors += list(self.core.coarse.edge_encoder.parameters())
        key = tuple((id(t), t._version) for t in tensors)
        cached = self.__dict__.get("_static_edges")
        if cached is not None and cached[0] == key:
            return cached[1]
        rest = self.settled_rest
        mesh = mesh_edge_set(self.template, rest)
        edges = {"mesh": replace(mesh, features=self.core.encode_edges(
            "mesh", self.edge_normalizers["mesh"](mesh.features).float()))}
        if self.coarse is not None:
            coarse = coarse_edges(self.coarse, rest)
            edges["coarse"] = replace(coarse, features=self.core.coarse.encode_edges(
                self.edge_normalizers["coarse"](coarse.features).float()))
        self.__dict__["_static_edges"] = (key, edges)
        return edges

    def _quasi_static_graph(self, frame: Frame) -> GraphInputs:
        """The graph on the settled rest X (velocity 0, world edges from X to the tool at t+1), with
        :func:`tool_features` appended to the node features. x_t and x_{t-1} are not inputs. At inference the
        mesh and coarse edge sets come encoded from :meth:`static_edges`."""
        rest = self.settled_rest.to(frame.x_t.dtype)
        static = self.static_edges()
        sdf = rest_sdf(self.template, rest, frame.pose_next)
        g = build_graph(self.template, rest, rest, frame.tool_t, frame.tool_next, frame.pose_next,
                        mesh=None if static is None else static["mesh"], node_sdf=sdf)
        tool = tool_features(self.template, rest, frame.tool_t, frame.tool_next, frame.pose_next, sdf)
        feats = torch.cat([g.node_features, tool], dim=1)
        if self.config.contact_depth:
            feats = torch.cat([feats, contact_features(self.rest_surface(), rest, frame.tool_next,
                                                       self.template.num_tool_nodes)], dim=1)
        if self.config.prior_kind and self.config.prior_input:
            feats = torch.cat([feats, prior_features(self._required_prior(frame.prior).to(rest.dtype),
                                                     self.template.num_tool_nodes)], dim=1)
        if self.coarse is not None:
            g = replace(g, coarse=coarse_edges(self.coarse, rest) if static is None else static["coarse"])
        return replace(g, node_features=feats, encoded=() if static is None else tuple(static))

    @staticmethod
    def _required_prior(prior: torch.Tensor | None) -> torch.Tensor:
        """``prior`` [N,3]; InputError when a model with a physics prior is not given one."""
        if prior is None:
            raise InputError("this model adds a physics prior: the frame must carry it (Frame.prior, [N,3] m)")
        return prior

    def normalise_graph(self, g: GraphInputs, accumulate: bool = False) -> tuple[MultiGraph, Pooling | None]:
        """Normalise raw features (optionally accumulating statistics) and cast to the network's float32.

        Returns the fine graph and, for a model with a coarse level, its pooling (normalised coarse edges). Edge sets
        that ``g`` holds encoded already (``g.encoded``) pass unchanged."""
        if accumulate and g.encoded:
            raise ValueError(f"cannot accumulate statistics over encoded edge sets {g.encoded}")
        nodes = self.node_normalizer(g.node_features, accumulate).float()
        edges = {}
        for name, es in (("mesh", g.mesh), ("world", g.world)):
            if name not in g.encoded:
                es = EdgeSet(self.edge_normalizers[name](es.features, accumulate).float(), es.senders, es.receivers)
            edges[name] = es
        pooling = None
        if self.coarse is not None:
            coarse, encoded = g.coarse, "coarse" in g.encoded
            if not encoded:
                coarse = EdgeSet(self.edge_normalizers["coarse"](coarse.features, accumulate).float(),
                                 coarse.senders, coarse.receivers)
            pooling = Pooling(self.coarse.assign, self.coarse.inverse_counts.float(), coarse, encoded)
        return MultiGraph(nodes, edges), pooling

    def network(self, g: GraphInputs, accumulate: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
        """Normalised output (acceleration or velocity) [N,3] and final processor latents [N,latent] of the
        object nodes."""
        graph, pooling = self.normalise_graph(g, accumulate)
        modes = None
        if self.global_head is not None:  # the modes in output units: the output normalizer divides by its std
            modes = (self.global_modes / self.output_normalizer.std()).float()
        return self.core_outputs(graph, g.num_object_nodes, pooling, modes, g.encoded)

    def core_outputs(self, graph: MultiGraph, num_object_nodes: int, pooling: Pooling | None = None,
                     modes: torch.Tensor | None = None, encoded: tuple[str, ...] = ()
                     ) -> tuple[torch.Tensor, torch.Tensor]:
        """Encode-process-decode a normalised graph: (outputs, final latents) of the object nodes.

        ``modes`` [K,N,3] (normalised output units, float32): the global modes, weighted by the head's
        coefficients and added to every node's output. ``encoded``: edge sets that hold latents already."""
        latent_graph = self.core.process(self.core.encode(graph, encoded), pooling)
        latents = latent_graph.node_features[:num_object_nodes]  # tool nodes need no decoding
        out = self.core.decode(latents)
        if modes is not None:
            coefficients = self.global_head(torch.cat([latents.mean(0), latents.amax(0)]))
            out = out + torch.einsum("k,knd->nd", coefficients, modes)
        return out, latents

    def integrate(self, pred_norm: torch.Tensor, x_t: torch.Tensor, x_prev: torch.Tensor,
                  prior: torch.Tensor | None = None) -> torch.Tensor:
        """De-normalise the output and step: ``x_{t+1} = 2 x_t - x_{t-1} + a`` (order 2), ``x_t + v`` (order 1) or
        ``X + u`` (order 0, X the settled rest, plus the ``prior`` [N,3] for a model with a physics prior); pinned nodes
        keep x_t."""
        out = self.output_normalizer.inverse(pred_norm.to(x_t.dtype))
        x_next = self._base(x_t, x_prev, prior) + out
        if self.template.num_node_types == 3:
            x_next = torch.where(self.template.pinned[:, None], x_t, x_next)
        return x_next

    def _base(self, x_t: torch.Tensor, x_prev: torch.Tensor, prior: torch.Tensor | None = None) -> torch.Tensor:
        """What the network's output is added to: 2 x_t - x_{t-1}, x_t or the rest X (order 2, 1, 0), the rest
        plus the prior for a model with a physics prior."""
        if self.config.order == 0:
            rest = self.settled_rest.to(x_t.dtype)
            if self.config.prior_kind:
                return rest + self._required_prior(prior).to(x_t.dtype)
            return rest
        return x_t if self.config.order == 1 else 2.0 * x_t - x_prev

    def decode_latent(self, z: torch.Tensor, x_t: torch.Tensor, x_prev: torch.Tensor,
                      prior: torch.Tensor | None = None) -> torch.Tensor:
        """Positions at t+1 decoded from latents ``z`` [N,latent] instead of the processor's (L_compact)."""
        return self.integrate(self.core.decode(z), x_t, x_prev, prior)

    def compile_network(self) -> None:
        """Run :meth:`core_outputs` through ``torch.compile`` (inductor: fused C++ kernels, ~1.8x faster on a CPU).

        For inference: the first call per grad mode and world-edge count class (0, or 2+) compiles
        (seconds; torch caches the result on disk for later processes). If compiling fails (e.g. no
        C++ compiler), a warning is issued and the eager network is used from then on.
        """
        if not isinstance(self.__dict__.get("core_outputs"), _CompiledOrEager):
            self.core_outputs = _CompiledOrEager(self.core_outputs)

    # -- entry points -----------------------------------------------------------------------------------------
    def predict(self, frame: Frame) -> torch.Tensor:
        """Object graph-node positions at t+1 [N,3] (float64). Statistics are not updated."""
        pred_norm, _ = self.network(self.build_graph(frame))
        return self.integrate(pred_norm, frame.x_t, frame.x_prev, frame.prior)

    def training_outputs(self, frame: Frame, x_next: torch.Tensor, generator: torch.Generator | None = None,
                         noise: bool = True, accumulate: bool = True, random_latent: bool = False) -> TrainingOutputs:
        """Outputs for the losses on one ground-truth transition (x_prev, x_t) -> ``x_next`` [N,3].

        ``generator`` drives the training noise and the random latents (a fixed seed gives the same run).
        """
        free = ~self.template.pinned
        x_t = frame.x_t
        target_pos = x_next
        if noise and self.config.noise_std > 0 and not self.config.quasi_static:  # x_t is no input there
            eps = torch.randn(x_t.shape, generator=generator, dtype=x_t.dtype) * self.config.noise_std
            eps = eps * free[:, None].to(x_t.dtype)
            x_t = x_t + eps
            target_pos = x_next + (1.0 - self.config.noise_gamma) * eps
        noisy = replace(frame, x_t=x_t)
        g = self.build_graph(noisy)
        pred_norm, latents = self.network(g, accumulate=accumulate)
        target_accel = target_pos - self._base(x_t, frame.x_prev, frame.prior)
        if accumulate:
            self.output_normalizer.accumulate(target_accel[free])
        target_norm = self.output_normalizer(target_accel).float()
        x_next_pred = self.integrate(pred_norm, x_t, frame.x_prev, frame.prior)
        x_next_random = None
        if random_latent:
            z = torch.randn(latents.shape, generator=generator, dtype=latents.dtype)
            x_next_random = self.decode_latent(z, x_t, frame.x_prev, frame.prior)
        return TrainingOutputs(pred_norm, target_norm, free, latents, x_t, x_next_pred, x_next_random, g)

    def forward(self, frame: Frame, x_next: torch.Tensor | None = None, **kwargs):
        """``predict(frame)``, or ``training_outputs(frame, x_next, **kwargs)`` when a target is given.

        One entry point so that a DistributedDataParallel wrapper sees every training computation.
        """
        if x_next is None:
            return self.predict(frame)
        return self.training_outputs(frame, x_next, **kwargs)


COMPILED_VARIANTS_LIMIT = 256  # compiled variants of the network per process (3 world-edge classes x 1-2 thread counts
# per compiled Simulator)


class _CompiledOrEager:
    """A compiled function that falls back, once and for good, to its eager original on any failure."""

    def __init__(self, fn) -> None:
        import torch._dynamo  # lazy: the compiler stack loads only when a network is compiled

        # Every Simulator's bound core_outputs shares one code object, and dynamo caps the compiled variants of a
        # code object (8 by default; each network needs 3 a thread count): past it, later networks in the same
        # process silently ran eagerly (~1.8x slower), which inflated timings of processes that compile many models.
        torch._dynamo.config.recompile_limit = max(torch._dynamo.config.recompile_limit, COMPILED_VARIANTS_LIMIT)
        torch._dynamo.config.accumulated_recompile_limit = max(
            torch._dynamo.config.accumulated_recompile_limit, 4 * COMPILED_VARIANTS_LIMIT)
        self.eager = fn
        self.compiled = torch.compile(fn, dynamic=True)
        self.failure: Exception | None = None

    def __call__(self, *args, **kwargs):
        if self.failure is None:
            try:
                return self.compiled(*args, **kwargs)
            except Exception as exc:  # noqa: BLE001 - any compiler failure: keep simulating, eagerly
                self.failure = exc
                warnings.warn(f"torch.compile failed, running the network eagerly: {type(exc).__name__}: {exc}",
                              RuntimeWarning, stacklevel=2)
        return self.eager(*args, **kwargs)
