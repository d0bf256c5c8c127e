"""Tests of ``gateway/kinds/slc_ascii/``: one test module per module, by its name (``test_<module>.py``)."""
