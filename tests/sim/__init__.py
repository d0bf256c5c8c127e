"""Tests of ``gateway/sim/``: one test module per module, by its name (``test_<module>.py``)."""
