"""The colgnn test suite (``make test``): shared fixtures in ``conftest.py``, shared helpers in ``tests.helpers``."""
