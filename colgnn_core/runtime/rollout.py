"""``colgnn rollout``: drive a trained model with a tool trajectory and record the predicted sequence.

``correction=False`` rolls the network alone out (:class:`~colgnn_core.runtime.stepper.RawStepper`);
``correction=True`` goes through the real-time :class:`~colgnn_core.runtime.predictor.Predictor` (network step +
collision-aware correction), behind the same loop (:func:`~colgnn_core.runtime.stepper.run_stepper`).

Nothing is clamped unless asked (``limits='data'`` or explicit ``max_displacement`` / ``max_deviation``): the
number of capped nodes per frame is recorded in ``extra['clamped_nodes']``.
"""

from __future__ import annotations

import numpy as np

from colgnn_core.errors import InputError
from colgnn_core.io import Sequence
from colgnn_core.runtime.models import model_and_scene, output_limits, settled_rest
from colgnn_core.runtime.predictor import Predictor
from colgnn_core.runtime.stepper import RawStepper, run_stepper


def rollout(checkpoint_or_scene, poses: np.ndarray, correction: bool = False, *, scene=None,
            initial_positions: np.ndarray | None = None, limits: str = "none", max_displacement: float | None = None,
            max_deviation: float | None = None, progress: bool = False,
            predictor_options: dict | None = None) -> Sequence:
    """Roll a model out over a tool trajectory.

    Args:
        checkpoint_or_scene: checkpoint path, :class:`LoadedCheckpoint`, or scene name (its shipped model).
        poses: [T,7] tool poses, one per model step, frame 0 = the initial state (checked against the
            scene workspace: InputError naming the row).
        correction: collision-aware correction: the rollout goes through the Predictor
            (large pose jumps subdivided; per-frame counts and stage timings added to ``extra``).
        scene: the Scene (default: the one the checkpoint names, at its resolution).
        initial_positions: [N_mesh,3] object vertices at frame 0 (default: the model's settled rest,
            :func:`colgnn_core.runtime.models.settled_rest`, the state the ground truth starts from).
        limits: 'none' (the raw network, nothing capped) or 'data': caps derived from the training data the
            checkpoint records (:func:`colgnn_core.runtime.models.output_limits`).
        max_displacement: explicit cap (m) on any node's displacement per step (overrides ``limits``).
        max_deviation: explicit cap (m) on any node's distance from its rest position (overrides ``limits``).
            Capped node counts per frame go to ``extra['clamped_nodes']``.
        progress: tqdm bar.
        predictor_options: keyword arguments for the Predictor (correction=True only), e.g. max_substeps.

    Returns:
        A contract :class:`Sequence` with every mesh vertex (interior ones interpolated when the model is
        surface-only), the tool's surface vertices per frame, ``extra['step_ms']`` [T] (model step wall
        time in ms, 0 for frame 0) and ``extra['clamped_nodes']`` [T].
    """
    loaded, scene = model_and_scene(checkpoint_or_scene, scene)
    poses = scene.check_poses(np.asarray(poses, dtype=np.float64))
    if poses is None or len(poses) < 1:
        raise InputError("poses must have at least one row (frame 0)")
    max_displacement, max_deviation = output_limits(loaded, limits, max_displacement, max_deviation)
    rest = settled_rest(loaded, scene)
    if initial_positions is None:
        initial_positions = rest
    if correction:
        stepper = Predictor(loaded, scene, correction=True, threads=None, max_displacement=max_displacement,
                            max_deviation=max_deviation, **(predictor_options or {})).stepper()
        seq = run_stepper(stepper, scene, poses, initial_positions, progress)
        seq.extra.update(stepper.extra())
        return seq
    stepper = RawStepper(loaded.simulator, scene, max_displacement, max_deviation, rest_mesh=rest)
    return run_stepper(stepper, scene, poses, initial_positions, progress)
