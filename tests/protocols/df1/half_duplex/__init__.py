"""Tests of ``gateway/protocols/df1/half_duplex/``: one test module per module, by its name (``test_<module>.py``)."""
