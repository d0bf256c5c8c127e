"""Tests of ``gateway/kinds/df1/half/``: one test module per module, by its name (``test_<module>.py``)."""
