"""The learned simulator.

* :mod:`.core_model`: generic encode-process-decode graph network (no domain knowledge).
* :mod:`.graph`: the object-tool graph (mesh edges, tool nodes, world edges, features).
* :mod:`.normalizer`: online feature normalizer.
* :mod:`.model`: ``Simulator`` (graph -> GNN -> acceleration -> x_{t+1}), ``ModelConfig``, ``Frame``.
* :mod:`.losses`: L_q, the latent KL term, L_ccd and ξ_Random.
* :mod:`.checkpoint`: one-file checkpoints bound to a scene, mesh and dt.
* :mod:`.data`: dataset folders as checked (sequence, t) transitions in a seeded order.
* :mod:`.train`: the training loop (variants full, baseline, no-compact; data-parallel under torchrun).
* :mod:`.subspace`: the PCA + MLP baseline (Holden et al. 2019).
"""
