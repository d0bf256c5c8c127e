"""Tests of ``gateway/sparkplug/``: one test module per module, by its name (``test_<module>.py``)."""
