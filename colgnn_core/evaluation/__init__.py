"""The evaluation: every number the project reports, measured by the runtime's own code on the same data.

* :mod:`.measure`: the shared statistics and data selections (median/p95, RMSE fraction, collision aggregates,
  test files, family trajectories);
* :mod:`.speed` (``colgnn bench``): the Predictor against the IPC solver on the same poses, in one run;
* :mod:`.collision_speed` (``colgnn bench --collision``): collision detection against ipctk's CCD;
* :mod:`.solver_speed`: the IPC solver's cost per step (generation-time estimates);
* :mod:`.stability` (``colgnn bench --stability``): a long random rollout, hard cases;
* :mod:`.accuracy` (``colgnn evaluate``): rollout RMSE and collision metrics on test sequences;
* :mod:`.frontier` (``colgnn evaluate --frontier``): speed against error of several models and the solver;
* :mod:`.report` (``colgnn evaluate --all``, ``make results``): all of the above for every scene, as typed
  :mod:`.report_data` written by :mod:`.report_markdown` into docs/RESULTS.md;
* :mod:`.render` (``colgnn render``): pictures of sequences and rollouts.
"""
