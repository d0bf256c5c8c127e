"""The DF1 kind's half-duplex master role: the stations of one multi-drop line (``duplex = "half"``).

What this package owns:

* :mod:`.driver` - the line owner: one port, the master core
  (:mod:`gateway.protocols.df1.half_duplex`) fed every byte, RTS driven, one handle per station;
* :mod:`.receive` - a station's register table (the words its MSG instructions write to the
  gateway) served as Modbus registers of its own unit.

The units that poll each station, the plan, config model, CLI commands and simulators are shared
by every role of the kind and stay in :mod:`gateway.kinds.df1`.
"""
