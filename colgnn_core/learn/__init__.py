"""The learned simulator.

* :mod:`.core_model`: generic encode-process-decode graph network (no domain knowledge).
* :mod:`.graph`: the object-tool graph (mesh edges, tool nodes, world edges, features).
* :mod:`.normalizer`: online feature normalizer.
* :mod:`.model`: ``Simulator`` (graph -> GNN -> acceleration -> x_{t+1}), ``ModelConfig``, ``Frame``.
* :mod:`.losses`: L_q and the latent KL term.
* :mod:`.checkpoint`: one-file checkpoints bound to a scene, mesh and dt.
"""
