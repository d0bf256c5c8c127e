"""Tests of ``gateway/protocols/``: one test module per module, by its name (``test_<module>.py``)."""
