"""Tests of ``gateway/modbus/``: one test module per module, by its name (``test_<module>.py``)."""
