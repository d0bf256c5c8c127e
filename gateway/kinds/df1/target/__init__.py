"""The DF1 kind's target role: a PLC's MSG instructions read and write the gateway (``role = "target"``).

What this package owns:

* :mod:`.config` - the ``[[link.file]]`` entries: the data files a PLC's MSG addresses;
* :mod:`.build` - such a link as a unit and its runner;
* :mod:`.driver` - the runner: owns the port, carries each command through the responder
  (:mod:`gateway.protocols.df1.full_duplex.responder`) to the core that answers it
  (:mod:`gateway.protocols.df1.pccc.target`) and its reply back;
* :mod:`.unit` - the data files served as Modbus registers;
* :mod:`.store` - ``persist``: the data table on disk, committed before each answer.

The ``[[link]]`` model, the simulators (``sim://plc-msg``) and the CLI commands are shared by every
role of the kind and stay in :mod:`gateway.kinds.df1`.
"""
