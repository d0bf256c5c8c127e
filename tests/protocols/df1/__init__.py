"""Tests of ``gateway/protocols/df1/``: one test module per module, by its name (``test_<module>.py``)."""
