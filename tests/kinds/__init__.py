"""Tests of ``gateway/kinds/``: one test module per module, by its name (``test_<module>.py``)."""
