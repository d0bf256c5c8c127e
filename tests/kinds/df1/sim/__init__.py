"""Tests of ``gateway/kinds/df1/sim/``: one test module per module, by its name (``test_<module>.py``)."""
