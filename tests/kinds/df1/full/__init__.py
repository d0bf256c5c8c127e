"""Tests of ``gateway/kinds/df1/full/``: one test module per module, by its name (``test_<module>.py``)."""
