"""Tests of ``gateway/protocols/df1/full_duplex/``: one test module per module, by its name (``test_<module>.py``)."""
