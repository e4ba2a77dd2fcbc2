"""The runtime: from a tool pose to a safe deformed mesh, in real time.

* :mod:`.models`: the shipped models (``assets/models``), loading a checkpoint or a scene's shipped model, and
  the output caps derived from the training data;
* :mod:`.stepper`: :class:`~.stepper.RawStepper` (one network step, its state as one
  :class:`~.stepper.StepperState`) and the rollout loop :func:`~.stepper.run_stepper`;
* :mod:`.predictor`: :class:`~.predictor.Predictor`, network step + collision-aware correction, the one stepping
  API behind ``colgnn rollout``, ``colgnn bench``, the evaluation and the ROS node;
* :mod:`.rollout`: :func:`~.rollout.rollout`, a model driven over a tool trajectory (raw or corrected).
"""
