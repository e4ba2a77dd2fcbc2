"""Helpers shared by the test modules (imported as ``tests.helpers.<module>``); the pytest fixtures are in
``tests/conftest.py``.

* :mod:`.learn_meshes`: small real meshes and a sphere tool for the learn/ tests;
* :mod:`.train_data`: tiny real ground truth and a tiny trained model, built once per session;
* :mod:`.sim_scenes`: a tet box and a sphere-tool scene for the simulator tests, and an ipctk sequence check;
* :mod:`.collision_cases`: random and adversarial CCD pairs, exact arithmetic;
* :mod:`.correction_cases`: untrained networks with controlled output and the ipctk oracle of the correction;
* :mod:`.ros`: helpers of the ROS tests (isolated domain, spinning, child processes).
"""
