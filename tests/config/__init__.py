"""Tests of ``gateway/config/``: one test module per module, by its name (``test_<module>.py``)."""
