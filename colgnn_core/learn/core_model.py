"""Generic encode-process-decode graph network (MeshGraphNets-style).

Nothing here knows about tools, meshes or physics: it maps a multigraph (node
features plus several named edge sets) to per-node outputs. The domain model in
:mod:`colgnn_core.learn.model` builds the graph and interprets the outputs.

Architecture (Pfaff et al. 2021, "Learning Mesh-Based Simulation with Graph
Networks"; the collision-aware GNN paper uses the same):

* encoder: one MLP for the nodes and one per edge set, each ending in LayerNorm;
* processor: ``message_passing_steps`` GraphNet blocks with *separate* weights.
  Each block updates every edge set with its own edge MLP on
  ``[h_sender, h_receiver, e]``, sums the new edge latents onto their receivers
  (one sum per edge set), updates the nodes with an MLP on
  ``[h, sum_mesh, sum_world, ...]``, and adds residuals to nodes and edges;
* decoder: an MLP without LayerNorm from the final node latents to the output.

Every MLP has ``mlp_layers`` hidden layers of width ``latent`` with ReLU.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import torch
from torch import nn


@dataclass(frozen=True, eq=False)
class EdgeSet:
    """One set of directed edges. ``features`` [E,F]; ``senders``/``receivers`` [E] int64 node ids."""

    features: torch.Tensor
    senders: torch.Tensor
    receivers: torch.Tensor


@dataclass(frozen=True, eq=False)
class MultiGraph:
    """Node features [N,F] and named edge sets (the names fix which edge MLP is used)."""

    node_features: torch.Tensor
    edge_sets: dict[str, EdgeSet]


def make_mlp(in_size: int, latent: int, out_size: int, layers: int, layer_norm: bool = True) -> nn.Sequential:
    """``layers`` hidden Linear+ReLU layers of width ``latent``, a final Linear to ``out_size``, optional LayerNorm."""
    modules: list[nn.Module] = []
    width = in_size
    for _ in range(layers):
        modules += [nn.Linear(width, latent), nn.ReLU()]
        width = latent
    modules.append(nn.Linear(width, out_size))
    if layer_norm:
        modules.append(nn.LayerNorm(out_size))
    return nn.Sequential(*modules)


def sum_to_receivers(messages: torch.Tensor, receivers: torch.Tensor, num_nodes: int) -> torch.Tensor:
    """Sum edge messages [E,D] onto their receiver nodes -> [num_nodes,D]; zero edges give zeros."""
    out = messages.new_zeros((num_nodes, messages.shape[1]))
    return out.index_add_(0, receivers, messages)


def edge_mlp_input(first: nn.Linear, h: torch.Tensor, es: EdgeSet) -> torch.Tensor:
    """The first layer of an edge MLP on ``[h_sender, h_receiver, e]`` without building that [E,3D] block.

    ``W [h_s, h_r, e] + b = (h W_s^T)[senders] + (h W_r^T)[receivers] + e W_e^T + b``: the node terms are
    projected once per node ([N,D]) and gathered per edge, which saves two thirds of the edge-level multiply and
    the concatenation. Same weights and the same function as the concatenated form (up to float rounding).
    """
    d = h.shape[1]
    w = first.weight                                         # [out, 2D + F_e]
    node_proj = h @ torch.cat([w[:, :d], w[:, d:2 * d]], dim=0).T   # [N, 2*out]: sender and receiver parts
    out = w.shape[0]
    x = torch.addmm(first.bias, es.features, w[:, 2 * d:].T)
    return x + node_proj[es.senders, :out] + node_proj[es.receivers, out:]


class GraphNetBlock(nn.Module):
    """One message-passing step over several edge sets, with residual connections."""

    def __init__(self, latent: int, mlp_layers: int, edge_set_names: tuple[str, ...]):
        super().__init__()
        self.edge_set_names = tuple(edge_set_names)
        # The first Linear of each edge MLP acts on [h_s, h_r, e] (see edge_mlp_input).
        self.edge_mlps = nn.ModuleDict({n: make_mlp(3 * latent, latent, latent,
                                                    mlp_layers) for n in self.edge_set_names})
        self.node_mlp = make_mlp((1 + len(self.edge_set_names)) * latent, latent, latent, mlp_layers)

    def forward(self, graph: MultiGraph) -> MultiGraph:
        h = graph.node_features
        n = h.shape[0]
        new_edges: dict[str, EdgeSet] = {}
        aggregated = [h]
        for name in self.edge_set_names:
            es = graph.edge_sets[name]
            mlp = self.edge_mlps[name]
            e_new = mlp[1:](edge_mlp_input(mlp[0], h, es))
            aggregated.append(sum_to_receivers(e_new, es.receivers, n))
            new_edges[name] = replace(es, features=es.features + e_new)  # residual on edges
        h_new = h + self.node_mlp(torch.cat(aggregated, dim=-1))  # residual on nodes
        return MultiGraph(h_new, new_edges)


@dataclass(frozen=True, eq=False)
class Pooling:
    """A coarse level for :class:`EncodeProcessDecode`: clusters of the first ``assign.shape[0]`` fine nodes.

    ``assign`` [P] int64 cluster (coarse node) of each pooled fine node; ``inverse_counts`` [K,1] float32 one over
    the cluster sizes (for the mean); ``edges`` the coarse edge set: raw features, encoded by the network, or with
    ``encoded`` its latents already (:meth:`CoarseLevel.encode_edges`; a graph whose coarse edges never change).
    """

    assign: torch.Tensor
    inverse_counts: torch.Tensor
    edges: EdgeSet
    encoded: bool = False

    @property
    def num_coarse(self) -> int:
        return int(self.inverse_counts.shape[0])


class CoarseLevel(nn.Module):
    """Pool fine latents to cluster means, run ``steps`` GraphNet blocks on the coarse graph, add the result back.

    It lets information cross the whole object in a few cheap steps: the coarse graph has far fewer nodes and
    edges than the fine one (the long-range part of multiscale MeshGraphNets / BSMS-GNN).
    """

    def __init__(self, edge_in: int, latent: int, steps: int, mlp_layers: int):
        super().__init__()
        self.edge_encoder = make_mlp(edge_in, latent, latent, mlp_layers)
        self.down = make_mlp(latent, latent, latent, mlp_layers)
        self.blocks = nn.ModuleList(GraphNetBlock(latent, mlp_layers, ("coarse",)) for _ in range(steps))
        self.up = make_mlp(latent, latent, latent, mlp_layers, layer_norm=False)

    def encode_edges(self, features: torch.Tensor) -> torch.Tensor:
        """Raw coarse edge features [Ec,F] -> latents [Ec,D]."""
        return self.edge_encoder(features)

    def forward(self, h: torch.Tensor, pooling: Pooling) -> torch.Tensor:
        """Fine node latents [N,D] -> updated fine latents [N,D] (nodes past the pooled ones unchanged)."""
        p = pooling.assign.shape[0]
        pooled = h.new_zeros((pooling.num_coarse, h.shape[1])).index_add_(0, pooling.assign, h[:p])
        edges = pooling.edges if pooling.encoded else replace(pooling.edges,
                                                              features=self.encode_edges(pooling.edges.features))
        coarse = MultiGraph(self.down(pooled * pooling.inverse_counts), {"coarse": edges})
        for block in self.blocks:
            coarse = block(coarse)
        back = self.up(coarse.node_features)[pooling.assign]
        return torch.cat([h[:p] + back, h[p:]], dim=0)


class EncodeProcessDecode(nn.Module):
    """Encoder, ``message_passing_steps`` GraphNet blocks, decoder.

    Args:
        node_in: node feature size.
        edge_in: edge feature size per edge set name (the order is kept).
        out_size: per-node output size.
        latent: latent width.
        message_passing_steps: number of processor blocks (separate weights each).
        mlp_layers: hidden layers per MLP.
    """

    def __init__(self, node_in: int, edge_in: dict[str, int], out_size: int, latent: int = 128,
                 message_passing_steps: int = 15, mlp_layers: int = 2, coarse_edge_in: int = 0,
                 coarse_steps: int = 0):
        super().__init__()
        if latent < 1 or message_passing_steps < 0 or mlp_layers < 0 or coarse_steps < 0:
            raise ValueError(f"bad sizes: latent={latent}, steps={message_passing_steps}, mlp_layers={mlp_layers}, "
                             f"coarse_steps={coarse_steps}")
        self.edge_set_names = tuple(edge_in)
        self.latent = latent
        self.node_encoder = make_mlp(node_in, latent, latent, mlp_layers)
        self.edge_encoders = nn.ModuleDict({n: make_mlp(f, latent, latent, mlp_layers) for n, f in edge_in.items()})
        self.processor = nn.ModuleList(
            GraphNetBlock(latent, mlp_layers, self.edge_set_names) for _ in range(message_passing_steps))
        # With a coarse level, it runs after the first half of the fine blocks (rounded up): the fine blocks before
        # it bring the tool's world edges into the node latents, those after it spread the result locally.
        self.coarse = CoarseLevel(coarse_edge_in, latent, coarse_steps, mlp_layers) if coarse_steps else None
        self.coarse_after = (message_passing_steps + 1) // 2
        self.decoder = make_mlp(latent, latent, out_size, mlp_layers, layer_norm=False)

    def encode(self, graph: MultiGraph, encoded: tuple[str, ...] = ()) -> MultiGraph:
        """Raw (normalised) features -> latent graph. The edge sets named in ``encoded`` hold latents already
        (:meth:`encode_edges`) and pass unchanged: a graph part that is the same every step is encoded once."""
        missing = set(self.edge_set_names) - set(graph.edge_sets)
        if missing:
            raise ValueError(f"graph lacks edge sets {sorted(missing)}")
        edges = {n: graph.edge_sets[n] if n in encoded else
                 replace(graph.edge_sets[n], features=self.encode_edges(n, graph.edge_sets[n].features))
                 for n in self.edge_set_names}
        return MultiGraph(self.node_encoder(graph.node_features), edges)

    def encode_edges(self, name: str, features: torch.Tensor) -> torch.Tensor:
        """Raw (normalised) features [E,F] of edge set ``name`` -> latents [E,latent]."""
        return self.edge_encoders[name](features)

    def process(self, latent_graph: MultiGraph, pooling: Pooling | None = None) -> MultiGraph:
        """Apply the message-passing blocks in order (and the coarse level, given its ``pooling``)."""
        for i, block in enumerate(self.processor):
            if i == self.coarse_after and self.coarse is not None:
                latent_graph = replace(latent_graph, node_features=self.coarse(latent_graph.node_features, pooling))
            latent_graph = block(latent_graph)
        if self.coarse is not None and self.coarse_after >= len(self.processor):
            latent_graph = replace(latent_graph, node_features=self.coarse(latent_graph.node_features, pooling))
        return latent_graph

    def decode(self, node_latents: torch.Tensor) -> torch.Tensor:
        """Node latents [N,latent] (processor output, or random z for L_compact) -> outputs [N,out]."""
        return self.decoder(node_latents)

    def forward(self, graph: MultiGraph, return_latents: bool = False, pooling: Pooling | None = None):
        """Outputs [N,out]; with ``return_latents`` also the final processor node latents [N,latent]."""
        latents = self.process(self.encode(graph), pooling).node_features
        out = self.decode(latents)
        return (out, latents) if return_latents else out
